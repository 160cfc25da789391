"""Differential reading: ismpy (written from the spec alone) and the reference implementation report the
same result — accepted, or the same rule at the same location — for every input the fuzzers kept
(fuzz/corpus/*: arbitrary bytes that reach deep into both decoders), wrapped in a container where the
target fuzzed a bare payload. A disagreement is a bug in one of them or a gap in the spec.
"""

from __future__ import annotations

import json
import lzma
import struct
import subprocess
from pathlib import Path

import pytest

import ismpy
from test_conformance import adapter

ROOT = Path(__file__).resolve().parents[2]
# Fuzz target -> container tag its inputs need (None: whole files).
TARGETS = {"cross_encoding": None, "read_any": None, "read_json": 1, "read_msgpack": 2, "read_binary": 3}


def python_result(data: bytes) -> dict:
    try:
        ismpy.read(data)
    except ismpy.IsmError as e:
        return {"rule": e.rule, "location": e.location}
    return {"ok": True}


#: (target, container tag) pairs: every target's own encoding, plus the compact binary reader (spec §7.4.1,
#: tag 4) on the other binary-ish corpora, whose arbitrary bytes exercise every varint error (the
#: read_compact corpus itself is small), and the compressed reader (spec §7.4.2, tag 5) on those payloads
#: compressed here, and on its own corpus (the fuzz target's first byte: even, a compressed payload as it is;
#: odd, a compact payload to compress).
RUNS = [(t, tag) for t, tag in sorted(TARGETS.items())] + [("read_binary", 4), ("read_msgpack", 4), ("read_compact", 4)]
RUNS += [("read_binary", 5), ("read_compact", 5), ("read_compressed", "mode")]


def compressed(compact: bytes) -> bytes:
    """A compressed payload (spec §7.4.2) holding `compact`, by Python's own xz encoder."""
    return struct.pack("<Q", len(compact)) + lzma.compress(compact, format=lzma.FORMAT_XZ, preset=0)


@pytest.mark.parametrize("target,tag", RUNS)
def test_both_implementations_agree_on_every_fuzz_input(target, tag, tmp_path):
    files = sorted((ROOT / "fuzz" / "corpus" / target).iterdir())
    assert len(files) > (20 if target in ("read_compact", "read_compressed") else 100), f"the {target} corpus is missing"
    inputs = []
    for i, f in enumerate(files):
        data = f.read_bytes()
        if tag == "mode":
            mode, data = data[:1], data[1:]
            data = ismpy.container(data if mode[0] % 2 == 0 else compressed(data), 5) if mode else b""
        elif tag == 5:
            data = ismpy.container(compressed(data), 5)
        elif tag is not None:
            data = ismpy.container(data, tag)
        if tag is not None:
            f = tmp_path / f"{i}"
            f.write_bytes(data)
        inputs.append((f, data))
    done = subprocess.run([adapter(), "read", *[str(f) for f, _ in inputs]], capture_output=True, text=True, timeout=600)
    lines = done.stdout.splitlines()
    assert len(lines) == len(inputs), done.stderr[-2000:]
    differ = []
    for (f, data), line in zip(inputs, lines):
        rust = json.loads(line)
        rust.pop("message", None)
        python = python_result(data)
        if rust != python:
            differ.append(f"{f.name}: reference {rust}, ismpy {python}")
    assert not differ, f"{len(differ)} of {len(inputs)} differ:\n" + "\n".join(differ[:10])
