"""Renders an ISM file with Cycles (CPU) after importing it through the extension: the README picture.

    .venv-blender/bin/python blender/render.py genus2.ismb blender/genus2.png --samples 32

Run with the Python that has `bpy` (tools/setup.sh makes .venv-blender). Standalone, the script
builds the extension zip (blender/build.py, wheel from target/wheels), installs it into a temporary
Blender user folder and imports the file with File > Import > Iso-Simplicial Model
(`bpy.ops.import_scene.ism`); blender/tests uses `render_file` the same way.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile


def render_file(model_path: str, png: str, *, width: int = 480, height: int = 360, samples: int = 16, tolerance: float = 1e-3) -> str:
    """Imports ``model_path`` into the current (emptied) scene and renders it to ``png``."""
    import bpy
    from mathutils import Vector

    result = bpy.ops.import_scene.ism(filepath=model_path, tolerance=tolerance)
    if result != {"FINISHED"}:
        raise RuntimeError(f"import of {model_path} gave {result}")
    obj = bpy.context.view_layer.objects.active
    scene = bpy.context.scene

    mat = bpy.data.materials.new("ISM surface")
    if mat.node_tree is None:  # Blender < 5 makes node trees only on request
        mat.use_nodes = True
    bsdf = mat.node_tree.nodes.get("Principled BSDF")
    bsdf.inputs["Base Color"].default_value = (0.85, 0.45, 0.15, 1.0)
    bsdf.inputs["Roughness"].default_value = 0.35
    obj.data.materials.append(mat)

    corners = [obj.matrix_world @ Vector(c) for c in obj.bound_box]
    centre = sum(corners, Vector()) / 8.0
    radius = max((c - centre).length for c in corners)

    cam_data = bpy.data.cameras.new("ISM camera")
    cam = bpy.data.objects.new("ISM camera", cam_data)
    scene.collection.objects.link(cam)
    direction = Vector((1.0, -1.4, 1.1)).normalized()
    cam.location = centre + direction * radius * 3.2
    cam.rotation_euler = (-direction).to_track_quat("-Z", "Y").to_euler()
    cam_data.lens = 50
    scene.camera = cam

    sun_data = bpy.data.lights.new("ISM sun", type="SUN")
    sun_data.energy = 4.0
    sun = bpy.data.objects.new("ISM sun", sun_data)
    sun.rotation_euler = (0.6, 0.3, 0.8)
    scene.collection.objects.link(sun)
    world = scene.world or bpy.data.worlds.new("ISM world")
    scene.world = world
    if world.node_tree is None:
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.9, 0.92, 0.95, 1.0)
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.6

    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_denoising = False
    scene.render.resolution_x = width
    scene.render.resolution_y = height
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGB"
    scene.render.image_settings.compression = 90
    scene.render.filepath = os.path.abspath(png)
    bpy.ops.render.render(write_still=True)
    return scene.render.filepath


def install_extension(zip_path: str) -> None:
    """Installs and enables the extension zip in the running Blender (user_default repository)."""
    import bpy

    result = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
    if result != {"FINISHED"}:
        raise RuntimeError(f"installing {zip_path} gave {result}")


def main(argv: "list[str] | None" = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("png")
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--width", type=int, default=480)
    ap.add_argument("--height", type=int, default=360)
    args = ap.parse_args(argv)
    user = tempfile.mkdtemp(prefix="ism-blender-user-")
    os.environ["BLENDER_USER_RESOURCES"] = user
    import bpy  # noqa: F401  (after BLENDER_USER_RESOURCES)

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import build

    zip_path = os.path.join(user, "ism_io.zip")
    assert build.main(["-o", zip_path]) == 0
    install_extension(zip_path)
    for o in list(bpy.data.objects):
        bpy.data.objects.remove(o, do_unlink=True)
    print(render_file(args.model, args.png, width=args.width, height=args.height, samples=args.samples))
    return 0


if __name__ == "__main__":
    sys.exit(main())
