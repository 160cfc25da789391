"""The docs page's scripts (python/examples) run and give what the CLI gives."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

import ism
from conftest import EXAMPLES, cli

HERE = Path(__file__).resolve().parents[1] / "examples"


def run(*args):
    done = subprocess.run([sys.executable, *map(str, args)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_convert_exports_like_the_cli(tmp_path):
    run(HERE / "convert.py", EXAMPLES / "torus.ismb", tmp_path / "py.glb")
    cli("export", EXAMPLES / "torus.ismb", tmp_path / "cli.glb", "--quiet")
    assert (tmp_path / "py.glb").read_bytes() == (tmp_path / "cli.glb").read_bytes()


def test_convert_imports_a_mesh_like_the_cli(tmp_path):
    import meshio

    m = ism.read(EXAMPLES / "sphere.ismb")
    meshio.write(tmp_path / "in.vtu", meshio.Mesh(m.vertices, [("tetra", m.simplices.astype(np.int64))], point_data={"phi": m.values}))
    out = run(HERE / "convert.py", tmp_path / "in.vtu", tmp_path / "py.ismb", "--field", "phi")
    assert "valid" in out
    cli("import", tmp_path / "in.vtu", tmp_path / "cli.ismb", "--field", "phi", "--quiet")
    py, ref = ism.read(tmp_path / "py.ismb"), ism.read(tmp_path / "cli.ismb")
    assert np.array_equal(py.vertices, ref.vertices) and np.array_equal(py.values, ref.values)
    assert np.array_equal(py.simplices, ref.simplices)


def test_walkthrough_draws_a_picture(tmp_path):
    import matplotlib.image

    out = run(HERE / "walkthrough.py", tmp_path / "w.png")
    assert "validate: valid" in out
    img = matplotlib.image.imread(tmp_path / "w.png")
    assert img.ndim == 3 and img.shape[0] > 300 and img.shape[1] > 300
    # Not blank: the curve (black) and the samples' normals (red) are drawn.
    assert (img[..., :3].max(axis=2) < 0.1).sum() > 500


def test_docstring_examples_run(monkeypatch):
    """Every `>>>` example in the package's docstrings (Python and Rust halves) runs from the
    repository root and prints what it shows."""
    import doctest

    import ism.errors

    monkeypatch.chdir(Path(__file__).resolve().parents[2])
    total = 0
    for module in (ism, ism.errors):
        result = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE, verbose=False)
        assert result.failed == 0
        total += result.attempted
    assert total >= 20
