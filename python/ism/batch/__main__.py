"""``python -m ism.batch MANIFEST -o OUT [options]``: the corpus pipeline from a shell.

Exit status: 0 when every item passed every step, 1 when some item failed (the summary names
them), 2 for a bad manifest or bad arguments.
"""

from __future__ import annotations

import argparse
import sys
from typing import List, Optional

from ._item import DEFAULTS, EXPORT_FORMATS, STEPS
from ._run import run

EPILOG = """\
manifest: a glob ("corpus/**/*.ismb"), a folder, a list file (.txt/.lst: one path per line), or a
table (.csv/.parquet) with a `path` column and optional `id`, `kind` (model|mesh) and per-row option
columns named as the options below with `_` for `-` (steps, encoding, export, export_tolerance,
surface, volume, near_surface, sigma, seed, resolution, tolerance, margin).
Inputs ending in .obj are closed triangle meshes: fitted first (as `ism fit --mesh`).

examples:
  python -m ism.batch "spec/examples/*.ismb" -o out --surface 5000 --seed 7
  python -m ism.batch corpus.csv -o out --workers 2 --memory-limit 2GiB
  python -m ism.batch corpus.parquet -o /shared/out --scheduler tcp://head:8786
"""


def _int_or_none(s: str) -> Optional[int]:
    return None if s.lower() in ("", "none") else int(s)


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m ism.batch",
        description="Read or fit, validate, convert, export and sample every item of a corpus on a Dask cluster.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("manifest", help="glob, folder, list file, .csv or .parquet table")
    p.add_argument("-o", "--out", required=True, help="output folder (reruns resume in it)")
    g = p.add_argument_group("pipeline (defaults for every item; table columns override per row)")
    g.add_argument("--steps", default=DEFAULTS["steps"], help=f"comma list of {','.join(STEPS)} (default: all); read/fit always runs")
    g.add_argument("--encoding", default=DEFAULTS["encoding"], choices=["binary", "compact", "compressed", "json", "msgpack", "structured"], help="convert: output encoding")
    g.add_argument("--export", default=DEFAULTS["export"], choices=EXPORT_FORMATS, help="export: format")
    g.add_argument("--export-tolerance", type=float, default=DEFAULTS["export_tolerance"], help="export: chordal tolerance")
    g.add_argument("--surface", type=int, default=DEFAULTS["surface"], help="sample: points on the shape (0: none)")
    g.add_argument("--volume", type=int, default=DEFAULTS["volume"], help="sample: points in |K| with inside/outside labels")
    g.add_argument("--near-surface", type=int, default=DEFAULTS["near_surface"], help="sample: labelled points near the shape")
    g.add_argument("--sigma", type=float, default=DEFAULTS["sigma"], help="near-surface displacement (model units)")
    g.add_argument("--seed", type=int, default=DEFAULTS["seed"], help="sampling seed (same seed = the CLI's points)")
    g.add_argument("--resolution", type=int, default=DEFAULTS["resolution"], help="mesh fit: initial grid cells")
    g.add_argument("--tolerance", type=float, default=None, help="mesh fit: tolerance (default as `ism fit`)")
    g.add_argument("--margin", type=float, default=DEFAULTS["margin"], help="mesh fit: domain margin")
    c = p.add_argument_group("cluster")
    c.add_argument("--scheduler", help="address of a running Dask scheduler (tcp://host:8786); default: a LocalCluster")
    c.add_argument("--workers", type=int, help="LocalCluster worker processes (default: the cores)")
    c.add_argument("--memory-limit", default="4GiB", help="LocalCluster: memory per worker; a worker above it is restarted")
    c.add_argument("--dashboard", default=":8787", help="LocalCluster dashboard address (default :8787)")
    c.add_argument("--threads", type=int, default=1, help="threads per task (rayon pool of each call)")
    c.add_argument("--retries", type=int, default=2, help="re-runs of a task that raised")
    c.add_argument("--allowed-failures", type=int, default=3, help="LocalCluster: worker deaths a task may cause before it fails")
    r = p.add_argument_group("run")
    r.add_argument("--force", action="store_true", help="recompute finished items too")
    r.add_argument("--redo-failed", action="store_true", help="recompute items that failed before")
    r.add_argument("--shard-items", type=int, default=256, help="items per sample shard")
    r.add_argument("--max-points", type=int, default=10_000_000, help="refuse sample counts above this (memory per task)")
    r.add_argument("--max-input-bytes", type=int, default=1 << 30, help="refuse input files above this size")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress line")
    a = p.parse_args(argv)
    defaults = {
        "steps": a.steps, "encoding": a.encoding, "export": a.export, "export_tolerance": a.export_tolerance,
        "surface": a.surface, "volume": a.volume, "near_surface": a.near_surface, "sigma": a.sigma, "seed": a.seed,
        "resolution": a.resolution, "tolerance": a.tolerance, "margin": a.margin,
    }  # fmt: skip
    try:
        result = run(
            a.manifest, a.out, defaults=defaults, scheduler=a.scheduler, workers=a.workers,
            memory_limit=a.memory_limit, dashboard=a.dashboard, threads=a.threads, retries=a.retries,
            allowed_failures=a.allowed_failures, force=a.force, redo_failed=a.redo_failed,
            shard_items=a.shard_items, max_points=a.max_points, max_input_bytes=a.max_input_bytes,
            progress=not a.quiet,
        )  # fmt: skip
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(
        f"{result.items} items: {result.submitted} computed, {result.resumed} resumed, {len(result.failed)} failed; "
        f"{result.shards_written} shard(s) written; {result.seconds:.1f} s; summary: {a.out}/summary.csv"
    )
    for i in result.failed:
        bad = [r for r in result.rows if r["item"] == i and r["verdict"] in ("error", "invalid", "undetermined")]
        for r in bad:
            print(f"  {i}: {r['step']} {r['verdict']}: {r['rule'] or ''} {r['error'] or ''}".rstrip())
    return 0 if result.ok else 1


if __name__ == "__main__":
    sys.exit(main())
