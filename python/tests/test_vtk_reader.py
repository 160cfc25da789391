"""The VTK reader (``ism.vtk_reader.ISMReader``) in real VTK pipelines (the ``vtk`` wheel).

Ground truth comes from outside the reader's construction of the cells:

- the model's ``F`` as the library's evaluator gives it (``Model.query``), compared with VTK's own
  interpolation of the written Bézier cells (``vtkCell.EvaluateLocation``) at random points;
- the linear isocomplex of ``circle-linear`` computed here from the vertex values alone (edge
  crossings of the linear interpolant), compared with VTK's contour of the volume block;
- the library's extracted surface (``Model.extract_surface``, what ``ism export`` writes) at a
  tighter tolerance, compared two-sided with VTK's pipeline reader → ``vtkTessellatorFilter`` →
  ``vtkContourFilter`` of ``F`` at the level;
- the reader vectors of ``spec/vectors/reader`` (each names the rule its failure must cite).
"""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest

pytest.importorskip("vtkmodules")  # the vtk wheel is in tools/requirements.txt (CI has it)

import ism  # noqa: E402
from conftest import EXAMPLES, VECTORS  # noqa: E402
from ism.vtk_reader import ISMReader  # noqa: E402
from vtkmodules.util.misc import calldata_type  # noqa: E402
from vtkmodules.util.numpy_support import vtk_to_numpy  # noqa: E402
from vtkmodules.vtkCommonCore import VTK_STRING, reference, vtkCommand, vtkIdList  # noqa: E402
from vtkmodules.vtkCommonDataModel import (  # noqa: E402
    VTK_BEZIER_TETRAHEDRON,
    VTK_BEZIER_TRIANGLE,
    vtkCompositeDataSet,
    vtkGenericCell,
    vtkMultiBlockDataSet,
    vtkPolyData,
    vtkUnstructuredGrid,
)
from vtkmodules.vtkFiltersCore import vtkContourFilter, vtkExtractCells, vtkImplicitPolyDataDistance  # noqa: E402
from vtkmodules.vtkFiltersGeneral import vtkTessellatorFilter  # noqa: E402


ENCODINGS = [".ismb", ".ismc", ".isms", ".ism.json", ".ism.msgpack"]

#: Examples the library writes exactly (no parametric stage after an implicit one, composed degree
#: at most 12).
EXACT = ["circle-linear", "quadratic-edges", "cubic-face-point", "rational-degree5", "circle-curved", "sphere", "torus", "monotonic"]
#: The others that the library's volume exporter approximates, with a bound (certified or not).
#: Value: whether the bound is certified (True: every stage implicit and the composed degree at
#: most the exporter's MAX_COMPOSED_DEGREE = 24 — stratified-3d's is 4·3·2 = 24 —, a Bernstein
#: bound of the exact rational form; False: an implicit stage before a parametric one gives a
#: sampled estimate).
APPROXIMATE = {"two-stage": False, "stratified-3d": True}

#: Agreement of VTK's interpolation of an exact cell with the library's F: both evaluate the same
#: rational function in double precision (different formulas), so they differ by rounding only —
#: a few ulps of |F| ≲ 1 times the number of terms; 1e-12 leaves a wide margin for that and is
#: still 8+ orders below any modelling tolerance.
EXACT_AGREEMENT = 1e-12


class Errors:
    """Collects the reader's VTK error events (the ``vtkErrorMacro`` path)."""

    def __init__(self, algorithm):
        self.messages = []

        @calldata_type(VTK_STRING)  # the observer receives the message text
        def on_error(obj, event, data):
            self.messages.append(data)

        algorithm.AddObserver(vtkCommand.ErrorEvent, on_error)


def read(path, tolerance=1e-3, **props):
    r = ISMReader()
    errors = Errors(r)
    r.SetFileName(str(path))
    r.SetTolerance(tolerance)
    for k, v in props.items():
        getattr(r, "Set" + k)(v)
    r.Update()
    return r, errors, r.GetOutputDataObject(0)


