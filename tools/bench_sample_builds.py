"""Two builds of `ism` side by side on `ism sample --surface N` (or, with `--command export`, on
`ism export --tolerance T`): what a change costs or saves.

For each MODEL:N, runs `BIN sample MODEL --surface N -j 1 -q --seed SEED -o out.npy` with the
old and the new binary alternately, REPEAT times each, and keeps the least CPU time of each
(user + system of the child, `resource.getrusage(RUSAGE_CHILDREN)` before and after: the machine
is shared, so wall time is noisy and the best of alternated runs is the fairest figure). Prints a
Markdown table — CPU seconds old and new, their ratio, the new CPU per simplex of the model for
N = 1 (the setup: read, evaluator, certified table, one sample) and whether the two outputs are
the same bytes (a change that keeps the tables must keep them) — and the load average before and
after.

With `--command export` each case is MODEL:T and the runs are `BIN export MODEL out.obj
--tolerance T -j 1 -q --json`; the table then gives each build's triangles (from `--json`) and
the new build's triangles per CPU-second instead of the per-simplex setup.

Usage: python3 tools/bench_sample_builds.py --old OLD_ISM --new NEW_ISM [--repeat 3] [--seed 3]
           [--seeds K] [--command sample|export] MODEL:N|MODEL:T [...]
  --seeds K (sample only): seeds 0..K-1, each the least of REPEAT runs; the table then gives the
  means over the seeds, and for N = 1 the new build's largest per-simplex figure as well (one
  sample's cost depends on the seed: its candidates are rejected at the rate the bounds allow).
  e.g. an old build from a worktree:
    git worktree add /tmp/old <rev> && CARGO_TARGET_DIR=/tmp/oldtarget cargo build --release -p ism-cli
    python3 tools/bench_sample_builds.py --old /tmp/oldtarget/release/ism \\
        --new target/release/ism spec/examples/torus.ismb:1 spec/examples/torus.ismb:10000
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


def child_cpu(cmd: list[str]) -> tuple[float, str]:
    """User + system CPU seconds of one run of `cmd` (which must succeed), and its stdout."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    out = subprocess.run(
        cmd, check=True, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    )
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), out.stdout


def simplices(ism: str, model: str) -> int | None:
    """The model's top simplex count from `ism info --json` (None if it does not say)."""
    out = subprocess.run([ism, "info", model, "--json"], capture_output=True, text=True)
    if out.returncode != 0:
        return None
    info = json.loads(out.stdout)
    count = info.get("simplices", info.get("num_simplices"))
    return count if isinstance(count, int) else None


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--old", required=True, help="the old `ism` binary")
    ap.add_argument("--new", required=True, help="the new `ism` binary")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seed", default="3")
    ap.add_argument(
        "--seeds",
        type=int,
        default=0,
        help="sample only: run seeds 0..SEEDS-1 instead of --seed and give the means over them "
        "(the least CPU of --repeat runs per seed), with the largest per-simplex figure for N = 1",
    )
    ap.add_argument("--command", choices=["sample", "export"], default="sample")
    ap.add_argument("cases", nargs="+", metavar="MODEL:N")
    args = ap.parse_args()
    bins = {"old": args.old, "new": args.new}

    def stamp() -> str:
        load = tuple(round(x, 2) for x in os.getloadavg())
        return f"load {load} at {time.strftime('%H:%M:%S', time.gmtime())} UTC"

    print(stamp())
    export = args.command == "export"
    if export:
        print(
            "| model | T | old CPU s | new CPU s | new / old | old triangles | new triangles "
            "| new triangles per CPU-s | same bytes |"
        )
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    else:
        print(
            "| model | N | old CPU s | new CPU s | new / old | new µs per simplex (N = 1) "
            "| same bytes |"
        )
        print("| --- | --- | --- | --- | --- | --- | --- |")
    with tempfile.TemporaryDirectory() as tmp:
        for case in args.cases:
            model, n = case.rsplit(":", 1)
            seeds = [str(s) for s in range(args.seeds)] if args.seeds and not export else [args.seed]
            per_seed: dict[str, list[float]] = {k: [] for k in bins}
            stdout: dict[str, str] = {}
            same = True
            for seed in seeds:
                best: dict[str, float] = {}
                out = {k: os.path.join(tmp, f"{k}.{'obj' if export else 'npy'}") for k in bins}
                for _ in range(args.repeat):
                    for k, ism in bins.items():
                        if export:
                            cmd = [ism, "export", model, out[k], "--tolerance", n]
                            cmd += ["-j", "1", "-q", "--json"]
                        else:
                            cmd = [ism, "sample", model, "--surface", n, "-j", "1", "-q"]
                            cmd += ["--seed", seed, "-o", out[k]]
                        cpu, stdout[k] = child_cpu(cmd)
                        best[k] = min(best.get(k, float("inf")), cpu)
                same = same and filecmp.cmp(out["old"], out["new"], shallow=False)
                for k in bins:
                    per_seed[k].append(best[k])
            # One seed: its least CPU; several: the mean over seeds of each seed's least.
            best = {k: sum(v) / len(v) for k, v in per_seed.items()}
            ratio = best["new"] / best["old"]
            head = f"| {os.path.basename(model)} | {n} | {best['old']:.4f} | {best['new']:.4f} | {ratio:.3f}"
            if export:
                tri = {k: json.loads(v)["cells"] for k, v in stdout.items()}
                rate = tri["new"] / best["new"] if best["new"] > 0 else float("inf")
                print(
                    f"{head} | {tri['old']} | {tri['new']} | {rate / 1e3:.0f}k "
                    f"| {'yes' if same else 'no'} |",
                    flush=True,
                )
                continue
            per = ""
            if n == "1":
                count = simplices(args.new, model)
                per = f"{best['new'] / count * 1e6:.1f}" if count else "?"
                if count and len(seeds) > 1:
                    per += f" (largest {max(per_seed['new']) / count * 1e6:.1f})"
            print(f"{head} | {per} | {'yes' if same else 'no'} |", flush=True)
    print(stamp())


if __name__ == "__main__":
    main()
