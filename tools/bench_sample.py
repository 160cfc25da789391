"""Peer benchmark of `ism sample --surface`: trimesh's `sample_surface` on an exported mesh.

Runs, in one process tree on the same machine, and reports CPU time (the machine is shared, so
wall time is noisy; `resource.getrusage` of the children for `ism`, `time.process_time` for
trimesh, best of 3 each):
  1. `ism export MODEL mesh.obj --tolerance TOL` once (the curved shape as a triangle mesh);
  2. trimesh: load the mesh and `trimesh.sample.sample_surface(mesh, N)`;
  3. `ism sample MODEL --surface N -j 1 -q -o out.ply` (the whole command: read, the certified
     table, N exact samples on the curved surface, the PLY write), and the same with N = 1,000 to
     separate the table's cost from the per-sample cost.
Prints samples per CPU-second for both and the ratios.

Usage: .venv/bin/python tools/bench_sample.py MODEL [N ...] [--tolerance TOL]
  ($ISM_BIN or target/release/ism: `cargo build --release -p ism-cli`)
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import tempfile
import time
from pathlib import Path

import trimesh

ROOT = Path(__file__).resolve().parents[1]


def child_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def ism_cpu(ism: str, model: str, n: int, out: Path) -> float:
    best = float("inf")
    for _ in range(3):
        before = child_cpu()
        subprocess.run(
            [ism, "sample", model, "--surface", str(n), "-j", "1", "-q", "-o", str(out)],
            check=True,
            env=dict(os.environ, RAYON_NUM_THREADS="1"),
        )
        best = min(best, child_cpu() - before)
    return best


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("model")
    ap.add_argument("n", nargs="*", type=int, default=[200_000])
    ap.add_argument("--tolerance", default="1e-4")
    args = ap.parse_args()
    ism = os.environ.get("ISM_BIN", str(ROOT / "target" / "release" / "ism"))
    with tempfile.TemporaryDirectory() as tmp:
        obj = Path(tmp) / "mesh.obj"
        subprocess.run([ism, "export", args.model, str(obj), "--tolerance", args.tolerance, "-q"], check=True)
        setup = ism_cpu(ism, args.model, 1000, Path(tmp) / "setup.ply")
        print(f"model {args.model}; ism table + 1,000 samples: {setup:.2f} CPU-s")
        for n in args.n:
            best = float("inf")
            for _ in range(3):
                t = time.process_time()
                mesh = trimesh.load(str(obj), force="mesh")
                trimesh.sample.sample_surface(mesh, n)
                best = min(best, time.process_time() - t)
            ours = ism_cpu(ism, args.model, n, Path(tmp) / "out.ply")
            per_sample = max(ours - setup, 1e-9) / max(n - 1000, 1)
            print(
                f"N={n:,}: trimesh load+sample {best:.3f} CPU-s ({len(mesh.faces):,} triangles at {args.tolerance}); "
                f"ism sample {ours:.3f} CPU-s; whole-run ratio ism/trimesh {ours / best:.2f}; "
                f"ism per sample {per_sample * 1e6:.2f} us ({1 / per_sample:,.0f}/CPU-s)"
            )


if __name__ == "__main__":
    main()
