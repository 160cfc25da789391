"""Every `ism export` output opened by a real consumer.

- trimesh: the sphere and torus OBJ exports are watertight, winding-consistent, Euler numbers 2 and 0,
  positive volume; the GLB loads with the same triangle count;
- the Khronos glTF-Validator (npm `gltf-validator`, via tools/export_gltf_validate.js): 0 errors and
  0 warnings for .glb and .gltf, surfaces and curves;
- Python `vtk`: reads the .vtu and legacy .vtk surface with their arrays; reads the --volume .vtu
  (Bézier cells), tessellates it (vtkTessellatorFilter, field-error criterion on F) and contours F = c,
  landing on the extracted shape;
- meshio reads the linear outputs.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import meshio
import numpy as np
import pytest
import trimesh
import vtk
from vtk.util.numpy_support import vtk_to_numpy

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "spec" / "examples"
VALIDATOR = ROOT / "tools" / "export_gltf_validate.js"
# Coarse enough that the debug binary CI builds exports each model in seconds.
TOLERANCE = 4e-3


def ism_bin() -> str:
    path = os.environ.get("ISM_BIN") or str(ROOT / "target" / "debug" / "ism")
    assert Path(path).exists(), f"ism binary not found at {path}: build it or set ISM_BIN"
    return path


def export(model: str, out: Path, *extra: str) -> dict:
    r = subprocess.run(
        [ism_bin(), "export", str(EXAMPLES / model), str(out), "--json", *extra],
        capture_output=True,
        text=True,
        check=False,
    )
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout) if r.stdout.strip() else {}


@pytest.fixture(scope="module")
def outputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("export")
    out = {}
    for name in ("sphere", "torus"):
        out[name] = export(f"{name}.ism.json", d / f"{name}.obj", "--tolerance", str(TOLERANCE))
        for ext in ("glb", "gltf", "vtu", "vtk") if name == "sphere" else ("glb",):
            export(f"{name}.ism.json", d / f"{name}.{ext}", "--tolerance", str(TOLERANCE))
    out["circle"] = export("circle-curved.ism.json", d / "circle.obj", "--tolerance", "1e-4")
    for ext in ("glb", "gltf", "vtu"):
        export("circle-curved.ism.json", d / f"circle.{ext}", "--tolerance", "1e-4")
    out["quadratic"] = export("quadratic-edges.ism.json", d / "quadratic.obj", "--tolerance", "1e-5", "--max-depth", "12")
    r = subprocess.run([ism_bin(), "export", str(EXAMPLES / "quadratic-edges.ism.json"), str(d / "quadratic-volume.vtu"), "--volume"],
                       capture_output=True, text=True, check=False)
    assert r.returncode == 0, r.stderr
    assert "certified" in r.stderr and "ESTIMATED" not in r.stderr, r.stderr
    r = subprocess.run([ism_bin(), "export", str(EXAMPLES / "sphere.ism.json"), str(d / "sphere-volume.vtu"), "--volume",
                        "--tolerance", str(TOLERANCE)],
                       capture_output=True, text=True, check=False)
    assert r.returncode == 0, r.stderr
    assert "certified" in r.stderr and "ESTIMATED" not in r.stderr, r.stderr
    return d, out


@pytest.mark.parametrize("name,euler", [("sphere", 2), ("torus", 0)])
def test_trimesh_finds_closed_oriented_surfaces(outputs, name, euler):
    d, summary = outputs
    mesh = trimesh.load(d / f"{name}.obj", process=True)
    assert mesh.is_watertight
    assert mesh.is_winding_consistent
    assert mesh.euler_number == euler
    assert mesh.volume > 0
    assert len(mesh.faces) == summary[name]["cells"]
    scene = trimesh.load(d / f"{name}.glb")
    assert sum(len(g.faces) for g in scene.geometry.values()) == summary[name]["cells"]


def test_curved_sphere_is_closer_to_the_ball_than_the_linear_isocomplex(outputs):
    d, _ = outputs
    curved = trimesh.load(d / "sphere.obj").volume
    linear_summary = export("sphere.ism.json", d / "sphere-linear.obj", "--linear")
    linear = trimesh.load(d / "sphere-linear.obj").volume
    assert abs(linear - linear_summary["enclosed_measure"]) < 1e-9
    # The example pins the surface to |p| = 0.7 on the crossed edges; between them it is a
    # curved interpolant, so the enclosed volume is near 4/3 π 0.7³, much nearer than the
    # piecewise-linear surface's (measured: 5.7 % against 16.6 % below).
    ball = 4.0 / 3.0 * np.pi * 0.7**3
    assert 0 < linear < curved
    assert abs(curved - ball) < 0.5 * abs(linear - ball)


def test_gltf_validator_reports_no_issue(outputs):
    d, _ = outputs
    node = shutil.which("node")
    assert node, "node is required (tools/setup.sh installs gltf-validator with npm)"
    files = [str(d / f) for f in ("sphere.glb", "sphere.gltf", "torus.glb", "circle.glb", "circle.gltf")]
    r = subprocess.run([node, str(VALIDATOR), *files], capture_output=True, text=True, check=False)
    assert r.returncode == 0, r.stdout + r.stderr
    reports = [json.loads(line) for line in r.stdout.splitlines()]
    assert len(reports) == len(files)
    for rep in reports:
        assert (rep["errors"], rep["warnings"]) == (0, 0), rep


def read_vtu(path: Path):
    reader = vtk.vtkXMLUnstructuredGridReader()
    reader.SetFileName(str(path))
    reader.Update()
    return reader.GetOutput()


def test_vtk_reads_the_surface_with_its_arrays(outputs):
    d, summary = outputs
    for path in (d / "sphere.vtu", d / "sphere.vtk"):
        if path.suffix == ".vtu":
            grid = read_vtu(path)
        else:
            reader = vtk.vtkUnstructuredGridReader()
            reader.SetFileName(str(path))
            reader.Update()
            grid = reader.GetOutput()
        assert grid.GetNumberOfPoints() == summary["sphere"]["vertices"]
        assert grid.GetNumberOfCells() == summary["sphere"]["cells"]
        pd = grid.GetPointData()
        # The .vtu marks them as the normals attribute; the legacy .vtk writes them as VECTORS (the
        # form meshio reads too), under the same name.
        normals = vtk_to_numpy(pd.GetNormals() if path.suffix == ".vtu" else pd.GetArray("Normals"))
        assert normals.shape == (grid.GetNumberOfPoints(), 3)
        assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-12)
        # Outward: on a sphere about the origin the normal points away from the centre.
        pts = vtk_to_numpy(grid.GetPoints().GetData())
        assert np.all(np.einsum("ij,ij->i", pts, normals) > 0)
        assert pd.GetArray("GradientNorm") is not None
        assert grid.GetCellData().GetArray("SourceSimplex") is not None
        # The contour filter works on the surface's own scalars: a level of |∇F| cuts it in lines.
        contour = vtk.vtkContourFilter()
        contour.SetInputData(grid)
        g = vtk_to_numpy(pd.GetArray("GradientNorm"))
        pd.SetActiveScalars("GradientNorm")
        contour.SetValue(0, float(np.median(g)))
        contour.Update()
        assert contour.GetOutput().GetNumberOfCells() > 0


def contour_volume(path: Path, level: float = 0.0, subdivisions: int = 3):
    grid = read_vtu(path)
    assert grid.GetPointData().GetScalars().GetName() == "F"
    tess = vtk.vtkTessellatorFilter()
    tess.SetInputData(grid)
    tess.SetMaximumNumberOfSubdivisions(subdivisions)
    tess.SetChordError(1e-4)
    # Refine on the field itself, so the contour follows F and not its control net.
    tess.SetFieldCriterion(0, 1e-4)
    tess.Update()
    contour = vtk.vtkContourFilter()
    contour.SetInputConnection(tess.GetOutputPort())
    contour.SetInputArrayToProcess(0, 0, 0, vtk.vtkDataObject.FIELD_ASSOCIATION_POINTS, "F")
    contour.SetValue(0, level)
    contour.Update()
    out = contour.GetOutput()
    return grid, vtk_to_numpy(out.GetPoints().GetData()) if out.GetNumberOfPoints() else np.zeros((0, 3))


def read_obj_polyline(path: Path):
    """The `v` and `l` records of an OBJ file (meshio and trimesh read no OBJ lines)."""
    verts, lines = [], []
    for line in path.read_text().splitlines():
        parts = line.split()
        if parts and parts[0] == "v":
            verts.append([float(x) for x in parts[1:4]])
        elif parts and parts[0] == "l":
            lines.append([int(x) - 1 for x in parts[1:3]])
    return np.array(verts), np.array(lines)


def segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from each point to the nearest of the segments a[i]–b[i]."""
    ab = b - a
    t = np.clip(np.einsum("pk,sk->ps", points, ab) - np.einsum("sk,sk->s", a, ab)[None, :], 0, None)
    t = np.minimum(t / np.einsum("sk,sk->s", ab, ab)[None, :], 1.0)
    closest = a[None, :, :] + t[:, :, None] * ab[None, :, :]
    return np.min(np.linalg.norm(points[:, None, :] - closest, axis=2), axis=1)


