"""The conformance kit (tools/conformance) run against both implementations of the format:

- ismpy (tests/python/ismpy.py), a reader and writer written from spec/ism-format.md alone;
- the reference implementation, through target/debug/ism-conformance-adapter (built by `cargo test`).

Both must pass every reader vector (rule and location), accept every example, and write every writer
vector byte for byte. ismpy also reproduces every example file and the spelling table of spec §7.7.
"""

from __future__ import annotations

import os
import re
import struct
import subprocess
import sys
from pathlib import Path

import pytest

import ismpy

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "spec" / "examples"
KIT = ROOT / "tools" / "conformance"


def adapter() -> str:
    path = os.environ.get("ISM_CONFORMANCE_ADAPTER") or str(ROOT / "target" / "debug" / "ism-conformance-adapter")
    assert Path(path).is_file(), f"{path} does not exist; build it with `cargo build -p ism-conformance`"
    return path


def run_kit(command: list[str]) -> str:
    done = subprocess.run([sys.executable, str(KIT), "--quiet", "--", *command], capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
    assert re.search(r"^\d+ passed, 0 failed$", done.stdout, re.M), done.stdout[-2000:]
    return done.stdout


def test_ismpy_passes_the_conformance_kit():
    out = run_kit([sys.executable, str(ROOT / "tests" / "python" / "ismpy.py")])
    assert int(out.split()[-4]) >= 150, out


def test_reference_implementation_passes_the_conformance_kit():
    run_kit([adapter()])


def test_the_kit_fails_an_implementation_that_accepts_everything(tmp_path):
    # The kit is only meaningful if it can fail.
    fake = tmp_path / "accept-all.py"
    fake.write_text("import json, sys\nprint(json.dumps({'ok': True}))\n")
    done = subprocess.run([sys.executable, str(KIT), "--quiet", "--", sys.executable, str(fake)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 1
    assert "FAIL reader/" in done.stdout and "FAIL writer/" in done.stdout


def example_names() -> list[str]:
    return sorted(p.name[: -len(".ism.json")] for p in EXAMPLES.glob("*.ism.json"))


@pytest.mark.parametrize("name", example_names())
def test_ismpy_reproduces_every_example_in_every_encoding(name):
    files = {
        "json-pretty": EXAMPLES / f"{name}.ism.json",
        "msgpack": EXAMPLES / f"{name}.ism.msgpack",
        "binary": EXAMPLES / f"{name}.ismb",
        "compact": EXAMPLES / f"{name}.ismc",
    }
    models = {enc: ismpy.read(path.read_bytes()) for enc, path in files.items()}
    bits = lambda m: ismpy.BinaryWriter().model(m)  # noqa: E731 -- every f64 as its 8 bytes
    assert bits(models["msgpack"]) == bits(models["json-pretty"])
    assert bits(models["binary"]) == bits(models["json-pretty"])
    assert bits(models["compact"]) == bits(models["json-pretty"])
    for enc, path in files.items():
        assert ismpy.write(models["binary"], enc) == path.read_bytes(), f"{path.name}"
    # The compressed encoding (spec §7.4.2) pins the compact payload inside, not the xz bytes (they depend on
    # the encoder): Python's lzma decompresses the reference file to exactly the compact file's payload, and
    # the file ismpy writes (Python's xz encoder) reads back to the same numbers in both implementations.
    z = EXAMPLES / f"{name}.ismz"
    payload = z.read_bytes()[ismpy.HEADER_LEN :]
    assert ismpy.decompress(payload, ismpy.DEFAULT_PAYLOAD_LIMIT) == files["compact"].read_bytes()[ismpy.HEADER_LEN :]
    assert bits(ismpy.read(ismpy.write(models["binary"], "compressed"))) == bits(models["json-pretty"])


def spelling_table() -> list[str]:
    """The example spellings in the number table of spec §7.7."""
    text = (ROOT / "spec" / "ism-format.md").read_text()
    table = text[text.index("| `P` | spelling | examples |") :].split("\n\n", 1)[0]
    return [x for row in table.splitlines()[2:] for x in re.findall(r"`([^`]+)`", row.split("|")[3])]


def test_spelling_table_of_the_spec_is_what_ismpy_writes():
    examples = spelling_table()
    assert len(examples) >= 12, examples
    for text in examples:
        assert ismpy.format_f64(float(text)) == text


@pytest.mark.parametrize("bits", [0x0000000000000001, 0x000FFFFFFFFFFFFF, 0x7FEFFFFFFFFFFFFF, 0x3FB999999999999A, 0x4340000000000000, 0x433FFFFFFFFFFFFF, 0x3EE4F8B588E368F1, 0xBCA0000000000000])
def test_canonical_spelling_round_trips_extreme_values(bits):
    (x,) = struct.unpack("<d", struct.pack("<Q", bits))
    text = ismpy.format_f64(x)
    assert float(text) == x
    assert ("e" in text) or ("." in text)
