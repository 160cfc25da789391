"""`ism validate` from the outside: exit codes, the JSON report against spec/schema/report.schema.json,
and the validator vectors' expected (code, location) pairs (spec/validation.md §6-§8)."""

import json
import os
import pathlib
import subprocess

import jsonschema
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
SPEC = ROOT / "spec"
ISM = os.environ.get("ISM_BIN", str(ROOT / "target" / "debug" / "ism"))
SCHEMA = json.loads((SPEC / "schema" / "report.schema.json").read_text())
EXAMPLES = sorted(p for p in (SPEC / "examples").glob("*") if p.is_file() and (p.name.endswith((".ism.json", ".ismb", ".ism.msgpack"))))
VECTORS = sorted((SPEC / "vectors" / "validate").glob("*.expect.json"))


def run(*args):
    res = subprocess.run([ISM, "validate", *map(str, args)], capture_output=True, text=True, timeout=300)
    return res.returncode, res.stdout, res.stderr


def test_there_is_something_to_check():
    assert EXAMPLES and VECTORS


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.name)
def test_examples_are_valid_and_reports_match_the_schema(path):
    code, out, err = run("--json", path)
    report = json.loads(out)
    jsonschema.validate(report, SCHEMA)
    assert code == 0, err
    assert report["verdict"] == "valid"
    assert report["issues"]["numErrors"] == 0
    for stage in report["stages"]:
        assert stage["status"] == "certified"
        assert stage["valid"] == report["model"]["simplices"]
        assert sum(stage["certificates"].values()) == stage["valid"]


@pytest.mark.parametrize("expect_path", VECTORS, ids=lambda p: p.name.removesuffix(".expect.json"))
def test_vectors_give_exactly_the_expected_pairs(expect_path):
    expect = json.loads(expect_path.read_text())
    model = expect_path.with_name(expect_path.name.removesuffix(".expect.json") + ".ism.json")
    code, out, err = run("--json", model)
    report = json.loads(out)
    jsonschema.validate(report, SCHEMA)
    got = sorted(json.dumps([m["code"], m["location"]], sort_keys=True) for m in report["issues"]["messages"])
    want = sorted(json.dumps([i["code"], i["location"]], sort_keys=True) for i in expect["issues"])
    assert got == want
    assert report["verdict"] == expect["verdict"]
    assert code == (0 if expect["verdict"] == "valid" else 1), err
    for m in report["issues"]["messages"]:
        if m["code"] == "ISM-301":
            w = m["witness"]
            assert w["det"] <= 0
            assert abs(sum(w["point"]) - 1) < 1e-12


def test_unreadable_file_exits_2_with_a_schema_valid_record(tmp_path):
    bad = tmp_path / "garbage.ismb"
    bad.write_bytes(b"\x89ISM\r\n\x1a\nnot a header at all")
    code, out, _ = run("--json", bad)
    assert code == 2
    record = json.loads(out)
    jsonschema.validate(record, SCHEMA)
    assert record["verdict"] == "unreadable"


def test_several_files_give_an_array_and_the_worst_exit_status():
    fold = SPEC / "vectors" / "validate" / "fig2-quartic-fold-2d.ism.json"
    code, out, _ = run("--json", EXAMPLES[0], fold)
    reports = json.loads(out)
    jsonschema.validate(reports, SCHEMA)
    assert [r["verdict"] for r in reports] == ["valid", "invalid"]
    assert code == 1


def test_quality_layer_reports_det_range_and_normal_jumps():
    sphere = SPEC / "examples" / "quadratic-edges.ism.json"
    code, out, _ = run("--json", "--quality", sphere)
    report = json.loads(out)
    jsonschema.validate(report, SCHEMA)
    assert code == 0
    codes = report["issues"]["counts"]
    assert codes.get("ISM-403", 0) == len(report["stages"])
    assert "ISM-401" in codes
    lo, hi = report["stages"][0]["detRange"]
    assert 0 < lo <= hi


def test_max_issues_truncates_messages_but_not_counts():
    fold = SPEC / "vectors" / "validate" / "fig2-quartic-fold-2d.ism.json"
    code, out, _ = run("--json", "--max-issues", "1", fold)
    report = json.loads(out)
    assert code == 1
    assert len(report["issues"]["messages"]) == 1
    assert report["issues"]["truncated"] is True
    assert report["issues"]["numErrors"] == 2
