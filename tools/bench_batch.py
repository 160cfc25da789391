"""Benchmark of the corpus pipeline (`python -m ism.batch`, issue 20) against the CLI alone on the
same items, in one run.

    ISM_BIN=target/release/ism .venv/bin/python tools/bench_batch.py [--variants 5] [--meshes 4]
        [--points 2000] [--workers 1,2]

Items: `tools/batch_corpus.py` (spec examples moved and rescaled, in rotating encodings, plus small
ellipsoid meshes to fit), the good ones only. Steps per item: read (or fit), validate, convert to
.ismb, export .glb (tolerance 1e-3), sample surface / volume / near-surface (--points each, seed 1).

Rows (CPU = user + system of every thread, from getrusage; wall from the clock):
1. the CLI alone: per item `ism fit --mesh` (meshes), `ism validate`, `ism convert`, `ism export`,
   three `ism sample` runs, one after another (children's CPU);
2. the same steps in this process through the package, no engine (`ism.batch.process_item` in a
   loop): the work without Dask;
3. `ism.batch.run` on a LocalCluster of 1 and of 2 single-threaded worker processes: wall of the
   run; CPU of the workers (getrusage inside each, before/after), of this process (the driver,
   which also hosts the scheduler) and of cluster start-up, reported apart.
Per-item overhead = (engine CPU − in-process CPU) / items. The projection to N machines uses the
measured per-item CPU and bytes; its assumptions are printed with it.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time

import ism
from ism import batch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_spec = importlib.util.spec_from_file_location("batch_corpus", os.path.join(ROOT, "tools", "batch_corpus.py"))
batch_corpus = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(batch_corpus)


def cpu_self() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def cpu_children() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _worker_cpu() -> float:
    return cpu_self()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--variants", type=int, default=5)
    ap.add_argument("--meshes", type=int, default=4)
    ap.add_argument("--points", type=int, default=2000)
    ap.add_argument("--workers", default="1,2")
    a = ap.parse_args()
    exe = os.environ.get("ISM_BIN") or os.path.join(ROOT, "target", "release", "ism")
    tmp = tempfile.mkdtemp(prefix="bench_batch_")
    corpus = batch_corpus.make_corpus(os.path.join(tmp, "corpus"), a.variants, a.meshes)
    folder = os.path.join(tmp, "corpus")
    good = [os.path.join(folder, g) for g in corpus["good"]]
    n = len(good)
    opts = {"surface": a.points, "volume": a.points, "near_surface": a.points, "sigma": 0.01, "seed": 1, "export_tolerance": 1e-3,
            "resolution": 4, "tolerance": 2e-2}  # fmt: skip
    in_bytes = sum(os.path.getsize(p) for p in good)
    print(f"machine: {platform.node()}, {os.cpu_count()} cores, {platform.processor() or platform.machine()}, "
          f"Python {platform.python_version()}, ism {ism.__version__}; CLI {exe}")  # fmt: skip
    print(f"items: {n} ({len(corpus['meshes'])} meshes), {in_bytes} input bytes; {a.points} points per sample set\n")

    # 1. The CLI alone.
    cli_out = os.path.join(tmp, "cli")
    os.makedirs(cli_out)
    c0, t0 = cpu_children(), time.perf_counter()
    p = str(a.points)
    for path in good:
        base = os.path.join(cli_out, os.path.basename(path))
        src = path
        q = ["--quiet"]
        if path.endswith(".obj"):
            subprocess.run([exe, "fit", "--mesh", path, "--resolution", "4", "--tolerance", "2e-2", "-o", base + ".fit.ismb", *q], check=True)
            src = base + ".fit.ismb"
        for cmd in (["validate", src, *q], ["convert", src, base + ".ismb"], ["export", src, base + ".glb", "--tolerance", "1e-3", *q],
                    ["sample", src, "--surface", p, "--seed", "1", "-o", base + ".s.npy", *q],
                    ["sample", src, "--volume", p, "--seed", "1", "-o", base + ".v.npy", *q],
                    ["sample", src, "--near-surface", p, "--sigma", "0.01", "--seed", "1", "-o", base + ".n.npy", *q]):  # fmt: skip
            subprocess.run([exe, *cmd], check=True, stdout=subprocess.DEVNULL)
    cli_cpu, cli_wall = cpu_children() - c0, time.perf_counter() - t0
    print(f"{'run':<34} {'wall s':>8} {'CPU s':>8} {'CPU ms/item':>12}")
    print(f"{'CLI alone (7 processes/item)':<34} {cli_wall:8.2f} {cli_cpu:8.2f} {1000 * cli_cpu / n:12.1f}")

    # 2. In process, no engine.
    out = os.path.join(tmp, "inproc")
    items = batch.load_manifest(folder)
    items = [it for it in items if it.id in set(corpus["good"])]
    from ism.batch._run import fingerprint

    c0, t0 = cpu_self(), time.perf_counter()
    out_bytes = 0
    for it in items:
        o = {**batch.DEFAULTS, **opts}
        res = batch.process_item({**it.to_dict(), "options": o, "fingerprint": fingerprint(it, o)}, out)
        out_bytes += sum(r["bytes"] or 0 for r in res["rows"] if r["step"] in ("convert", "export", "fit"))
        assert not [r for r in res["rows"] if r["verdict"] in ("error", "invalid")], res
    ip_cpu, ip_wall = cpu_self() - c0, time.perf_counter() - t0
    sample_bytes = sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(os.path.join(out, "parts")) for f in fs)
    out_bytes += sample_bytes
    print(f"{'in process, no engine':<34} {ip_wall:8.2f} {ip_cpu:8.2f} {1000 * ip_cpu / n:12.1f}")

    # 3. The engine.
    from distributed import Client, LocalCluster

    engine = {}
    for w in [int(x) for x in a.workers.split(",")]:
        c0, t0 = cpu_self(), time.perf_counter()
        cluster = LocalCluster(n_workers=w, threads_per_worker=1, processes=True, dashboard_address=None, memory_limit="4GiB")
        client = Client(cluster)
        start_cpu, start_wall = cpu_self() - c0, time.perf_counter() - t0
        wc0 = sum(client.run(_worker_cpu).values())
        out = os.path.join(tmp, f"engine{w}")
        c0, t0 = cpu_self(), time.perf_counter()
        res = batch.run(items, out, defaults=opts, client=client, progress=False)
        wall, drv = time.perf_counter() - t0, cpu_self() - c0
        wcpu = sum(client.run(_worker_cpu).values()) - wc0
        assert not res.failed and res.submitted == n
        c0, t0 = cpu_self(), time.perf_counter()
        res2 = batch.run(items, out, defaults=opts, client=client, progress=False)
        rerun = time.perf_counter() - t0
        assert res2.submitted == 0
        client.close()
        cluster.close()
        engine[w] = (wall, wcpu, drv)
        print(f"{f'ism.batch, {w} worker(s)':<34} {wall:8.2f} {wcpu + drv:8.2f} {1000 * (wcpu + drv) / n:12.1f}"
              f"   (workers {wcpu:.2f} s, driver+scheduler {drv:.2f} s; cluster start {start_wall:.1f} s wall, "
              f"{start_cpu:.2f} s CPU; rerun with nothing to do {rerun:.2f} s)")  # fmt: skip
    shutil.rmtree(tmp)

    w1 = engine[min(engine)]
    over = (w1[1] + w1[2] - ip_cpu) / n
    print(f"\nper-item overhead of the engine: {1000 * over:.1f} ms CPU "
          f"(workers {1000 * (w1[1] - ip_cpu) / n:.1f} ms, driver+scheduler {1000 * w1[2] / n:.1f} ms); "
          f"CLI alone costs {1000 * (cli_cpu - ip_cpu) / n:.1f} ms CPU/item more than in-process")  # fmt: skip
    if len(engine) > 1:
        lo, hi = min(engine), max(engine)
        print(f"speed-up {lo} -> {hi} workers: {engine[lo][0] / engine[hi][0]:.2f}x wall")
    per_item = (w1[1]) / n
    drv_item = w1[2] / n
    io_item = (in_bytes + out_bytes) / n
    print(f"\nprojection: per item {per_item * 1000:.1f} ms worker CPU, {drv_item * 1000:.2f} ms scheduler+driver CPU, "
          f"{io_item / 1e3:.1f} kB read+written")  # fmt: skip
    print("assumptions: machines of c=16 cores as fast per core as this VM's (which has 2), one "
          "single-threaded worker per core, the same item mix; one scheduler (Dask's is one Python "
          "process) whose CPU per task stays at the driver+scheduler cost measured here; a shared "
          "file system giving 1 GB/s in aggregate; no other bottleneck.")  # fmt: skip
    for N in (1, 10, 100, 1000):
        compute = N * 16 / per_item
        sched = 1 / drv_item
        io_rate = 1e9 / io_item
        rate = min(compute, sched, io_rate)
        lim = "compute" if rate == compute else ("scheduler" if rate == sched else "storage")
        print(f"  N={N:5d}: {rate:10.0f} items/s ({lim}-bound), 1e6 items in {1e6 / rate / 60:8.1f} min")


if __name__ == "__main__":
    main()
