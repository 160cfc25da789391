"""Benchmark of the `ism` Python package against the Rust side, in one run (issue 14).

    ISM_BIN=target/release/ism .venv/bin/python tools/bench_python.py LARGE.ismb \
        --bench-format target/release/examples/bench_format [--surface-model M] [--n 1000000]

Needs the package installed from a release wheel (tools/setup.sh) and release builds of `ism`
(`cargo build --release -p ism-cli`) and of `bench_format`
(`cargo build --release -p ism-conformance --example bench_format`). LARGE.ismb is made by
`target/release/ism-make-examples --no-examples --large 1000000 LARGE.ismb`.

Rows (best of --repeat; CPU = user + system of every thread, from getrusage; wall from the clock):
1. read LARGE into numpy arrays (`ism.read`, checked, keeping the index; then vertices/simplices/
   values; then also the faces and every stage's dense indexed tables, both views; then also the
   per-record flat tables, copied) vs the Rust checked read that keeps the index
   (`bench_format read FILE --indexed`, the same `io` calls);
2. N surface samples into numpy (`ism.read(M).sample_surface(N, 1)`) vs `ism sample M --surface N
   --seed 1 -o x.npy` (read, table, sampling, NPY written), and the two results compared bit for bit;
3. query of N points on LARGE (`m.query(points)`, model already read) vs the library's rate inside
   `ism query`: (time for N points) − (time for 1 point), which removes reading the model; results
   compared bit for bit.
Machine noise: the machine is shared, so CPU times are the figures to compare.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import ism


def cpu_self() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def cpu_children() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def timed_self(fn):
    gc.collect()
    c0, t0 = cpu_self(), time.perf_counter()
    out = fn()
    return out, cpu_self() - c0, time.perf_counter() - t0


def timed_child(cmd):
    c0, t0 = cpu_children(), time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        sys.exit(f"{' '.join(map(str, cmd))}: {done.stderr}")
    return done.stdout, cpu_children() - c0, wall


def best(runs):
    """Best (lowest CPU) of (cpu, wall) pairs."""
    return min(runs, key=lambda r: r[0])


def row(name, py, rust):
    ratio_cpu = py[0] / rust[0]
    ratio_wall = py[1] / rust[1]
    print(f"| {name} | {py[0]:.3f} s CPU, {py[1]:.3f} s wall | {rust[0]:.3f} s CPU, {rust[1]:.3f} s wall | {ratio_cpu:.3f} | {ratio_wall:.3f} |")
    return {"name": name, "python": py, "rust": rust, "ratio_cpu": ratio_cpu, "ratio_wall": ratio_wall}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("large", type=Path)
    ap.add_argument("--bench-format", default="target/release/examples/bench_format")
    ap.add_argument("--surface-model", type=Path, default=Path("spec/examples/sphere.ismb"))
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    ism_bin = os.environ.get("ISM_BIN", "target/release/ism")
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; python {platform.python_version()}, ism {ism.__version__}, numpy {np.__version__}")
    results = []
    print("| what | Python (`ism` package) | Rust | ratio CPU | ratio wall |")
    print("| --- | --- | --- | --- | --- |")

    # 1. Reading the large model.
    py_runs, py_dense_runs, py_tables_runs, rust_runs = [], [], [], []
    for _ in range(args.repeat):
        def read_arrays():
            m = ism.read(args.large)
            return m, (m.vertices, m.simplices, m.values)

        (m, arrays), cpu, wall = timed_self(read_arrays)
        py_runs.append((cpu, wall))
        _, cpu_d, wall_d = timed_self(lambda: ([m.faces(k) for k in range(m.dimension + 1)], m.neighbours, [m.stage_tables(i) for i in range(len(m.stages))]))
        py_dense_runs.append((cpu + cpu_d, wall + wall_d))
        _, cpu_t, wall_t = timed_self(lambda: [s.tables() for s in m.stages])
        py_tables_runs.append((cpu + cpu_d + cpu_t, wall + wall_d + wall_t))
        nv, ns = len(arrays[0]), len(arrays[1])
        del m, arrays
        gc.collect()
        out, cpu, wall = timed_child([args.bench_format, "read", str(args.large), "--indexed", "--repeat", "1"])
        rust_runs.append((cpu, json.loads(out.splitlines()[-1])["seconds"]))
    print(f"<!-- large model: {nv} vertices, {ns} tetrahedra, {args.large.stat().st_size} bytes -->")
    results.append(row(f"read {args.large.name} ({ns:,} tets) into numpy: vertices, simplices, values (views)", best(py_runs), best(rust_runs)))
    results.append(row("… and the faces, neighbours and every stage's dense indexed tables (views)", best(py_dense_runs), best(rust_runs)))
    results.append(row("… and every stage's per-record flat tables (copied)", best(py_tables_runs), best(rust_runs)))

    # 2. Surface samples.
    with tempfile.TemporaryDirectory() as tmp:
        npy = Path(tmp) / "s.npy"
        py_runs, rust_runs = [], []
        for _ in range(args.repeat):
            pts, cpu, wall = timed_self(lambda: ism.read(args.surface_model).sample_surface(args.n, 1))
            py_runs.append((cpu, wall))
            _, cpu, wall = timed_child([ism_bin, "sample", str(args.surface_model), "--surface", str(args.n), "--seed", "1", "-o", str(npy), "--quiet"])
            rust_runs.append((cpu, wall))
        same = np.load(npy).tobytes() == pts.tobytes()
        print(f"<!-- surface samples bit-identical to the CLI: {same} -->")
        assert same
        del pts
        results.append(row(f"{args.n:,} surface samples of {args.surface_model.name} into numpy vs `ism sample -o x.npy`", best(py_runs), best(rust_runs)))

        # 3. Queries on the large model. The evaluator builds each simplex's local map on first
        # touch, and a Model keeps its evaluator: the first query on a fresh model ("cold") is what
        # `ism query` does; a repeated query ("warm") reuses the maps.
        m = ism.read(args.large)
        rng = np.random.default_rng(1)
        lo, hi = m.vertices.min(axis=0), m.vertices.max(axis=0)
        points = rng.uniform(lo, hi, size=(args.n, m.dimension))
        pfile, one, qout = Path(tmp) / "p.npy", Path(tmp) / "one.npy", Path(tmp) / "q.npy"
        np.save(pfile, points)
        np.save(one, points[:1])
        py_runs, warm_runs, rust_runs = [], [], []
        for _ in range(args.repeat):
            del m
            gc.collect()
            m = ism.read(args.large)
            q, cpu, wall = timed_self(lambda: m.query(points))
            py_runs.append((cpu, wall))
            _, cpu, wall = timed_self(lambda: m.query(points))
            warm_runs.append((cpu, wall))
            _, cpu_n, wall_n = timed_child([ism_bin, "query", str(args.large), str(pfile), "-o", str(qout), "--quiet"])
            _, cpu_1, wall_1 = timed_child([ism_bin, "query", str(args.large), str(one), "-o", str(Path(tmp) / "q1.npy"), "--quiet"])
            rust_runs.append((cpu_n - cpu_1, wall_n - wall_1))
        same = np.load(qout).tobytes() == q.tobytes()
        print(f"<!-- query results bit-identical to the CLI: {same} -->")
        assert same
        results.append(row(f"query {args.n:,} points on {args.large.name}, first query of a fresh model, vs the library inside `ism query` (N points − 1 point)", best(py_runs), best(rust_runs)))
        results.append(row("… the same query repeated on the same Model (local maps kept), vs the same CLI figure", best(warm_runs), best(rust_runs)))
    print(json.dumps(results))


if __name__ == "__main__":
    main()
