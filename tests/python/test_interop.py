"""Language-neutral reading of the ISM examples (spec/ism-format.md §7), with no Rust involved.

Reads every example in spec/examples/ with Python's json and msgpack and with a binary decoder written
from the spec's byte grammar (§7.4), checks the container header per §7.1 with zlib.crc32, compares the
three encodings number for number (bit for bit), compares counts and values with what the Rust reader
reports (`$ISM_BIN info --json`), validates the JSON examples against spec/schema/ism.schema.json, and
checks the container-level reader vectors against a header checker written from §7.1.
"""

from __future__ import annotations

import itertools
import json
import os
import struct
import subprocess
import zlib
from pathlib import Path

import jsonschema
import msgpack
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "spec" / "examples"
VECTORS = ROOT / "spec" / "vectors" / "reader"
SCHEMA = ROOT / "spec" / "schema" / "ism.schema.json"

MAGIC = b"\x89ISM\r\n\x1a\n"
HEADER_LEN = 32
TAGS = {1: "json", 2: "msgpack", 3: "binary", 4: "compact", 5: "compressed", 6: "structured"}
EXPECTED_EXAMPLES = {
    "circle-linear",
    "circle-curved",
    "sphere",
    "quadratic-edges",
    "cubic-face-point",
    "stratified-3d",
    "rational-degree5",
    "monotonic",
    "two-stage",
    "torus",
}


def example_names() -> list[str]:
    return sorted(p.name[: -len(".ism.json")] for p in EXAMPLES.glob("*.ism.json"))


def ism_bin() -> str:
    path = os.environ.get("ISM_BIN") or str(ROOT / "target" / "debug" / "ism")
    assert Path(path).is_file(), f"ISM_BIN={path} does not exist; build it with `cargo build -p ism-cli`"
    return path


# ---------------------------------------------------------------- container (§7.1)


def split_container(data: bytes) -> tuple[dict, bytes]:
    """Parses and verifies the 32-byte header; returns (header fields, payload)."""
    assert data[:8] == MAGIC
    major, minor, tag = struct.unpack_from("<HHB", data, 8)
    assert data[13:16] == b"\0\0\0", "reserved bytes are zero"
    (length,) = struct.unpack_from("<Q", data, 16)
    payload_crc, header_crc = struct.unpack_from("<II", data, 24)
    assert zlib.crc32(data[:28]) == header_crc, "header CRC-32"
    assert len(data) == HEADER_LEN + length, "payload length"
    payload = data[HEADER_LEN:]
    assert zlib.crc32(payload) == payload_crc, "payload CRC-32"
    return {"major": major, "minor": minor, "encoding": TAGS[tag], "payload_len": length, "crc32": payload_crc}, payload


def container_rule(data: bytes) -> tuple[str, int] | None:
    """The first container-level failure of §7.1 steps 1-9 as (rule, offset), or None."""
    if data[:8] != MAGIC:
        stripped = data.lstrip(b" \t\n\r")  # RFC 8259 whitespace; no byte-order mark (§7.5)
        return None if stripped[:1] == b"{" else ("ISM-001", 0)
    if len(data) < HEADER_LEN:
        return ("ISM-004", len(data))
    if zlib.crc32(data[:28]) != struct.unpack_from("<I", data, 28)[0]:
        return ("ISM-003", 28)
    if struct.unpack_from("<H", data, 8)[0] != 1:
        return ("ISM-002", 8)
    if data[12] not in TAGS:
        return ("ISM-005", 12)
    if data[13:16] != b"\0\0\0":
        return ("ISM-006", 13)
    (length,) = struct.unpack_from("<Q", data, 16)
    if length > 8 << 30:
        return ("ISM-007", 16)
    if len(data) - HEADER_LEN < length:
        return ("ISM-004", len(data))
    if len(data) > HEADER_LEN + length:
        return ("ISM-010", HEADER_LEN + length)
    if zlib.crc32(data[HEADER_LEN:]) != struct.unpack_from("<I", data, 24)[0]:
        return ("ISM-003", 24)
    return None


# ---------------------------------------------------------------- binary encoding (§7.4)


