"""Headless Blender (the `bpy` module from PyPI) with the ISM extension installed from its zip.

Blender's user folders (preferences, extensions) go to a fresh temporary folder
(BLENDER_USER_RESOURCES, read when bpy is first imported), so the tests never touch a real Blender
setup. The extension zip is built by blender/build.py from the wheel tools/setup.sh made, and
installed through Blender's own extension API (`bpy.ops.extensions.package_install_files`), which
also unpacks the bundled `ism` wheel into Blender's extension site-packages: the `ism` the tests
use is that one (the venv has no `ism` of its own; `test_extension_installed` checks this).
"""

from __future__ import annotations

import glob
import os
import shutil
import sys
import tempfile

import pytest

USER_RESOURCES = tempfile.mkdtemp(prefix="ism-blender-user-")
os.environ["BLENDER_USER_RESOURCES"] = USER_RESOURCES

import bpy  # noqa: E402  (after BLENDER_USER_RESOURCES)

HERE = os.path.dirname(os.path.abspath(__file__))
BLENDER_DIR = os.path.dirname(HERE)
ROOT = os.path.dirname(BLENDER_DIR)
sys.path.insert(0, BLENDER_DIR)

import build  # noqa: E402  (blender/build.py)


def pytest_sessionfinish(session, exitstatus):
    shutil.rmtree(USER_RESOURCES, ignore_errors=True)


@pytest.fixture(scope="session")
def extension_zip(tmp_path_factory):
    wheels = sorted(glob.glob(os.path.join(ROOT, "target", "wheels", "ism-*.whl")))
    assert len(wheels) == 1, f"expected the one wheel tools/setup.sh builds in target/wheels, found {wheels}"
    out = tmp_path_factory.mktemp("zip") / "ism_io.zip"
    return build.build(wheels[0], str(out))


@pytest.fixture(scope="session")
def extension(extension_zip):
    """Installs and enables the extension zip; returns the installed add-on module."""
    result = bpy.ops.extensions.package_install_files(
        filepath=extension_zip, repo="user_default", enable_on_install=True
    )
    assert result == {"FINISHED"}, result
    module = sys.modules.get("bl_ext.user_default.ism_io")
    assert module is not None, "the add-on module was not enabled"
    return module


@pytest.fixture
def scene(extension):
    """An empty scene (all objects, meshes and curves removed) with the extension enabled."""
    for o in list(bpy.data.objects):
        bpy.data.objects.remove(o, do_unlink=True)
    for coll in (bpy.data.meshes, bpy.data.curves, bpy.data.materials, bpy.data.cameras, bpy.data.lights):
        for block in list(coll):
            coll.remove(block)
    return bpy.context.scene
