"""Shared fixtures: the repository's spec files and the `ism` CLI binary, the peer every result is
compared with (ISM_BIN, else target/debug/ism)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "spec" / "examples"
VECTORS = ROOT / "spec" / "vectors"
SCHEMA = ROOT / "spec" / "schema"

EXAMPLE_NAMES = sorted({p.name.split(".")[0] for p in EXAMPLES.glob("*.ism.json")})
ENCODINGS = {"json": ".ism.json", "msgpack": ".ism.msgpack", "binary": ".ismb", "compact": ".ismc", "structured": ".isms"}


def ism_bin() -> str:
    path = os.environ.get("ISM_BIN") or str(ROOT / "target" / "debug" / "ism")
    assert Path(path).is_file(), f"{path} does not exist; build it with `cargo build -p ism-cli` or set ISM_BIN"
    return path


def cli(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    done = subprocess.run([ism_bin(), *map(str, args)], capture_output=True, text=True, timeout=600)
    if check:
        assert done.returncode == 0, f"ism {' '.join(map(str, args))}: {done.returncode}\n{done.stderr}"
    return done


@pytest.fixture(scope="session")
def cli_run():
    return cli
