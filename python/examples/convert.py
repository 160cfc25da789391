"""Conversion script: any mesh meshio reads, with a point scalar field, to an ISM; and any ISM to
the formats other tools read.

    python convert.py in.vtu out.ismb --field distance    # mesh + field -> linear ISM
    python convert.py model.ismb out.glb                  # ISM -> curved surface (glTF)
    python convert.py model.ism.json out.npz              # ISM -> numpy arrays
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

import ism

ISM_SUFFIXES = (".ismb", ".ism.json", ".ism.msgpack")
EXPORT_SUFFIXES = (".obj", ".gltf", ".glb", ".vtk", ".vtu")


def is_ism(path: Path) -> bool:
    return path.name.endswith(ISM_SUFFIXES)


def mesh_to_ism(src: Path, field: str, level: float) -> ism.Model:
    """A simplicial mesh (triangles in 2D, tetrahedra in 3D) with a point field as a linear ISM."""
    import meshio

    mesh = meshio.read(src)
    tets = [c.data for c in mesh.cells if c.type == "tetra"]
    tris = [c.data for c in mesh.cells if c.type == "triangle"]
    if tets:
        points, cells = mesh.points[:, :3], np.concatenate(tets)
    elif tris:
        points, cells = mesh.points[:, :2], np.concatenate(tris)
    else:
        sys.exit(f"{src}: no triangles or tetrahedra")
    values = np.asarray(mesh.point_data[field], dtype=np.float64)
    # Orient every simplex positively (the format requires it): swap two corners where the
    # determinant is negative.
    e = points[cells[:, 1:]] - points[cells[:, :1]]
    negative = np.linalg.det(e) < 0
    cells = cells.copy()
    cells[negative, 0], cells[negative, 1] = cells[negative, 1], cells[negative, 0].copy()
    # Values exactly at the level count as outside, as `ism fit` does.
    values = np.where(values == level, level + 1e-12 * np.max(np.abs(values)), values)
    return ism.Model(points, cells, values, level, metadata={"name": src.stem, "generator": "convert.py"})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("input", type=Path)
    ap.add_argument("output", type=Path)
    ap.add_argument("--field", help="point field giving the vertex values (mesh input)")
    ap.add_argument("--level", type=float, default=0.0)
    ap.add_argument("--tolerance", type=float, default=1e-3, help="chordal tolerance of exported surfaces")
    args = ap.parse_args()

    model = ism.read(args.input) if is_ism(args.input) else mesh_to_ism(args.input, args.field, args.level)
    out = args.output
    if is_ism(out):
        model.write(out)
    elif out.suffix in EXPORT_SUFFIXES:
        model.export(out, tolerance=args.tolerance)
    elif out.suffix == ".npz":
        np.savez(out, vertices=model.vertices, simplices=model.simplices, values=model.values, level=model.level)
    else:
        sys.exit(f"{out}: unknown output format")
    report = model.validate()
    print(f"{args.input} -> {out}: {model.num_vertices} vertices, {model.num_simplices} simplices, {report.verdict}")


if __name__ == "__main__":
    main()