class BinaryReader:
    """Decodes the binary payload from the grammar of spec §7.4 alone."""

    KINDS = ["bezier", "rational", "monotonic"]
    DIRECTIONS = ["implicit", "parametric"]

    def __init__(self, payload: bytes):
        self.b = payload
        self.at = 0

    def take(self, fmt: str):
        values = struct.unpack_from(fmt, self.b, self.at)
        self.at += struct.calcsize(fmt)
        return values

    def u8(self) -> int:
        return self.take("<B")[0]

    def u32(self) -> int:
        return self.take("<I")[0]

    def length(self) -> int:
        n = self.take("<Q")[0]
        assert n <= len(self.b) - self.at, "declared length reaches past the payload"
        return n

    def f64(self) -> float:
        return self.take("<d")[0]

    def string(self) -> str:
        n = self.length()
        s = self.b[self.at : self.at + n].decode("utf-8")
        self.at += n
        return s

    def f64s(self) -> list[float]:
        n = self.length()
        out = list(self.take(f"<{n}d")) if n else []
        return out

    def u32s(self) -> list[int]:
        n = self.length()
        return list(self.take(f"<{n}I")) if n else []

    def optional(self, read):
        tag = self.u8()
        assert tag in (0, 1), f"optional tag {tag}"
        return read() if tag else None

    def json(self):
        return json.loads(self.string())

    def enum(self, names: list[str]) -> str:
        i = self.u32()
        return names[i]

    def seq(self, read) -> list:
        return [read() for _ in range(self.length())]

    def metadata(self) -> dict:
        out = {}
        for key in ("name", "generator", "units", "description"):
            value = self.optional(self.string)
            if value is not None:
                out[key] = value
        return out

    def face_record(self) -> dict:
        return {"face": self.u32s(), "points": self.f64s(), "weights": self.f64s()}

    def vertex_map(self) -> dict:
        return {"vertex": self.u32(), "coefficients": self.f64s()}

    def stage(self) -> dict:
        return {
            "kind": self.enum(self.KINDS),
            "degree": self.u32(),
            "direction": self.enum(self.DIRECTIONS),
            "name": self.optional(self.string),
            "faces": self.seq(self.face_record),
            "vertexMaps": self.seq(self.vertex_map),
            "extras": self.json(),
        }

    def model(self) -> dict:
        m = {
            "version": self.string(),
            "dimension": self.u8(),
            "metadata": self.metadata(),
            "vertices": self.f64s(),
            "simplices": self.u32s(),
            "values": self.f64s(),
            "level": self.f64(),
            "stages": self.seq(self.stage),
            "extensionsUsed": self.seq(self.string),
            "extensionsRequired": self.seq(self.string),
            "extensions": dict(self.seq(lambda: (self.string(), self.json()))),
            "extras": self.json(),
        }
        assert self.at == len(self.b), f"{len(self.b) - self.at} bytes after the model"
        return m


# ---------------------------------------------------------------- normal form for comparison


def normal(model: dict) -> dict:
    """Applies the defaults of spec §2 so the three encodings compare equal; floats become bit patterns."""

    def bits(x) -> str:
        return struct.pack("<d", float(x)).hex()

    def stage(s: dict) -> dict:
        return {
            "kind": s["kind"],
            "degree": s["degree"],
            "direction": s.get("direction", "implicit"),
            "name": s.get("name"),
            "faces": [
                {
                    "face": list(r["face"]),
                    "points": [bits(x) for x in r.get("points", [])],
                    "weights": [bits(x) for x in r.get("weights", [])],
                }
                for r in s.get("faces", [])
            ],
            "vertexMaps": [
                {"vertex": v["vertex"], "coefficients": [bits(x) for x in v["coefficients"]]}
                for v in s.get("vertexMaps", [])
            ],
            "extras": s.get("extras"),
        }

    return {
        "version": model["version"],
        "dimension": model["dimension"],
        "metadata": {k: v for k, v in model.get("metadata", {}).items() if v is not None},
        "vertices": [bits(x) for x in model["vertices"]],
        "simplices": list(model["simplices"]),
        "values": [bits(x) for x in model["values"]],
        "level": bits(model.get("level", 0.0)),
        "stages": [stage(s) for s in model.get("stages", [])],
        "extensionsUsed": model.get("extensionsUsed", []),
        "extensionsRequired": model.get("extensionsRequired", []),
        "extensions": model.get("extensions", {}),
        "extras": model.get("extras"),
    }


