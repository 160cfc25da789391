"""A VTK reader of Iso-Simplicial Models: ``ism.vtk_reader.ISMReader``.

A ``VTKPythonAlgorithmBase`` source, usable in a plain VTK pipeline (the ``vtk`` wheel) and, through
the decorated subclass in ``paraview/ism_reader_plugin.py``, as a ParaView reader::

    from ism.vtk_reader import ISMReader
    r = ISMReader()
    r.SetFileName("spec/examples/sphere.ismb")      # .ism.json, .ismb, .ismc, .ismz, .isms or .ism.msgpack
    r.SetTolerance(1e-3)
    r.Update()
    mb = r.GetOutputDataObject(0)                   # vtkMultiBlockDataSet

The output is a ``vtkMultiBlockDataSet`` of two blocks (block names in the metadata key
``vtkCompositeDataSet.NAME()``):

0. ``"Surface"`` — ``vtkPolyData``: the curved shape ``F = c`` extracted at ``Tolerance`` by the
   library (``Model.extract_surface``, what ``ism export`` writes): triangles (3D) or polylines
   (2D models, ``z = 0``), point data ``Normals`` (∇F/|∇F|, set as the normals), ``F``
   (``Model.query`` at the points) and ``Gradient`` (∇F in the simplex the point was extracted
   from), cell data ``SourceSimplex``.
1. ``"Volume"`` — ``vtkUnstructuredGrid`` of VTK Bézier cells (``VTK_BEZIER_TRIANGLE`` in 2D,
   ``VTK_BEZIER_TETRAHEDRON`` in 3D, degrees in the cell data ``HigherOrderDegrees``, weights in
   the point data ``RationalWeights`` when the cells are rational) carrying ``F`` as point data
   and ``SourceSimplex`` as cell data; contouring ``F`` at the level gives the shape. How the
   field relates to the model's ``F`` is in the field data (see :func:`volume_grid`):
   ``FieldRepresentation`` (``"exact"`` or ``"approximate"``), ``FieldErrorBound`` (largest
   ``|F_vtk − F|`` over the cells the level may cross; rounding only when exact), ``FieldErrorCertified``
   (1: a conservative bound, 0: an estimate) and ``FieldNote``.

Both blocks also carry the field data ``Level`` (the model's ``c``) and ``ModelName``.

A file that cannot be read (missing, not an ISM, structurally invalid) makes ``RequestData``
report a VTK error (the ``ErrorEvent`` of the reader, else the output window, as
``vtkErrorMacro`` does) and return 0: the pipeline's ``Update()`` fails and the output is empty —
nothing is raised into the caller and nothing crashes.
"""

from __future__ import annotations

import os
import tempfile
from typing import Any, List, Optional, Tuple

import numpy as np
from vtkmodules.util import numpy_support
from vtkmodules.util.vtkAlgorithm import VTKPythonAlgorithmBase
from vtkmodules.vtkCommonCore import (
    vtkCommand,
    vtkDoubleArray,
    vtkIntArray,
    vtkOutputWindow,
    vtkPoints,
    vtkStringArray,
)
from vtkmodules.vtkCommonDataModel import (
    vtkCellArray,
    vtkCompositeDataSet,
    vtkMultiBlockDataSet,
    vtkPolyData,
    vtkUnstructuredGrid,
)
from vtkmodules.vtkIOXML import vtkXMLUnstructuredGridReader

import ism

#: Surface tolerance used when none is set (the CLI's ``ism export`` default).
DEFAULT_TOLERANCE = 1e-3

SURFACE_BLOCK = 0
VOLUME_BLOCK = 1


def _array(values: np.ndarray, name: str) -> Any:
    a = numpy_support.numpy_to_vtk(np.ascontiguousarray(values), deep=True)
    a.SetName(name)
    return a


def _string_field(data: Any, name: str, text: str) -> None:
    s = vtkStringArray()
    s.SetName(name)
    s.InsertNextValue(text)
    data.GetFieldData().AddArray(s)


def _double_field(data: Any, name: str, value: float) -> None:
    a = vtkDoubleArray()
    a.SetName(name)
    a.InsertNextValue(float(value))
    data.GetFieldData().AddArray(a)


def _int_field(data: Any, name: str, value: int) -> None:
    a = vtkIntArray()
    a.SetName(name)
    a.InsertNextValue(int(value))
    data.GetFieldData().AddArray(a)


def _cells(connectivity: np.ndarray) -> vtkCellArray:
    """A ``vtkCellArray`` of equal-size cells from an (N, k) index array."""
    conn = np.ascontiguousarray(connectivity, dtype=np.int64)
    offsets = np.arange(0, conn.size + 1, conn.shape[1] if conn.ndim == 2 else 1, dtype=np.int64)
    ca = vtkCellArray()
    ca.SetData(
        numpy_support.numpy_to_vtkIdTypeArray(offsets, deep=True),
        numpy_support.numpy_to_vtkIdTypeArray(conn.ravel(), deep=True),
    )
    return ca


