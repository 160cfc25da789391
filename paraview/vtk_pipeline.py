"""From an ISM file to VTK data in a plain VTK pipeline (the ``vtk`` wheel, no ParaView).

    python paraview/vtk_pipeline.py spec/examples/sphere.ismb sphere

reads the model with ``ism.vtk_reader.ISMReader`` and writes, next to the given prefix:

- ``<prefix>-surface.vtp``: the curved surface (normals, F), as extracted by the library;
- ``<prefix>-volume.vtu``: the complex as (rational) Bézier cells carrying F;
- ``<prefix>-contour.vtp``: VTK's own contour of F at the level, after ``vtkTessellatorFilter``
  linearised the cells the level may cross.

Every file opens in ParaView (or any VTK ≥ 9.1 reader). ``python/tests/test_vtk_reader.py`` runs this
script.
"""

import sys

import numpy as np
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkCommonCore import vtkIdList
from vtkmodules.vtkFiltersCore import vtkContourFilter, vtkExtractCells
from vtkmodules.vtkFiltersGeneral import vtkTessellatorFilter
from vtkmodules.vtkIOXML import vtkXMLPolyDataWriter, vtkXMLUnstructuredGridWriter

from ism.vtk_reader import ISMReader


def main(path: str, prefix: str, tolerance: float = 1e-3) -> int:
    reader = ISMReader()
    reader.SetFileName(path)
    reader.SetTolerance(tolerance)
    reader.Update()
    if reader.last_error:
        return 1  # the reader has reported the error (VTK error output)
    blocks = reader.GetOutputDataObject(0)
    surface, volume = blocks.GetBlock(0), blocks.GetBlock(1)
    level = blocks.GetBlock(1).GetFieldData().GetArray("Level").GetValue(0)

    # Only cells whose control values straddle the level can hold the contour (convex hull).
    f = vtk_to_numpy(volume.GetPointData().GetArray("F"))
    conn = vtk_to_numpy(volume.GetCells().GetConnectivityArray())
    per_cell = int(volume.GetCells().GetOffsetsArray().GetValue(1))
    fc = f[conn].reshape(-1, per_cell)
    crossed = vtkIdList()
    for i in np.nonzero((fc.min(axis=1) <= level) & (fc.max(axis=1) >= level))[0]:
        crossed.InsertNextId(int(i))
    cells = vtkExtractCells()
    cells.SetInputData(volume)
    cells.SetCellList(crossed)
    tessellate = vtkTessellatorFilter()
    tessellate.SetInputConnection(cells.GetOutputPort())
    tessellate.SetMaximumNumberOfSubdivisions(2)
    tessellate.SetFieldCriterion(0, 1e-3)  # subdivide where F is not yet linear to 1e-3
    contour = vtkContourFilter()
    contour.SetInputConnection(tessellate.GetOutputPort())
    contour.SetInputArrayToProcess(0, 0, 0, 0, "F")  # point data F
    contour.SetValue(0, level)
    contour.Update()

    for data, suffix, writer in (
        (surface, "-surface.vtp", vtkXMLPolyDataWriter()),
        (volume, "-volume.vtu", vtkXMLUnstructuredGridWriter()),
        (contour.GetOutput(), "-contour.vtp", vtkXMLPolyDataWriter()),
    ):
        writer.SetFileName(prefix + suffix)
        writer.SetInputData(data)
        if not writer.Write():
            return 1
        print(f"{prefix + suffix}: {data.GetNumberOfPoints()} points, {data.GetNumberOfCells()} cells")
    print(volume.GetFieldData().GetAbstractArray("FieldNote").GetValue(0))
    return 0


if __name__ == "__main__":
    if len(sys.argv) not in (3, 4):
        sys.exit(__doc__)
    sys.exit(main(sys.argv[1], sys.argv[2], *(float(a) for a in sys.argv[3:])))
