"""`ism import` of meshes written by meshio, in every supported format and both quadratic-tet
node conventions (VTK and Gmsh), each exported again and checked with trimesh.

The test mesh is a Kuhn-triangulated cube with the field |p|² − 0.5²: every import must give the
same linear model (same vertex and simplex counts, same surface), whatever the container.
"""

from __future__ import annotations

import itertools
import json
import os
import re
import subprocess
from pathlib import Path

import meshio
import numpy as np
import pytest
import trimesh

ROOT = Path(__file__).resolve().parents[2]


def ism_bin() -> str:
    path = os.environ.get("ISM_BIN") or str(ROOT / "target" / "debug" / "ism")
    assert Path(path).exists(), f"ism binary not found at {path}: build it or set ISM_BIN"
    return path


def kuhn_ball(n: int = 8):
    """Points, tetrahedra (some deliberately negatively oriented) and the field |p|² − 0.25 + tiny
    offset so no vertex sits on the level."""
    g = np.linspace(-1.0, 1.0, n + 1)
    pts = np.array([[x, y, z] for z in g for y in g for x in g])
    idx = lambda i, j, k: i + (n + 1) * (j + (n + 1) * k)
    tets = []
    for i, j, k in itertools.product(range(n), repeat=3):
        for perm in itertools.permutations(range(3)):
            c = [i, j, k]
            path = [idx(*c)]
            for axis in perm:
                c[axis] += 1
                path.append(idx(*c))
            tets.append(path)  # orientation follows the permutation's sign: half are negative
    tets = np.array(tets)
    field = (pts**2).sum(axis=1) - 0.55**2
    return pts, tets, field


def quadratic(pts, tets):
    """tetra10 in VTK order: corners, then edge midpoints (01, 12, 02, 03, 13, 23)."""
    edges = [(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)]
    extra = {}
    new_pts = list(pts)
    cells = []
    for t in tets:
        row = list(t)
        for a, b in edges:
            key = tuple(sorted((t[a], t[b])))
            if key not in extra:
                extra[key] = len(new_pts)
                new_pts.append((pts[t[a]] + pts[t[b]]) / 2)
            row.append(extra[key])
        cells.append(row)
    return np.array(new_pts), np.array(cells)