def test_exact_bezier_volume_contours_onto_the_extracted_curve(outputs):
    d, _ = outputs
    grid, pts = contour_volume(d / "quadratic-volume.vtu")
    assert grid.GetCellType(0) == 76  # VTK_BEZIER_TRIANGLE
    assert len(pts) > 20
    verts, lines = read_obj_polyline(d / "quadratic.obj")
    assert len(lines) > 20
    dist = segment_distance(pts, verts[lines[:, 0]], verts[lines[:, 1]])
    # Both sides approximate the same exact curve: ours to 1e-5, VTK's tessellation to its own
    # subdivision limit.
    assert dist.max() < 5e-3, dist.max()


def test_volume_of_the_sphere_contours_near_the_sphere(outputs):
    d, _ = outputs
    grid, pts = contour_volume(d / "sphere-volume.vtu", subdivisions=1)
    assert grid.GetCellType(0) == 78  # VTK_BEZIER_TETRAHEDRON
    assert len(pts) > 100
    r = np.linalg.norm(pts, axis=1)
    # F within the certified field tolerance: near the exported surface, which is near |p| = 0.7.
    assert np.all(np.abs(r - 0.7) < 0.05), (r.min(), r.max())


def test_meshio_reads_the_linear_outputs(outputs):
    d, summary = outputs
    for ext in ("vtu", "vtk", "obj"):
        m = meshio.read(d / f"sphere.{ext}")
        tris = sum(len(c.data) for c in m.cells if c.type == "triangle")
        assert tris == summary["sphere"]["cells"], ext
        if ext != "obj":
            normals = m.point_data["Normals"]
            assert normals.shape == (len(m.points), 3)
            assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-12)
    m = meshio.read(d / "circle.vtu")
    assert sum(len(c.data) for c in m.cells if c.type == "line") == summary["circle"]["cells"]


