"""`ism sample` / `ism query` outputs opened by real readers.

- numpy loads the NPY structured arrays (fields x, y, z, nx, ny, nz, f, simplex / label);
- plyfile and trimesh load the binary and ASCII PLY point clouds with the same coordinates;
- numpy reads the CSV; query results agree with the sampled F (points on the surface give F ≈ c).
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "spec" / "examples"
ISM = os.environ.get("ISM_BIN", str(ROOT / "target" / "debug" / "ism"))


def ism(*args: str, stdin: bytes | None = None) -> bytes:
    out = subprocess.run([ISM, *args], input=stdin, capture_output=True, check=False)
    assert out.returncode == 0, out.stderr.decode()
    return out.stdout


def level(model: Path) -> float:
    return float(json.loads(model.read_text()).get("level", 0.0))


@pytest.fixture(scope="module")
def sphere() -> Path:
    # A small 3D model with three stratified Bézier stages (162 tetrahedra): quick in a debug build.
    return EXAMPLES / "stratified-3d.ism.json"


def test_npy_surface_loads_in_numpy(tmp_path: Path, sphere: Path) -> None:
    out = tmp_path / "s.npy"
    ism("sample", str(sphere), "--surface", "2000", "--seed", "1", "-o", str(out))
    a = np.load(out)
    assert a.shape == (2000,)
    assert a.dtype.names == ("x", "y", "z", "nx", "ny", "nz", "f", "simplex")
    assert a["x"].dtype == np.float64 and a["simplex"].dtype == np.int32
    n = np.stack([a["nx"], a["ny"], a["nz"]], axis=1)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    assert np.all(np.abs(a["f"] - level(sphere)) < 1e-8)
    assert np.all(a["simplex"] >= 0)


def test_npy_volume_labels(tmp_path: Path, sphere: Path) -> None:
    out = tmp_path / "v.npy"
    ism("sample", str(sphere), "--volume", "3000", "-o", str(out))
    a = np.load(out)
    assert a.dtype.names == ("x", "y", "z", "f", "label", "simplex")
    assert a["label"].dtype == np.int8
    assert np.array_equal(a["label"], (a["f"] < level(sphere)).astype(np.int8))
    assert 0 < a["label"].sum() < len(a)


def test_ply_loads_in_plyfile_and_trimesh(tmp_path: Path, sphere: Path) -> None:
    plyfile = pytest.importorskip("plyfile")
    import trimesh

    binary = tmp_path / "s.ply"
    ascii_ = tmp_path / "a.ply"
    ism("sample", str(sphere), "--surface", "1500", "--seed", "4", "-o", str(binary))
    ism("sample", str(sphere), "--surface", "1500", "--seed", "4", "--format", "ply-ascii", "-o", str(ascii_))
    ref = np.load(_npy(tmp_path, sphere, "--surface", "1500", "--seed", "4"))
    for path in (binary, ascii_):
        ply = plyfile.PlyData.read(str(path))
        v = ply["vertex"]
        assert len(v) == 1500
        assert {"x", "y", "z", "nx", "ny", "nz", "f", "simplex"} <= set(v.data.dtype.names)
        assert np.array_equal(v["x"], ref["x"]) and np.array_equal(v["simplex"], ref["simplex"])
        cloud = trimesh.load(str(path))
        assert isinstance(cloud, trimesh.PointCloud)
        assert np.allclose(cloud.vertices[:, 2], ref["z"])


def _npy(tmp_path: Path, model: Path, *args: str) -> Path:
    out = tmp_path / "ref.npy"
    ism("sample", str(model), *args, "-o", str(out))
    return out


def test_csv_and_query_agree(tmp_path: Path, sphere: Path) -> None:
    text = ism("sample", str(sphere), "--surface", "300", "--seed", "9").decode()
    a = np.genfromtxt(text.splitlines(), delimiter=",", names=True)
    assert len(a) == 300
    pts = np.stack([a["x"], a["y"], a["z"]], axis=1)
    q = ism("query", str(sphere), "-", stdin="\n".join(" ".join(repr(float(x)) for x in p) for p in pts).encode())
    b = np.genfromtxt(q.decode().splitlines(), delimiter=",", names=True)
    assert np.all(b["simplex"] >= 0)
    assert np.all(np.abs(b["f"] - level(sphere)) < 1e-8)
    g = np.stack([b["gx"], b["gy"], b["gz"]], axis=1)
    n = np.stack([a["nx"], a["ny"], a["nz"]], axis=1)
    # Same direction as the sampler's normals (a point on a shared face may be located in the
    # neighbouring simplex, where the gradient differs: the shape is only C0 across faces).
    cos = np.sum(g * n, axis=1) / np.linalg.norm(g, axis=1)
    assert np.median(cos) > 0.999
