"""Runs in ParaView's ``pvpython`` (under ``xvfb-run``): loads the ISM reader plugin, opens a model,
checks what ParaView got, renders it and saves a screenshot checked to be non-empty.

    PYTHONPATH=<dir with the ism package> xvfb-run -a pvpython paraview/test_paraview.py \\
        paraview/ism_reader_plugin.py spec/examples/torus.ismb out.png

(``tools/test_paraview.sh`` does that; ``.ci/run`` runs it.) Exits non-zero on any failed check.
"""

import sys

from paraview import servermanager
from paraview.simple import (
    Clip,
    Contour,
    Delete,
    ColorBy,
    ExtractBlock,
    GetActiveViewOrCreate,
    GetColorTransferFunction,
    LoadPlugin,
    OpenDataFile,
    ResetSession,
    SaveScreenshot,
    Show,
    Slice,
)
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkCommonDataModel import VTK_BEZIER_TETRAHEDRON, vtkCompositeDataSet
from vtkmodules.vtkIOImage import vtkPNGReader


def check(condition, message):
    if not condition:
        print("FAILED:", message)
        sys.exit(1)
    print("ok:", message)


plugin, path, png = sys.argv[1:4]
LoadPlugin(plugin, ns=globals())
reader = OpenDataFile(path)  # ParaView picks the reader by the file's extension
check(reader is not None and reader.GetXMLName() == "ISMReader", f"ParaView opens {path} with the ISM reader")
reader.Tolerance = 2e-3
reader.UpdatePipeline()

# What the server-side reader produced, fetched to the client.
mb = servermanager.Fetch(reader)
names = [mb.GetMetaData(i).Get(vtkCompositeDataSet.NAME()) for i in range(mb.GetNumberOfBlocks())]
check(names == ["Surface", "Volume"], f"blocks {names}")
surface, volume = mb.GetBlock(0), mb.GetBlock(1)
check(surface.GetNumberOfPolys() > 1000, f"surface: {surface.GetNumberOfPolys()} triangles")
check(surface.GetPointData().GetNormals() is not None, "surface has normals")
cell_types = {volume.GetCellType(i) for i in range(volume.GetNumberOfCells())}
check(cell_types == {VTK_BEZIER_TETRAHEDRON}, f"volume: {volume.GetNumberOfCells()} Bézier tetrahedra")
check(volume.GetPointData().GetRationalWeights() is not None, "volume has rational weights")
check(volume.GetPointData().GetArray("F") is not None, "volume carries F")
print("field:", volume.GetFieldData().GetAbstractArray("FieldNote").GetValue(0))

# A bad file: ParaView reports the reader's error and carries on with an empty output.
import os  # noqa: E402
import tempfile  # noqa: E402

with tempfile.TemporaryDirectory() as tmp:
    bad_path = os.path.join(tmp, "bad.ismb")
    with open(bad_path, "wb") as f:
        f.write(b"not an ISM file" * 4)
    bad = OpenDataFile(bad_path)
    check(bad is not None and bad.GetXMLName() == "ISMReader", "a bad .ismb is still given to the ISM reader")
    bad.UpdatePipeline()  # prints the reader's VTK error; must not raise or crash
    bad_mb = servermanager.Fetch(bad)
    check(bad_mb.GetNumberOfBlocks() == 0, "the bad file gives an empty output")
    Delete(bad)

# Render: the back half of the surface (y > 0; ParaView's Clip of the polydata) in a plain colour,
# and the slice y = 0 of the volume coloured by F (ParaView linearises the Bézier cells to slice):
# F < c inside the shape's cross-sections, F > c outside.
view = GetActiveViewOrCreate("RenderView")
view.ViewSize = [900, 600]
view.OrientationAxesVisibility = 0
if hasattr(view, "UseColorPaletteForBackground"):
    view.UseColorPaletteForBackground = 0
view.Background = [1.0, 1.0, 1.0]
surf = ExtractBlock(Input=reader, Selectors=["/Root/Surface"])
half = Clip(Input=surf)
half.ClipType.Normal = [0.0, 1.0, 0.0]
half.Invert = 0
surf_display = Show(half, view)
ColorBy(surf_display, None)
surf_display.DiffuseColor = [0.85, 0.75, 0.45]
surf_display.Specular = 0.3
vol = ExtractBlock(Input=reader, Selectors=["/Root/Volume"])
cut = Slice(Input=vol)
cut.SliceType.Normal = [0.0, 1.0, 0.0]
cut_display = Show(cut, view)
ColorBy(cut_display, ("POINTS", "F"))
cut_display.RescaleTransferFunctionToDataRange(True)
GetColorTransferFunction("F").ApplyPreset("Cool to Warm", True)
# The level set of the volume's F on the slice (black): it meets the clipped surface's rim.
rim = Contour(Input=cut, ContourBy=["POINTS", "F"], Isosurfaces=[0.0])
rim_display = Show(rim, view)
ColorBy(rim_display, None)
rim_display.AmbientColor = rim_display.DiffuseColor = [0.0, 0.0, 0.0]
rim_display.LineWidth = 3.0
view.CameraPosition = [0.6, -2.2, 3.0]
view.CameraFocalPoint = [0.0, 0.0, 0.0]
view.CameraViewUp = [0.0, 0.0, 1.0]
view.ResetCamera()
SaveScreenshot(png, view, ImageResolution=[900, 600])

# The picture is not empty: many distinct colours, pixel variance well above a blank frame's 0.
image = vtkPNGReader()
image.SetFileName(png)
image.Update()
pixels = vtk_to_numpy(image.GetOutput().GetPointData().GetScalars()).astype(float)
dims = image.GetOutput().GetDimensions()
check(dims[0] == 900 and dims[1] == 600, f"screenshot {dims[0]}×{dims[1]}")
background = pixels[0]
covered = (abs(pixels[:, :3] - background[:3]).sum(axis=1) > 30).mean()
colours = len({tuple(p) for p in pixels[:, :3].astype(int)[::7]})
check(pixels[:, :3].var() > 100.0, f"pixel variance {pixels[:, :3].var():.0f}")
check(0.1 < covered < 0.95, f"object covers {covered:.0%} of the frame")
check(colours > 200, f"{colours} distinct colours")
ResetSession()
print("paraview test passed:", png)
