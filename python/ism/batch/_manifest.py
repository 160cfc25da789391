"""The manifest: which inputs to process, each with its own options.

A manifest is one of

- a glob pattern (``"corpus/**/*.ismb"``, recursive ``**`` allowed) or a directory (every file
  under it whose name ends in a known extension);
- a list file (``.txt`` / ``.lst``): one path per line, ``#`` starts a comment;
- a table (``.csv``, ``.parquet``): a ``path`` column and optional ``id``, ``kind`` and option
  columns (:data:`OPTION_TYPES`); an empty cell takes the run's default.

Relative paths in a list file or table are relative to the manifest's folder. Item ids default
to the path relative to the deepest folder holding every input, with ``/`` turned into ``__``
(ids name the per-item output files, so they are made file-name safe and must be unique).
"""

from __future__ import annotations

import csv
import glob
import os
import re
from dataclasses import dataclass, field
from typing import Any, Dict, Iterable, List, Optional

#: Per-item options (manifest columns / run defaults) and their types.
OPTION_TYPES: Dict[str, type] = {
    "steps": str,  # comma list of validate,convert,export,sample (read/fit always runs)
    "encoding": str,  # convert: binary | compact | json | msgpack
    "export": str,  # export format: glb | gltf | obj | vtk | vtu
    "export_tolerance": float,
    "surface": int,  # sample counts (0 = none)
    "volume": int,
    "near_surface": int,
    "sigma": float,  # near-surface displacement
    "seed": int,
    "resolution": int,  # fit_mesh (mesh inputs)
    "tolerance": float,
    "margin": float,
}

#: File endings of models and meshes (a directory manifest takes these).
MODEL_SUFFIXES = (".ism.json", ".ism.msgpack", ".ismb", ".ismc", ".ismz", ".isms")
MESH_SUFFIXES = (".obj",)
KNOWN_SUFFIXES = MODEL_SUFFIXES + MESH_SUFFIXES + (".json", ".msgpack")

_UNSAFE = re.compile(r"[^A-Za-z0-9._+-]+")


@dataclass
class Item:
    """One input of the corpus."""

    id: str
    path: str
    kind: str  # "model" (an ISM file, any encoding) or "mesh" (a closed triangle mesh to fit)
    options: Dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> Dict[str, Any]:
        return {"id": self.id, "path": self.path, "kind": self.kind, "options": dict(self.options)}


def kind_of(path: str) -> str:
    """``"mesh"`` for mesh files (fitted first), ``"model"`` for everything else (the reader
    detects the encoding from the content and rejects what is not a model)."""
    return "mesh" if path.lower().endswith(MESH_SUFFIXES) else "model"


def item_id(path: str, base: str) -> str:
    """A file-name-safe id from ``path`` relative to ``base``."""
    rel = os.path.relpath(path, base) if base else os.path.basename(path)
    rel = rel.replace(os.sep, "/").replace("/", "__")
    return _UNSAFE.sub("_", rel)


def coerce(name: str, value: Any) -> Any:
    """An option value of the manifest as its type; ``None``/empty stays ``None`` (the default)."""
    if name not in OPTION_TYPES:
        raise ValueError(f"unknown option {name!r}; known: {', '.join(sorted(OPTION_TYPES))}")
    if value is None or (isinstance(value, str) and value.strip() == ""):
        return None
    if isinstance(value, float) and value != value:  # NaN = missing cell in a Parquet/pandas table
        return None
    t = OPTION_TYPES[name]
    if t is int:
        f = float(value)
        if f != int(f):
            raise ValueError(f"option {name}: expected an integer, got {value!r}")
        return int(f)
    return t(value)


def _common_folder(paths: List[str]) -> str:
    return os.path.commonpath([os.path.dirname(os.path.abspath(p)) for p in paths]) if paths else ""


def _from_paths(paths: Iterable[str]) -> List[Item]:
    full = [os.path.abspath(p) for p in paths]
    base = _common_folder(full)
    return [Item(item_id(p, base), p, kind_of(p)) for p in full]


def _from_rows(rows: Iterable[Dict[str, Any]], folder: str, where: str) -> List[Item]:
    items = []
    unnamed = []
    for n, row in enumerate(rows, 1):
        row = {str(k).strip(): v for k, v in row.items() if k is not None}
        path = row.pop("path", None)
        if path is None or str(path).strip() == "":
            raise ValueError(f"{where}, row {n}: no path")
        path = str(path).strip()
        full = path if os.path.isabs(path) else os.path.join(folder, path)
        given_id = row.pop("id", None)
        kind = row.pop("kind", None)
        options = {}
        for k, v in row.items():
            c = coerce(k, v)
            if c is not None:
                options[k] = c
        ident = _UNSAFE.sub("_", str(given_id).strip()) if given_id not in (None, "") else ""
        if not ident:
            unnamed.append(len(items))
        items.append(Item(ident, os.path.abspath(full), (kind or kind_of(full)).strip(), options))
    base = _common_folder([items[i].path for i in unnamed])
    for i in unnamed:
        items[i].id = item_id(items[i].path, base)
    return items


def load_manifest(source: str) -> List[Item]:
    """The items of a manifest (see the module doc), in manifest order.

    Raises ``ValueError`` for an empty manifest, a row without a path, an unknown option column,
    an unknown kind or two items with the same id.
    """
    src = os.fspath(source)
    lower = src.lower()
    if os.path.isdir(src):
        paths = sorted(
            os.path.join(d, f) for d, _, fs in os.walk(src) for f in fs if f.lower().endswith(KNOWN_SUFFIXES)
        )
        items = _from_paths(paths)
    elif glob.has_magic(src):
        items = _from_paths(sorted(p for p in glob.glob(src, recursive=True) if os.path.isfile(p)))
    elif lower.endswith((".txt", ".lst")):
        folder = os.path.dirname(os.path.abspath(src))
        with open(src, encoding="utf-8") as f:
            lines = [ln.split("#", 1)[0].strip() for ln in f]
        items = _from_rows(({"path": ln} for ln in lines if ln), folder, src)
    elif lower.endswith(".csv"):
        with open(src, newline="", encoding="utf-8") as f:
            items = _from_rows(csv.DictReader(f), os.path.dirname(os.path.abspath(src)), src)
    elif lower.endswith((".parquet", ".pq")):
        import pyarrow.parquet as pq

        items = _from_rows(pq.read_table(src).to_pylist(), os.path.dirname(os.path.abspath(src)), src)
    elif os.path.isfile(src):
        items = _from_paths([src])
    else:
        raise ValueError(f"manifest {src!r}: no such file, folder or matching glob")
    if not items:
        raise ValueError(f"manifest {src!r} names no input")
    seen: Dict[str, str] = {}
    for it in items:
        if it.kind not in ("model", "mesh"):
            raise ValueError(f"item {it.id}: kind must be 'model' or 'mesh', got {it.kind!r}")
        if it.id in seen:
            raise ValueError(f"manifest {src!r}: two items have the id {it.id!r} ({seen[it.id]} and {it.path}); give an id column")
        seen[it.id] = it.path
    return items


def merged_options(item: Item, defaults: Optional[Dict[str, Any]]) -> Dict[str, Any]:
    """The run's defaults overridden by the item's own options."""
    out = dict(defaults or {})
    out.update(item.options)
    return out
