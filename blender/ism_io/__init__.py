"""Blender extension: File > Import / Export > Iso-Simplicial Model (.ism.json, .ismb, .ismc, .ismz, .isms, .ism.msgpack).

A thin layer over the ``ism`` Python package (bundled as a wheel in the extension zip): reading,
validation, surface extraction and fitting are the package's; this add-on turns its arrays into
Blender objects and Blender meshes into its arrays. Errors of the package (``ism.ISMError`` and
subclasses, each with its rule id and location) are shown as the operator's report.
"""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty
from bpy_extras.io_utils import ExportHelper, ImportHelper

from . import exporter, importer

EXTENSIONS = (".ism.json", ".ismb", ".ismc", ".ismz", ".isms", ".ism.msgpack")
FILTER_GLOB = ";".join("*" + e for e in EXTENSIONS)
ENCODING_EXT = {
    "binary": ".ismb",
    "compact": ".ismc",
    "compressed": ".ismz",
    "structured": ".isms",
    "json": ".ism.json",
    "msgpack": ".ism.msgpack",
}


def _package_errors() -> tuple:
    """The exceptions a call into the package may raise for bad input (reported, not re-raised)."""
    import ism

    return (ism.ISMError, OSError, ValueError)


class ISM_OT_import(bpy.types.Operator, ImportHelper):
    """Import an Iso-Simplicial Model: its curved surface (2D: curve) at a chosen tolerance"""

    bl_idname = "import_scene.ism"
    bl_label = "Import ISM"
    bl_options = {"REGISTER", "UNDO", "PRESET"}

    filename_ext = ".ismb"
    filter_glob: StringProperty(default=FILTER_GLOB, options={"HIDDEN"})  # type: ignore[valid-type]

    tolerance: FloatProperty(  # type: ignore[valid-type]
        name="Tolerance",
        description="Largest distance between the triangle mesh and the curved surface (model units)",
        default=1e-3,
        min=1e-7,
        soft_max=0.1,
        precision=6,
    )
    max_depth: IntProperty(  # type: ignore[valid-type]
        name="Max Depth",
        description=(
            "Subdivision levels after which an edge is subdivided further only while it is still "
            "long in space (ism export --max-depth; 0: the linear patches' corners only)"
        ),
        default=8,
        min=0,
        max=16,
    )
    validate: BoolProperty(  # type: ignore[valid-type]
        name="Validate",
        description="Run the ISM validator and store its verdict as custom properties",
        default=True,
    )
    wireframe: BoolProperty(  # type: ignore[valid-type]
        name="Complex as Wireframe",
        description="Also add the simplicial complex's edges as a wireframe object",
        default=False,
    )
    control_points: BoolProperty(  # type: ignore[valid-type]
        name="Control Points",
        description="Also add the stages' stored control points as a point cloud (vertex-only mesh)",
        default=False,
    )

    def execute(self, context):  # noqa: D102 - Blender operator protocol
        opts = importer.ImportOptions(
            tolerance=self.tolerance,
            max_depth=self.max_depth,
            validate=self.validate,
            wireframe=self.wireframe,
            control_points=self.control_points,
        )
        try:
            errors = _package_errors()
        except ImportError as e:
            self.report({"ERROR"}, f"the ism package is not installed in Blender's Python: {e}")
            return {"CANCELLED"}
        try:
            result = importer.import_file(context, self.filepath, opts)
        except errors as e:
            self.report({"ERROR"}, f"Cannot import {self.filepath}: {importer.summary_of_error(e)}")
            return {"CANCELLED"}
        level = {"WARNING"} if result.verdict not in (None, "valid") else {"INFO"}
        self.report(level, result.summary)
        return {"FINISHED"}


