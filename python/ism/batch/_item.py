"""The work of one item, as it runs on a worker: read or fit, validate, convert, export, sample.

Every per-item file is written under a temporary name in its final folder and then renamed
(:func:`atomic_write`), so a reader, a rerun or a retried task never sees half a file; the item's
done marker (``done/<id>.json``, holding its summary rows) is written last. A task that dies before
its marker is simply run again: every step is deterministic (sampling is seeded), so a retry
writes the same bytes.

Errors of the input (an :class:`ism.ISMError`, an unreadable mesh) become summary rows with the
rule id and location; they are not raised, so one bad file never stops the corpus.
"""

from __future__ import annotations

import json
import os
import time
import uuid
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np

import ism

#: Steps in the order they run; ``read`` (model inputs) or ``fit`` (mesh inputs) always runs first.
STEPS = ("validate", "convert", "export", "sample")
#: The three sample sets: (option name, step name, Model method).
SAMPLE_KINDS = (
    ("surface", "sample-surface", "sample_surface"),
    ("volume", "sample-volume", "sample_volume"),
    ("near_surface", "sample-near-surface", "sample_near_surface"),
)
ENCODING_SUFFIX = {"binary": ".ismb", "compact": ".ismc", "compressed": ".ismz", "structured": ".isms", "json": ".ism.json", "msgpack": ".ism.msgpack"}
EXPORT_FORMATS = ("glb", "gltf", "obj", "vtk", "vtu")

#: Run defaults (every one can be overridden per row of a table manifest).
DEFAULTS: Dict[str, Any] = {
    "steps": ",".join(STEPS),
    "encoding": "binary",
    "export": "glb",
    "export_tolerance": 1e-3,  # the CLI's `ism export --tolerance` default
    "surface": 10_000,
    "volume": 10_000,
    "near_surface": 10_000,
    "sigma": 0.01,
    "seed": 0,
    "resolution": 8,  # `ism fit --resolution` default
    "tolerance": None,  # `ism fit`: 1e-3 × the domain's longest side
    "margin": 0.05,  # `ism fit --mesh-margin` default
}

#: Columns of the summary table, in order.
SUMMARY_COLUMNS = (
    "item", "input", "step", "verdict", "dimension", "vertices", "simplices", "points", "bytes",
    "seconds", "cpu_seconds", "rule", "location", "error", "output",
)  # fmt: skip

#: Verdicts that make an item "failed" in the summary and the progress counts.
BAD_VERDICTS = ("error", "invalid", "undetermined")


def atomic_write(path: str, write: Callable[[str], None]) -> None:
    """Calls ``write(tmp)`` for a temporary name beside ``path`` (same suffix, so writers that
    choose a format from the extension work) and renames it to ``path``; the temporary file is
    removed if ``write`` fails."""
    folder, name = os.path.split(path)
    os.makedirs(folder, exist_ok=True)
    tmp = os.path.join(folder, f".tmp-{uuid.uuid4().hex}-{name}")
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def write_bytes_atomic(path: str, data: bytes) -> None:
    def put(tmp: str) -> None:
        with open(tmp, "wb") as f:
            f.write(data)

    atomic_write(path, put)


def read_obj(path: str, max_bytes: int) -> Tuple[np.ndarray, np.ndarray]:
    """The triangles of an OBJ file as ``ism fit --mesh`` reads them (tobj with triangulation):
    positions as float32 (then float64), faces fan-triangulated, vertices numbered in order of
    first use by a face, negative (relative) indices resolved; texture and normal indices ignored.

    Hand-written because the compiled package takes arrays, not mesh files (``TriangleMesh::load``
    is not bound), and the fit is bit-identical to the CLI only on the very arrays the CLI reads:
    trimesh and meshio renumber or merge vertices differently. ``python/tests/test_batch.py``
    checks the result against ``ism fit --mesh``.
    """
    size = os.path.getsize(path)
    if size > max_bytes:
        raise ValueError(f"{path}: {size} bytes, more than the limit of {max_bytes} (--max-input-bytes)")
    positions: List[Tuple[float, float, float]] = []
    order: Dict[int, int] = {}
    faces: List[Tuple[int, int, int]] = []
    with open(path, encoding="utf-8", errors="strict") as f:
        for lineno, line in enumerate(f, 1):
            parts = line.split("#", 1)[0].split()
            if not parts:
                continue
            if parts[0] == "v":
                if len(parts) < 4:
                    raise ValueError(f"{path}:{lineno}: a vertex needs 3 coordinates")
                positions.append(tuple(float(np.float32(p)) for p in parts[1:4]))  # type: ignore[misc]
            elif parts[0] == "f":
                ids = []
                for p in parts[1:]:
                    k = int(p.split("/", 1)[0])
                    k = k - 1 if k > 0 else len(positions) + k
                    if not 0 <= k < len(positions):
                        raise ValueError(f"{path}:{lineno}: vertex index {p} out of range")
                    ids.append(order.setdefault(k, len(order)))
                if len(ids) < 3:
                    raise ValueError(f"{path}:{lineno}: a face needs at least 3 vertices")
                faces.extend((ids[0], ids[i], ids[i + 1]) for i in range(1, len(ids) - 1))
    if not faces:
        raise ValueError(f"{path}: no triangle")
    used = sorted(order, key=order.__getitem__)
    return np.array([positions[k] for k in used], dtype=np.float64), np.array(faces, dtype=np.int64)


