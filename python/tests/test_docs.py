"""Every Python example of the docs runs: the ```python blocks of README.md and python/README.md
(Blender's `bpy` blocks excepted)
(each file's blocks in order, in one namespace, from a scratch directory that sees the
repository's spec/), and the scripts in python/examples (test_examples.py runs those against the
CLI)."""
from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", ROOT / "python" / "README.md"]


def blocks(path: Path) -> list[str]:
    """The file's python blocks, except those for Blender's own Python (`bpy`, run inside Blender;
    the add-on's tests cover them)."""
    found = re.findall(r"^```python\n(.*?)^```", path.read_text(), flags=re.S | re.M)
    return [b for b in found if "import bpy" not in b]


@pytest.mark.parametrize("doc", DOCS, ids=[str(d.relative_to(ROOT)) for d in DOCS])
def test_doc_examples_run(doc, tmp_path, monkeypatch, capsys):
    found = blocks(doc)
    assert found, f"no python examples in {doc}"
    (tmp_path / "spec").symlink_to(ROOT / "spec")
    monkeypatch.chdir(tmp_path)
    os.environ.setdefault("MPLBACKEND", "Agg")
    namespace: dict = {"__name__": "__doc_example__"}
    for i, code in enumerate(found):
        try:
            exec(compile(code, f"{doc.name}[python block {i}]", "exec"), namespace)
        except Exception as e:  # name the block in the failure
            raise AssertionError(f"{doc.name}, python block {i} failed: {e!r}\n{code}") from e


def test_readme_3d_fit_example_does_what_it_says(tmp_path, monkeypatch):
    """The README's 3D fit: a sphere of radius 0.5, meeting its tolerance, one component of
    Euler characteristic 2."""
    import ism

    code = next(b for b in blocks(ROOT / "README.md") if "ism.fit(" in b)
    line = next(l for l in code.splitlines() if "ism.fit(" in l)
    namespace = {"ism": ism}
    exec(line, namespace)
    fitted, report = namespace["fitted"], namespace["report"]
    assert report["toleranceMet"] and report["components"] == 1 and report["euler"] == 2
    assert fitted.dimension == 3
    # Samples of the fitted surface lie on the sphere |p| = 0.5 within the reported distance.
    pts = fitted.sample_surface(2000, seed=1)
    import numpy as np

    r = np.sqrt(pts["x"] ** 2 + pts["y"] ** 2 + pts["z"] ** 2)
    assert np.abs(r - 0.5).max() <= 2 * report["maxDistance"] + 1e-9
