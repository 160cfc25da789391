"""Peer benchmark of `ism sample --surface`: trimesh's `sample_surface` on an exported mesh.

Runs, in one process tree on the same machine:
  1. `ism export MODEL mesh.obj --tolerance TOL` (the curved shape as a triangle mesh within TOL);
  2. trimesh.sample.sample_surface(mesh, N) timed (best of 3);
  3. `sample_timing MODEL N N` (the release example of ism-sample: table build, surface and volume
     samples/s), with RAYON_NUM_THREADS=1 and 2.
Prints the figures and the ratio ism/trimesh.

Usage: .venv/bin/python tools/bench_sample.py MODEL [N] [TOL]
  (needs target/debug/ism or $ISM_BIN and target/release/examples/sample_timing:
   cargo build --release -p ism-sample --example sample_timing)
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import trimesh

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    model = sys.argv[1]
    n = int(sys.argv[2]) if len(sys.argv) > 2 else 200_000
    tol = sys.argv[3] if len(sys.argv) > 3 else "1e-4"
    ism = os.environ.get("ISM_BIN", str(ROOT / "target" / "debug" / "ism"))
    timing = str(ROOT / "target" / "release" / "examples" / "sample_timing")
    with tempfile.TemporaryDirectory() as tmp:
        obj = Path(tmp) / "mesh.obj"
        subprocess.run([ism, "export", model, str(obj), "--tolerance", tol], check=True)
        mesh = trimesh.load(str(obj), force="mesh")
        best = float("inf")
        for _ in range(3):
            t = time.perf_counter()
            trimesh.sample.sample_surface(mesh, n)
            best = min(best, time.perf_counter() - t)
        peer = n / best
        print(f"trimesh sample_surface: {len(mesh.faces)} triangles (tolerance {tol}), {n} samples in {best:.3f}s = {peer:,.0f}/s")
    for threads in ("1", "2"):
        env = dict(os.environ, RAYON_NUM_THREADS=threads)
        out = subprocess.run([timing, model, str(n), str(n)], check=True, capture_output=True, text=True, env=env).stdout
        print(f"ism-sample, {threads} thread(s):")
        print("  " + out.strip().replace("\n", "\n  "))
        rate = float(re.search(r"surface: \d+ samples in [\d.]+s = (\d+)/s", out).group(1))
        print(f"  surface ratio ism/trimesh = {rate / peer:.3f}")


if __name__ == "__main__":
    main()