def read_all(name: str) -> dict[str, dict]:
    """The example in each encoding, decoded in Python only."""
    out = {}
    text = (EXAMPLES / f"{name}.ism.json").read_bytes()
    assert text[:1] == b"{", "the JSON examples have no container"
    out["json"] = json.loads(text)
    header, payload = split_container((EXAMPLES / f"{name}.ism.msgpack").read_bytes())
    assert header["encoding"] == "msgpack"
    out["msgpack"] = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    header, payload = split_container((EXAMPLES / f"{name}.ismb").read_bytes())
    assert header["encoding"] == "binary"
    out["binary"] = BinaryReader(payload).model()
    return out


# ---------------------------------------------------------------- tests


def test_every_required_example_is_present_in_three_encodings():
    names = set(example_names())
    assert EXPECTED_EXAMPLES <= names, f"missing: {EXPECTED_EXAMPLES - names}"
    for name in names:
        for ext in ("ism.json", "ism.msgpack", "ismb"):
            path = EXAMPLES / f"{name}.{ext}"
            assert path.is_file(), path
            assert path.stat().st_size < 1 << 20, f"{path} is over 1 MB"


@pytest.mark.parametrize("name", example_names())
def test_three_encodings_carry_identical_numbers(name):
    models = read_all(name)
    reference = normal(models["json"])
    assert normal(models["msgpack"]) == reference
    assert normal(models["binary"]) == reference


@pytest.mark.parametrize("name", example_names())
def test_json_example_validates_against_schema(name):
    schema = json.loads(SCHEMA.read_text())
    validator_class = jsonschema.validators.validator_for(schema)
    validator_class.check_schema(schema)
    instance = json.loads((EXAMPLES / f"{name}.ism.json").read_text())
    errors = sorted(validator_class(schema).iter_errors(instance), key=lambda e: list(e.path))
    assert not errors, "\n".join(f"{list(e.path)}: {e.message}" for e in errors[:5])


def test_schema_rejects_a_broken_document():
    # The schema check above is only meaningful if the schema can fail.
    schema = json.loads(SCHEMA.read_text())
    instance = json.loads((EXAMPLES / "circle-linear.ism.json").read_text())
    del instance["values"]
    instance["dimension"] = "two"
    assert not jsonschema.validators.validator_for(schema)(schema).is_valid(instance)


