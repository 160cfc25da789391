"""Peer benchmark of `ism sample --surface`: trimesh's `sample_surface` on an exported mesh.

Runs, in one process tree on the same machine, and reports CPU time (the machine is shared, so
wall time is noisy; `resource.getrusage` of the children for `ism`, `time.process_time` for
trimesh, best of --repeat each), for every MODEL given:
  1. `ism export MODEL mesh.obj --tolerance TOL` once (the curved shape as a triangle mesh);
  2. trimesh: load the mesh and `trimesh.sample.sample_surface(mesh, N)`;
  3. `ism sample MODEL --surface 1 -j 1 -q -o out.ply`: the setup (read, evaluator, the certified
     table) and one sample; divided by the model's simplex count: setup per simplex;
  4. `ism sample MODEL --surface N -j 1 -q -o out.ply`: the whole command; (this − setup) / N is
     the per-sample CPU cost;
  5. with --threads 2 (default): step 4 with `-j 2`, CPU and wall, the wall-time ratio j1/j2
     next to the load average (on a loaded 2-core machine the wall ratio cannot show 2x), and a
     byte comparison of the -j 1 and -j 2 outputs (a seed's output must not depend on threads).
Prints samples per CPU-second for both and the ratios.

Usage: .venv/bin/python tools/bench_sample.py MODEL [MODEL ...] [--n N ...] [--tolerance TOL]
           [--repeat R] [--threads T ...] [--no-trimesh]
  A bare integer argument is taken as an N (the old `bench_sample.py MODEL N ...` form).
  ($ISM_BIN or target/release/ism: `cargo build --release -p ism-cli`)
"""

from __future__ import annotations

import argparse
import filecmp
import json
import os
import resource
import subprocess
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def child_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def ism_run(ism: str, model: str, n: int, out: Path, threads: int, repeat: int) -> tuple[float, float]:
    """Best CPU and best wall time of `ism sample MODEL --surface n -j threads`."""
    best_cpu = best_wall = float("inf")
    for _ in range(repeat):
        # A fresh path every run: replacing the previous run's output frees its pages inside the
        # rename, serially, at the end of the timed command (60 MB at 10^6 samples: ~60 ms of wall
        # time, which cut the 2-thread ratio of a fitted torus from 1.89x to 1.74x, session 38).
        # That is the kernel releasing the old file, not the sampler.
        out.unlink(missing_ok=True)
        before = child_cpu()
        t = time.perf_counter()
        subprocess.run(
            [ism, "sample", model, "--surface", str(n), "-j", str(threads), "-q", "-o", str(out)],
            check=True,
            env=dict(os.environ, RAYON_NUM_THREADS=str(threads)),
        )
        best_wall = min(best_wall, time.perf_counter() - t)
        best_cpu = min(best_cpu, child_cpu() - before)
    return best_cpu, best_wall


def simplices(ism: str, model: str) -> int:
    out = subprocess.run([ism, "info", "--json", model], check=True, capture_output=True, text=True)
    return int(json.loads(out.stdout)["simplices"])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("models", nargs="+")
    ap.add_argument("--n", type=int, action="append", default=[])
    ap.add_argument("--tolerance", default="1e-4")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, action="append", default=[])
    ap.add_argument("--no-trimesh", action="store_true")
    args = ap.parse_args()
    models = [m for m in args.models if not m.isdigit()]
    ns = args.n + [int(m) for m in args.models if m.isdigit()] or [200_000]
    threads = args.threads or [2]
    ism = os.environ.get("ISM_BIN", str(ROOT / "target" / "release" / "ism"))
    print(f"ism = {ism}; load average at start {os.getloadavg()}")
    with tempfile.TemporaryDirectory() as tmp:
        for model in models:
            count = simplices(ism, model)
            obj = Path(tmp) / "mesh.obj"
            if not args.no_trimesh:
                subprocess.run(
                    [ism, "export", model, str(obj), "--tolerance", args.tolerance, "-q"],
                    check=True,
                    stdout=subprocess.DEVNULL,
                )
            setup, _ = ism_run(ism, model, 1, Path(tmp) / "setup.ply", 1, args.repeat)
            print(
                f"model {model} ({count:,} simplices): setup (--surface 1 -j 1) {setup:.3f} CPU-s = "
                f"{setup / count * 1e6:.1f} us per simplex"
            )
            for n in ns:
                line = f"  N={n:,}:"
                ours, wall1 = ism_run(ism, model, n, Path(tmp) / "out1.ply", 1, args.repeat)
                per_sample = max(ours - setup, 1e-9) / max(n - 1, 1)
                line += (
                    f" ism -j 1 {ours:.3f} CPU-s (wall {wall1:.2f}); per sample {per_sample * 1e6:.3f} us "
                    f"({1 / per_sample:,.0f}/CPU-s)"
                )
                if not args.no_trimesh:
                    import trimesh

                    best = best_sample = float("inf")
                    for _ in range(args.repeat):
                        t = time.process_time()
                        mesh = trimesh.load(str(obj), force="mesh")
                        t1 = time.process_time()
                        trimesh.sample.sample_surface(mesh, n)
                        t2 = time.process_time()
                        best = min(best, t2 - t)
                        best_sample = min(best_sample, t2 - t1)
                    line += (
                        f"; trimesh load+sample {best:.3f} CPU-s, sample alone {best_sample:.3f} "
                        f"({n / best_sample:,.0f}/CPU-s; {len(mesh.faces):,} triangles at {args.tolerance}); "
                        f"whole-run ratio ism/trimesh {ours / best:.2f}, per-sample ratio "
                        f"{per_sample / (best_sample / n):.1f}"
                    )
                print(line, flush=True)
                for t in threads:
                    load = os.getloadavg()[0]
                    cpu, wall = ism_run(ism, model, n, Path(tmp) / f"out{t}.ply", t, args.repeat)
                    same = filecmp.cmp(Path(tmp) / "out1.ply", Path(tmp) / f"out{t}.ply", shallow=False)
                    print(
                        f"    -j {t}: {cpu:.3f} CPU-s (wall {wall:.2f}); wall ratio j1/j{t} {wall1 / wall:.2f} "
                        f"at load {load:.1f}; output {'identical to' if same else 'DIFFERS from'} -j 1",
                        flush=True,
                    )


if __name__ == "__main__":
    main()