def arrays(attrs):
    return {attrs.GetArrayName(i) for i in range(attrs.GetNumberOfArrays())}


def field(data, name):
    a = data.GetFieldData().GetAbstractArray(name)
    assert a is not None, name
    return a.GetValue(0)


def sample_cells(grid, model, per_cell=4, max_cells=400, seed=7):
    """(points, F as VTK interpolates it) at random parametric points of sampled cells."""
    rng = np.random.default_rng(seed)
    n = model.dimension
    F = vtk_to_numpy(grid.GetPointData().GetArray("F"))
    cell = vtkGenericCell()
    xs, fs = [], []
    step = max(1, grid.GetNumberOfCells() // max_cells)
    for c in range(0, grid.GetNumberOfCells(), step):
        grid.GetCell(c, cell)
        ids = [cell.GetPointId(i) for i in range(cell.GetNumberOfPoints())]
        for _ in range(per_cell):
            b = rng.dirichlet(np.ones(n + 1))
            x, w = [0.0, 0.0, 0.0], [0.0] * len(ids)
            cell.EvaluateLocation(reference(0), list(b[1:]) + [0.0] * (3 - n), x, w)
            xs.append(x[:n])
            fs.append(float(np.dot(w, F[ids])))
    return np.array(xs), np.array(fs)


def crossed_cells(grid, level):
    """The cells whose control values straddle the level (a Bézier/rational cell with weights > 0
    lies in the convex hull of its control values, so the others cannot meet the level)."""
    F = vtk_to_numpy(grid.GetPointData().GetArray("F"))
    conn = vtk_to_numpy(grid.GetCells().GetConnectivityArray())
    offsets = vtk_to_numpy(grid.GetCells().GetOffsetsArray())
    per = int(offsets[1] - offsets[0])
    fc = F[conn].reshape(-1, per)
    return np.nonzero((fc.min(axis=1) <= level) & (fc.max(axis=1) >= level))[0]


def pipeline_contour(reader, level, subdivisions, field_error):
    """reader → block "Volume" → cells the level may cross → vtkTessellatorFilter (field criterion
    on F) → vtkContourFilter of F at the level: a VTK-only pipeline."""
    grid = reader.GetOutputDataObject(0).GetBlock(1)
    ids = vtkIdList()
    for i in crossed_cells(grid, level):
        ids.InsertNextId(int(i))
    extract = vtkExtractCells()
    extract.SetInputData(grid)
    extract.SetCellList(ids)
    tess = vtkTessellatorFilter()
    tess.SetInputConnection(extract.GetOutputPort())
    tess.SetMaximumNumberOfSubdivisions(subdivisions)
    tess.SetChordError(1e-3)
    tess.SetFieldCriterion(0, field_error)
    tess.MergePointsOn()
    contour = vtkContourFilter()
    contour.SetInputConnection(tess.GetOutputPort())
    contour.SetInputArrayToProcess(0, 0, 0, 0, "F")  # association 0: point data
    contour.SetValue(0, level)
    contour.Update()
    return contour.GetOutput()


def to_polydata(positions, cells):
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray

    pd = vtkPolyData()
    pts = vtkPoints()
    for p in positions:
        pts.InsertNextPoint(*(list(p) + [0.0] * (3 - len(p))))
    pd.SetPoints(pts)
    ca = vtkCellArray()
    for c in cells:
        ca.InsertNextCell(len(c))
        for i in c:
            ca.InsertCellPoint(int(i))
    if len(cells) and len(cells[0]) == 2:
        pd.SetLines(ca)
    else:
        pd.SetPolys(ca)
    return pd


def segment_distances(points, a, b):
    """Distance of each 2D point to the nearest of the segments ``a[i]–b[i]`` (numpy, exact)."""
    ab = b - a
    t = np.einsum("pmk,mk->pm", points[:, None, :] - a[None], ab) / np.einsum("mk,mk->m", ab, ab)
    closest = a[None] + np.clip(t, 0.0, 1.0)[..., None] * ab[None]
    return np.min(np.linalg.norm(points[:, None, :] - closest, axis=2), axis=1)


def distances(points, surface):
    """Unsigned distance of each point to the cells of ``surface``: its segments (2D, numpy) or
    triangles (3D, VTK's implicit distance)."""
    if surface.GetNumberOfLines():
        p = points_of(surface)[:, :2]
        segs = []
        lines = surface.GetLines()
        lines.InitTraversal()
        ids = vtkIdList()
        while lines.GetNextCell(ids):
            chain = [ids.GetId(i) for i in range(ids.GetNumberOfIds())]
            segs += list(zip(chain[:-1], chain[1:]))
        segs = np.array(segs)
        return segment_distances(np.asarray(points)[:, :2], p[segs[:, 0]], p[segs[:, 1]])
    d = vtkImplicitPolyDataDistance()
    d.SetInput(surface)
    return np.array([abs(d.EvaluateFunction(list(p) + [0.0] * (3 - len(p)))) for p in points])


def points_of(data):
    return vtk_to_numpy(data.GetPoints().GetData()).astype(np.float64)


# --- blocks and arrays ---------------------------------------------------------------------------


@pytest.mark.parametrize("encoding", ENCODINGS)
@pytest.mark.parametrize("name", ["sphere", "circle-curved"])
def test_multiblock_structure_and_arrays(name, encoding):
    model = ism.read(EXAMPLES / (name + ".ismb"))
    r, errors, mb = read(EXAMPLES / (name + encoding), 2e-3)
    assert errors.messages == [] and r.last_error is None
    assert isinstance(mb, vtkMultiBlockDataSet) and mb.GetNumberOfBlocks() == 2
    assert [mb.GetMetaData(i).Get(vtkCompositeDataSet.NAME()) for i in range(2)] == ["Surface", "Volume"]
    surf, vol = mb.GetBlock(0), mb.GetBlock(1)
    assert isinstance(surf, vtkPolyData) and isinstance(vol, vtkUnstructuredGrid)

    # Surface: the library's extraction, with normals, F and ∇F at its points.
    s = model.extract_surface(2e-3)
    assert np.array_equal(points_of(surf)[:, : model.dimension], s.positions)
    assert {"Normals", "F", "Gradient"} <= arrays(surf.GetPointData())
    assert surf.GetPointData().GetNormals().GetName() == "Normals"
    assert arrays(surf.GetCellData()) == {"SourceSimplex"}
    normals = vtk_to_numpy(surf.GetPointData().GetNormals())
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    grad = vtk_to_numpy(surf.GetPointData().GetArray("Gradient"))[:, : model.dimension]
    # ∇F from the library's query where it evaluates the same simplex as the extraction (∇F jumps
    # across faces of these C⁰ models, so elsewhere the query's simplex may give another one).
    q = model.query(s.positions)
    same = q["simplex"] == s.vertex_simplex
    assert same.mean() > 0.5
    q_grad = np.column_stack([q[k] for k in ("gx", "gy", "gz")[: model.dimension]])
    assert np.allclose(grad[same], q_grad[same], rtol=1e-9, atol=1e-12)
    # The extraction's normals are single precision (as the mesh formats it writes): 1e-6.
    assert np.allclose(normals[:, : model.dimension], grad / np.linalg.norm(grad, axis=1)[:, None], atol=1e-6)
    f = vtk_to_numpy(surf.GetPointData().GetArray("F"))
    # On the extracted surface |F − c| / |∇F| (first-order distance) is within the tolerance.
    assert np.max(np.abs(f - model.level) / np.linalg.norm(grad, axis=1)) <= 2e-3
    if model.dimension == 3:
        assert surf.GetNumberOfPolys() == len(s.cells) and surf.GetNumberOfLines() == 0
    else:
        assert surf.GetNumberOfPolys() == 0
        assert surf.GetNumberOfLines() == len(s.polylines())
        assert sum(surf.GetCell(i).GetNumberOfPoints() - 1 for i in range(surf.GetNumberOfCells())) == len(s.cells)

    # Volume: Bézier cells (rational here: both examples have a degree-1 monotonic stage) with F.
    ctype = VTK_BEZIER_TETRAHEDRON if model.dimension == 3 else VTK_BEZIER_TRIANGLE
    assert {vol.GetCellType(i) for i in range(vol.GetNumberOfCells())} == {ctype}
    assert vol.GetNumberOfCells() == model.num_simplices
    assert {"F", "RationalWeights"} <= arrays(vol.GetPointData())
    assert vol.GetPointData().GetRationalWeights().GetName() == "RationalWeights"
    assert np.all(vtk_to_numpy(vol.GetPointData().GetRationalWeights()) > 0)
    degrees = vtk_to_numpy(vol.GetCellData().GetHigherOrderDegrees())
    assert degrees.shape == (model.num_simplices, 3) and np.all(degrees == 3)  # quadratic stage + 1
    assert np.array_equal(vtk_to_numpy(vol.GetCellData().GetArray("SourceSimplex")), np.arange(model.num_simplices))
    assert field(vol, "FieldRepresentation") == "exact" and field(vol, "FieldErrorBound") <= 1e-9
    for data in (surf, vol):
        assert field(data, "Level") == model.level and field(data, "ModelName") == name


def test_properties_tolerance_and_block_switches():
    r, _, mb = read(EXAMPLES / "sphere.ismb", 4e-3)
    coarse = mb.GetBlock(0).GetNumberOfPoints()
    r.SetTolerance(5e-4)
    r.Update()
    mb = r.GetOutputDataObject(0)
    assert mb.GetBlock(0).GetNumberOfPoints() > coarse  # a tighter tolerance refines the surface
    assert r.GetTolerance() == 5e-4 and r.GetFileName().endswith("sphere.ismb")
    r.SetReadVolume(False)
    r.Update()
    mb = r.GetOutputDataObject(0)
    assert mb.GetBlock(1) is None and mb.GetBlock(0) is not None
    r.SetReadVolume(True)
    r.SetReadSurface(False)
    r.Update()
    mb = r.GetOutputDataObject(0)
    assert mb.GetBlock(0) is None and mb.GetBlock(1).GetNumberOfCells() == 1296


# --- the volume field ----------------------------------------------------------------------------


@pytest.mark.parametrize("name", EXACT)
def test_exact_cells_interpolate_the_model_function(name):
    """VTK's own (rational) Bézier interpolation of the written cells equals the library's F at
    random points (VTK also gives the physical point, so the linear geometry is checked too)."""
    model = ism.read(EXAMPLES / (name + ".ismb"))
    _, errors, mb = read(EXAMPLES / (name + ".ismb"))
    vol = mb.GetBlock(1)
    assert errors.messages == []
    assert field(vol, "FieldRepresentation") == "exact"
    xs, fs = sample_cells(vol, model)
    q = model.query(xs)
    assert np.all(q["simplex"] >= 0)  # VTK's point lies in the complex
    assert np.max(np.abs(q["f"] - fs)) <= EXACT_AGREEMENT
    rational = vol.GetPointData().GetRationalWeights() is not None
    assert rational == any(s.kind in ("rational", "monotonic") for s in model.stages)


#: Models with parametric stages that the library writes exactly (parametric stages before
#: implicit ones), made from the examples by changing stage directions or order (each stored map
#: is a diffeomorphism either way, so each is a valid model): (example, stage order, directions).
LIBRARY_EXACT = {
    "sphere-all-parametric": ("sphere", [0, 1], ["parametric", "parametric"]),
    "rational-degree5-parametric": ("rational-degree5", [0], ["parametric"]),
    "circle-curved-parametric-then-implicit": ("circle-curved", [0, 1], ["parametric", "implicit"]),
    "two-stage-reversed": ("two-stage", [1, 0], ["parametric", "implicit"]),
    "monotonic-parametric": ("monotonic", [0], ["parametric"]),
}


@pytest.mark.parametrize("name", sorted(LIBRARY_EXACT))
def test_library_writes_parametric_chains_exactly(tmp_path, name):
    """Issue 19: parametric stages (every fitted model's) used to get a sampled estimate; the
    library now writes F itself — cells whose geometry is the model's parametrisation and whose
    field is F on it. VTK's own interpolation
    (``EvaluateLocation``: the physical point and the weights of the cell's (rational) basis)
    equals ``Model.query`` there, whose F inverts the parametric stages by Newton: an independent
    evaluation."""
    example, order, directions = LIBRARY_EXACT[name]
    doc = json.loads((EXAMPLES / (example + ".ism.json")).read_text())
    doc["stages"] = [dict(doc["stages"][i], direction=d) for i, d in zip(order, directions)]
    path = tmp_path / (name + ".ism.json")
    path.write_text(json.dumps(doc))
    model = ism.read(path)
    _, errors, mb = read(path)
    vol = mb.GetBlock(1)
    assert errors.messages == []
    assert field(vol, "FieldRepresentation") == "exact"
    assert field(vol, "FieldErrorCertified") == 1
    assert 0.0 <= field(vol, "FieldErrorBound") <= 1e-9
    assert "EXACT" in field(vol, "FieldNote")
    xs, fs = sample_cells(vol, model)
    q = model.query(xs)
    assert np.all(q["simplex"] >= 0)
    assert np.max(np.abs(q["f"] - fs)) <= EXACT_AGREEMENT
    rational = vol.GetPointData().GetRationalWeights() is not None
    assert rational == any(s.kind in ("rational", "monotonic") for s in model.stages)


@pytest.mark.parametrize("name", sorted(APPROXIMATE))
def test_approximate_cells_stay_within_the_reported_bound(name):
    """Compositions the library cannot write exactly get its interpolant; VTK's interpolation is
    within the bound the field data reports, everywhere."""
    model = ism.read(EXAMPLES / (name + ".ismb"))
    _, errors, mb = read(EXAMPLES / (name + ".ismb"))
    vol = mb.GetBlock(1)
    assert errors.messages == []
    assert field(vol, "FieldRepresentation") == "approximate"
    assert field(vol, "FieldErrorCertified") == int(APPROXIMATE[name])
    bound = field(vol, "FieldErrorBoundEverywhere")
    assert 0.0 < field(vol, "FieldErrorBound") <= bound
    note = field(vol, "FieldNote")
    assert ("ESTIMATED" in note) != APPROXIMATE[name], note
    assert ("certified: Bernstein bound" in note) == APPROXIMATE[name], note
    xs, fs = sample_cells(vol, model)
    err = np.max(np.abs(model.query(xs)["f"] - fs))
    assert 0.0 < err <= bound


# --- the VTK pipeline: tessellate and contour ----------------------------------------------------


def test_contour_of_the_linear_example_is_its_linear_isocomplex():
    """circle-linear has no stage: F is the linear interpolant, so VTK's contour of the volume
    block must be the polygon through the edge crossings, computed here from the values alone."""
    model = ism.read(EXAMPLES / "circle-linear.ismb")
    r, _, _ = read(EXAMPLES / "circle-linear.ismb")
    contour = pipeline_contour(r, model.level, 0, 1e-3)
    v, f = np.asarray(model.vertices), np.asarray(model.values) - model.level
    crossings, segments = {}, []
    for tri in np.asarray(model.simplices, dtype=np.int64):
        pts = []
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            if (f[a] < 0) != (f[b] < 0):
                key = (min(a, b), max(a, b))
                t = f[a] / (f[a] - f[b])
                crossings[key] = v[a] + t * (v[b] - v[a])
                pts.append(key)
        if pts:
            segments.append(pts)
    reference_pts = np.array(list(crossings.values()))
    index = {k: i for i, k in enumerate(crossings)}
    truth = to_polydata(reference_pts, [[index[a], index[b]] for a, b in segments])
    got = points_of(contour)[:, :2]
    assert len(got) >= len(reference_pts)
    # VTK's tessellator and contour filter make single-precision points: agreement to 1e-6
    # (coordinates are below 1; a wrong crossing would be off by a fraction of an edge, 0.25).
    assert np.max(distances(got, truth)) <= 1e-6
    assert np.max(distances(reference_pts, contour)) <= 1e-6


#: (example, tessellation levels, field criterion, tolerance of the two-sided distance). The
#: contour of VTK's *linear* tessellation is what limits agreement (the cells are exact, checked
#: above): the tolerance is VTK's tessellation error at those levels plus the reference surface's
#: own 1e-4, with about a factor 2 of margin over the distances measured when this was written
#: (sphere 4.9e-3, circle-curved 3.0e-4, two-stage 5.0e-4 as |F − c|/|∇F| at the contour points).
PIPELINE_CASES = [
    ("sphere", 2, 1e-3, 1e-2),
    ("circle-curved", 4, 1e-4, 1e-3),
    ("two-stage", 4, 1e-4, 1.5e-3),
]


@functools.lru_cache(maxsize=None)
def example_contour(name, levels, field_error):
    """The pipeline's contour of an example (cached: the sphere's takes a few seconds)."""
    model = ism.read(EXAMPLES / (name + ".ismb"))
    r, errors, _ = read(EXAMPLES / (name + ".ismb"))
    assert errors.messages == []
    return pipeline_contour(r, model.level, levels, field_error)


@pytest.mark.parametrize("name,levels,field_error,tolerance", PIPELINE_CASES)
def test_pipeline_contour_matches_the_extracted_surface(name, levels, field_error, tolerance):
    model = ism.read(EXAMPLES / (name + ".ismb"))
    contour = example_contour(name, levels, field_error)
    n = model.dimension
    got = points_of(contour)[:, :n]
    assert len(got) > 50
    reference_surface = model.extract_surface(1e-4)
    truth = to_polydata(reference_surface.positions, reference_surface.cells)
    forward = distances(got, truth)
    backward = distances(reference_surface.positions, contour)
    assert max(forward.max(), backward.max()) <= tolerance, (forward.max(), backward.max())
    # And independently of any extraction: the true F vanishes (to first order) at the contour.
    q = model.query(got)
    g = np.linalg.norm(np.column_stack([q[k] for k in ("gx", "gy", "gz")[:n]]), axis=1)
    assert np.max(np.abs(q["f"] - model.level) / g) <= tolerance


def test_sphere_contour_is_near_the_analytic_sphere():
    """The sphere example is |p|² − 0.7² with stages placing the shape on the sphere where it
    crosses the complex's edges (metadata); between edges the model's own shape deviates by up to
    the distance its extracted surface shows. VTK's contour stays within that band plus the
    pipeline tolerance of PIPELINE_CASES."""
    model = ism.read(EXAMPLES / "sphere.ismb")
    radius = np.linalg.norm(points_of(example_contour("sphere", 2, 1e-3)), axis=1)
    own = np.linalg.norm(model.extract_surface(1e-4).positions, axis=1)
    assert own.min() > 0.6 and own.max() < 0.71  # the model is a sphere of radius about 0.7
    assert own.min() - 1e-2 <= radius.min() and radius.max() <= own.max() + 1e-2


# --- bad input -----------------------------------------------------------------------------------


def _reader_vectors():
    return sorted(p for p in (VECTORS / "reader").iterdir() if p.name.split(".", 1)[-1] in ("ismb", "ism.json", "ism.msgpack"))


@pytest.mark.parametrize("path", _reader_vectors(), ids=lambda p: p.name)
def test_bad_file_is_a_vtk_error_not_a_crash(path):
    """Every reader vector: RequestData reports an error event naming the vector's rule, the
    output stays empty, and the same reader then reads a good file."""
    expect = json.loads(path.with_name(path.name.split(".")[0] + ".expect.json").read_text())
    r, errors, mb = read(path)
    assert len(errors.messages) == 1 and "ERROR" in errors.messages[0]
    assert expect["rule"] in errors.messages[0]
    assert r.last_error is not None and mb.GetNumberOfBlocks() == 0
    r.SetFileName(str(EXAMPLES / "circle-curved.ismb"))
    r.Update()
    assert r.GetOutputDataObject(0).GetNumberOfBlocks() == 2 and r.last_error is None


@pytest.mark.parametrize("what", ["missing", "directory", "garbage", "no-name", "bad-tolerance"])
def test_unreadable_inputs_are_vtk_errors(tmp_path, what):
    garbage = tmp_path / "x.ismb"
    garbage.write_bytes(b"\x00\x01 not an ism at all" * 10)
    path = {
        "missing": tmp_path / "nope.ismb",
        "directory": tmp_path,
        "garbage": garbage,
        "no-name": "",
        "bad-tolerance": EXAMPLES / "sphere.ismb",
    }[what]
    r, errors, mb = read(path, -1.0 if what == "bad-tolerance" else 1e-3)
    assert len(errors.messages) == 1 and r.last_error and mb.GetNumberOfBlocks() == 0


# --- the README's VTK pipeline script ------------------------------------------------------------


def test_vtk_pipeline_script_writes_files_vtk_reads_back(tmp_path):
    """paraview/vtk_pipeline.py (the README's VTK route): its .vtu keeps the rational Bézier
    cells and their weights through VTK's XML writer and reader, and its contour is non-empty."""
    import subprocess
    import sys

    from conftest import ROOT
    from vtkmodules.vtkIOXML import vtkXMLPolyDataReader, vtkXMLUnstructuredGridReader

    prefix = str(tmp_path / "sphere")
    done = subprocess.run(
        [sys.executable, str(ROOT / "paraview" / "vtk_pipeline.py"), str(EXAMPLES / "sphere.ismb"), prefix],
        capture_output=True, text=True, timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert "EXACT: one rational Bézier cell of degree 3" in done.stdout
    ug = vtkXMLUnstructuredGridReader()
    ug.SetFileName(prefix + "-volume.vtu")
    ug.Update()
    vol = ug.GetOutput()
    assert vol.GetNumberOfCells() == 1296 and vol.GetCellType(0) == VTK_BEZIER_TETRAHEDRON
    _, _, mb = read(EXAMPLES / "sphere.ismb")
    assert np.array_equal(
        vtk_to_numpy(vol.GetPointData().GetRationalWeights()),
        vtk_to_numpy(mb.GetBlock(1).GetPointData().GetRationalWeights()),
    )
    pd = vtkXMLPolyDataReader()
    pd.SetFileName(prefix + "-contour.vtp")
    pd.Update()
    assert pd.GetOutput().GetNumberOfPolys() > 1000
    bad = subprocess.run(
        [sys.executable, str(ROOT / "paraview" / "vtk_pipeline.py"), str(tmp_path / "missing.ismb"), prefix],
        capture_output=True, text=True, timeout=300,
    )
    assert bad.returncode == 1 and "cannot read" in bad.stderr


@pytest.mark.parametrize("dimension", [2, 3])
def test_model_without_shape_gives_an_empty_surface_and_its_volume(tmp_path, dimension):
    """All values above the level: no shape. The surface block is empty (not an error) and the
    volume still carries F (linear here: one degree-1 cell per simplex, F at the vertices)."""
    if dimension == 2:
        m = ism.Model(np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float), np.array([[0, 1, 2], [0, 2, 3]]), [1.0, 2, 3, 4], 0.0)
    else:
        m = ism.Model(np.eye(4, 3, -1), np.array([[0, 1, 2, 3]]), [1.0, 2, 3, 4], 0.0)
    m.write(tmp_path / "m.ismb")
    r, errors, mb = read(tmp_path / "m.ismb")
    assert errors.messages == [] and mb.GetNumberOfBlocks() == 2
    assert mb.GetBlock(0).GetNumberOfPoints() == 0 and mb.GetBlock(0).GetNumberOfCells() == 0
    vol = mb.GetBlock(1)
    assert vol.GetNumberOfCells() == m.num_simplices
    assert sorted(vtk_to_numpy(vol.GetPointData().GetArray("F"))) == [1.0, 2.0, 3.0, 4.0]
