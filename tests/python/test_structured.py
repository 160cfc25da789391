"""The structured encoding (spec/ism-format.md §7.4.3: container tag 6, `.isms`) in ismpy, the reader and writer
written from the spec alone:

(a) Appendix A's model in this encoding, assembled here byte by byte from the spec's text, is what ismpy writes,
    and reads back to the model;
(b) every example converts to the structured encoding and back with every f64 bit for bit, and the bytes are a
    fixpoint of reading and writing;
(c) the writer's canonical choices (§7.4.3 "Canonical form", §7.7): `recordForm` 1 exactly when the records are
    those of some masks with the right counts, `dims`, the smallest lattice `width`, and the k-face lists;
(d) every reader error of §7.4.3, with the rule, pointer and file offset its error paragraph gives, and no
    allocation for what the bytes present cannot hold;
(e) differential: the Rust `ism` binary writes exactly ismpy's bytes for every example and each reads the other's
    files (skipped, saying why, when the binary is absent: set ISM_BIN or build target/debug/ism); and the
    reference's conformance adapter reports the same rule and location as ismpy for every file of (d) (skipped
    when absent: set ISM_CONFORMANCE_ADAPTER or build target/debug/ism-conformance-adapter).
"""

from __future__ import annotations

import itertools
import json
import os
import struct
import subprocess
import sys
import time
import tracemalloc
import zlib
from pathlib import Path

import pytest

import ismpy

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "spec" / "examples"
WRITER_VECTORS = ROOT / "spec" / "vectors" / "writer"
HEADER_LEN = ismpy.HEADER_LEN


def example_names() -> list[str]:
    return sorted(p.name[: -len(".ism.json")] for p in EXAMPLES.glob("*.ism.json"))


def bits(model: dict) -> bytes:
    """Every member of the model, every f64 as its 8 bytes (the binary encoding of §7.4)."""
    return ismpy.BinaryWriter().model(model)


def parse_model(text: str) -> dict:
    return ismpy.read(text.encode("utf-8"))


def f64s(*xs) -> str:
    return " ".join(struct.pack("<d", x).hex(" ") for x in xs)


# ---------------------------------------------------------------- (a) Appendix A, byte by byte

APPENDIX_A_MODEL = (
    '{"version":"1.0","dimension":2,"metadata":{"name":"t"},"vertices":[0,0,1,0,0,1],"simplices":[0,1,2],'
    '"values":[-1,1,1],"stages":[{"kind":"bezier","degree":2,"faces":[{"face":[1,2],"points":[0.5,0.5]}]}]}'
)

# The file, as Appendix A writes the binary one: offset (hexadecimal), bytes, what they are. The payload is the
# compact payload of §7.4.1 (varints; "03 31 2E 30 02 01 01 74 00 00 00 06 ..."), with §7.4.3's two changes:
# `complexForm` before `vertices`, and the stage's records by the complex (`recordForm` 1).
APPENDIX_A_STRUCTURED = f"""
0000  89 49 53 4d 0d 0a 1a 0a   magic
0008  01 00                     major 1
000a  00 00                     minor 0
000c  06                        encoding 6 (structured)
000d  00 00 00                  reserved
0010  7a 00 00 00 00 00 00 00   payload length 122
0018  31 6a 9c d7               payload CRC-32
001c  fd 1b 3a 15               header CRC-32
0020  03                        version: length 3
0021  31 2e 30                  "1.0"
0024  02                        dimension 2
0025  01                        metadata.name: present
0026  01                        length 1
0027  74                        "t"
0028  00 00 00                  generator, units, description: absent
002b  00                        complexForm 0: vertices and simplices as in the compact encoding
002c  06                        vertices: length 6
002d  {f64s(0.0, 0.0)}          0.0 0.0
003d  {f64s(1.0, 0.0)}          1.0 0.0
004d  {f64s(0.0, 1.0)}          0.0 1.0
005d  03                        simplices: length 3
005e  00 01 02                  0 1 2
0061  03                        values: length 3
0062  {f64s(-1.0, 1.0)}         -1.0 1.0
0072  {f64s(1.0)}               1.0
007a  {f64s(0.0)}               level 0.0
0082  01                        stages: length 1
0083  00                        kind 0 (bezier)
0084  02                        degree 2
0085  00                        direction 0 (implicit)
0086  00                        name: absent
0087  01                        recordForm 1: records by the complex
0088  02                        dims: bit 1, records of 1-faces follow
0089  04                        mask_1: the 1-faces (0,1) (0,2) (1,2); bit 2, the record on [1, 2]
008a  01                        width 1: the lattice of step 2^-8
008b  80                        the point (0.5, 0.5): n1 = 128 (c1 = 128/256, c0 = (256 - 128)/256)
008c  00                        vertexMaps: length 0 (a bezier stage has no weights before them)
008d  04                        extras: length 4
008e  6e 75 6c 6c               "null"
0092  00                        extensionsUsed: length 0
0093  00                        extensionsRequired: length 0
0094  00                        extensions: length 0
0095  04                        extras: length 4
0096  6e 75 6c 6c               "null"
"""


def dump_bytes(dump: str) -> tuple[bytes, dict]:
    """The bytes of a dump, and the file offset of each line by its description's first words."""
    data = bytearray()
    where = {}
    for line in dump.strip().splitlines():
        offset, rest = line[:4], line[6:]
        hexes, _, what = rest.partition("   ")
        assert int(offset, 16) == len(data), f"offset {offset}: {what.strip()}"
        where[what.strip().split(":")[0]] = len(data)
        data += bytes.fromhex(hexes)
    return bytes(data), where


APPENDIX_A_BYTES, APPENDIX_A_AT = dump_bytes(APPENDIX_A_STRUCTURED)


def test_appendix_a_in_the_structured_encoding_is_what_ismpy_writes():
    data = APPENDIX_A_BYTES
    assert len(data) == 154 and len(data) - HEADER_LEN == 122
    assert data[:HEADER_LEN] == ismpy.container(data[HEADER_LEN:], 6)[:HEADER_LEN], "header, lengths and CRCs"
    model = parse_model(APPENDIX_A_MODEL)
    assert ismpy.write(model, "structured") == data
    back = ismpy.read(data)
    assert bits(back) == bits(model)
    assert back["stages"][0]["faces"] == [{"face": [1, 2], "points": [0.5, 0.5], "weights": []}]
    assert ismpy.decode(data)[1] == "structured"