def _xyz(positions: np.ndarray) -> np.ndarray:
    p = np.asarray(positions, dtype=np.float64)
    if p.shape[1] == 3:
        return p
    return np.column_stack([p, np.zeros((len(p), 3 - p.shape[1]))])


def surface_polydata(model: Any, tolerance: float) -> vtkPolyData:
    """The curved shape at ``tolerance`` (``Model.extract_surface``) as ``vtkPolyData``: triangles
    (3D) or polylines (2D, ``z = 0``), point data ``Normals``, ``F``, ``Gradient``, cell data
    ``SourceSimplex`` (per triangle; per polyline, the simplex of its first segment)."""
    s = model.extract_surface(tolerance)
    pd = vtkPolyData()
    pts = vtkPoints()
    pts.SetData(_array(_xyz(s.positions), "Points"))
    pd.SetPoints(pts)
    if s.dimension == 3:
        pd.SetPolys(_cells(s.cells))
        cell_simplex = np.asarray(s.cell_simplex, dtype=np.int64)
    else:
        lines = s.polylines()
        ca = vtkCellArray()
        first_segment = {int(a): i for i, (a, _) in enumerate(s.cells)}
        cell_simplex_l: List[int] = []
        for line in lines:
            ca.InsertNextCell(len(line))
            for v in line:
                ca.InsertCellPoint(int(v))
            cell_simplex_l.append(int(s.cell_simplex[first_segment[int(line[0])]]))
        pd.SetLines(ca)
        cell_simplex = np.array(cell_simplex_l, dtype=np.int64)
    normals = _array(_xyz(s.normals), "Normals")
    pd.GetPointData().SetNormals(normals)
    # F is continuous, so the library's query gives it at the points whichever simplex it picks;
    # ∇F may jump across faces (C⁰ models), so it is the extraction's own: normal × |∇F| in the
    # simplex the point was extracted from.
    f = np.asarray(model.query(s.positions)["f"], dtype=np.float64) if len(s.positions) else np.zeros(0)
    grad = np.asarray(s.normals) * np.asarray(s.gradient_norm, dtype=np.float64)[:, None]
    pd.GetPointData().AddArray(_array(f, "F"))
    pd.GetPointData().AddArray(_array(_xyz(grad), "Gradient"))
    pd.GetPointData().SetActiveScalars("F")
    pd.GetCellData().AddArray(_array(cell_simplex, "SourceSimplex"))
    _double_field(pd, "Tolerance", tolerance)
    for key in ("euler_characteristic", "components", "enclosed_measure"):
        if key in s.report and isinstance(s.report[key], (int, float)):
            _double_field(pd, "".join(w.title() for w in key.split("_")), s.report[key])
    return pd


def volume_grid(model: Any, tolerance: float) -> vtkUnstructuredGrid:
    """The complex with ``F`` as VTK Bézier cells, written by the library (:func:`library_bezier_grid`:
    exact cells wherever the stages allow them, else an interpolant with its bound). The cell data
    ``HigherOrderDegrees`` gives every cell's degree."""
    grid = library_bezier_grid(model, tolerance)
    degree = int(grid.GetFieldData().GetArray("Degree").GetValue(0))
    grid.GetCellData().SetHigherOrderDegrees(
        _array(np.full((grid.GetNumberOfCells(), 3), degree, dtype=np.int32), "HigherOrderDegrees")
    )
    grid.GetPointData().SetActiveScalars("F")
    return grid


def library_bezier_grid(model: Any, tolerance: float) -> vtkUnstructuredGrid:
    """The complex with ``F`` as the library's VTK Bézier cells (``ism export --volume``,
    ``ism_export::volume``, reached through ``Model.export(volume=True)``).

    Wherever the stages allow it — parametric stages (if any) before implicit ones, composed degree
    at most 12: every example but ``two-stage`` and ``stratified-3d``, every fitted model — the
    cells are *exact*: (rational) Bézier cells whose geometry is the model's own parametrisation
    and whose field is ``F`` on it (``FieldRepresentation = "exact"``, the bound covers rounding).
    Otherwise each simplex, red-refined ``k`` times, carries the degree-``p`` polynomial
    interpolant of ``F`` on linear geometry, with ``(p, k)`` chosen so the bound on ``|F_vtk − F|``
    meets ``tolerance · median |∇F|`` (the library's default field tolerance; contouring then
    moves the surface by about ``tolerance``): certified for all-implicit models of composed degree
    at most 24 (above 12 only on models small enough for their exact forms; ``stratified-3d``'s is
    24), a dense-sample estimate otherwise (``FieldErrorCertified = 0``). The field data says what was written:
    ``FieldErrorBound`` (on the cells the level may cross), ``FieldErrorBoundEverywhere``,
    ``FieldErrorCertified``, ``FieldTolerance``, ``Degree``, ``RefinementLevels``, ``FieldNote``.
    """
    with tempfile.TemporaryDirectory(prefix="ism-vtk-") as d:
        path = os.path.join(d, "volume.vtu")
        summary = model.export(path, tolerance=tolerance, volume=True)
        reader = vtkXMLUnstructuredGridReader()
        reader.SetFileName(path)
        reader.Update()
        grid = vtkUnstructuredGrid()
        grid.DeepCopy(reader.GetOutput())
    _string_field(grid, "FieldRepresentation", "exact" if summary["field_exact"] else "approximate")
    _double_field(grid, "FieldErrorBound", summary["field_error_bound"])
    _double_field(grid, "FieldErrorBoundEverywhere", summary["field_error_bound_everywhere"])
    _int_field(grid, "FieldErrorCertified", bool(summary["field_error_certified"]))
    _double_field(grid, "FieldTolerance", summary["field_tolerance"])
    _int_field(grid, "Degree", summary["degree"])
    _int_field(grid, "RefinementLevels", summary["refinement_levels"])
    _string_field(grid, "FieldNote", str(summary["field_note"]))
    return grid


