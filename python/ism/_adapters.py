"""Adapters to trimesh, PyVista and meshio, imported only when called (those packages are
optional)."""

from __future__ import annotations

from typing import Any

import numpy as np


def _need(module: str) -> Any:
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise ImportError(f"this adapter needs the {module!r} package: pip install {module}") from e


def to_trimesh(model: Any, tolerance: float = 1e-3, **options: Any) -> Any:
    """The curved surface of a 3D model as a ``trimesh.Trimesh`` with vertex normals and the
    source simplex of each face as face attribute ``simplex``."""
    trimesh = _need("trimesh")
    if model.dimension != 3:
        raise ValueError("to_trimesh needs a 3D model (a 2D model's shape is a curve)")
    s = model.extract_surface(tolerance, **options)
    return trimesh.Trimesh(
        vertices=s.positions,
        faces=s.cells.astype(np.int64),
        vertex_normals=s.normals,
        face_attributes={"simplex": s.cell_simplex},
        process=False,
    )


def to_pyvista(model: Any, tolerance: float = 1e-3, *, volume: bool = False, **options: Any) -> Any:
    """The curved surface as ``pyvista.PolyData`` (triangles, or lines in 2D; point data
    ``Normals``, cell data ``simplex``); with ``volume=True`` the complex with F as VTK Bézier
    cells (``pyvista.UnstructuredGrid``, written by the library's .vtu exporter and read back)."""
    pv = _need("pyvista")
    if volume:
        import os
        import tempfile

        with tempfile.TemporaryDirectory() as d:
            path = os.path.join(d, "volume.vtu")
            model.export(path, volume=True)
            return pv.read(path)
    s = model.extract_surface(tolerance, **options)
    pts = s.positions
    if s.dimension == 2:
        pts = np.column_stack([pts, np.zeros(len(pts))])
        normals = np.column_stack([s.normals, np.zeros(len(pts))])
        cells = np.column_stack([np.full(len(s.cells), 2), s.cells]).astype(np.int64).ravel()
        mesh = pv.PolyData(pts, lines=cells)
    else:
        normals = s.normals
        cells = np.column_stack([np.full(len(s.cells), 3), s.cells]).astype(np.int64).ravel()
        mesh = pv.PolyData(pts, faces=cells)
    mesh.point_data["Normals"] = normals
    mesh.cell_data["simplex"] = s.cell_simplex
    return mesh


def to_meshio(model: Any) -> Any:
    """The linear complex as a ``meshio.Mesh`` (triangles or tetrahedra) with the vertex values as
    point data ``"f"`` (stages are not applied: meshio has no cells for them)."""
    meshio = _need("meshio")
    cell_type = "triangle" if model.dimension == 2 else "tetra"
    return meshio.Mesh(
        points=np.array(model.vertices),
        cells=[(cell_type, np.array(model.simplices, dtype=np.int64))],
        point_data={"f": np.array(model.values)},
        field_data={},
    )
