"""Iso-Simplicial Model -> Blender objects.

Everything geometric comes from the ``ism`` package (reading, validation, extraction of the curved
surface with its ∇F normals); this module only copies arrays into Blender datablocks. The whole
model is read, validated and extracted before the first datablock is created, and every datablock
made here is removed again if a later step fails, so a bad file leaves the scene as it was.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Any, List, Optional

import bpy
import numpy as np


class InvalidModel(ValueError):
    """The file reads but the validator proves it invalid (e.g. a stage that folds a simplex):
    not imported, the message names the rules and the first findings."""


@dataclass
class ImportOptions:
    """The Import operator's settings (see ``ISM_OT_import`` for their meaning)."""

    tolerance: float = 1e-3
    max_depth: int = 8
    validate: bool = True
    wireframe: bool = False
    control_points: bool = False


@dataclass
class ImportResult:
    """What an import made: the objects (surface first) and a one-line summary for the report."""

    objects: List[Any] = field(default_factory=list)
    summary: str = ""
    verdict: Optional[str] = None


def _model_name(model: Any, path: str) -> str:
    name = model.metadata.get("name") if model.metadata else None
    if name:
        return str(name)
    base = os.path.basename(path)
    for ext in (".ism.json", ".ism.msgpack", ".ismb", ".ismc", ".ismz", ".isms"):
        if base.lower().endswith(ext):
            return base[: -len(ext)]
    return os.path.splitext(base)[0]


def _xyz(points: np.ndarray) -> np.ndarray:
    """(N, 2) or (N, 3) -> (N, 3) float32 (2D models lie in the z = 0 plane)."""
    out = np.zeros((points.shape[0], 3), dtype=np.float32)
    out[:, : points.shape[1]] = points
    return out


def _triangle_mesh(name: str, positions: np.ndarray, triangles: np.ndarray) -> Any:
    """A mesh datablock from welded triangles, with exactly the given vertices and faces."""
    me = bpy.data.meshes.new(name)
    nv, nf = positions.shape[0], triangles.shape[0]
    me.vertices.add(nv)
    me.vertices.foreach_set("co", _xyz(positions).ravel())
    me.loops.add(3 * nf)
    me.loops.foreach_set("vertex_index", triangles.astype(np.int32).ravel())
    me.polygons.add(nf)
    me.polygons.foreach_set("loop_start", np.arange(0, 3 * nf, 3, dtype=np.int32))
    me.update(calc_edges=True)
    return me