class _Step:
    """Times one step and turns its outcome into a summary row."""

    def __init__(self, rows: List[Dict[str, Any]], item: Dict[str, Any], step: str) -> None:
        self.row: Dict[str, Any] = {c: None for c in SUMMARY_COLUMNS}
        self.row.update(item=item["id"], input=item["path"], step=step, verdict="ok")
        rows.append(self.row)

    def __enter__(self) -> "_Step":
        self.t0, self.c0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, kind: Any, exc: Any, tb: Any) -> bool:
        self.row["seconds"] = time.perf_counter() - self.t0
        self.row["cpu_seconds"] = time.process_time() - self.c0
        if exc is None:
            return False
        if not isinstance(exc, Exception):  # KeyboardInterrupt, SystemExit: not the input's fault
            return False
        self.row["verdict"] = "error"
        self.row["error"] = f"{type(exc).__name__}: {exc}"
        self.row["rule"] = getattr(exc, "rule", None)
        location = getattr(exc, "location", None)
        self.row["location"] = json.dumps(location, sort_keys=True) if location else None
        return True  # recorded: the item goes on (or stops) by the row's verdict

    @property
    def failed(self) -> bool:
        return self.row["verdict"] in BAD_VERDICTS


def _skip(rows: List[Dict[str, Any]], item: Dict[str, Any], step: str, why: str) -> None:
    row = {c: None for c in SUMMARY_COLUMNS}
    row.update(item=item["id"], input=item["path"], step=step, verdict="skipped", error=why)
    rows.append(row)


def _steps_of(opts: Dict[str, Any]) -> List[str]:
    steps = [s.strip() for s in str(opts["steps"]).split(",") if s.strip()]
    unknown = [s for s in steps if s not in STEPS]
    if unknown:
        raise ValueError(f"unknown step(s) {unknown}; known: {', '.join(STEPS)}")
    return steps


def sample_table(item_id: str, points: np.ndarray) -> Any:
    """A sample set as an Arrow table: the item id, then the sampler's fields, same dtypes (so
    each column holds the bits of ``ism sample -o x.npy``)."""
    import pyarrow as pa

    cols = [pa.array(np.full(len(points), item_id, dtype=object), type=pa.string())]
    cols += [pa.array(np.ascontiguousarray(points[name])) for name in points.dtype.names]
    return pa.Table.from_arrays(cols, names=["item", *points.dtype.names])


def write_parquet_atomic(path: str, table: Any, metadata: Optional[Dict[str, str]] = None) -> None:
    """One row group for the whole table (``row_group_size`` = its length)."""
    import pyarrow.parquet as pq

    if metadata:
        table = table.replace_schema_metadata({**(table.schema.metadata or {}), **metadata})
    atomic_write(path, lambda tmp: pq.write_table(table, tmp, row_group_size=max(1, table.num_rows)))


def output_paths(out: str, item_id: str, opts: Dict[str, Any]) -> Dict[str, str]:
    """Where an item's files go (relative folders of the output directory)."""
    p = {
        "fit": os.path.join(out, "fitted", item_id + ".ismb"),
        "report": os.path.join(out, "reports", item_id + ".json"),
        "convert": os.path.join(out, "models", item_id + ENCODING_SUFFIX.get(str(opts["encoding"]), ".bad")),
        "export": os.path.join(out, "exports", f"{item_id}.{opts['export']}"),
        "done": os.path.join(out, "done", item_id + ".json"),
    }
    for key, _, _ in SAMPLE_KINDS:
        p[key] = os.path.join(out, "parts", key.replace("_", "-"), item_id + ".parquet")
    return p


