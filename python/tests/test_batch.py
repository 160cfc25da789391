"""The corpus pipeline (`ism.batch`) on a local Dask cluster of 2 worker processes, against the
`ism` CLI.

One generated corpus (`tools/batch_corpus.py`: ~180 models and meshes, with corrupt, hostile,
non-manifold and invalid inputs mixed in, known by construction) is run once while a worker is
killed by its PID mid-run; then the summary must name exactly the bad items with their rules, every
good output must validate and equal the CLI's output for the same options and seed, byte for byte,
the shards must hold one row group per item, and a second run must compute nothing.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import signal
import subprocess
import sys
import threading

import numpy as np
import pytest

import ism
from conftest import ROOT, cli, ism_bin

pytest.importorskip("distributed")
pq = pytest.importorskip("pyarrow.parquet")
from ism import batch  # noqa: E402

_spec = importlib.util.spec_from_file_location("batch_corpus", ROOT / "tools" / "batch_corpus.py")
batch_corpus = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(batch_corpus)

#: Small per-item work, so the corpus runs in seconds (sizes do not change what is compared).
OPTIONS = {"surface": 200, "volume": 200, "near_surface": 200, "sigma": 0.02, "seed": 11,
           "export_tolerance": 1e-2, "resolution": 4, "tolerance": 2e-2}  # fmt: skip


@pytest.fixture(scope="module")
def client():
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None, memory_limit="2GiB")
    c = Client(cluster)
    yield c
    c.close()
    cluster.close()


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    """The generated corpus and a CSV manifest of it. Surface and near-surface sampling cost ~3 s
    per 3D model (the sampler's area table), so the manifest's per-row `surface` and `near_surface`
    options keep them to one variant of each 3D example: the other 3D items and the fitted meshes
    sample the volume only."""
    folder = tmp_path_factory.mktemp("corpus")
    c = batch_corpus.make_corpus(str(folder), variants=17, meshes=2)
    surface = {}
    with open(folder / "manifest.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["path", "surface", "near_surface"])
        for path in sorted(c["files"]):
            name = os.path.basename(path)
            costly = name.startswith(("sphere-", "torus-", "stratified-3d-", "ellipsoid-"))
            cheap_one = "-v00." in name
            w.writerow([name] + [0 if costly and not cheap_one else ""] * 2)
            surface[name] = not (costly and not cheap_one)
    return {"folder": folder, "manifest": str(folder / "manifest.csv"), "surface": surface, **c}


@pytest.fixture(scope="module")
def first_run(client, corpus, tmp_path_factory):
    """The corpus run once; after 40 items, the worker busy with the most tasks is killed (SIGKILL
    to its PID) while it holds some."""
    out = tmp_path_factory.mktemp("out")
    pids = client.run(os.getpid)  # worker address -> pid
    killed = {}
    lock = threading.Lock()

    def on_result(res, partial):
        with lock:
            if killed or len(partial.pids) < 40:
                return
            processing = {w: ks for w, ks in client.processing().items() if ks}
            if not processing:
                return
            worker = max(processing, key=lambda w: len(processing[w]))
            killed.update(pid=pids[worker], worker=worker, keys=list(processing[worker]))
            os.kill(pids[worker], signal.SIGKILL)

    result = batch.run(corpus["manifest"], str(out), defaults=OPTIONS, client=client, on_result=on_result,
                       shard_items=50, progress=False)  # fmt: skip
    return {"out": out, "result": result, "killed": killed}


def test_summary_names_exactly_the_bad_items(first_run, corpus):
    res, out = first_run["result"], first_run["out"]
    assert res.items == len(corpus["files"]) >= 180
    assert sorted(res.failed) == sorted(corpus["bad"])
    rows = {}
    for r in res.rows:
        rows.setdefault(r["item"], []).append(r)
    for item, want in corpus["bad"].items():
        bad = [r for r in rows[item] if r["verdict"] in ("error", "invalid")]
        assert len(bad) == 1 and bad[0]["step"] == want["step"], (item, rows[item])
        if want["rule"] is None:  # a mesh the fit refuses: the message says why
            assert "FitError" in bad[0]["error"] or "ValueError" in bad[0]["error"], bad[0]
        else:
            assert bad[0]["rule"].startswith(want["rule"]), (item, bad[0])
    # The summary files hold the same rows (CSV and Parquet).
    with open(out / "summary.csv", newline="") as f:
        table = list(csv.DictReader(f))
    assert [(r["item"], r["step"], r["verdict"]) for r in table] == [(r["item"], r["step"], r["verdict"]) for r in res.rows]
    parquet = pq.read_table(out / "summary.parquet").to_pylist()
    assert [(r["item"], r["step"], r["verdict"], r["rule"]) for r in parquet] == [(r["item"], r["step"], r["verdict"], r["rule"]) for r in res.rows]
    assert list(table[0]) == list(batch.SUMMARY_COLUMNS)
    # Every good item ran every step to a pass.
    for item in corpus["good"]:
        steps = {r["step"]: r["verdict"] for r in rows[item]}
        first = "fit" if item.endswith(".obj") else "read"
        want = {first: "ok", "validate": "valid", "convert": "ok", "export": "ok", "sample-volume": "ok"}
        if corpus["surface"][item]:
            want.update({"sample-surface": "ok", "sample-near-surface": "ok"})
        assert steps == want, (item, steps)


def test_a_killed_worker_loses_nothing(first_run, corpus):
    killed, res, out = first_run["killed"], first_run["result"], first_run["out"]
    assert killed and killed["keys"], "no worker was killed while holding tasks"
    with pytest.raises(ProcessLookupError):
        os.kill(killed["pid"], 0)
    # Every item has its done marker and rows; none was computed by the dead worker after all.
    assert len(res.pids) == res.items
    for name in corpus["files"]:
        item = os.path.basename(name)
        assert (out / "done" / (item + ".json")).is_file()
    assert not [r for r in res.rows if r["step"] == "task"], "an item failed in the engine"
    # The items the dead worker held were computed again, by a live worker.
    # (One of them may have sent its result just before the kill; the others were re-run.)
    held = [res.tasks[k] for k in killed["keys"]]
    assert all(i in res.pids for i in held)
    assert any(res.pids[i] != killed["pid"] for i in held), (held, killed)


def test_good_outputs_validate_and_equal_the_cli(first_run, corpus, tmp_path):
    out = first_run["out"]
    models = sorted(str(out / "models" / (i + ".ismb")) for i in corpus["good"])
    # The CLI validates every converted model (one process for all of them).
    done = subprocess.run([ism_bin(), "validate", "--quiet", *models], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    # A subset against the CLI's own outputs for the same options and seed.
    subset = list(dict.fromkeys(corpus["good"][::12] + corpus["meshes"][:1] + [pick(corpus, "sphere-v00.")]))
    src = corpus["folder"]
    for item in subset:
        model_path = src / item
        if item.endswith(".obj"):
            fitted = tmp_path / (item + ".ismb")
            cli("fit", "--mesh", model_path, "--resolution", 4, "--tolerance", 2e-2, "-o", fitted, "--quiet")
            assert (out / "fitted" / (item + ".ismb")).read_bytes() == fitted.read_bytes(), item
            model_path = fitted
        conv = tmp_path / (item + ".conv.ismb")
        cli("convert", model_path, conv)
        assert (out / "models" / (item + ".ismb")).read_bytes() == conv.read_bytes(), item
        glb = tmp_path / (item + ".glb")
        cli("export", model_path, glb, "--tolerance", 1e-2, "--quiet", check=False)
        assert (out / "exports" / (item + ".glb")).read_bytes() == glb.read_bytes(), item
        for kind, flag in (("surface", "--surface"), ("volume", "--volume"), ("near-surface", "--near-surface")):
            if kind != "volume" and not corpus["surface"][item]:
                continue
            npy = tmp_path / f"{item}.{kind}.npy"
            extra = ["--sigma", 0.02] if kind == "near-surface" else []
            cli("sample", model_path, flag, 200, *extra, "--seed", 11, "-o", npy, "--quiet")
            want = np.load(npy)
            got = pq.read_table(out / "parts" / kind / (item + ".parquet"))
            assert got.column_names == ["item", *want.dtype.names]
            assert set(got.column("item").to_pylist()) == {item}
            for name in want.dtype.names:
                col = got.column(name).to_numpy()
                assert col.dtype == want[name].dtype and col.tobytes() == np.ascontiguousarray(want[name]).tobytes(), (item, kind, name)


def test_shards_hold_one_row_group_per_item(first_run, corpus):
    out = first_run["out"]
    for kind in ("surface", "volume", "near-surface"):
        seen = []
        for path in sorted((out / "samples").glob(f"{kind}-*d/shard-*.parquet")):
            f = pq.ParquetFile(path)
            for g in range(f.num_row_groups):
                t = f.read_row_group(g)
                ids = set(t.column("item").to_pylist())
                assert len(ids) == 1 and t.num_rows == 200, (path, g, ids)
                item = ids.pop()
                assert t.equals(pq.read_table(out / "parts" / kind / (item + ".parquet")).cast(t.schema))
                seen.append(item)
        assert sorted(seen) == sorted(i for i in corpus["good"] if kind == "volume" or corpus["surface"][i]), kind


def test_second_run_does_no_work(first_run, corpus, client):
    out = first_run["out"]
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file() and not p.name.startswith("summary.")}
    res = batch.run(corpus["manifest"], str(out), defaults=OPTIONS, client=client, shard_items=50, progress=False)
    assert res.submitted == 0 and res.resumed == res.items and res.shards_written == 0
    assert sorted(res.failed) == sorted(first_run["result"].failed)
    after = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file() and not p.name.startswith("summary.")}
    assert after == before


def pick(corpus, prefix):
    """The corpus file whose name starts with ``prefix`` (the encodings rotate)."""
    (name,) = [n for n in corpus["good"] if n.startswith(prefix)]
    return name


def test_manifests_list_csv_parquet_and_glob(corpus, tmp_path):
    import pyarrow as pa

    names = [pick(corpus, "circle-curved-v00."), pick(corpus, "sphere-v01."), "ellipsoid-00.obj"]
    folder = corpus["folder"]
    (tmp_path / "list.txt").write_text("# three items\n" + "".join(f"{folder / n}\n" for n in names))
    with open(tmp_path / "rows.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["path", "id", "seed", "surface", "encoding"])
        w.writerow([folder / names[0], "a", 5, "", "json"])
        w.writerow([folder / names[1], "b", "", 0, ""])
        w.writerow([folder / names[2], "c", 2, 10, ""])
    pq.write_table(pa.table({"path": [str(folder / n) for n in names], "seed": [1, None, 3]}), tmp_path / "rows.parquet")
    listed = batch.load_manifest(str(tmp_path / "list.txt"))
    assert [i.path for i in listed] == [str(folder / n) for n in names]
    assert [i.kind for i in listed] == ["model", "model", "mesh"]
    rows = batch.load_manifest(str(tmp_path / "rows.csv"))
    assert [i.id for i in rows] == ["a", "b", "c"]
    assert [i.options for i in rows] == [{"seed": 5, "encoding": "json"}, {"surface": 0}, {"seed": 2, "surface": 10}]
    table = batch.load_manifest(str(tmp_path / "rows.parquet"))
    assert [i.options for i in table] == [{"seed": 1}, {}, {"seed": 3}]
    globbed = batch.load_manifest(str(folder / "circle-curved-v0*.ism.json"))
    assert [i.id for i in globbed] == sorted(n for n in corpus["good"] if n.startswith("circle-curved-v0") and n.endswith(".ism.json"))
    for bad, message in (("path,colour\nx,red\n", "unknown option"), ("path,seed\n,1\n", "no path"), ("path,id\nx,a\ny,a\n", "two items have the id")):
        (tmp_path / "bad.csv").write_text(bad)
        with pytest.raises(ValueError, match=message):
            batch.load_manifest(str(tmp_path / "bad.csv"))


def test_per_row_seed_and_limits(client, corpus, tmp_path):
    """A table's per-row options reach the worker: each row's seed gives the CLI's points for that
    seed; a sample count above --max-points is an error row, not an allocation."""
    src = corpus["folder"] / pick(corpus, "circle-curved-v03.")
    with open(tmp_path / "m.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["path", "id", "seed", "surface", "steps"])
        w.writerow([src, "seed5", 5, 100, "sample"])
        w.writerow([src, "seed6", 6, 100, "sample"])
        w.writerow([src, "huge", 6, 10**12, "sample"])
    res = batch.run(str(tmp_path / "m.csv"), str(tmp_path / "out"), defaults={"volume": 0, "near_surface": 0}, client=client, progress=False)
    assert res.failed == ["huge"]
    huge = [r for r in res.rows if r["item"] == "huge" and r["verdict"] == "error"]
    assert len(huge) == 1 and "max-points" in huge[0]["error"]
    for seed in (5, 6):
        npy = tmp_path / f"{seed}.npy"
        cli("sample", src, "--surface", 100, "--seed", seed, "-o", npy, "--quiet")
        got = pq.read_table(tmp_path / "out" / "parts" / "surface" / f"seed{seed}.parquet")
        assert got.column("x").to_numpy().tobytes() == np.ascontiguousarray(np.load(npy)["x"]).tobytes()
    assert {r["step"] for r in res.rows if r["item"] == "seed5"} == {"read", "sample-surface"}


def test_command_line_runs_a_local_cluster(corpus, tmp_path):
    """`python -m ism.batch` with its own LocalCluster: exit 1 naming the bad item, progress on
    stderr, the summary CSV; run again: nothing computed, still exit 1."""
    folder = corpus["folder"]
    good = pick(corpus, "circle-linear-v01.")
    (tmp_path / "list.txt").write_text(f"{folder / good}\n{folder / 'corrupt-cut.ism.json'}\n")
    cmd = [sys.executable, "-m", "ism.batch", str(tmp_path / "list.txt"), "-o", str(tmp_path / "out"), "--workers", "1",
           "--surface", "50", "--volume", "50", "--near-surface", "0", "--dashboard", ":0", "--memory-limit", "1GiB"]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert done.returncode == 1, done.stderr
    assert "2 items: 2 computed, 0 resumed, 1 failed" in done.stdout
    assert "corrupt-cut.ism.json: read error: ISM-006" in done.stdout
    assert "[ism.batch] 2/2 items (1 failed, 0 resumed)" in done.stderr and "dashboard: http" in done.stderr
    with open(tmp_path / "out" / "summary.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert {(r["item"], r["step"], r["verdict"]) for r in rows} >= {("corrupt-cut.ism.json", "read", "error"), (good, "sample-volume", "ok")}
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert again.returncode == 1 and "2 items: 0 computed, 2 resumed, 1 failed" in again.stdout
    bad = subprocess.run([*cmd[:3], str(tmp_path / "nothing-*.ismb"), *cmd[4:]], capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and "names no input" in bad.stderr
