"""`ism export` of a fitted rational model whose stages run at very uneven parameter speed stays
near its tolerance, measured independently of the exporter.

The model, `tests/data/rational-ellipsoid.ismb`, was written by

    ism fit --expr "x^2/0.81 + y^2/0.09 + z^2/0.0036 - 1" --domain=-1,1,-1,1,-1,1 \
        --tolerance 1e-2 --rational -o rational-ellipsoid.ismb -q -j 1

(four parametric stages, the last rational with weights 0.05-20: the fitter's limits). Its stages
carry the exporter's fixed-parameter test points far from the middle of their edges in space; before
the gap probes and size-based interior levels (session 30) its export at 1e-3 lay 3.3 x the
tolerance from its own shape, after them 1.30 x, and since facet edges are also checked near
their ends (a bend inside their first eighth, session 31) 0.99 x. At 1e-4, 228 edges stopped at
the depth limit (`--max-depth`, 8 halvings of the parameter) while still long in space: 1.87 x;
since long edges go on halving past it (session 31), 1.52 x by this test's damped Newton, 0.86 x
once the benchmark tightens its largest distances by sign changes of F nearby (BENCHMARKS.md,
issue 19, sessions 30 and 31).

Ground truth comes from elsewhere than the exporter: the two-sided distance between the OBJ and
O = {F = 0}, with F and its gradient from `ism query` (a direct evaluation of F), by the functions
of `tools/bench_export_error.py` (damped Newton from mesh points onto O, an upper bound of their
distance; exact point-to-triangle distances from points that `ism sample --surface` puts on O).
The exporter checks its tolerance at test points and does not bound it, so the assertion is a
regression guard with a stated margin, not the contract: 0.95 x the tolerance at 1e-3 (0.89 x
measured since each edge's ends' normals also predict its bend, session 33; 0.99 x before it, 1.30 x
before session 31), 1.65 x at 1e-4 (1.52 x; 1.87 x before session 31).
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
MODEL = ROOT / "tests" / "data" / "rational-ellipsoid.ismb"
SAMPLES = 50_000


def ism_bin() -> str:
    path = os.environ.get("ISM_BIN") or str(ROOT / "target" / "debug" / "ism")
    assert Path(path).exists(), f"ism binary not found at {path}: build it or set ISM_BIN"
    return path


def bench():
    spec = importlib.util.spec_from_file_location("bench_export_error", ROOT / "tools" / "bench_export_error.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize(
    ("tolerance", "margin"),
    [
        # Measured 0.89 x (mesh -> O) and 0.75 x (O -> mesh) at session 33; 0.99 x before it (the
        # normals' prediction), 1.30 x before session 31, 3.29 x before session 30.
        (1e-3, 0.95),
        # Measured 1.52 x and 0.76 x at session 31; 1.87 x before (the depth limit on long edges).
        (1e-4, 1.65),
    ],
)
def test_rational_fit_exports_near_its_tolerance(tmp_path, tolerance, margin):
    b = bench()
    out = tmp_path / "ell.obj"
    subprocess.run(
        [ism_bin(), "export", str(MODEL), str(out), "--tolerance", str(tolerance), "-q"],
        check=True,
    )
    v, c = b.read_obj(out)
    model = b.Model(ism_bin(), str(MODEL), tmp_path)

    # Mesh -> O at the probes of the benchmark (vertices, edge midpoints and quarters, centroids,
    # points halfway to the corners and edge midpoints).
    d, failed = model.distance(b.probes(v, c))
    probes = len(d)
    # A probe whose damped Newton stalls is not measured; there must be few (162 of 363,074 in the
    # benchmark), and none may hide the answer: they are reported in the message.
    assert failed <= probes // 1000, f"{failed} of {probes} probes did not converge"
    mesh_to_o = float(np.nanmax(d))

    # O -> mesh from points on O, uniform by area.
    pts = tmp_path / "surface.npy"
    subprocess.run(
        [ism_bin(), "sample", str(MODEL), "--surface", str(SAMPLES), "--seed", "1", "-o", str(pts), "-q"],
        check=True,
    )
    sa = np.load(pts)
    s = np.stack([sa[n] for n in ("x", "y", "z")], axis=1)
    o_to_mesh = float(b.surface_to_mesh(s, v, c, 16).max())

    msg = f"mesh -> O {mesh_to_o / tolerance:.3f} T, O -> mesh {o_to_mesh / tolerance:.3f} T ({failed} of {probes} probes unmeasured)"
    assert mesh_to_o <= margin * tolerance, msg
    assert o_to_mesh <= margin * tolerance, msg