def _set_smooth_normals(me: Any, normals: np.ndarray) -> None:
    """Smooth shading with the extraction's per-vertex normals ∇F/|∇F| as custom split normals."""
    me.polygons.foreach_set("use_smooth", np.ones(len(me.polygons), dtype=bool))
    n = np.asarray(normals, dtype=np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    me.normals_split_custom_set_from_vertices(n.astype(np.float32).tolist())


def _curve(name: str, surface: Any) -> Any:
    """A curve datablock from a 2D shape's segments: one poly spline per polyline, closed curves
    cyclic."""
    cu = bpy.data.curves.new(name, type="CURVE")
    cu.dimensions = "2D"
    cu.fill_mode = "NONE"
    pos = _xyz(surface.positions)
    for line in surface.polylines():
        ids = [int(i) for i in line]
        cyclic = len(ids) > 2 and ids[0] == ids[-1]
        if cyclic:
            ids = ids[:-1]
        sp = cu.splines.new("POLY")
        sp.points.add(len(ids) - 1)
        co = np.ones((len(ids), 4), dtype=np.float32)
        co[:, :3] = pos[ids]
        sp.points.foreach_set("co", co.ravel())
        sp.use_cyclic_u = cyclic
    return cu


def _wireframe(name: str, model: Any) -> Any:
    """The complex's edges (dimension-1 faces of the checked index) over its vertices."""
    me = bpy.data.meshes.new(name)
    edges = np.asarray(model.faces(1), dtype=np.int32)
    me.vertices.add(model.num_vertices)
    me.vertices.foreach_set("co", _xyz(np.asarray(model.vertices)).ravel())
    me.edges.add(edges.shape[0])
    me.edges.foreach_set("vertices", edges.ravel())
    me.update()
    return me


def control_point_positions(model: Any) -> "tuple[np.ndarray, np.ndarray]":
    """Positions of the control points each stage stores, and the stage of each.

    A stored control point is given by face-local barycentric coordinates with respect to its
    face's vertices (spec/ism-format.md §4.3), so its position is that combination of the vertex
    positions. Monotonic stages store coefficients, not points, and contribute none.
    """
    verts = np.asarray(model.vertices, dtype=np.float64)
    out: List[np.ndarray] = []
    stage_ids: List[np.ndarray] = []
    for si, stage in enumerate(model.stages):
        if stage.kind == "monotonic":
            continue
        fo, fv = np.asarray(stage.face_offsets), np.asarray(stage.face_vertices)
        po, pts = np.asarray(stage.point_offsets), np.asarray(stage.points)
        for r in range(len(fo) - 1):
            face = fv[fo[r] : fo[r + 1]]
            bary = pts[po[r] : po[r + 1]].reshape(-1, len(face))
            out.append(bary @ verts[face])
            stage_ids.append(np.full(bary.shape[0], si, dtype=np.int32))
    if not out:
        return np.zeros((0, verts.shape[1])), np.zeros(0, dtype=np.int32)
    return np.concatenate(out), np.concatenate(stage_ids)


def _point_cloud(name: str, model: Any) -> Any:
    """The stored control points as a vertex-only mesh, with an integer ``stage`` attribute."""
    pos, stage_of = control_point_positions(model)
    me = bpy.data.meshes.new(name)
    me.vertices.add(pos.shape[0])
    me.vertices.foreach_set("co", _xyz(pos).ravel())
    attr = me.attributes.new("stage", "INT", "POINT")
    attr.data.foreach_set("value", stage_of)
    me.update()
    return me


def _idprop_safe(value: Any) -> Any:
    """Custom properties take str/int/float/dicts/lists of them, not None: JSON text otherwise."""
    if isinstance(value, (str, int, float)) and not isinstance(value, bool):
        return value
    if isinstance(value, bool):
        return int(value)
    return json.dumps(value)


def _set_properties(obj: Any, model: Any, path: str, opts: ImportOptions, surface: Any, report: Any) -> None:
    obj["ism_file"] = os.path.abspath(path)
    obj["ism_version"] = model.version
    obj["ism_dimension"] = model.dimension
    obj["ism_vertices"] = model.num_vertices
    obj["ism_simplices"] = model.num_simplices
    obj["ism_level"] = float(model.level)
    obj["ism_stages"] = ", ".join(f"{s.kind} degree {s.degree}" for s in model.stages) or "none (linear)"
    obj["ism_tolerance"] = float(opts.tolerance)
    obj["ism_metadata"] = {str(k): str(v) for k, v in (model.metadata or {}).items()}
    if model.extras is not None:
        obj["ism_extras"] = json.dumps(model.extras)
    obj["ism_extraction"] = json.dumps(surface.report)
    if report is not None:
        rep = report.to_dict()
        obj["ism_verdict"] = report.verdict
        obj["ism_errors"] = rep["issues"]["numErrors"]
        obj["ism_warnings"] = rep["issues"]["numWarnings"]
        obj["ism_rules"] = ", ".join(sorted(report.counts)) if report.counts else ""
        obj["ism_certificates"] = _idprop_safe(report.certificates)
    else:
        obj["ism_verdict"] = "not validated"


def import_file(context: Any, path: str, opts: ImportOptions) -> ImportResult:
    """Reads ``path`` and adds its objects to the active collection.

    Raises the package's ``ism.ISMError`` subclasses (unreadable or invalid file, extraction
    failure) before anything is created; if Blender itself fails half-way, the datablocks made so
    far are removed and the error re-raised.
    """
    import ism

    model = ism.read(path)
    if model.dimension not in (2, 3):
        raise ism.FormatError(f"a {model.dimension}D model has no surface or curve Blender can show")
    report = model.validate() if opts.validate else None
    if report is not None and report.verdict == "invalid":
        counts = ", ".join(f"{rule} x{n}" for rule, n in sorted(report.counts.items()))
        first = "; ".join(
            f"{d.get('code')}: {d.get('message')}" for d in report.diagnostics[:2] if d.get("severity") == "error"
        )
        raise InvalidModel(f"the validator proves the model invalid ({counts}): {first}")
    surface = model.extract_surface(opts.tolerance, max_depth=opts.max_depth)
    name = _model_name(model, path)

    made: List[Any] = []  # datablocks, removed again on failure
    try:
        if model.dimension == 3:
            data = _triangle_mesh(name, surface.positions, surface.cells)
            made.append(data)
            _set_smooth_normals(data, surface.normals)
        else:
            data = _curve(name, surface)
            made.append(data)
        obj = bpy.data.objects.new(name, data)
        made.append(obj)
        _set_properties(obj, model, path, opts, surface, report)
        objects = [obj]
        if opts.wireframe:
            wire = _wireframe(f"{name} complex", model)
            made.append(wire)
            wobj = bpy.data.objects.new(f"{name} complex", wire)
            made.append(wobj)
            wobj.display_type = "WIRE"
            objects.append(wobj)
        if opts.control_points:
            cloud = _point_cloud(f"{name} control points", model)
            made.append(cloud)
            cobj = bpy.data.objects.new(f"{name} control points", cloud)
            made.append(cobj)
            objects.append(cobj)
        collection = context.collection or context.scene.collection
        for o in objects:
            collection.objects.link(o)
        for o in objects[1:]:
            o.parent = obj
    except BaseException:
        _remove(made)
        raise

    for o in context.view_layer.objects:
        o.select_set(False)
    obj.select_set(True)
    context.view_layer.objects.active = obj
    kind = f"{len(surface.cells)} triangles" if model.dimension == 3 else f"{len(surface.cells)} segments"
    verdict = report.verdict if report is not None else "not validated"
    summary = f"{name}: {surface.positions.shape[0]} vertices, {kind} at tolerance {opts.tolerance:g}; validator: {verdict}"
    return ImportResult(objects=objects, summary=summary, verdict=None if report is None else report.verdict)


def _remove(made: List[Any]) -> None:
    """Removes datablocks in reverse order of creation (objects before their data)."""
    for block in reversed(made):
        try:
            if isinstance(block, bpy.types.Object):
                bpy.data.objects.remove(block, do_unlink=True)
            elif isinstance(block, bpy.types.Mesh):
                bpy.data.meshes.remove(block)
            elif isinstance(block, bpy.types.Curve):
                bpy.data.curves.remove(block)
        except ReferenceError:
            pass


def summary_of_error(err: BaseException) -> str:
    """One line for the operator report: the error's class and message. The package's messages
    already name the rule and the place (byte offset, JSON pointer, simplex); the rule and pointer
    are added only where the message lacks them."""
    text = f"{type(err).__name__}: {err}"
    for attr in ("rule", "pointer"):
        v = getattr(err, attr, None)
        if v and str(v) not in text:
            text += f" ({attr} {v})"
    return text