class ISM_OT_export(bpy.types.Operator, ExportHelper):
    """Fit the selected closed meshes with an Iso-Simplicial Model and write it"""

    bl_idname = "export_scene.ism"
    bl_label = "Export ISM"
    bl_options = {"PRESET"}

    filename_ext = ".ismb"
    filter_glob: StringProperty(default=FILTER_GLOB, options={"HIDDEN"})  # type: ignore[valid-type]

    encoding: EnumProperty(  # type: ignore[valid-type]
        name="Encoding",
        items=(
            ("binary", "Binary (.ismb)", "Binary encoding, fixed-width integers"),
            ("compact", "Compact binary (.ismc)", "Binary encoding with variable-length integers"),
            ("compressed", "Compressed (.ismz)", "Compact binary compressed with xz: the smallest file, slower to write"),
            ("structured", "Structured (.isms)", "Compact binary with face records given by the complex: the smallest uncompressed file"),
            ("json", "JSON (.ism.json)", "Human-readable JSON encoding"),
            ("msgpack", "MessagePack (.ism.msgpack)", "MessagePack encoding"),
        ),
        default="binary",
    )
    resolution: IntProperty(  # type: ignore[valid-type]
        name="Resolution",
        description="Lattice cells along the longest side of the domain",
        default=8,
        min=1,
        max=256,
    )
    tolerance: FloatProperty(  # type: ignore[valid-type]
        name="Tolerance",
        description="Largest allowed distance from the fitted surface to the mesh (0: the fitter's default)",
        default=0.0,
        min=0.0,
        precision=6,
    )
    margin: FloatProperty(  # type: ignore[valid-type]
        name="Margin",
        description="Space around the mesh's bounding box, relative to its size",
        default=0.05,
        min=0.0,
        max=1.0,
    )
    max_simplices: IntProperty(  # type: ignore[valid-type]
        name="Max Simplices",
        description="Refinement stops at this many simplices",
        default=200000,
        min=1,
    )
    optimize: BoolProperty(name="Optimize", description="Optimise the control points", default=True)  # type: ignore[valid-type]
    rational: BoolProperty(name="Rational", description="Fit rational stages (weights)", default=False)  # type: ignore[valid-type]
    topology: BoolProperty(  # type: ignore[valid-type]
        name="Keep Topology",
        description="Refine until the fitted surface has the mesh's topology",
        default=True,
    )

    def check(self, context):  # noqa: D102 - keeps the file name's extension that of the encoding
        import os

        ext = ENCODING_EXT[self.encoding]
        path = self.filepath
        base = os.path.basename(path)
        for e in EXTENSIONS:
            if base.lower().endswith(e):
                path = path[: -len(e)]
                break
        new = path + ext
        if new != self.filepath:
            self.filepath = new
            return True
        return False

    def execute(self, context):  # noqa: D102 - Blender operator protocol
        self.check(context)
        opts = exporter.ExportOptions(
            resolution=self.resolution,
            tolerance=self.tolerance,
            margin=self.margin,
            max_simplices=self.max_simplices,
            optimize=self.optimize,
            rational=self.rational,
            topology=self.topology,
            encoding=self.encoding,
        )
        try:
            errors = _package_errors()
        except ImportError as e:
            self.report({"ERROR"}, f"the ism package is not installed in Blender's Python: {e}")
            return {"CANCELLED"}
        depsgraph = context.evaluated_depsgraph_get()
        try:
            rep = exporter.export_objects(list(context.selected_objects), depsgraph, self.filepath, opts)
        except exporter.MeshRefused as e:
            self.report({"ERROR"}, f"Export refused: {e}")
            return {"CANCELLED"}
        except errors as e:
            self.report({"ERROR"}, f"Export failed: {importer.summary_of_error(e)}")
            return {"CANCELLED"}
        for note in rep["notes"]:
            self.report({"INFO"}, note)
        met = bool(rep.get("toleranceMet"))
        msg = (
            f"Wrote {self.filepath}: {rep['simplices']} simplices, largest distance to the mesh "
            f"{rep['maxDistance']:.3g}, tolerance {'met' if met else 'NOT met'}, validator: {rep['verdict']}"
        )
        self.report({"INFO"} if met else {"WARNING"}, msg)
        return {"FINISHED"}


class ISM_FH_import(bpy.types.FileHandler):
    """Drag and drop of .ism.json / .ismb / .ismc / .ismz / .isms / .ism.msgpack files onto the viewport."""

    bl_idname = "ISM_FH_import"
    bl_label = "Iso-Simplicial Model"
    bl_import_operator = "import_scene.ism"
    bl_export_operator = "export_scene.ism"
    bl_file_extensions = ";".join(EXTENSIONS)

    @classmethod
    def poll_drop(cls, context):  # noqa: D102
        return context.area is not None and context.area.type == "VIEW_3D"


def _menu_import(self, context):
    self.layout.operator(ISM_OT_import.bl_idname, text="Iso-Simplicial Model (.ism.json, .ismb, .ismc, .ismz, .isms, .ism.msgpack)")


def _menu_export(self, context):
    self.layout.operator(ISM_OT_export.bl_idname, text="Iso-Simplicial Model (.ism.json, .ismb, .ismc, .ismz, .isms, .ism.msgpack)")


_CLASSES = (ISM_OT_import, ISM_OT_export, ISM_FH_import)


def register():
    for cls in _CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.TOPBAR_MT_file_import.append(_menu_import)
    bpy.types.TOPBAR_MT_file_export.append(_menu_export)


def unregister():
    bpy.types.TOPBAR_MT_file_export.remove(_menu_export)
    bpy.types.TOPBAR_MT_file_import.remove(_menu_import)
    for cls in reversed(_CLASSES):
        bpy.utils.unregister_class(cls)
