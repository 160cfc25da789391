"""Whole corpora on a Dask cluster: read or fit, validate, convert, export and sample thousands
of models, resumably.

    python -m ism.batch "corpus/**/*.ismb" -o out/                 # a LocalCluster on this machine
    python -m ism.batch manifest.csv -o out/ --scheduler tcp://head:8786   # an existing cluster

or from Python::

    from ism import batch
    result = batch.run("corpus/*.ismb", "out", defaults={"surface": 5000, "seed": 7})
    result.failed          # ids of the items with an error / invalid verdict

Outputs under ``out/``: ``fitted/<id>.ismb`` (mesh inputs), ``reports/<id>.json`` (validation),
``models/<id>.<ext>`` (convert), ``exports/<id>.<fmt>``, ``parts/<kind>/<id>.parquet`` (one
sample set per item), ``samples/<kind>-<n>d/shard-NNNNN.parquet`` (the parts of up to
``shard_items`` items, one row group per item, an ``item`` column), ``done/<id>.json`` (the
item's done marker and summary rows) and ``summary.parquet`` / ``summary.csv``. See
``python/README.md`` ("Whole corpora on a cluster") for the manifest, the options and the
engine's behaviour on faults.

The engine is Dask (``dask.distributed``), chosen over Ray because it is pip-light (pure Python
wheels; Ray is a large binary wheel with its own object store and raylet processes), a
``LocalCluster`` runs the same code on one machine as a scheduler address does on many, its
nannies restart a killed or over-memory worker and its scheduler re-runs that worker's tasks, and
its dashboard (bokeh) shows the tasks' progress without extra setup. Both would do; on a 2-core CI
machine the smaller footprint decides.
"""

from ._item import DEFAULTS, STEPS, SUMMARY_COLUMNS, process_item, read_obj
from ._manifest import OPTION_TYPES, Item, load_manifest
from ._run import Progress, RunResult, compact_shard, make_client, run

__all__ = [
    "DEFAULTS",
    "OPTION_TYPES",
    "STEPS",
    "SUMMARY_COLUMNS",
    "Item",
    "Progress",
    "RunResult",
    "compact_shard",
    "load_manifest",
    "make_client",
    "process_item",
    "read_obj",
    "run",
]
