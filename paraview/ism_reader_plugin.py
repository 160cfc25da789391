"""ParaView plugin: a reader of Iso-Simplicial Models (``.ism.json``, ``.ismb``, ``.ismc``, ``.ismz``, ``.isms``, ``.ism.msgpack``).

Load it in ParaView (Tools > Manage Plugins > Load New, or ``LoadPlugin(path, ns=globals())`` in
``pvpython``); the ``ism`` Python package must be importable by ParaView's Python (see
``paraview/README.md``). Opening a file gives the multiblock of ``ism.vtk_reader.ISMReader``: the
curved surface (polydata with normals and F) and the volume as VTK Bézier cells carrying F.
"""

import inspect

# ParaView 5.11's decorators call inspect.getargspec, removed in Python 3.11; the full spec is a
# superset with the same first fields, which is all they read.
if not hasattr(inspect, "getargspec"):
    inspect.getargspec = inspect.getfullargspec  # type: ignore[attr-defined]

from paraview.util.vtkAlgorithm import smdomain, smhint, smproperty, smproxy  # noqa: E402

from ism.vtk_reader import DEFAULT_TOLERANCE  # noqa: E402
from ism.vtk_reader import ISMReader as _ISMReader  # noqa: E402

_EXTENSIONS = "ism.json ismb ismc ismz isms ism.msgpack"
_DESCRIPTION = "Iso-Simplicial Model files"


@smproxy.reader(name="ISMReader", label="ISM Reader", extensions=_EXTENSIONS, file_description=_DESCRIPTION)
class ISMReader(_ISMReader):
    """The ``ism.vtk_reader.ISMReader`` with ParaView's server-manager properties."""

    def __init__(self):
        _ISMReader.__init__(self)

    @smproperty.stringvector(name="FileName")
    @smdomain.filelist()
    @smhint.filechooser(extensions=_EXTENSIONS, file_description=_DESCRIPTION)
    def SetFileName(self, name):
        _ISMReader.SetFileName(self, name)

    @smproperty.doublevector(name="Tolerance", default_values=DEFAULT_TOLERANCE)
    @smdomain.doublerange(min=1e-6, max=0.1)
    def SetTolerance(self, tolerance):
        _ISMReader.SetTolerance(self, tolerance)

    @smproperty.xml(
        """<IntVectorProperty name="ReadSurface" command="SetReadSurface" number_of_elements="1"
             default_values="1"><BooleanDomain name="bool"/>
             <Documentation>Extract the curved surface F = c at Tolerance (block "Surface").</Documentation>
           </IntVectorProperty>"""
    )
    def SetReadSurface(self, on):
        _ISMReader.SetReadSurface(self, on)

    @smproperty.xml(
        """<IntVectorProperty name="ReadVolume" command="SetReadVolume" number_of_elements="1"
             default_values="1"><BooleanDomain name="bool"/>
             <Documentation>Write the complex with F as VTK Bezier cells (block "Volume").</Documentation>
           </IntVectorProperty>"""
    )
    def SetReadVolume(self, on):
        _ISMReader.SetReadVolume(self, on)
