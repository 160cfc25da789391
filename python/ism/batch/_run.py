"""The driver: resumes finished items, submits the rest to a Dask cluster, shows progress,
compacts the sample shards and writes the summary table."""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import sys
import time
import uuid
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Iterable, List, Optional, Sequence, Union

import ism

from ._item import (
    BAD_VERDICTS,
    DEFAULTS,
    SAMPLE_KINDS,
    SUMMARY_COLUMNS,
    atomic_write,
    output_paths,
    process_item,
    write_bytes_atomic,
)
from ._manifest import Item, load_manifest, merged_options


@dataclass
class RunResult:
    """What a run did. ``rows`` is the summary (resumed items' rows included)."""

    rows: List[Dict[str, Any]]
    items: int
    submitted: int  # items computed in this run
    resumed: int  # items whose done marker was current (no work)
    failed: List[str]  # ids of items with a bad row (error / invalid / undetermined)
    seconds: float
    shards_written: int = 0
    shards_kept: int = 0
    dashboard: Optional[str] = None
    pids: Dict[str, int] = field(default_factory=dict)  # item id -> worker pid that computed it
    tasks: Dict[Any, str] = field(default_factory=dict)  # task key -> item id

    @property
    def ok(self) -> bool:
        return not self.failed


def fingerprint(item: Item, options: Dict[str, Any]) -> str:
    """What an item's outputs depend on: input path, kind, options and the package version.
    Inputs are taken as immutable (``--force`` redoes everything after an input changed)."""
    key = {"path": item.path, "kind": item.kind, "options": options, "ism": ism.__version__, "format": ism.FORMAT_VERSION}
    return hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()


def item_failed(rows: Iterable[Dict[str, Any]]) -> bool:
    return any(r["verdict"] in BAD_VERDICTS for r in rows)


class Progress:
    """Items done/failed, rate and ETA on a terminal (one rewritten line) or a log (a line every
    ``interval`` seconds)."""

    def __init__(self, total: int, resumed: int, stream: Any = None, interval: Optional[float] = None) -> None:
        self.total, self.resumed = total, resumed
        self.done = self.failed = 0
        self.stream = stream if stream is not None else sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.interval = interval if interval is not None else (0.25 if self.tty else 5.0)
        self.t0 = time.monotonic()
        self.last = 0.0

    def line(self) -> str:
        elapsed = time.monotonic() - self.t0
        rate = self.done / elapsed if elapsed > 0 else 0.0
        todo = self.total - self.resumed - self.done
        eta = f"{todo / rate:.0f} s" if rate > 0 else "?"
        return (
            f"[ism.batch] {self.resumed + self.done}/{self.total} items "
            f"({self.failed} failed, {self.resumed} resumed), {rate:.2f} items/s, ETA {eta}"
        )

    def update(self, failed: bool, force: bool = False) -> None:
        self.done += 1
        self.failed += failed
        self.show(force)

    def show(self, force: bool = False) -> None:
        now = time.monotonic()
        if force or now - self.last >= self.interval:
            self.last = now
            if self.tty:
                self.stream.write("\r" + self.line() + "\x1b[K")
            else:
                self.stream.write(self.line() + "\n")
            self.stream.flush()

    def close(self) -> None:
        self.show(force=True)
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()


def _task_error_rows(item: Dict[str, Any], exc: BaseException) -> List[Dict[str, Any]]:
    row = {c: None for c in SUMMARY_COLUMNS}
    row.update(item=item["id"], input=item["path"], step="task", verdict="error", error=f"{type(exc).__name__}: {exc}")
    return [row]


def compact_shard(parts: Sequence[str], dest: str, token: str) -> int:
    """Concatenates per-item sample parts into one shard, one row group per item (in the given
    order); ``token`` (the items and their fingerprints) goes into the file's metadata so that a
    rerun keeps a current shard. Returns the number of rows."""
    import pyarrow.parquet as pq

    tables = [pq.read_table(p) for p in parts]
    schema = tables[0].schema.with_metadata({"ism.batch.token": token})

    def put(tmp: str) -> None:
        with pq.ParquetWriter(tmp, schema) as w:
            for t in tables:
                w.write_table(t.cast(schema), row_group_size=max(1, t.num_rows))

    atomic_write(dest, put)
    return sum(t.num_rows for t in tables)


def _shard_token(dest: str) -> Optional[str]:
    import pyarrow.parquet as pq

    try:
        meta = pq.read_schema(dest).metadata or {}
    except (OSError, ValueError):
        return None
    v = meta.get(b"ism.batch.token")
    return v.decode() if v else None