def faces_by_dimension(model: dict) -> list[int]:
    n = model["dimension"]
    simplices = np.asarray(model["simplices"], dtype=np.int64).reshape(-1, n + 1)
    counts = [len(model["vertices"]) // n]
    for size in range(2, n + 2):
        keys = set()
        for row in np.sort(simplices, axis=1):
            keys.update(itertools.combinations(row.tolist(), size))
        counts.append(len(keys))
    return counts


def stored_numbers(stage: dict) -> int:
    return sum(len(r.get("points", [])) + len(r.get("weights", [])) for r in stage.get("faces", [])) + sum(
        len(v["coefficients"]) for v in stage.get("vertexMaps", [])
    )


@pytest.mark.parametrize("name", example_names())
@pytest.mark.parametrize("ext", ["ism.json", "ism.msgpack", "ismb"])
def test_python_reading_agrees_with_rust_info(name, ext):
    path = EXAMPLES / f"{name}.{ext}"
    result = subprocess.run([ism_bin(), "info", "--json", str(path)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    info = json.loads(result.stdout)
    model = read_all(name)[{"ism.json": "json", "ism.msgpack": "msgpack", "ismb": "binary"}[ext]]
    n = model["dimension"]
    vertices = np.asarray(model["vertices"], dtype=np.float64).reshape(-1, n)
    values = np.asarray(model["values"], dtype=np.float64)
    level = model.get("level", 0.0)

    assert info["encoding"] == {"ism.json": "json", "ism.msgpack": "msgpack", "ismb": "binary"}[ext]
    assert info["version"] == model["version"] == "1.0"
    assert info["dimension"] == n
    assert info["vertices"] == len(vertices) == len(values)
    assert info["simplices"] == len(model["simplices"]) // (n + 1)
    assert info["level"] == level
    assert info["inside_vertices"] == int(np.sum(values < level))
    assert info["name"] == model["metadata"]["name"] == name
    assert info["bounding_box"] == [[float(vertices[:, a].min()), float(vertices[:, a].max())] for a in range(n)]
    assert info["faces_by_dimension"] == faces_by_dimension(model)
    assert len(info["stages"]) == len(model.get("stages", []))
    for summary, stage in zip(info["stages"], model.get("stages", [])):
        assert summary["kind"] == stage["kind"]
        assert summary["degree"] == stage["degree"]
        assert summary["direction"] == stage.get("direction", "implicit")
        assert summary["face_records"] == len(stage.get("faces", []))
        assert summary["vertex_maps"] == len(stage.get("vertexMaps", []))
        assert summary["stored_numbers"] == stored_numbers(stage)
    data = path.read_bytes()
    if ext == "ism.json":
        assert info["container"] is None
    else:
        header, _ = split_container(data)
        assert info["container"] == {k: header[k] for k in ("major", "minor", "payload_len", "crc32")}
    assert info["bytes"] == len(data)


def test_face_records_follow_the_counting_rules():
    # §2.5: a record on a face with k + 1 vertices stores (k + 1)·C(d − 1, k) coordinates and, for rational
    # stages, C(d − 1, k) weights; checked over every example, so the examples exercise the storage rules.
    from math import comb

    checked = 0
    for name in example_names():
        for stage in json.loads((EXAMPLES / f"{name}.ism.json").read_text()).get("stages", []):
            d = stage["degree"]
            for record in stage.get("faces", []):
                k = len(record["face"]) - 1
                assert record["face"] == sorted(set(record["face"]))
                assert len(record["points"]) == (k + 1) * comb(d - 1, k)
                owned = comb(d - 1, k)
                assert len(record.get("weights", [])) == (owned if stage["kind"] == "rational" else 0)
                for j in range(owned):
                    point = record["points"][j * (k + 1) : (j + 1) * (k + 1)]
                    assert all(c > 0 for c in point) and abs(sum(point) - 1.0) < 1e-12
                checked += 1
    assert checked > 1000


def container_vectors() -> list[Path]:
    paths = []
    for expect in sorted(VECTORS.glob("*.expect.json")):
        stem = expect.name[: -len(".expect.json")]
        [data] = [p for p in VECTORS.glob(f"{stem}.*") if p != expect]
        paths.append(data)
    return paths


@pytest.mark.parametrize("path", container_vectors(), ids=lambda p: p.name)
def test_container_checks_of_the_spec_reproduce_reader_vectors(path):
    """A header checker written from §7.1 reports what the Rust reader reports for container defects,
    and finds nothing wrong at container level in every other vector."""
    stem = path.name.split(".")[0]
    expect = json.loads((VECTORS / f"{stem}.expect.json").read_text())
    got = container_rule(path.read_bytes())
    offset = expect["location"].get("offset")
    container_level = expect["rule"] in {"ISM-001", "ISM-003", "ISM-004", "ISM-005", "ISM-010"} or (
        expect["rule"] in {"ISM-002", "ISM-006", "ISM-007"} and offset in {8, 13, 16} and "pointer" not in expect["location"]
    )
    if container_level and not (expect["rule"] == "ISM-004" and path.suffix == ".json"):
        assert got == (expect["rule"], offset)
    else:
        assert got is None, f"container checker reports {got}; the reader reports {expect}"


# ---------------------------------------------------------------- a binary writer from the spec (§7.1, §7.4)


class BinaryWriter:
    """Writes the binary encoding from the grammar of spec §7.4 alone (no bincode)."""

    def __init__(self):
        self.out = bytearray()

    def put(self, fmt: str, *values):
        self.out += struct.pack(fmt, *values)

    def string(self, s: str):
        data = s.encode("utf-8")
        self.put("<Q", len(data))
        self.out += data

    def optional(self, value, write):
        if value is None:
            self.put("<B", 0)
        else:
            self.put("<B", 1)
            write(value)

    def f64s(self, xs):
        self.put("<Q", len(xs))
        self.put(f"<{len(xs)}d", *xs)

    def u32s(self, xs):
        self.put("<Q", len(xs))
        self.put(f"<{len(xs)}I", *xs)

    def json(self, value):
        self.string(json.dumps(value, separators=(",", ":"), ensure_ascii=False))

    def model(self, m: dict) -> bytes:
        self.string(m["version"])
        self.put("<B", m["dimension"])
        meta = m.get("metadata", {})
        for key in ("name", "generator", "units", "description"):
            self.optional(meta.get(key), self.string)
        self.f64s(m["vertices"])
        self.u32s(m["simplices"])
        self.f64s(m["values"])
        self.put("<d", m.get("level", 0.0))
        self.put("<Q", len(m.get("stages", [])))
        for s in m.get("stages", []):
            self.put("<I", BinaryReader.KINDS.index(s["kind"]))
            self.put("<I", s["degree"])
            self.put("<I", BinaryReader.DIRECTIONS.index(s.get("direction", "implicit")))
            self.optional(s.get("name"), self.string)
            self.put("<Q", len(s.get("faces", [])))
            for r in s.get("faces", []):
                self.u32s(r["face"])
                self.f64s(r.get("points", []))
                self.f64s(r.get("weights", []))
            self.put("<Q", len(s.get("vertexMaps", [])))
            for v in s.get("vertexMaps", []):
                self.put("<I", v["vertex"])
                self.f64s(v["coefficients"])
            self.json(s.get("extras"))
        for key in ("extensionsUsed", "extensionsRequired"):
            self.put("<Q", len(m.get(key, [])))
            for name in m.get(key, []):
                self.string(name)
        extensions = m.get("extensions", {})
        self.put("<Q", len(extensions))
        for name in sorted(extensions, key=lambda k: k.encode("utf-8")):
            self.string(name)
            self.json(extensions[name])
        self.json(m.get("extras"))
        return bytes(self.out)


def container(payload: bytes, tag: int, major: int = 1, minor: int = 0) -> bytes:
    header = MAGIC + struct.pack("<HHB3xQI", major, minor, tag, len(payload), zlib.crc32(payload))
    return header + struct.pack("<I", zlib.crc32(header)) + payload


def appendix_a() -> tuple[dict, bytes]:
    """The model and the bytes of spec Appendix A."""
    text = (ROOT / "spec" / "ism-format.md").read_text()
    section = text[text.index("## Appendix A.") :]
    model_json = section.split("```json\n", 1)[1].split("\n```", 1)[0]
    dump = section.split("```text\n", 1)[1].split("\n```", 1)[0]
    data = bytearray()
    for line in dump.splitlines():
        offset, rest = line[:4], line[6:53]
        assert int(offset, 16) == len(data), f"offset {offset} in Appendix A"
        data += bytes.fromhex(rest)
    return json.loads(model_json), bytes(data)


def test_python_writer_reproduces_appendix_a_and_the_rust_writer(tmp_path):
    model, spec_bytes = appendix_a()
    ours = container(BinaryWriter().model(model), tag=3)
    assert ours == spec_bytes
    source = tmp_path / "tiny.ism.json"
    source.write_text(json.dumps(model))
    target = tmp_path / "tiny.ismb"
    result = subprocess.run([ism_bin(), "convert", str(source), str(target)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert target.read_bytes() == spec_bytes


@pytest.mark.parametrize("name", example_names())
def test_python_writer_reproduces_every_binary_example(name):
    # Byte-identical to the Rust writer on every example: the spec defines the binary encoding.
    model = json.loads((EXAMPLES / f"{name}.ism.json").read_text())
    expected = (EXAMPLES / f"{name}.ismb").read_bytes()
    assert container(BinaryWriter().model(model), tag=3) == expected


@pytest.mark.parametrize("name", example_names())
def test_python_msgpack_matches_the_rust_writer(name):
    # MessagePack: the named-map image of the JSON document, floats as float 64, smallest ints.
    model = json.loads((EXAMPLES / f"{name}.ism.json").read_text())
    expected = (EXAMPLES / f"{name}.ism.msgpack").read_bytes()
    assert container(msgpack.packb(model, use_bin_type=True, use_single_float=False), tag=2) == expected
