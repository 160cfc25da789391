"""Adapters: trimesh, PyVista and the meshio plugin, checked against the library's own arrays and
against meshio reading the CLI's export."""

from __future__ import annotations

import numpy as np
import pytest

import ism
from conftest import EXAMPLES, cli


@pytest.mark.parametrize("name", ["sphere", "circle-curved"])
@pytest.mark.parametrize("encoding", [".ismb", ".ism.json", ".ism.msgpack"])
def test_meshio_reads_an_ism_as_its_linear_complex(name, encoding):
    import meshio

    m = ism.read(EXAMPLES / (name + ".ismb"))
    mesh = meshio.read(EXAMPLES / (name + encoding))
    assert np.array_equal(mesh.points, m.vertices)
    assert mesh.cells[0].type == ("tetra" if m.dimension == 3 else "triangle")
    assert np.array_equal(mesh.cells[0].data, m.simplices)
    assert np.array_equal(mesh.point_data["f"], m.values)


def test_meshio_mesh_written_as_vtu_imports_back_with_the_cli(tmp_path):
    import meshio

    mesh = meshio.read(EXAMPLES / "sphere.ismb")
    meshio.write(tmp_path / "linear.vtu", mesh)
    cli("import", tmp_path / "linear.vtu", tmp_path / "back.ismb", "--field", "f", "--quiet")
    back = ism.read(tmp_path / "back.ismb")
    m = ism.read(EXAMPLES / "sphere.ismb")
    assert np.array_equal(back.vertices, m.vertices) and np.array_equal(back.values, m.values)


def test_to_trimesh_is_the_extracted_surface():
    m = ism.read(EXAMPLES / "torus.ismb")
    tm = m.to_trimesh(2e-3)
    s = m.extract_surface(2e-3)
    assert np.array_equal(tm.vertices, s.positions)
    assert np.array_equal(tm.faces, s.cells)
    assert tm.is_watertight
    assert tm.euler_number == s.report["euler_characteristic"] == 0
    assert abs(tm.volume - s.report["enclosed_measure"]) < 1e-9 * abs(tm.volume)
    with pytest.raises(ValueError):
        ism.read(EXAMPLES / "circle-curved.ismb").to_trimesh()


def test_to_pyvista_surface_and_bezier_volume():
    import pyvista as pv

    m = ism.read(EXAMPLES / "sphere.ismb")
    surf = m.to_pyvista(2e-3)
    s = m.extract_surface(2e-3)
    assert surf.n_points == len(s.positions) and surf.n_cells == len(s.cells)
    assert np.array_equal(surf.points, s.positions)
    curve = ism.read(EXAMPLES / "circle-curved.ismb").to_pyvista()
    assert curve.n_lines > 0
    vol = m.to_pyvista(volume=True)
    assert isinstance(vol, pv.UnstructuredGrid)
    assert vol.n_cells == m.num_simplices