def write_summary(out: str, rows: List[Dict[str, Any]]) -> None:
    """``summary.parquet`` and ``summary.csv`` (same rows and columns), each written atomically."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    types = {
        "vertices": pa.int64(), "simplices": pa.int64(), "points": pa.int64(), "bytes": pa.int64(),
        "dimension": pa.int64(), "seconds": pa.float64(), "cpu_seconds": pa.float64(),
    }  # fmt: skip
    columns = list(SUMMARY_COLUMNS)
    schema = pa.schema([(c, types.get(c, pa.string())) for c in columns])
    table = pa.Table.from_pylist([{c: r.get(c) for c in columns} for r in rows], schema=schema)
    atomic_write(os.path.join(out, "summary.parquet"), lambda tmp: pq.write_table(table, tmp))
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow(["" if r.get(c) is None else r.get(c) for c in columns])
    write_bytes_atomic(os.path.join(out, "summary.csv"), buf.getvalue().encode())


def make_client(scheduler: Optional[str] = None, workers: Optional[int] = None, memory_limit: Union[str, int] = "4GiB",
                dashboard: Optional[str] = ":8787", allowed_failures: int = 3) -> Any:  # fmt: skip
    """A Dask client: to the scheduler at ``scheduler`` (``tcp://host:8786``), else to a new
    ``LocalCluster`` of ``workers`` single-threaded worker processes (default: this machine's
    cores), each restarted by its nanny if it dies or passes ``memory_limit``."""
    import dask
    from distributed import Client, LocalCluster

    if scheduler:
        return Client(scheduler)
    # A task whose worker died this many times is failed (KilledWorker) instead of retried again:
    # a file that kills every worker it touches must not take the run down.
    with dask.config.set({"distributed.scheduler.allowed-failures": allowed_failures}):
        cluster = LocalCluster(
            n_workers=workers or os.cpu_count() or 1,
            threads_per_worker=1,
            processes=True,
            memory_limit=memory_limit,
            dashboard_address=dashboard,
        )
    return Client(cluster)


def run(
    manifest: Union[str, Sequence[Item]],
    out: str,
    *,
    defaults: Optional[Dict[str, Any]] = None,
    client: Any = None,
    scheduler: Optional[str] = None,
    workers: Optional[int] = None,
    memory_limit: Union[str, int] = "4GiB",
    dashboard: Optional[str] = ":8787",
    threads: int = 1,
    retries: int = 2,
    allowed_failures: int = 3,
    window: Optional[int] = None,
    force: bool = False,
    redo_failed: bool = False,
    shard_items: int = 256,
    max_points: int = 10_000_000,
    max_input_bytes: int = 1 << 30,
    progress: Union[bool, Progress] = True,
    on_result: Optional[Callable[[Dict[str, Any], "RunResult"], None]] = None,
) -> RunResult:
    """Runs the pipeline on every item of ``manifest`` into the folder ``out``.

    Items whose done marker matches their fingerprint are not recomputed (unless ``force``;
    failed ones also with ``redo_failed``). ``client`` (a ``distributed.Client``) or
    ``scheduler`` (an address) selects the cluster; neither starts a ``LocalCluster``.
    ``retries`` re-runs a task that raised; a task whose worker died is re-run by the scheduler
    up to ``allowed_failures`` times (LocalCluster only; a remote scheduler has its own setting).
    At most ``window`` tasks are in flight (default: 4 per worker thread, at least 16), so the
    driver's memory does not grow with the corpus. ``on_result(result, partial)`` is called on
    the driver after each item (tests use it to kill a worker mid-run).
    """
    from distributed import as_completed

    t_start = time.monotonic()
    items = load_manifest(manifest) if isinstance(manifest, (str, os.PathLike)) else list(manifest)
    out = os.path.abspath(out)
    os.makedirs(out, exist_ok=True)
    base = {**DEFAULTS, **(defaults or {})}

    rows_by_item: Dict[str, List[Dict[str, Any]]] = {}
    fingerprints: Dict[str, str] = {}
    todo: List[Dict[str, Any]] = []
    for it in items:
        opts = merged_options(it, base)
        fp = fingerprint(it, opts)
        fingerprints[it.id] = fp
        marker = output_paths(out, it.id, opts)["done"]
        if not force and os.path.exists(marker):
            try:
                with open(marker, encoding="utf-8") as f:
                    done = json.load(f)
            except (OSError, ValueError):
                done = None
            if done and done.get("fingerprint") == fp and not (redo_failed and item_failed(done["rows"])):
                rows_by_item[it.id] = done["rows"]
                continue
        todo.append({**it.to_dict(), "options": opts, "fingerprint": fp})

    result = RunResult(rows=[], items=len(items), submitted=len(todo), resumed=len(items) - len(todo), failed=[], seconds=0.0)
    prog = progress if isinstance(progress, Progress) else Progress(len(items), result.resumed, stream=None if progress else io.StringIO())
    own_client = client is None
    if own_client and (todo or _shards_needed(out, items, rows_by_item, fingerprints, shard_items)):
        client = make_client(scheduler, workers, memory_limit, dashboard, allowed_failures)
    try:
        if client is not None:
            result.dashboard = getattr(client, "dashboard_link", None)
            if progress is not False and todo:
                prog.stream.write(f"[ism.batch] {len(todo)} item(s) to compute, {result.resumed} resumed; dashboard: {result.dashboard}\n")
        if todo:
            token = uuid.uuid4().hex[:8]
            nthreads = sum(client.nthreads().values()) or 1
            limit = window or max(16, 4 * nthreads)
            pending = iter(enumerate(todo))
            by_key: Dict[Any, Dict[str, Any]] = {}
            ac = as_completed()

            def submit_next() -> None:
                nxt = next(pending, None)
                if nxt is None:
                    return
                i, it = nxt
                # Tuple keys: the dashboard groups tasks by the first element ("ism-item").
                fut = client.submit(process_item, it, out, threads, max_points, max_input_bytes,
                                    key=("ism-item", token, i), retries=retries)  # fmt: skip
                by_key[fut.key] = it
                result.tasks[fut.key] = it["id"]
                ac.add(fut)

            prog.t0 = time.monotonic()  # the rate counts from the first task, not the cluster's start
            for _ in range(min(limit, len(todo))):
                submit_next()
            for fut in ac:
                it = by_key.pop(fut.key)
                try:
                    res = fut.result()
                    rows = res["rows"]
                    result.pids[it["id"]] = res["pid"]
                except Exception as exc:  # the engine gave up on it (KilledWorker, a bug): a row
                    rows = _task_error_rows(it, exc)
                fut.release()
                rows_by_item[it["id"]] = rows
                prog.update(item_failed(rows))
                submit_next()
                if on_result is not None:
                    on_result({"id": it["id"], "rows": rows}, result)
        # Shards of the sample parts: one row group per item, items in id order.
        result.shards_written, result.shards_kept = _compact(client, out, items, rows_by_item, fingerprints, shard_items)
    finally:
        if own_client and client is not None:
            cluster = getattr(client, "cluster", None)
            client.close()
            if cluster is not None and scheduler is None:
                cluster.close()
    prog.close()
    for it in items:
        result.rows.extend(rows_by_item.get(it.id, []))
    result.failed = [it.id for it in items if item_failed(rows_by_item.get(it.id, []))]
    write_summary(out, result.rows)
    result.seconds = time.monotonic() - t_start
    return result


def _shard_plan(out: str, items: Sequence[Item], rows_by_item: Dict[str, List[Dict[str, Any]]],
                fingerprints: Dict[str, str], shard_items: int) -> List[Dict[str, Any]]:  # fmt: skip
    """Every shard to have: kind (and dimension), destination, parts in id order, token."""
    plan = []
    for key, step, _ in SAMPLE_KINDS:
        by_dim: Dict[int, List[str]] = {}
        for it in items:
            for r in rows_by_item.get(it.id, []):
                if r["step"] == step and r["verdict"] == "ok" and r.get("output"):
                    by_dim.setdefault(int(r.get("dimension") or 0), []).append(it.id)
        for dim, ids in sorted(by_dim.items()):
            ids.sort()
            name = f"{key.replace('_', '-')}-{dim}d"
            for s in range(0, len(ids), shard_items):
                chunk = ids[s : s + shard_items]
                token = hashlib.sha256(json.dumps([[i, fingerprints[i]] for i in chunk]).encode()).hexdigest()
                parts = [os.path.join(out, "parts", key.replace("_", "-"), i + ".parquet") for i in chunk]
                dest = os.path.join(out, "samples", name, f"shard-{s // shard_items:05d}.parquet")
                plan.append({"dest": dest, "parts": parts, "token": token})
    return plan


def _shards_needed(out: str, items: Sequence[Item], rows_by_item: Dict[str, List[Dict[str, Any]]],
                   fingerprints: Dict[str, str], shard_items: int) -> bool:  # fmt: skip
    plan = _shard_plan(out, items, rows_by_item, fingerprints, shard_items)
    return any(_shard_token(p["dest"]) != p["token"] for p in plan) or bool(_stale_shards(out, plan))


def _stale_shards(out: str, plan: List[Dict[str, Any]]) -> List[str]:
    wanted = {p["dest"] for p in plan}
    root = os.path.join(out, "samples")
    found = [os.path.join(d, f) for d, _, fs in os.walk(root) for f in fs if f.startswith("shard-") and f.endswith(".parquet")]
    return [p for p in found if p not in wanted]


def _compact(client: Any, out: str, items: Sequence[Item], rows_by_item: Dict[str, List[Dict[str, Any]]],
             fingerprints: Dict[str, str], shard_items: int) -> "tuple[int, int]":  # fmt: skip
    plan = _shard_plan(out, items, rows_by_item, fingerprints, shard_items)
    todo = [p for p in plan if _shard_token(p["dest"]) != p["token"]]
    for stale in _stale_shards(out, plan):
        os.unlink(stale)
    if todo:
        futs = [client.submit(compact_shard, p["parts"], p["dest"], p["token"], key=("ism-shard", uuid.uuid4().hex[:8], i), retries=2)
                for i, p in enumerate(todo)]  # fmt: skip
        client.gather(futs)
    return len(todo), len(plan) - len(todo)