def test_appendix_a_structured_is_the_compact_payload_with_two_members_changed():
    # §7.4.1: the compact payload is 138 bytes and begins 03 31 2E 30 02 01 01 74 00 00 00 06; its face record is
    # 02 01 02 (face [1, 2]), 02 and the two points, 00 (no weights). The structured payload is the same bytes with
    # complexForm 00 before the vertex count and the records' part replaced.
    compact = ismpy.write(parse_model(APPENDIX_A_MODEL), "compact")[HEADER_LEN:]
    assert len(compact) == 138 and compact.startswith(bytes.fromhex("03 31 2E 30 02 01 01 74 00 00 00 06"))
    record = bytes.fromhex("01 02 01 02 02") + struct.pack("<2d", 0.5, 0.5) + b"\0"  # faces: length 1, the record
    assert compact.count(record) == 1
    expected = compact[:11] + b"\0" + compact[11:].replace(record, bytes.fromhex("01 02 04 01 80"))
    assert APPENDIX_A_BYTES[HEADER_LEN:] == expected


def test_ismpy_command_line_converts_to_structured(tmp_path):
    source = tmp_path / "a.ism.json"
    source.write_text(APPENDIX_A_MODEL)
    target = tmp_path / "a.isms"
    done = subprocess.run([sys.executable, str(Path(ismpy.__file__)), "convert", str(source), str(target), "structured"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    assert target.read_bytes() == APPENDIX_A_BYTES
    done = subprocess.run([sys.executable, str(Path(ismpy.__file__)), "read", str(target)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and json.loads(done.stdout) == {"ok": True}


# ---------------------------------------------------------------- (b) round trips


@pytest.mark.parametrize("name", example_names())
def test_every_example_round_trips_through_structured(name):
    model = ismpy.read((EXAMPLES / f"{name}.ism.json").read_bytes())
    data = ismpy.write(model, "structured")
    assert data[12] == 6
    back = ismpy.read(data)
    assert bits(back) == bits(model), "every member, every f64 bit for bit"
    assert ismpy.write(back, "structured") == data, "canonical bytes are a fixpoint"
    # The same model from every other encoding gives the same structured bytes.
    for ext in ("ismb", "ismc", "ism.msgpack", "ismz"):
        path = EXAMPLES / f"{name}.{ext}"
        if path.exists():
            assert ismpy.write(ismpy.read(path.read_bytes()), "structured") == data, ext
    # The records are stored by the complex wherever the canonical form allows, and never larger than compact
    # by more than the one recordForm/dims/width byte per stage.
    assert len(data) <= len(ismpy.write(model, "compact")) + 2 * len(model["stages"]) + 1
    if (EXAMPLES / f"{name}.isms").exists():
        assert (EXAMPLES / f"{name}.isms").read_bytes() == data, "the checked-in example"


@pytest.mark.parametrize("path", sorted(WRITER_VECTORS.glob("*.input.json")), ids=lambda p: p.name)
def test_every_writer_vector_round_trips_through_structured(path):
    model = ismpy.read(path.read_bytes())
    data = ismpy.write(model, "structured")
    back = ismpy.read(data)
    assert bits(back) == bits(model)
    assert ismpy.write(back, "structured") == data
    vector = path.with_name(path.name.replace(".input.json", ".isms"))
    if vector.exists():
        assert vector.read_bytes() == data


def test_lattice_points_read_back_bit_for_bit():
    # Points on the 2^-8w lattices at every width, including a negative c0 (a sum above 2^8w, which the encoding
    # carries) and zeros; each reads back to the same bits.
    model = strip_model(4)
    edges = ismpy.complex_faces(model["simplices"], 2, 1)
    cases = [
        [0.5, 0.5],
        [1 - 3 / 256, 3 / 256],
        [1 - 3 / 65536, 3 / 65536],
        [1 - 5 / 2**24, 5 / 2**24],
        [1 - 7 / 2**32, 7 / 2**32],
        [1.0, 0.0],
        [0.0, 1 - 2**-32],
    ]
    for points in cases:
        model["stages"] = [bezier(3, [{"face": list(edges[0]), "points": points + points[::-1]}])]
        back = ismpy.read(ismpy.write(model, "structured"))
        assert bits(back) == bits(model), points


# ---------------------------------------------------------------- models used below


def strip_model(count: int, degree: int = 2) -> dict:
    """`count` triangles in a strip (valid: positive orientation), no stages."""
    vertices = []
    for i in range(count // 2 + 2):
        vertices += [float(i), 0.0, float(i), 1.0]
    simplices = []
    for t in range(count):
        i = t // 2
        a, b, c, d = 2 * i, 2 * i + 1, 2 * i + 2, 2 * i + 3  # (i,0) (i,1) (i+1,0) (i+1,1)
        simplices += [a, c, b] if t % 2 == 0 else [c, d, b]
    model = ismpy.new_model()
    model.update(version="1.0", dimension=2, vertices=vertices, simplices=simplices, values=[(-1.0) ** v for v in range(len(vertices) // 2)])
    assert not ismpy.structural_errors(model)
    return model


def bezier(degree, faces, kind="bezier"):
    return {"kind": kind, "degree": degree, "direction": "implicit", "name": None, "faces": [{"face": f["face"], "points": f.get("points", []), "weights": f.get("weights", [])} for f in faces], "vertexMaps": [], "extras": None}


def choices(model):
    return ismpy.structured_choices(model)


# ---------------------------------------------------------------- (c) canonical choices and k-faces


def test_k_faces_follow_the_definition():
    # Sorted tuples of k + 1 distinct ids of one top simplex, each once, lexicographic; from the simplices as
    # decoded: ids out of range and repeated ids count, a trailing incomplete group is no simplex.
    simplices = [5, 1, 3, 3, 1, 9, 2, 2, 2, 7, 8]
    assert ismpy.complex_faces(simplices, 2, 0) == [(1,), (2,), (3,), (5,), (9,)]
    assert ismpy.complex_faces(simplices, 2, 1) == [(1, 3), (1, 5), (1, 9), (3, 5), (3, 9)]
    assert ismpy.complex_faces(simplices, 2, 2) == [(1, 3, 5), (1, 3, 9)]
    assert ismpy.complex_faces(simplices, 2, 3) == []
    assert ismpy.complex_faces([0, 1, 2, 0, 2, 3], 2, 1) == [(0, 1), (0, 2), (0, 3), (1, 2), (2, 3)]
    # Brute force against the definition on a random complex.
    import random

    rnd = random.Random(7)
    simplices = [rnd.randrange(12) for _ in range(4 * 40)]
    for k in range(4):
        expected = set()
        for s in range(40):
            expected |= set(itertools.combinations(sorted(set(simplices[4 * s : 4 * s + 4])), k + 1))
        assert ismpy.complex_faces(simplices, 3, k) == sorted(expected)


def test_record_form_one_whenever_the_records_are_those_of_masks():
    model = strip_model(6)
    n = 2
    edges = ismpy.complex_faces(model["simplices"], n, 1)
    triangles = ismpy.complex_faces(model["simplices"], n, 2)
    vertices = ismpy.complex_faces(model["simplices"], n, 0)
    half = [0.5, 0.5]
    third = [0.25, 0.25, 0.5]

    def form(*stages):
        model["stages"] = list(stages)
        return choices(model)[0]

    e = lambda i, pts=half: {"face": list(edges[i]), "points": list(pts)}  # noqa: E731
    assert form(bezier(2, [e(0), e(3), e(4)])) == (1, 0b010, 1)
    assert form(bezier(2, [])) == (1, 0, 1), "no records: masks of nothing, width 1 (no point is off the lattice)"
    assert form(bezier(3, [{"face": list(vertices[1]), "points": [1.0]}, e(2, half * 2), {"face": list(triangles[0]), "points": third}])) == (1, 0b111, 1)
    # Out of face order, a face twice, k not ascending: recordForm 0.
    assert form(bezier(2, [e(3), e(0)]))[0] == 0
    assert form(bezier(2, [e(3), e(3)]))[0] == 0
    assert form(bezier(3, [{"face": list(triangles[0]), "points": third}, e(0, half * 2)]))[0] == 0
    # Not a face of the complex, or not sorted: recordForm 0.
    assert form(bezier(2, [{"face": [0, 5], "points": half}]))[0] == 0
    assert form(bezier(2, [{"face": list(edges[0])[::-1], "points": half}]))[0] == 0
    assert form(bezier(2, [{"face": [], "points": []}]))[0] == 0
    # Counts: C(d - 1, k) points of k + 1 coordinates, weights only and exactly in rational stages.
    assert form(bezier(2, [e(0, half * 2)]))[0] == 0
    assert form(bezier(2, [e(0, [])]))[0] == 0
    assert form(bezier(2, [{"face": list(edges[0]), "points": half, "weights": [1.0]}]))[0] == 0
    assert form(bezier(2, [{"face": list(edges[0]), "points": half, "weights": [1.0]}], kind="rational")) == (1, 0b010, 1)
    assert form(bezier(2, [e(0)], kind="rational"))[0] == 0
    # A face owning nothing at this degree (k >= d) has records of no points: still a mask's record.
    assert form(bezier(1, [e(0, [])])) == (1, 0b010, 1)
    assert form(bezier(1, [{"face": list(triangles[0]), "points": []}])) == (1, 0b100, 1)
    # Monotonic: recordForm 1 (dims 0) only without records.
    mono = {"kind": "monotonic", "degree": 2, "direction": "implicit", "name": None, "faces": [], "vertexMaps": [{"vertex": 0, "coefficients": [0.0, 0.5, 1.0]}], "extras": None}
    assert form(mono) == (1, 0, 1)
    assert form(dict(mono, faces=[{"face": list(edges[0]), "points": half, "weights": []}]))[0] == 0


def test_record_form_zero_round_trips():
    model = strip_model(6)
    edges = ismpy.complex_faces(model["simplices"], 2, 1)
    model["stages"] = [bezier(2, [{"face": list(edges[3]), "points": [0.5, 0.5]}, {"face": list(edges[1]), "points": [0.25, 0.75]}])]
    data = ismpy.write(model, "structured")
    assert choices(model) == [(0, None, None)]
    back = ismpy.decode(data)[0]
    assert bits(back) == bits(model)
    assert ismpy.write(back, "structured") == data


@pytest.mark.parametrize(
    "point,width",
    [
        ([0.5, 0.5], 1),
        ([1 - 255 / 256, 255 / 256], 1),
        ([1 - 1 / 512, 1 / 512], 2),
        ([1 - 3 / 2**16, 3 / 2**16], 2),
        ([1 - 1 / 2**17, 1 / 2**17], 3),
        ([1 - 5 / 2**24, 5 / 2**24], 3),
        ([1 - 1 / 2**25, 1 / 2**25], 4),
        ([1 - 1 / 2**32, 1 / 2**32], 4),
        ([1 - 1 / 2**33, 1 / 2**33], 0),
        ([0.9, 0.1], 0),
        ([1.0, 0.0], 1),
        ([0.0, 1.0], 0),  # n1 = 2^8w is not below 2^8w
        ([0.0, 1 - 1 / 256], 0),  # c0 is not 1 - c1
        ([0.5, 0.25], 0),  # does not sum to 1
        ([1.0, -0.0], 0),  # -0.0 is on no lattice
        ([-0.0, 1 - 2**-8], 0),  # c0 would be +0.0 ... and c1 + c0 != 1 anyway
        ([1.5, -0.5], 0),  # negative n1
    ],
)
def test_smallest_lattice_width_of_an_edge_point(point, width):
    model = strip_model(2)
    edges = ismpy.complex_faces(model["simplices"], 2, 1)
    model["stages"] = [bezier(2, [{"face": list(edges[0]), "points": point}])]
    assert choices(model) == [(1, 0b010, width)]
    data = ismpy.write(model, "structured")
    back = ismpy.decode(data)[0]
    assert bits(back) == bits(model)


def test_lattice_width_of_triangle_points_and_vertices():
    model = strip_model(2)
    tri = list(ismpy.complex_faces(model["simplices"], 2, 2)[0])
    vertex = [tri[0]]
    form = lambda *faces: (model.update(stages=[bezier(3, list(faces))]), choices(model)[0])[1]  # noqa: E731
    assert form({"face": tri, "points": [0.25, 0.25, 0.5]}) == (1, 0b100, 1)
    # c0 = 0.0 on the lattice (n1 + n2 = 2^8w)
    assert form({"face": tri, "points": [0.0, 0.25, 0.75]}) == (1, 0b100, 1)
    assert form({"face": tri, "points": [-0.0, 0.25, 0.75]}) == (1, 0b100, 0)
    # c0 negative: the sum is above 2^8w (ISM-201 for a validator), still on the lattice
    assert form({"face": tri, "points": [-0.5, 0.75, 0.75]}) == (1, 0b100, 1)
    assert form({"face": tri, "points": [1 - 2**-9 - 0.5, 2**-9, 0.5]}) == (1, 0b100, 2)
    # The stage's width is the largest of its points' smallest widths.
    e = list(ismpy.complex_faces(model["simplices"], 2, 1)[0])
    assert form({"face": e, "points": [0.5, 0.5, 1 - 2**-20, 2**-20]}, {"face": tri, "points": [0.25, 0.25, 0.5]}) == (1, 0b110, 3)
    # A vertex record's point is (1.0): on every lattice, no bytes; anything else is width 0.
    assert form({"face": vertex, "points": [1.0]}) == (1, 0b001, 1)
    assert form({"face": vertex, "points": [0.75]}) == (1, 0b001, 0)
    for points in ([1.0], [0.75]):
        model["stages"] = [bezier(2, [{"face": vertex, "points": points}])]
        back = ismpy.decode(ismpy.write(model, "structured"))[0]
        assert bits(back) == bits(model)


def test_points_and_weights_bytes():
    # Points of every record first (record order), then weights of every record: a rational stage of degree 3 on
    # two edges at width 2.
    model = strip_model(2)
    edges = ismpy.complex_faces(model["simplices"], 2, 1)
    a, b = 1 / 512, 3 / 512
    faces = [
        {"face": list(edges[0]), "points": [1 - a, a, 1 - b, b], "weights": [2.0, 3.0]},
        {"face": list(edges[2]), "points": [1 - b, b, 1 - a, a], "weights": [4.0, 5.0]},
    ]
    model["stages"] = [bezier(3, faces, kind="rational")]
    assert choices(model) == [(1, 0b010, 2)]
    data = ismpy.write(model, "structured")
    mask = bytes([0b101])  # edges (0,1) (0,2) (1,2) (1,3) (2,3): positions 0 and 2
    # 1/512 = 128/2^16, 3/512 = 384/2^16: one 2-byte integer per point, then the four weights.
    tail = bytes.fromhex("01 02") + mask + bytes([2]) + bytes.fromhex("8000 8001 8001 8000") + struct.pack("<4d", 2.0, 3.0, 4.0, 5.0)
    assert len(ismpy.complex_faces(model["simplices"], 2, 1)) == 5
    assert tail + bytes.fromhex("00 04") + b"null" in data
    assert bits(ismpy.read(data)) == bits(model)


def tet_grid(cells: int) -> dict:
    """A valid grid of cells^3 cubes, six positively oriented tetrahedra each."""
    side = cells + 1
    vid = lambda i, j, k: (i * side + j) * side + k  # noqa: E731
    vertices = [float(c) for i in range(side) for j in range(side) for k in range(side) for c in (i, j, k)]
    simplices = []
    for i, j, k in itertools.product(range(cells), repeat=3):
        for perm in itertools.permutations(range(3)):
            p = [i, j, k]
            ids = [vid(*p)]
            for axis in perm:
                p[axis] += 1
                ids.append(vid(*p))
            P = [vertices[3 * v : 3 * v + 3] for v in ids]
            e = [[P[r + 1][c] - P[0][c] for c in range(3)] for r in range(3)]
            det = e[0][0] * (e[1][1] * e[2][2] - e[1][2] * e[2][1]) - e[0][1] * (e[1][0] * e[2][2] - e[1][2] * e[2][0]) + e[0][2] * (e[1][0] * e[2][1] - e[1][1] * e[2][0])
            if det < 0:
                ids[0], ids[1] = ids[1], ids[0]
            simplices += ids
    model = ismpy.new_model()
    model.update(version="1.0", dimension=3, vertices=vertices, simplices=simplices, values=[1.5 if v % 3 else -1.5 for v in range(side**3)])
    return model


def test_large_models_convert_in_seconds():
    # 29 478 tetrahedra and 20 000 records on the 2^-24 lattice (as `ism fit` writes them): reading and writing
    # take dicts and sorting, no quadratic loop.
    import random

    rnd = random.Random(3)
    model = tet_grid(17)
    assert len(model["simplices"]) // 4 == 29478
    complex_ = ismpy.ComplexFaces(model["simplices"], 3)
    edges, triangles = complex_.faces(1), complex_.faces(2)
    faces = []
    for i in sorted(rnd.sample(range(len(edges)), 10000)):
        a = rnd.randrange(1, 1 << 23) / 2**24
        faces.append({"face": list(edges[i]), "points": [1 - a, a, a, 1 - a]})
    for i in sorted(rnd.sample(range(len(triangles)), 10000)):
        x, y = rnd.randrange(1, 1 << 22) / 2**24, rnd.randrange(1, 1 << 22) / 2**24
        faces.append({"face": list(triangles[i]), "points": [1 - x - y, x, y]})
    model["stages"] = [bezier(3, faces)]
    start = time.perf_counter()
    assert not ismpy.structural_errors(model)
    data = ismpy.write(model, "structured")
    back = ismpy.read(data)
    again = ismpy.write(back, "structured")
    elapsed = time.perf_counter() - start
    assert again == data and bits(back) == bits(model)
    assert choices(model) == [(1, 0b110, 3)]
    assert len(data) < 0.6 * len(ismpy.write(model, "compact"))
    assert elapsed < 30, f"{elapsed:.1f} s"


# ---------------------------------------------------------------- (d) reader errors


def varint(n: int) -> bytes:
    if n <= 250:
        return bytes([n])
    if n < 1 << 16:
        return b"\xfb" + struct.pack("<H", n)
    if n < 1 << 32:
        return b"\xfc" + struct.pack("<I", n)
    return b"\xfd" + struct.pack("<Q", n)


class Payload:
    """A structured payload assembled part by part; `at[label]` is the file offset of a part."""

    def __init__(self):
        self.b = bytearray()
        self.at = {}

    def add(self, label: str, data: bytes) -> "Payload":
        self.at[label] = HEADER_LEN + len(self.b)
        self.b += data
        return self

    def file(self, cut: int | None = None) -> bytes:
        payload = bytes(self.b) if cut is None else bytes(self.b[: cut - HEADER_LEN])
        return ismpy.container(payload, 6)


def head(model: dict, stages: int = 1, metadata: bytes = b"\0\0\0\0") -> Payload:
    """Everything up to and including the stages' count."""
    p = Payload()
    p.add("version", b"\x031.0").add("dimension", bytes([model["dimension"]])).add("metadata", metadata)
    p.add("complexForm", b"\0")
    p.add("vertices", varint(len(model["vertices"])) + struct.pack(f"<{len(model['vertices'])}d", *model["vertices"]))
    p.add("simplices", varint(len(model["simplices"])) + b"".join(varint(i) for i in model["simplices"]))
    p.add("values", varint(len(model["values"])) + struct.pack(f"<{len(model['values'])}d", *model["values"]))
    p.add("level", struct.pack("<d", 0.0)).add("stages", varint(stages))
    return p


def stage_head(p: Payload, kind: int = 0, degree: int = 2, name: bytes | None = None) -> Payload:
    """A stage's members before its records. A `name` keeps a truncated payload long enough for the stages'
    count (the smallest stage, §7.4.1: 7 bytes), so that the truncation, not the count, is the first error."""
    named = b"\0" if name is None else b"\1" + varint(len(name)) + name
    return p.add("kind", bytes([kind])).add("degree", varint(degree)).add("direction", b"\0").add("name", named)


PAD = b"padding!"


def mask_of(model: dict, k: int, positions) -> bytes:
    """mask_k with bits `positions` set: ceil(F_k / 8) bytes."""
    mask = bytearray((len(ismpy.complex_faces(model["simplices"], model["dimension"], k)) + 7) // 8)
    for i in positions:
        mask[i // 8] |= 1 << (i % 8)
    return bytes(mask)


def tail(p: Payload) -> Payload:
    return p.add("vertexMaps", b"\0").add("stage extras", b"\x04null").add("model tail", b"\0\0\0\x04null")


def expect(data: bytes, pointer: str, offset: int, rule: str = "ISM-006"):
    with pytest.raises(ismpy.IsmError) as error:
        ismpy.read(data)
    assert (error.value.rule, error.value.location) == (rule, {"pointer": pointer, "offset": offset}), str(error.value)
    return error.value


def appendix_a_with(offset: int, byte: int) -> bytes:
    payload = bytearray(APPENDIX_A_BYTES[HEADER_LEN:])
    payload[offset - HEADER_LEN] = byte
    return ismpy.container(bytes(payload), 6)


def test_the_hand_assembled_payloads_are_right():
    model = parse_model(APPENDIX_A_MODEL)
    p = tail(stage_head(head(model, metadata=b"\1\1t\0\0\0")).add("records", bytes.fromhex("01 02 04 01 80")))
    assert p.file() == APPENDIX_A_BYTES
    assert APPENDIX_A_AT["complexForm 0"] == p.at["complexForm"]


@pytest.mark.parametrize("value", [2, 3, 255])
def test_complex_form_other_than_zero_or_one(value):
    expect(appendix_a_with(APPENDIX_A_AT["complexForm 0"], value), "/vertices", 0x2B)


def test_complex_form_one_reads_the_vertices_as_a_box():
    # complexForm 1 in 2D: the vertex count 6 is box's length, not the 4 of lo0 hi0 lo1 hi1: at box's first byte.
    expect(appendix_a_with(APPENDIX_A_AT["complexForm 0"], 1), "/vertices", 0x2C)


@pytest.mark.parametrize("value", [2, 3, 255])
def test_record_form_above_one(value):
    expect(appendix_a_with(APPENDIX_A_AT["recordForm 1"], value), "/stages/0/faces", 0x87)


@pytest.mark.parametrize("dims", [0b1000, 0b1010, 0x80, 0xFF])
def test_dims_bits_above_the_dimension(dims):
    expect(appendix_a_with(APPENDIX_A_AT["dims"], dims), "/stages/0/faces", 0x88)


def test_dims_bit_three_is_allowed_in_dimension_three():
    # A single tetrahedron: one 3-face; a degree-4 stage's record on it holds C(3, 3) = 1 point.
    model = ismpy.new_model()
    model.update(version="1.0", dimension=3, vertices=[0.0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1], simplices=[0, 1, 2, 3], values=[-1.0, 1, 1, 1])
    model["stages"] = [bezier(4, [{"face": [0, 1, 2, 3], "points": [0.25] * 4}])]
    assert choices(model) == [(1, 0b1000, 1)]
    data = ismpy.write(model, "structured")
    assert bytes.fromhex("01 08 01 01 40 40 40") in data
    assert bits(ismpy.read(data)) == bits(model)


@pytest.mark.parametrize("mask", [0b1100, 0b1000, 0xF0, 0xFF])
def test_mask_padding_bits(mask):
    expect(appendix_a_with(APPENDIX_A_AT["mask_1"], mask), "/stages/0/faces", 0x89)


def test_mask_padding_bits_in_the_last_byte_of_a_longer_mask():
    model = strip_model(20)  # 20 triangles: 2 + 2*11 + ... edges
    count = len(ismpy.complex_faces(model["simplices"], 2, 1))
    assert count % 8 and count > 16
    size = (count + 7) // 8
    mask = bytearray(size)
    mask[0] = 1
    mask[-1] = 1 << (count % 8)
    p = tail(stage_head(head(model)).add("recordForm", b"\x01").add("dims", b"\x02").add("mask", bytes(mask)).add("width", b"\x01").add("points", b"\x80"))
    expect(p.file(), "/stages/0/faces", p.at["mask"] + size - 1)
    mask[-1] = 0
    p = tail(stage_head(head(model)).add("recordForm", b"\x01").add("dims", b"\x02").add("mask", bytes(mask)).add("width", b"\x01").add("points", b"\x80"))
    faces = ismpy.decode(p.file())[0]["stages"][0]["faces"]
    assert faces == [{"face": list(ismpy.complex_faces(model["simplices"], 2, 1)[0]), "points": [0.5, 0.5], "weights": []}]


@pytest.mark.parametrize("width", [5, 6, 255])
def test_width_above_four(width):
    expect(appendix_a_with(APPENDIX_A_AT["width 1"], width), "/stages/0/faces", 0x8A)


def test_truncated_mask():
    model = strip_model(20)
    mask = mask_of(model, 1, [0])
    size = len(mask)
    assert size > 3
    p = stage_head(head(model), name=PAD).add("recordForm", b"\x01").add("dims", b"\x02").add("mask", mask)
    for cut in range(p.at["mask"], p.at["mask"] + size):
        expect(p.file(cut), "/stages/0/faces", p.at["mask"])
    # The second of two masks.
    p = stage_head(head(model), degree=3, name=PAD).add("recordForm", b"\x01").add("dims", b"\x06").add("mask1", mask).add("mask2", mask_of(model, 2, [0]))
    expect(p.file(p.at["mask2"] + 1), "/stages/0/faces", p.at["mask2"])
    # A mask longer than the whole payload.
    big = strip_model(400)
    p = stage_head(head(big), name=PAD).add("recordForm", b"\x01").add("dims", b"\x02").add("mask", b"\x01")
    expect(p.file(), "/stages/0/faces", p.at["mask"])


def test_missing_single_bytes():
    model = parse_model(APPENDIX_A_MODEL)
    p = tail(stage_head(head(model), name=PAD).add("recordForm", b"\x01").add("dims", b"\x02").add("mask", b"\x04").add("width", b"\x01").add("points", b"\x80"))
    assert ismpy.read(p.file())["stages"][0]["faces"] == [{"face": [1, 2], "points": [0.5, 0.5], "weights": []}]
    expect(p.file(p.at["complexForm"]), "/vertices", p.at["complexForm"])
    for part in ("recordForm", "dims", "mask", "width"):
        expect(p.file(p.at[part]), "/stages/0/faces", p.at[part])
    expect(p.file(p.at["vertexMaps"]), "/stages/0/vertexMaps", p.at["vertexMaps"])


@pytest.mark.parametrize("width", [0, 1, 2, 3, 4])
def test_truncated_points(width):
    # Four edge records of a degree-3 stage: 2 points each; at width 0, 2 f64 per point, else 1 w-byte integer.
    model = strip_model(4)
    point = 16 if width == 0 else width
    points = bytes(4 * 2 * point)
    p = tail(stage_head(head(model), degree=3, name=PAD).add("recordForm", b"\x01").add("dims", b"\x02").add("mask", mask_of(model, 1, [0, 2, 4, 8])).add("width", bytes([width])).add("points", points))
    assert len(ismpy.decode(p.file())[0]["stages"][0]["faces"]) == 4
    # Cut anywhere in the points: the bytes the records need are checked at width, before any record exists.
    for cut in [p.at["points"], p.at["points"] + 1, p.at["points"] + len(points) - 1]:
        expect(p.file(cut), "/stages/0/faces", p.at["width"])
    # With the points complete, what is missing is the next member.
    expect(p.file(p.at["vertexMaps"]), "/stages/0/vertexMaps", p.at["vertexMaps"])


def test_truncated_points_is_checked_against_the_whole_section():
    # The whole section must fit before any record is decoded: 4 records of 2 points at width 0 need 128 bytes,
    # and the bytes after width (vertexMaps, extras, the model's tail: 14) are fewer, though more than one point.
    model = strip_model(4)
    p = tail(stage_head(head(model), degree=3).add("recordForm", b"\x01").add("dims", b"\x02").add("mask", mask_of(model, 1, [0, 1, 2, 3])).add("width", b"\x00"))
    expect(p.file(), "/stages/0/faces", p.at["width"])


@pytest.mark.parametrize("width", [0, 3])
def test_truncated_weights(width):
    # A rational stage of degree 2 on three edges: a point and a weight each.
    model = strip_model(4)
    points = struct.pack("<6d", 0.5, 0.5, 0.5, 0.5, 0.5, 0.5) if width == 0 else bytes.fromhex("000080" * 3)
    weights = struct.pack("<3d", 1.0, 2.0, 3.0)
    p = tail(stage_head(head(model), kind=1, name=PAD).add("recordForm", b"\x01").add("dims", b"\x02").add("mask", mask_of(model, 1, [0, 1, 2])).add("width", bytes([width])).add("points", points).add("weights", weights))
    faces = ismpy.decode(p.file())[0]["stages"][0]["faces"]
    assert [f["weights"] for f in faces] == [[1.0], [2.0], [3.0]]
    assert [f["points"] for f in faces] == [[0.5, 0.5]] * 3
    for cut in [p.at["weights"], p.at["weights"] + 8, p.at["weights"] + 23]:
        expect(p.file(cut), "/stages/0/faces", p.at["width"])


@pytest.mark.parametrize("dims", [0b001, 0b010, 0b100])
def test_monotonic_stage_with_dims(dims):
    model = parse_model(APPENDIX_A_MODEL)
    p = tail(stage_head(head(model), kind=2).add("recordForm", b"\x01").add("dims", bytes([dims])).add("mask", b"\x00").add("width", b"\x01"))
    expect(p.file(), "/stages/0/faces", p.at["dims"])
    # dims 0 decodes (no records): the stage has no faces.
    p = tail(stage_head(head(model), kind=2).add("recordForm", b"\x01").add("dims", b"\x00").add("width", b"\x01"))
    assert ismpy.decode(p.file())[0]["stages"][0]["faces"] == []


@pytest.mark.parametrize("kind,dims,mask", [(0, 0b010, b"\x04"), (1, 0b010, b"\x07"), (1, 0b100, b"\x01"), (0, 0b110, b"\x07\x01")])
def test_huge_degree_does_not_allocate(kind, dims, mask):
    # degree 2^32 - 1: a 1-face owns 2^32 - 2 points, a 2-face C(2^32 - 2, 2) ~ 9.2e18; counts are exact (no
    # saturation needed) and compared with the bytes left before any record exists.
    model = parse_model(APPENDIX_A_MODEL)
    p = tail(stage_head(head(model), kind=kind, degree=0xFFFFFFFF).add("recordForm", b"\x01").add("dims", bytes([dims])).add("mask", mask).add("width", b"\x01").add("points", bytes(64)))
    tracemalloc.start()
    try:
        expect(p.file(), "/stages/0/faces", p.at["width"])
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20, peak


def test_vertex_records_of_a_huge_degree_take_no_bytes():
    # A vertex owns C(d - 1, 0) = 1 multi-index at any degree: its point is (1.0), no bytes at width >= 1.
    model = parse_model(APPENDIX_A_MODEL)
    p = tail(stage_head(head(model), degree=0xFFFFFFFF).add("recordForm", b"\x01").add("dims", b"\x01").add("mask", b"\x07").add("width", b"\x04"))
    faces = ismpy.decode(p.file())[0]["stages"][0]["faces"]
    assert faces == [{"face": [v], "points": [1.0], "weights": []} for v in range(3)]
    with pytest.raises(ismpy.IsmError) as error:
        ismpy.read(p.file())
    assert (error.value.rule, error.value.location["pointer"]) == ("ISM-120", "/stages/0/degree")


def test_record_form_1_outside_2d_and_3d_is_refused_without_listing_the_faces():
    # Dimension 15, one top simplex of 16 ids: C(16, 8) = 12 870 7-faces. §7.4.3 allows recordForm 1 only in 2D
    # and 3D, so the byte itself is refused, before any face is listed.
    model = ismpy.new_model()
    model.update(dimension=15, vertices=[], simplices=list(range(16)), values=[])
    p = stage_head(head(model)).add("recordForm", b"\x01").add("dims", b"\x80").add("mask", bytes(20))
    tracemalloc.start()
    try:
        expect(p.file(), "/stages/0/faces", p.at["recordForm"])
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20, peak


def test_a_mask_the_payload_cannot_hold_is_refused_at_its_first_byte():
    # Three tetrahedra around the triangle (0, 1, 2): 12 edges, a two-byte mask; the payload ends one byte into it
    # (the stage still has the 7 bytes a stage takes at least, so the stage count is not what is refused).
    model = ismpy.new_model()
    model.update(dimension=3, vertices=[0.0] * 18, simplices=[0, 1, 2, 3, 0, 1, 2, 4, 0, 1, 2, 5], values=[-1.0] + [1.0] * 5)
    p = stage_head(head(model)).add("recordForm", b"\x01").add("dims", b"\x02").add("mask", b"\x00")
    expect(p.file(), "/stages/0/faces", p.at["mask"])


def test_records_of_an_invalid_complex_decode_then_fail_the_structural_checks():
    # The k-faces come from the simplices as decoded: an id out of range, a repeated id.
    model = ismpy.new_model()
    model.update(dimension=2, vertices=[0.0, 0, 1, 0, 0, 1], simplices=[0, 0, 7], values=[-1.0, 1, 1])
    p = tail(stage_head(head(model)).add("recordForm", b"\x01").add("dims", b"\x03").add("mask0", b"\x02").add("mask1", b"\x01").add("width", b"\x01").add("points", b"\x40"))
    decoded = ismpy.decode(p.file())[0]
    assert decoded["stages"][0]["faces"] == [
        {"face": [7], "points": [1.0], "weights": []},
        {"face": [0, 7], "points": [0.75, 0.25], "weights": []},
    ]
    with pytest.raises(ismpy.IsmError) as error:
        ismpy.read(p.file())
    assert error.value.rule == "ISM-104"


def test_a_record_owning_nothing_decodes_and_is_ism_124():
    model = parse_model(APPENDIX_A_MODEL)
    p = tail(stage_head(head(model), degree=1).add("recordForm", b"\x01").add("dims", b"\x02").add("mask", b"\x01").add("width", b"\x01"))
    assert ismpy.decode(p.file())[0]["stages"][0]["faces"] == [{"face": [0, 1], "points": [], "weights": []}]
    with pytest.raises(ismpy.IsmError) as error:
        ismpy.read(p.file())
    assert (error.value.rule, error.value.location["pointer"]) == ("ISM-124", "/stages/0/faces/0/points")


def test_a_negative_c0_is_carried():
    model = strip_model(2)
    p = tail(stage_head(head(model), degree=3).add("recordForm", b"\x01").add("dims", b"\x04").add("mask", b"\x01").add("width", b"\x01").add("points", b"\xc0\xc0"))
    face = ismpy.read(p.file())["stages"][0]["faces"][0]
    assert face["points"] == [-0.5, 0.75, 0.75]
    assert ismpy.write(ismpy.read(p.file()), "structured") == p.file()


def test_record_form_zero_keeps_the_compact_errors():
    model = parse_model(APPENDIX_A_MODEL)
    # faces: length 1, face: length 2, ids 1 and a non-minimal varint FB 02 00
    p = tail(stage_head(head(model)).add("recordForm", b"\x00").add("count", b"\x01").add("face", b"\x02\x01").add("id", b"\xfb\x02\x00"))
    expect(p.file(), "/stages/0/faces/0/face", p.at["id"])
    p = stage_head(head(model)).add("recordForm", b"\x00").add("count", b"\x05").add("rest", b"\x00" * 9)
    expect(p.file(), "/stages/0/faces", p.at["count"])


def test_encoding_tag_six_is_known_and_seven_is_not():
    data = bytearray(APPENDIX_A_BYTES)
    data[12] = 7
    data[28:32] = struct.pack("<I", zlib.crc32(bytes(data[:28])))
    with pytest.raises(ismpy.IsmError) as error:
        ismpy.read(bytes(data))
    assert (error.value.rule, error.value.location) == ("ISM-005", {"offset": 12})


# ---------------------------------------------------------------- (e) differential, against the Rust `ism`


def ism_bin() -> str:
    path = os.environ.get("ISM_BIN") or str(ROOT / "target" / "debug" / "ism")
    if not Path(path).is_file():
        pytest.skip(f"the Rust `ism` binary is absent ({path}): build it with `cargo build -p ism-cli` or set ISM_BIN")
    return path


def ism(*args) -> subprocess.CompletedProcess:
    return subprocess.run([ism_bin(), *map(str, args)], capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("name", example_names())
def test_rust_and_ismpy_write_the_same_structured_bytes_and_read_each_other(name, tmp_path):
    binary = ism_bin()
    source = EXAMPLES / f"{name}.ism.json"
    model = ismpy.read(source.read_bytes())
    ours = ismpy.write(model, "structured")
    theirs = tmp_path / f"{name}.isms"
    done = subprocess.run([binary, "convert", str(source), str(theirs)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    got = theirs.read_bytes()
    at = next((i for i, (a, b) in enumerate(zip(got, ours)) if a != b), min(len(got), len(ours)))
    assert got == ours, f"the reference writes {len(got)} bytes, ismpy {len(ours)}; first difference at byte {at}"
    # ismpy reads the reference's file ...
    assert bits(ismpy.read(got)) == bits(model)
    # ... and the reference reads ismpy's: converted to the binary encoding, every f64 bit for bit.
    mine = tmp_path / f"{name}-ismpy.isms"
    mine.write_bytes(ours)
    back = tmp_path / f"{name}-back.ismb"
    done = subprocess.run([binary, "convert", str(mine), str(back)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert back.read_bytes() == ismpy.write(model, "binary")


def adapter() -> str:
    path = os.environ.get("ISM_CONFORMANCE_ADAPTER") or str(ROOT / "target" / "debug" / "ism-conformance-adapter")
    if not Path(path).is_file():
        pytest.skip(f"the reference's conformance adapter is absent ({path}): build it with `cargo build -p ism-conformance` or set ISM_CONFORMANCE_ADAPTER")
    return path


def reader_cases() -> dict:
    """Files of every reader error above (and a few that decode), by name."""
    a = APPENDIX_A_AT
    cases = {
        "complex-form-1": appendix_a_with(a["complexForm 0"], 1),
        "complex-form-2": appendix_a_with(a["complexForm 0"], 2),
        "record-form-2": appendix_a_with(a["recordForm 1"], 2),
        "dims-bit-3": appendix_a_with(a["dims"], 0b1010),
        "dims-bit-7": appendix_a_with(a["dims"], 0x82),
        "mask-padding": appendix_a_with(a["mask_1"], 0b1100),
        "width-5": appendix_a_with(a["width 1"], 5),
        "appendix-a": APPENDIX_A_BYTES,
    }
    strip = strip_model(20)
    p = stage_head(head(strip), name=PAD).add("recordForm", b"\x01").add("dims", b"\x02").add("mask", mask_of(strip, 1, [0]))
    cases["truncated-mask"] = p.file(p.at["mask"] + 2)
    four = strip_model(4)
    for width in (0, 3):
        p = tail(stage_head(head(four), degree=3, name=PAD).add("recordForm", b"\x01").add("dims", b"\x02").add("mask", mask_of(four, 1, [0, 2, 4, 8])).add("width", bytes([width])).add("points", bytes(4 * 2 * (16 if width == 0 else width))))
        cases[f"width-{width}"] = p.file()
        cases[f"truncated-points-width-{width}"] = p.file(p.at["points"] + 1)
    p = tail(stage_head(head(four), kind=1, name=PAD).add("recordForm", b"\x01").add("dims", b"\x02").add("mask", mask_of(four, 1, [0, 1, 2])).add("width", b"\x03").add("points", bytes.fromhex("000080" * 3)).add("weights", struct.pack("<3d", 1.0, 2.0, 3.0)))
    cases["rational"] = p.file()
    cases["truncated-weights"] = p.file(p.at["weights"] + 8)
    model = parse_model(APPENDIX_A_MODEL)
    p = tail(stage_head(head(model), kind=2).add("recordForm", b"\x01").add("dims", b"\x02").add("mask", b"\x00").add("width", b"\x01"))
    cases["monotonic-dims"] = p.file()
    p = tail(stage_head(head(model), kind=1, degree=0xFFFFFFFF).add("recordForm", b"\x01").add("dims", b"\x04").add("mask", b"\x01").add("width", b"\x01").add("points", bytes(64)))
    cases["huge-degree"] = p.file()
    p = tail(stage_head(head(model), degree=0xFFFFFFFF).add("recordForm", b"\x01").add("dims", b"\x01").add("mask", b"\x07").add("width", b"\x04"))
    cases["huge-degree-vertices"] = p.file()
    p = tail(stage_head(head(model), degree=1).add("recordForm", b"\x01").add("dims", b"\x02").add("mask", b"\x01").add("width", b"\x01"))
    cases["owns-nothing"] = p.file()
    p = tail(stage_head(head(strip_model(2)), degree=3).add("recordForm", b"\x01").add("dims", b"\x04").add("mask", b"\x01").add("width", b"\x01").add("points", b"\xc0\xc0"))
    cases["negative-c0"] = p.file()
    bad = ismpy.new_model()
    bad.update(dimension=2, vertices=[0.0, 0, 1, 0, 0, 1], simplices=[0, 0, 7], values=[-1.0, 1, 1])
    p = tail(stage_head(head(bad)).add("recordForm", b"\x01").add("dims", b"\x03").add("mask0", b"\x02").add("mask1", b"\x01").add("width", b"\x01").add("points", b"\x40"))
    cases["repeated-and-out-of-range-ids"] = p.file()
    wide = ismpy.new_model()
    wide.update(dimension=15, vertices=[], simplices=list(range(16)), values=[])
    cases["record-form-1-in-dimension-15"] = stage_head(head(wide)).add("recordForm", b"\x01").add("dims", b"\x80").add("mask", bytes(20)).file()
    tets = ismpy.new_model()
    tets.update(dimension=3, vertices=[0.0] * 18, simplices=[0, 1, 2, 3, 0, 1, 2, 4, 0, 1, 2, 5], values=[-1.0] + [1.0] * 5)
    cases["mask-beyond-payload"] = stage_head(head(tets)).add("recordForm", b"\x01").add("dims", b"\x02").add("mask", b"\x00").file()
    p = tail(stage_head(head(model)).add("recordForm", b"\x00").add("count", b"\x01").add("face", b"\x02\x01").add("id", b"\xfb\x02\x00"))
    cases["record-form-0-varint"] = p.file()
    p = tail(stage_head(head(model), name=PAD).add("recordForm", b"\x01").add("dims", b"\x02").add("mask", b"\x04").add("width", b"\x01").add("points", b"\x80"))
    for part in ("complexForm", "recordForm", "dims", "mask", "width"):
        cases[f"missing-{part}"] = p.file(p.at[part])
    return cases


def differences_from_the_reference(named: dict, tmp_path) -> list:
    """Reads every file of `named` (name -> bytes) with the reference's conformance adapter (one process) and
    with ismpy: the names whose verdicts differ (accepted by one only, or another first rule or location)."""
    binary = adapter()
    files = []
    for i, data in enumerate(named.values()):
        (tmp_path / f"{i}.isms").write_bytes(data)
        files.append(tmp_path / f"{i}.isms")
    done = subprocess.run([binary, "read", *map(str, files)], capture_output=True, text=True, timeout=600)
    lines = done.stdout.splitlines()
    assert len(lines) == len(files), done.stderr[-2000:]
    differ = []
    for (name, data), line in zip(named.items(), lines):
        reference = json.loads(line)
        reference.pop("message", None)
        try:
            ismpy.read(data)
            ours = {"ok": True}
        except ismpy.IsmError as e:
            ours = {"rule": e.rule, "location": e.location}
        if reference != ours:
            differ.append(f"{name}: reference {reference}, ismpy {ours}")
    return differ


def test_reader_cases_are_what_the_reference_reports(tmp_path):
    differ = differences_from_the_reference(reader_cases(), tmp_path)
    assert not differ, "\n".join(differ)


def mutants(seeds: list, count: int, seed: int) -> list[bytes]:
    """`count` structured files from `seeds` with bytes changed (often to varint prefixes and small values),
    the payload cut or bytes inserted; the container rewrapped, so that the payload's decoding is exercised."""
    import random

    rnd = random.Random(seed)
    out = []
    for _ in range(count):
        payload = bytearray(rnd.choice(seeds)[HEADER_LEN:])
        op = rnd.random()
        if op < 0.45:
            for _ in range(rnd.randint(1, 3)):
                payload[rnd.randrange(len(payload))] = rnd.choice([0, 1, 2, 3, 4, 5, 7, 8, 0x7F, 0x80, 0xFB, 0xFF, rnd.randrange(256)])
        elif op < 0.72:
            del payload[rnd.randrange(len(payload) + 1) :]
        else:
            at = rnd.randrange(len(payload) + 1)
            payload[at:at] = bytes(rnd.randrange(256) for _ in range(rnd.randint(1, 4)))
        out.append(ismpy.container(bytes(payload), 6))
    return out


def mutated_files(count: int, seed: int = 17) -> list[bytes]:
    """Mutants of the examples' structured files and of the reader cases."""
    seeds = [ismpy.write(ismpy.read((EXAMPLES / f"{name}.ism.json").read_bytes()), "structured") for name in example_names()]
    return mutants(seeds + list(reader_cases().values()), count, seed)


def test_mutated_structured_files_read_alike(tmp_path):
    # Every mutated file: accepted by both, or the same first rule at the same location.
    named = {f"mutant {i}": data for i, data in enumerate(mutated_files(1500))}
    differ = differences_from_the_reference(named, tmp_path)
    assert not differ, f"{len(differ)} of {len(named)} differ:\n" + "\n".join(differ[:10])