def process_item(item: Dict[str, Any], out: str, threads: int = 1, max_points: int = 10_000_000,
                 max_input_bytes: int = 1 << 30) -> Dict[str, Any]:  # fmt: skip
    """Runs the item's steps and returns ``{"id", "fingerprint", "rows", "pid"}``; writes its
    outputs and, last, its done marker. ``item`` is :meth:`Item.to_dict` plus ``fingerprint``
    and the merged ``options``."""
    opts = {**DEFAULTS, **item["options"]}
    rows: List[Dict[str, Any]] = []
    paths = output_paths(out, item["id"], opts)
    model: Optional[ism.Model] = None
    first = "fit" if item["kind"] == "mesh" else "read"
    with _Step(rows, item, first) as st:
        steps = _steps_of(opts)
        if opts["encoding"] not in ENCODING_SUFFIX:
            raise ValueError(f"encoding {opts['encoding']!r}: expected one of {', '.join(ENCODING_SUFFIX)}")
        if opts["export"] not in EXPORT_FORMATS:
            raise ValueError(f"export {opts['export']!r}: expected one of {', '.join(EXPORT_FORMATS)}")
        if item["kind"] == "mesh":
            vertices, faces = read_obj(item["path"], max_input_bytes)
            name = os.path.basename(item["path"]).rsplit(".", 1)[0]
            model, report = ism.fit_mesh(vertices, faces, resolution=int(opts["resolution"]),
                                         tolerance=opts["tolerance"], margin=float(opts["margin"]), name=name)  # fmt: skip
            data = model.to_bytes("binary")
            write_bytes_atomic(paths["fit"], data)
            st.row.update(bytes=len(data), output=paths["fit"])
            # The library's verdict (`outcome`, as `ism fit` exits 1 on anything but "passed").
            if report["outcome"] != "passed":
                st.row["verdict"] = "warning"
                st.row["error"] = f"fit: {report['outcome']} (tolerance met {report.get('toleranceMet')}, topology matches {report.get('topologyMatches')})"
        else:
            size = os.path.getsize(item["path"])
            if size > max_input_bytes:
                raise ValueError(f"{size} bytes, more than the limit of {max_input_bytes} (--max-input-bytes)")
            model = ism.read(item["path"])
            st.row["bytes"] = size
        st.row.update(dimension=model.dimension, vertices=model.num_vertices, simplices=model.num_simplices)
    if st.failed or model is None:
        for step in ("validate", "convert", "export", "sample"):
            if step in opts.get("steps", ""):
                _skip(rows, item, step, f"{first} failed")
        return _finish(item, rows, paths)

    valid = True
    if "validate" in steps:
        with _Step(rows, item, "validate") as st:
            report = model.validate(threads=threads)
            d = report.to_dict()
            write_bytes_atomic(paths["report"], json.dumps(d, sort_keys=True).encode())
            st.row.update(verdict=report.verdict, output=paths["report"],
                          vertices=model.num_vertices, simplices=model.num_simplices)  # fmt: skip
            errors = [m for m in report.diagnostics if m.get("severity") == "error"]
            if errors:
                st.row.update(rule=errors[0].get("code"), error=errors[0].get("message"),
                              location=json.dumps(errors[0].get("location"), sort_keys=True))  # fmt: skip
        valid = not st.failed
    rest = [s for s in steps if s != "validate"]
    if not valid:
        for step in rest:
            _skip(rows, item, step, "model not valid")
        return _finish(item, rows, paths)

    if "convert" in rest:
        with _Step(rows, item, "convert") as st:
            data = model.to_bytes(str(opts["encoding"]))
            write_bytes_atomic(paths["convert"], data)
            st.row.update(bytes=len(data), output=paths["convert"])
    if "export" in rest:
        with _Step(rows, item, "export") as st:
            final = paths["export"]
            atomic_write(final, lambda tmp: model.export(tmp, tolerance=float(opts["export_tolerance"]), threads=threads))
            st.row.update(bytes=os.path.getsize(final), output=final)
    if "sample" in rest:
        for key, step, method in SAMPLE_KINDS:
            n = int(opts[key] or 0)
            if n <= 0:
                continue
            with _Step(rows, item, step) as st:
                if n > max_points:
                    raise ValueError(f"{key} = {n} points, more than the limit of {max_points} (--max-points)")
                seed = int(opts["seed"])
                if key == "near_surface":
                    pts = model.sample_near_surface(n, float(opts["sigma"]), seed=seed, threads=threads)
                else:
                    pts = getattr(model, method)(n, seed=seed, threads=threads)
                write_parquet_atomic(paths[key], sample_table(item["id"], pts))
                st.row.update(dimension=model.dimension, points=len(pts), output=paths[key])
    return _finish(item, rows, paths)


def _finish(item: Dict[str, Any], rows: List[Dict[str, Any]], paths: Dict[str, str]) -> Dict[str, Any]:
    result = {"id": item["id"], "fingerprint": item["fingerprint"], "rows": rows, "pid": os.getpid()}
    write_bytes_atomic(paths["done"], json.dumps(result, sort_keys=True).encode())
    return result