def test_compressed_vtu_reads_as_the_raw_one_in_vtk_and_meshio(tmp_path):
    """`--compress` (zlib, vtkZLibDataCompressor): VTK's reader and meshio's read the same points,
    cells and arrays from it as from the uncompressed file, bit for bit, for a surface (sphere
    example at 1e-4: the points span several 32 KiB blocks) and, in VTK, for a --volume file
    (Bézier cells, which meshio does not read); the file is smaller. A non-.vtu output refuses the
    flag."""
    for name, extra in (("surface", ["--tolerance", "1e-4"]), ("volume", ["--volume"])):
        raw, packed = tmp_path / f"{name}.vtu", tmp_path / f"{name}-zlib.vtu"
        for out, more in ((raw, []), (packed, ["--compress"])):
            r = subprocess.run([ism_bin(), "export", str(EXAMPLES / "sphere.ism.json"), str(out), "-q", *extra, *more],
                               capture_output=True, text=True, check=False)
            assert r.returncode == 0, r.stderr
        assert b'compressor="vtkZLibDataCompressor"' in packed.read_bytes()[:400]
        assert packed.stat().st_size < 0.7 * raw.stat().st_size, (packed.stat().st_size, raw.stat().st_size)
        a, b = read_vtu(raw), read_vtu(packed)
        assert a.GetNumberOfPoints() == b.GetNumberOfPoints() > 0
        assert a.GetNumberOfCells() == b.GetNumberOfCells() > 0
        assert np.array_equal(vtk_to_numpy(a.GetPoints().GetData()), vtk_to_numpy(b.GetPoints().GetData()))
        assert np.array_equal(vtk_to_numpy(a.GetCells().GetConnectivityArray()),
                              vtk_to_numpy(b.GetCells().GetConnectivityArray()))
        assert np.array_equal(vtk_to_numpy(a.GetCellTypesArray()), vtk_to_numpy(b.GetCellTypesArray()))
        for data in ("GetPointData", "GetCellData"):
            da, db = getattr(a, data)(), getattr(b, data)()
            assert da.GetNumberOfArrays() == db.GetNumberOfArrays() > 0
            for i in range(da.GetNumberOfArrays()):
                assert da.GetArrayName(i) == db.GetArrayName(i)
                assert np.array_equal(vtk_to_numpy(da.GetArray(i)), vtk_to_numpy(db.GetArray(i))), da.GetArrayName(i)
        if name == "volume":
            continue  # meshio has no Bézier cells (KeyError 'VTK_BEZIER_TETRAHEDRON' on either file)
        ma, mb = meshio.read(raw), meshio.read(packed)
        assert np.array_equal(ma.points, mb.points)
        assert [(c.type, c.data.tolist()) for c in ma.cells] == [(c.type, c.data.tolist()) for c in mb.cells]
        assert sorted(ma.point_data) == sorted(mb.point_data)
        for key in ma.point_data:
            assert np.array_equal(ma.point_data[key], mb.point_data[key]), key
    r = subprocess.run([ism_bin(), "export", str(EXAMPLES / "sphere.ism.json"), str(tmp_path / "s.obj"), "--compress"],
                       capture_output=True, text=True, check=False)
    assert r.returncode == 2 and "--compress needs a .vtu output" in r.stderr, r.stderr
    assert not (tmp_path / "s.obj").exists()