def read_multiblock(path: str, tolerance: float = DEFAULT_TOLERANCE, *, surface: bool = True, volume: bool = True) -> vtkMultiBlockDataSet:
    """Reads ``path`` into the reader's multiblock (raises ``ism.ISMError`` for a bad file)."""
    model = ism.read(path)
    mb = vtkMultiBlockDataSet()
    mb.SetNumberOfBlocks(2)
    blocks: List[Tuple[int, str, Optional[Any]]] = [
        (SURFACE_BLOCK, "Surface", surface_polydata(model, tolerance) if surface else None),
        (VOLUME_BLOCK, "Volume", volume_grid(model, tolerance) if volume else None),
    ]
    name = model.metadata.get("name", os.path.basename(path))
    for index, label, data in blocks:
        mb.GetMetaData(index).Set(vtkCompositeDataSet.NAME(), label)
        if data is not None:
            _double_field(data, "Level", model.level)
            _string_field(data, "ModelName", name)
            mb.SetBlock(index, data)
    return mb


class ISMReader(VTKPythonAlgorithmBase):
    """VTK source reading an ``.ism.json`` / ``.ismb`` / ``.ismc`` / ``.ismz`` / ``.isms`` / ``.ism.msgpack`` file (see the module
    docstring for the output). Properties: ``FileName``, ``Tolerance`` (surface tolerance, model
    units), ``ReadSurface`` and ``ReadVolume`` (both on by default)."""

    def __init__(self) -> None:
        VTKPythonAlgorithmBase.__init__(self, nInputPorts=0, nOutputPorts=1, outputType="vtkMultiBlockDataSet")
        self._file_name: Optional[str] = None
        self._tolerance = DEFAULT_TOLERANCE
        self._read_surface = True
        self._read_volume = True
        #: The last error message (``None`` after a successful read); also reported as a VTK error.
        self.last_error: Optional[str] = None

    # Properties (each setter marks the algorithm modified only on a change, as vtkSetMacro does).
    def SetFileName(self, name: Optional[str]) -> None:
        name = None if name is None else os.fspath(name)
        if name != self._file_name:
            self._file_name = name
            self.Modified()

    def GetFileName(self) -> Optional[str]:
        return self._file_name

    def SetTolerance(self, tolerance: float) -> None:
        if float(tolerance) != self._tolerance:
            self._tolerance = float(tolerance)
            self.Modified()

    def GetTolerance(self) -> float:
        return self._tolerance

    def SetReadSurface(self, on: bool) -> None:
        if bool(on) != self._read_surface:
            self._read_surface = bool(on)
            self.Modified()

    def GetReadSurface(self) -> bool:
        return self._read_surface

    def SetReadVolume(self, on: bool) -> None:
        if bool(on) != self._read_volume:
            self._read_volume = bool(on)
            self.Modified()

    def GetReadVolume(self) -> bool:
        return self._read_volume

    def _error(self, message: str) -> None:
        """Reports an error as ``vtkErrorMacro`` does: to the ``ErrorEvent`` observers when there
        are any, else to the output window."""
        self.last_error = message
        text = f"ERROR: In {__file__}\n{type(self).__name__} ({self.GetClassName()}): {message}\n"
        if self.HasObserver(vtkCommand.ErrorEvent):
            self.InvokeEvent(vtkCommand.ErrorEvent, text)
        else:
            vtkOutputWindow.GetInstance().DisplayErrorText(text)

    def RequestData(self, request: Any, inInfo: Any, outInfo: Any) -> int:
        output = vtkMultiBlockDataSet.GetData(outInfo, 0)
        self.last_error = None
        if not self._file_name:
            self._error("no file name set (SetFileName)")
            return 0
        if not (self._tolerance > 0.0):
            self._error(f"Tolerance must be positive, got {self._tolerance}")
            return 0
        try:
            mb = read_multiblock(
                self._file_name, self._tolerance, surface=self._read_surface, volume=self._read_volume
            )
        except (ism.ISMError, OSError, ValueError) as e:
            self._error(f"cannot read {self._file_name}: {type(e).__name__}: {e}")
            return 0
        output.ShallowCopy(mb)
        return 1