def run_import(src: Path, out: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([ism_bin(), "import", str(src), str(out), *extra], capture_output=True, text=True, check=False)


def info(model: Path) -> dict:
    r = subprocess.run([ism_bin(), "info", "--json", str(model)], capture_output=True, text=True, check=True)
    return json.loads(r.stdout)


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    d = tmp_path_factory.mktemp("import")
    pts, tets, field = kuhn_ball()
    linear = meshio.Mesh(pts, [("tetra", tets)], point_data={"phi": field, "other": field * 0 + 3.0})
    files = {
        "vtu-ascii": (d / "ball-ascii.vtu", dict(binary=False)),
        "vtu-binary": (d / "ball-binary.vtu", dict(binary=True, compression=None)),
        "vtk": (d / "ball.vtk", dict(binary=False)),
        "msh": (d / "ball.msh", dict(file_format="gmsh", binary=False)),
    }
    for path, kw in files.values():
        meshio.write(path, linear, **kw)
    qpts, qtets = quadratic(pts, tets)
    qfield = (qpts**2).sum(axis=1) - 0.55**2
    quad = meshio.Mesh(qpts, [("tetra10", qtets)], point_data={"phi": qfield})
    meshio.write(d / "ball-quadratic.vtu", quad, binary=False)
    meshio.write(d / "ball-quadratic.msh", quad, file_format="gmsh", binary=False)
    for msh in (d / "ball.msh", d / "ball-quadratic.msh"):
        # meshio 5.3 with numpy 2 writes Gmsh NodeData values as "np.float64(x)"; restore the plain
        # numbers its own reader and Gmsh expect.
        msh.write_text(re.sub(r"np\.float64\(([^)]*)\)", r"\1", msh.read_text()))
    files["vtu-quadratic"] = (d / "ball-quadratic.vtu", {})
    files["msh-quadratic"] = (d / "ball-quadratic.msh", {})
    return d, files, len(pts), len(tets)


@pytest.mark.parametrize("kind", ["vtu-ascii", "vtu-binary", "vtk", "msh", "vtu-quadratic", "msh-quadratic"])
def test_import_gives_the_same_linear_ball(written, kind):
    d, files, npts, ntets = written
    src = files[kind][0]
    model = d / f"{kind}.ism.json"
    r = run_import(src, model, "--field", "phi")
    assert r.returncode == 0, r.stderr
    s = info(model)
    assert (s["dimension"], s["vertices"], s["simplices"]) == (3, npts, ntets)
    assert s["stages"] == []
    obj = d / f"{kind}.obj"
    r = subprocess.run([ism_bin(), "export", str(model), str(obj), "--json"], capture_output=True, text=True, check=False)
    assert r.returncode == 0, r.stderr
    mesh = trimesh.load(obj)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.euler_number == 2
    assert mesh.volume > 0
    # A ball of radius 0.55 on a grid of spacing 0.25, linear: within 40 % of its volume.
    assert abs(mesh.volume - 4 / 3 * np.pi * 0.55**3) < 0.4 * 4 / 3 * np.pi * 0.55**3


def test_import_refuses_a_value_on_the_level_and_a_missing_field(written):
    d, files, _, _ = written
    src = files["vtu-ascii"][0]
    r = run_import(src, d / "x.ism.json", "--field", "other", "--level", "3")
    assert r.returncode == 2 and "equals the level" in r.stderr
    r = run_import(src, d / "x.ism.json", "--field", "nope")
    assert r.returncode == 2 and "no point field" in r.stderr
    assert not (d / "x.ism.json").exists()


def vtk_grid(pts, tets, field):
    """The same mesh as a vtkUnstructuredGrid with float64 points and the field "phi" (active)."""
    import vtk
    from vtk.util import numpy_support

    points = vtk.vtkPoints()
    points.SetDataTypeToDouble()
    points.SetData(numpy_support.numpy_to_vtk(np.ascontiguousarray(pts, dtype=np.float64), deep=True))
    grid = vtk.vtkUnstructuredGrid()
    grid.SetPoints(points)
    for t in tets:
        grid.InsertNextCell(vtk.VTK_TETRA, 4, [int(i) for i in t])
    phi = numpy_support.numpy_to_vtk(np.ascontiguousarray(field, dtype=np.float64), deep=True)
    phi.SetName("phi")
    grid.GetPointData().SetScalars(phi)
    return grid


def write_vtk(grid, path: Path, **settings) -> Path:
    import vtk

    w = vtk.vtkXMLUnstructuredGridWriter()
    w.SetInputData(grid)
    w.SetFileName(str(path))
    for name, value in settings.items():
        getattr(w, name)(*([] if value is None else [value]))
    assert w.Write() == 1
    return path


@pytest.fixture(scope="module")
def compressed(tmp_path_factory):
    """The ball as real writers write it: meshio's default (inline base64, zlib) and lzma, and
    vtkXMLUnstructuredGridWriter's default (appended base64, zlib), its LZ4 and LZMA compressors,
    raw appended data, inline binary, 64-bit headers and no compression; each with its own ASCII
    reference written by the same library."""
    d = tmp_path_factory.mktemp("compressed")
    pts, tets, field = kuhn_ball()
    mesh = meshio.Mesh(pts, [("tetra", tets)], point_data={"phi": field})
    meshio.write(d / "meshio-ascii.vtu", mesh, binary=False)
    meshio.write(d / "meshio-default.vtu", mesh)
    meshio.write(d / "meshio-lzma.vtu", mesh, compression="lzma")
    grid = vtk_grid(pts, tets, field)
    write_vtk(grid, d / "vtk-ascii.vtu", SetDataModeToAscii=None)
    write_vtk(grid, d / "vtk-default.vtu")
    write_vtk(grid, d / "vtk-lz4.vtu", SetCompressorTypeToLZ4=None)
    write_vtk(grid, d / "vtk-lzma.vtu", SetCompressorTypeToLZMA=None)
    write_vtk(grid, d / "vtk-raw.vtu", SetEncodeAppendedData=0)
    write_vtk(grid, d / "vtk-inline.vtu", SetDataModeToBinary=None)
    write_vtk(grid, d / "vtk-uint64.vtu", SetHeaderTypeToUInt64=None, SetEncodeAppendedData=0)
    write_vtk(grid, d / "vtk-uncompressed.vtu", SetCompressorTypeToNone=None)
    return d


def imported(src: Path, out: Path) -> dict:
    r = run_import(src, out, "--field", "phi")
    assert r.returncode == 0, r.stderr
    return json.loads(out.read_text())


@pytest.mark.parametrize(
    "name",
    ["meshio-default", "meshio-lzma", "vtk-default", "vtk-lz4", "vtk-lzma", "vtk-raw", "vtk-inline", "vtk-uint64",
     "vtk-uncompressed"],
)
def test_compressed_vtu_imports_like_ascii(compressed, name):
    d = compressed
    text = (d / f"{name}.vtu").read_bytes()
    if name != "vtk-uncompressed":
        assert b"compressor=" in text  # the writer did compress
    if name in ("vtk-raw", "vtk-uint64"):
        assert b'encoding="raw"' in text
    # Ground truth: the arrays the writers were given (float64 throughout, so bit for bit), and
    # the simplices of the same library's ASCII file (integers: exact in ASCII).
    pts, tets, field = kuhn_ball()
    model = imported(d / f"{name}.vtu", d / f"{name}.ism.json")
    assert model["dimension"] == 3
    assert model["vertices"] == pts.ravel().tolist()
    assert model["values"] == field.tolist()
    reference = imported(d / f"{name.split('-')[0]}-ascii.vtu", d / f"{name}-ref.ism.json")
    assert model["simplices"] == reference["simplices"]
    assert len(model["simplices"]) == 4 * len(tets)