def contour_topology(path: Path, level: float, subdivisions: int):
    """Contour F = level of a --volume output in VTK: points, components and Euler characteristic
    (V − E + F of the merged contour; 0 per closed curve in 2D, 2 − 2g per closed surface in 3D)."""
    grid = read_vtu(path)
    tess = vtk.vtkTessellatorFilter()
    tess.SetInputData(grid)
    tess.SetMaximumNumberOfSubdivisions(subdivisions)
    tess.SetFieldCriterion(0, 1e-5)
    tess.Update()
    contour = vtk.vtkContourFilter()
    contour.SetInputConnection(tess.GetOutputPort())
    contour.SetInputArrayToProcess(0, 0, 0, vtk.vtkDataObject.FIELD_ASSOCIATION_POINTS, "F")
    contour.SetValue(0, level)
    clean = vtk.vtkCleanPolyData()
    clean.SetInputConnection(contour.GetOutputPort())
    clean.Update()
    poly = clean.GetOutput()
    conn = vtk.vtkPolyDataConnectivityFilter()
    conn.SetInputData(poly)
    conn.SetExtractionModeToAllRegions()
    conn.Update()
    edges = vtk.vtkExtractEdges()
    edges.SetInputData(poly)
    edges.Update()
    v = poly.GetNumberOfPoints()
    e = edges.GetOutput().GetNumberOfLines()
    f = poly.GetNumberOfPolys()
    euler = v - e + f if f else v - poly.GetNumberOfLines()
    pts = vtk_to_numpy(poly.GetPoints().GetData()) if v else np.zeros((0, 3))
    return pts, conn.GetNumberOfExtractedRegions(), euler


def surface_distance(points: np.ndarray, obj: Path, dim: int) -> float:
    if dim == 2:
        verts, lines = read_obj_polyline(obj)
        return float(segment_distance(points, verts[lines[:, 0]], verts[lines[:, 1]]).max())
    # The distance to the surface export itself (trimesh's closest point on the mesh, through its
    # R-tree). The triangles around the 4 nearest vertices, used before, gave 0.116 on the torus
    # example where the true distance is 3.8e-3: the export's long triangles put those vertices
    # 0.1 away.
    mesh = trimesh.load(obj, process=False)
    _, dist, _ = trimesh.proximity.closest_point(mesh, points)
    return float(dist.max())


# Every example. (The torus was left out while its field was an interpolant: 12,288 degree-6 cells
# that still missed 4.2e-4; its exact cells are 1,536 of degree 3.)
VOLUME_EXAMPLES = sorted(p.name for p in EXAMPLES.glob("*.ism.json"))


@pytest.mark.parametrize("model", VOLUME_EXAMPLES)
def test_volume_contours_to_the_models_topology_near_its_surface(tmp_path, model):
    """Issue 19: for every example, contouring the --volume field at the
    level in VTK gives the surface export's components (and, for curves, its Euler characteristic:
    VTK's tessellation of Bézier tetrahedra is not conforming across cells, so a 3D contour's V − E + F
    is not the surface's), within a small distance of it; the stated bound meets the tolerance."""
    # The refined surface (not coarsened), a close reference for the distance below.
    surface = export(model, tmp_path / "s.obj", "--tolerance", "1e-4", "--max-depth", "12", "--no-coarsen")
    vol = export(model, tmp_path / "v.vtu", "--volume", "--tolerance", str(TOLERANCE))
    assert vol["field_tolerance_met"], vol
    assert vol["field_error_bound"] <= vol["field_tolerance"], vol
    doc = json.loads((EXAMPLES / model).read_text())
    dim, level = doc["dimension"], doc["level"]
    # The torus's exact cells are few (1,536) and its F steep (a monotonic weight of 7): VTK's
    # tessellation needs a second subdivision to follow F within the distance below (its own
    # chordal error: 3.7e-2, 1.7e-2, 7.4e-3 as |F − c| / |∇F| at 1, 2, 3 subdivisions).
    subdivisions = 2 if dim == 2 or model == "torus.ism.json" else 1
    pts, components, euler = contour_topology(tmp_path / "v.vtu", level, subdivisions=subdivisions)
    assert len(pts) > 10
    assert components == surface["components"], (components, surface)
    if dim == 2:
        assert euler == surface["euler_characteristic"], (euler, surface)
    # A field error of ε moves the level set by about ε/|∇F| (the default ε is the tolerance times
    # the median |∇F|); VTK's tessellation of the Bézier cells adds its own chordal error, and the
    # distance is measured to the nearest vertex of the export (an upper bound).
    assert surface_distance(pts, tmp_path / "s.obj", dim) < 5e-2


def test_fitted_volume_is_exact_in_vtk(tmp_path):
    """Issue 19: a fitted model (parametric stages only) is written as exact isoparametric Bézier
    cells. VTK's own evaluation of a cell at random parameters (``EvaluateLocation``: the point and
    the basis weights) gives a point where ``ism query`` — which inverts the stages by Newton, an
    independent evaluation — finds the F that VTK interpolates there; contouring F in VTK gives
    the fit's one closed surface, near the surface export."""
    fitted = tmp_path / "fitted.ismb"
    subprocess.run([ism_bin(), "fit", "--preset", "sphere", "-o", str(fitted), "-q"], check=True)
    vol = export(str(fitted), tmp_path / "v.vtu", "--volume")
    assert vol["field_exact"] and vol["field_error_certified"] and vol["field_tolerance_met"], vol
    assert vol["field_error_bound"] < 1e-9, vol
    assert vol["refinement_levels"] == 0 and vol["degree"] <= 12, vol
    grid = read_vtu(tmp_path / "v.vtu")
    assert grid.GetCellType(0) == 78
    F = vtk_to_numpy(grid.GetPointData().GetArray("F"))
    rng = np.random.default_rng(3)
    xs, fs = [], []
    for c in rng.choice(grid.GetNumberOfCells(), size=200, replace=False):
        cell = grid.GetCell(int(c))
        ids = [cell.GetPointId(i) for i in range(cell.GetNumberOfPoints())]
        for _ in range(3):
            b = rng.dirichlet(np.ones(4))
            x, w = [0.0, 0.0, 0.0], [0.0] * len(ids)
            cell.EvaluateLocation(vtk.reference(0), list(b[1:]), x, w)
            xs.append(x)
            fs.append(float(np.dot(w, F[ids])))
    np.savetxt(tmp_path / "p.csv", np.array(xs), delimiter=",")
    out = subprocess.run(
        [ism_bin(), "query", str(fitted), str(tmp_path / "p.csv"), "-q", "--format", "csv"],
        capture_output=True, text=True, check=True,
    ).stdout
    rows = [line.split(",") for line in out.splitlines()[1:]]
    assert all(int(r[3]) >= 0 for r in rows)  # VTK's points lie in the complex
    f = np.array([float(r[4]) for r in rows])
    # Both sides evaluate F in double precision by different formulas: rounding only.
    assert np.max(np.abs(f - np.array(fs))) < 1e-12
    surface = export(str(fitted), tmp_path / "s.obj", "--tolerance", "1e-4", "--max-depth", "12", "--no-coarsen")
    pts, components, _ = contour_topology(tmp_path / "v.vtu", 0.0, subdivisions=0)
    assert components == surface["components"] == 1, (components, surface)
    # VTK's tessellation without subdivision linearises each degree-6 cell (its chordal error, 2e-2
    # at most here, is VTK's); the field it tessellates is F itself.
    assert surface_distance(pts, tmp_path / "s.obj", 3) < 5e-2

