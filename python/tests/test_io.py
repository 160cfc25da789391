"""Reading and writing: every example in every encoding and source kind, bit-exact round trips
compared with `ism convert`, arrays compared with the JSON text read by Python's json module, and
models rebuilt from their own arrays."""

from __future__ import annotations

import gc
import io
import json

import numpy as np
import pytest

import ism
from conftest import ENCODINGS, EXAMPLE_NAMES, EXAMPLES, cli


def test_version():
    assert isinstance(ism.__version__, str) and ism.__version__.count(".") == 2
    assert ism.FORMAT_VERSION == "1.0"


@pytest.mark.parametrize("name", EXAMPLE_NAMES)
def test_every_source_and_encoding_reads_the_same_model(name):
    models = []
    for enc, ext in ENCODINGS.items():
        path = EXAMPLES / (name + ext)
        data = path.read_bytes()
        by_path = ism.read(path)
        by_str = ism.read(str(path))
        by_bytes = ism.read(data)
        by_file = ism.read(io.BytesIO(data))
        with open(path, "rb") as f:
            by_handle = ism.read(f)
        for m in (by_path, by_str, by_bytes, by_file, by_handle):
            assert m.encoding == enc
            assert m == by_path
        models.append(by_path)
    assert models[0] == models[1] == models[2]


@pytest.mark.parametrize("name", EXAMPLE_NAMES)
def test_arrays_match_the_json_text(name):
    doc = json.loads((EXAMPLES / (name + ".ism.json")).read_text())
    m = ism.read(EXAMPLES / (name + ".ismb"))
    n = doc["dimension"]
    assert m.dimension == n
    assert m.vertices.dtype == np.float64 and m.vertices.shape == (len(doc["vertices"]) // n, n)
    assert m.simplices.dtype == np.uint32 and m.simplices.shape == (len(doc["simplices"]) // (n + 1), n + 1)
    # Python's float parser is correctly rounded: equal arrays mean bit-equal numbers.
    assert m.vertices.ravel().tolist() == doc["vertices"]
    assert m.simplices.ravel().tolist() == doc["simplices"]
    assert m.values.tolist() == doc["values"]
    assert m.level == doc.get("level", 0.0)
    assert m.metadata == doc.get("metadata", {})
    assert m.extras == doc.get("extras")
    assert len(m.stages) == len(doc.get("stages", []))
    for st, sd in zip(m.stages, doc.get("stages", [])):
        assert st.kind == sd["kind"] and st.degree == sd["degree"]
        assert st.direction == sd.get("direction", "implicit")
        faces = sd.get("faces", [])
        assert st.num_faces == len(faces)
        assert st.face_vertices.tolist() == [v for f in faces for v in f["face"]]
        assert np.diff(st.face_offsets).tolist() == [len(f["face"]) for f in faces]
        assert st.points.tolist() == [x for f in faces for x in f.get("points", [])]
        assert np.diff(st.point_offsets).tolist() == [len(f.get("points", [])) for f in faces]
        assert st.weights.tolist() == [x for f in faces for x in f.get("weights", [])]
        maps = sd.get("vertexMaps", [])
        assert st.map_vertices.tolist() == [v["vertex"] for v in maps]
        assert st.coefficients.tolist() == [x for v in maps for x in v["coefficients"]]


@pytest.mark.parametrize("name", EXAMPLE_NAMES)
@pytest.mark.parametrize("enc", list(ENCODINGS))
def test_writing_is_bit_identical_to_ism_convert(name, enc, tmp_path):
    src = EXAMPLES / (name + ".ism.json")
    out = tmp_path / ("cli" + ENCODINGS[enc])
    cli("convert", src, out, "--quiet")
    m = ism.read(src)
    assert m.to_bytes(enc) == out.read_bytes()
    # Through a path (encoding from the extension) and a file object.
    mine = tmp_path / ("py" + ENCODINGS[enc])
    m.write(mine)
    assert mine.read_bytes() == out.read_bytes()
    buf = io.BytesIO()
    m.write(buf, enc)
    assert buf.getvalue() == out.read_bytes()
    # And back: the bytes read give the same model.
    assert ism.loads(out.read_bytes()) == m


@pytest.mark.parametrize("name", EXAMPLE_NAMES)
def test_pretty_and_container_json_match_the_cli(name, tmp_path):
    src = EXAMPLES / (name + ".ismb")
    m = ism.read(src)
    out = tmp_path / "p.ism.json"
    cli("convert", src, out, "--pretty", "--quiet")
    assert m.to_bytes("json", pretty=True) == out.read_bytes()
    out2 = tmp_path / "c.ism.json"
    cli("convert", src, out2, "--container", "--quiet")
    assert m.to_bytes("json", container=True) == out2.read_bytes()


@pytest.mark.parametrize("name", EXAMPLE_NAMES)
def test_model_rebuilt_from_its_arrays_is_the_same(name):
    m = ism.read(EXAMPLES / (name + ".ismb"))
    stages = [ism.Stage.from_tables(**s.tables()) for s in m.stages]
    again = ism.Model(
        m.vertices,
        m.simplices,
        m.values,
        m.level,
        stages,
        metadata=m.metadata,
        extras=m.extras,
        extensions_used=m.extensions_used,
        extensions_required=m.extensions_required,
        extensions=m.extensions,
    )
    assert again == m
    for enc in ENCODINGS:
        assert again.to_bytes(enc) == m.to_bytes(enc)
    # The per-face constructor gives the same stages.
    for s in m.stages:
        assert ism.Stage(s.kind, s.degree, s.direction, faces=s.faces, vertex_maps=s.vertex_maps, name=s.name, extras=s.extras) == s


def test_arrays_outlive_the_model():
    m = ism.read(EXAMPLES / "sphere.ismb")
    expected = m.vertices.copy(), m.simplices.copy(), m.values.copy(), m.stages[1].points.copy()
    v, s, f, p = m.vertices, m.simplices, m.values, m.stages[1].points
    del m
    gc.collect()
    # Allocate and free enough to reuse freed memory, then read the arrays again.
    junk = [ism.read(EXAMPLES / "torus.ismb").vertices.copy() for _ in range(20)]
    del junk
    gc.collect()
    assert np.array_equal(v, expected[0]) and np.array_equal(s, expected[1])
    assert np.array_equal(f, expected[2]) and np.array_equal(p, expected[3])
    # The views keep the model alive through numpy's base chain.
    assert isinstance(v.base, ism.Model)


def test_arrays_are_read_only():
    m = ism.read(EXAMPLES / "circle-curved.ismb")
    for a in (m.vertices, m.simplices, m.values, m.stages[0].points):
        with pytest.raises(ValueError):
            a[0] = 0


def test_pickle_round_trip():
    import pickle

    m = ism.read(EXAMPLES / "two-stage.ismb")
    assert pickle.loads(pickle.dumps(m)) == m


def test_metadata_and_extras_are_python_objects():
    v = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    extras = {"a": [1, 2.5, None, True], "b": {"c": "text"}}
    m = ism.Model(v, [[0, 1, 2]], [-1.0, 1.0, 1.0], 0.0, metadata={"name": "tri", "units": "mm"}, extras=extras)
    back = ism.loads(m.to_bytes("binary"))
    assert back.metadata == {"name": "tri", "units": "mm"}
    assert back.extras == extras
    # Python's own JSON view of the file agrees.
    doc = json.loads(m.to_bytes("json"))
    assert doc["extras"] == extras and doc["metadata"]["name"] == "tri"


NONE = 2**32 - 1


@pytest.mark.parametrize("name", EXAMPLE_NAMES)
def test_indexed_faces_neighbours_and_dense_stage_tables(name):
    from itertools import combinations

    m = ism.read(EXAMPLES / (name + ".ismb"))
    n = m.dimension
    simplices = m.simplices.tolist()
    # Ground truth computed here: every k-face of every simplex, sorted, in lexicographic order.
    for k in range(1, n):
        expected = sorted({tuple(sorted(c)) for s in simplices for c in combinations(s, k + 1)})
        assert m.faces(k).tolist() == [list(f) for f in expected]
    # Facet neighbours: the other simplex sharing the facet opposite local vertex i.
    owners = {}
    for s, simplex in enumerate(simplices):
        for i in range(n + 1):
            owners.setdefault(tuple(sorted(simplex[:i] + simplex[i + 1 :])), []).append(s)
    nb = m.neighbours
    for s, simplex in enumerate(simplices):
        for i in range(n + 1):
            others = [t for t in owners[tuple(sorted(simplex[:i] + simplex[i + 1 :]))] if t != s]
            assert nb[s, i] == (others[0] if others else NONE)
    # The dense tables hold each record's numbers at its face's row.
    rows = {k: {tuple(f): j for j, f in enumerate(m.faces(k).tolist())} for k in range(n)}
    rows[n] = {tuple(sorted(s)): j for j, s in enumerate(simplices)}
    for i, st in enumerate(m.stages):
        tab = m.stage_tables(i)
        assert tab["kind"] == st.kind and tab["degree"] == st.degree
        if st.kind == "monotonic":
            for r, (v, coefficients) in enumerate(st.vertex_maps):
                assert tab["vertex_records"][v] == r
                assert tab["coefficients"][v].tolist() == coefficients.tolist()
            assert (tab["vertex_records"] != NONE).sum() == len(st.vertex_maps)
            continue
        per_dim = [0] * (n + 1)
        for r, (face, points, weights) in enumerate(st.faces):
            k = len(face) - 1
            j = rows[k][tuple(face.tolist())]
            per_dim[k] += 1
            assert tab["records"][k][j] == r
            assert tab["points"][k][j].tolist() == points.ravel().tolist()
            if st.kind == "rational" and len(weights):
                assert tab["weights"][k][j].tolist() == weights.tolist()
        assert [(rec != NONE).sum() for rec in tab["records"]] == per_dim


def test_indexed_views_outlive_the_model_and_unchecked_models_are_indexed_on_demand():
    faces = ism.read(EXAMPLES / "torus.ismb").faces(2)
    points = ism.read(EXAMPLES / "torus.ismb").stage_tables(1)["points"][1]
    gc.collect()
    again = ism.read(EXAMPLES / "torus.ismb")
    assert np.array_equal(faces, again.faces(2))
    assert np.array_equal(points, again.stage_tables(1)["points"][1])
    with pytest.raises(ValueError):
        faces[0, 0] = 1
    # A model read without the check (or built in memory) is indexed on first use.
    loose = ism.read(EXAMPLES / "torus.ismb", check=False)
    assert np.array_equal(loose.faces(1), again.faces(1))
    v = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    broken = ism.Model(v, [[0, 2, 1]], [-1.0, 1.0, 1.0], check=False)  # negatively oriented
    with pytest.raises(ism.StructureError):
        broken.neighbours


def _counts(name):
    """Entity counts of an example from its JSON text (Python's json module, not the reader)."""
    d = json.loads((EXAMPLES / (name + ".ism.json")).read_text())
    n = d["dimension"]
    records = [len(s.get("faces", [])) + len(s.get("vertexMaps", [])) for s in d["stages"]]
    return {
        "max_vertices": len(d["vertices"]) // n,
        "max_simplices": len(d["simplices"]) // (n + 1),
        "max_stages": len(d["stages"]),
        "max_records": sum(records),
    }, records


def _payload_bytes(path):
    """The payload length: a container header's `u64` at offset 16 (spec §7.3), else the whole
    JSON text."""
    data = path.read_bytes()
    if data.startswith(b"\x89ISM\r\n\x1a\n"):
        return int.from_bytes(data[16:24], "little")
    return len(data)


@pytest.mark.parametrize("name", ["two-stage", "torus", "sphere"])
@pytest.mark.parametrize("ext", list(ENCODINGS.values()))
def test_limits_refuse_one_below_the_count_and_accept_the_count(name, ext):
    path = EXAMPLES / (name + ext)
    counts, records = _counts(name)
    counts["max_payload_bytes"] = _payload_bytes(path)
    # The stage where the running total of records first passes `total - 1`: the last one with any.
    last = max(k for k, r in enumerate(records) if r) if any(records) else None
    pointers = {
        "max_vertices": "/vertices",
        "max_simplices": "/simplices",
        "max_stages": "/stages",
        "max_records": f"/stages/{last}",
    }
    for key, count in counts.items():
        if count == 0:
            continue
        at = {key: count}
        assert ism.read(path, limits=at) == ism.read(path)
        assert ism.loads(path.read_bytes(), limits=at) == ism.read(path)
        assert ism.validate(path, limits=at).valid
        for reader in (
            lambda: ism.read(path, limits={key: count - 1}),
            lambda: ism.read(path.read_bytes(), check=False, limits={key: count - 1}),
            lambda: ism.validate(path, limits={key: count - 1}),
            lambda: ism.validate(path.read_bytes(), limits={key: count - 1}),
        ):
            with pytest.raises(ism.FormatError) as e:
                reader()
            assert e.value.rule == "ISM-007", (key, e.value)
            if key in pointers:
                assert e.value.pointer == pointers[key], (key, e.value)


def test_limits_keys_and_values_are_checked():
    path = EXAMPLES / "two-stage.ismb"
    with pytest.raises(ValueError, match='unknown key "max_vertex"'):
        ism.read(path, limits={"max_vertex": 10})
    with pytest.raises(ValueError, match="whole number"):
        ism.read(path, limits={"max_vertices": -1})
    with pytest.raises(TypeError, match="expected a dict"):
        ism.read(path, limits=[("max_vertices", 10)])
    assert ism.read(path, limits={}) == ism.read(path, limits=None) == ism.read(path)


def reads_and_writes_like_the_cli(name, tmp_path, encoding, suffix):
    """The example's NAME.SUFFIX reads as the .ismb's model, and the bytes the package writes in `encoding` are
    `ism convert`'s, by name and by extension; returns them."""
    m = ism.read(EXAMPLES / (name + ".ismb"))
    example = EXAMPLES / (name + suffix)
    assert ism.read(example) == m
    assert ism.read(example).encoding == encoding
    out = tmp_path / ("cli" + suffix)
    cli("convert", EXAMPLES / (name + ".ismb"), out, "--quiet")
    assert m.to_bytes(encoding) == out.read_bytes()
    mine = tmp_path / ("py" + suffix)
    m.write(mine)
    assert mine.read_bytes() == out.read_bytes()
    return out.read_bytes()


@pytest.mark.parametrize("name", EXAMPLE_NAMES)
def test_compressed_encoding_reads_and_writes_like_the_cli(name, tmp_path):
    # The compressed encoding (spec §7.4.2); the payload is the compact payload in xz, which Python's own lzma
    # module decompresses to exactly the .ismc's payload.
    import lzma
    import struct

    payload = reads_and_writes_like_the_cli(name, tmp_path, "compressed", ".ismz")[32:]
    (length,) = struct.unpack_from("<Q", payload)
    inner = lzma.decompress(payload[8:], format=lzma.FORMAT_XZ)
    assert len(inner) == length
    assert inner == ism.read(EXAMPLES / (name + ".ismb")).to_bytes("compact")[32:]


@pytest.mark.parametrize("name", EXAMPLE_NAMES)
def test_structured_encoding_reads_and_writes_like_the_cli(name, tmp_path):
    # The structured encoding (spec §7.4.3): what the package and the CLI write is the example file itself.
    written = reads_and_writes_like_the_cli(name, tmp_path, "structured", ".isms")
    assert written == (EXAMPLES / (name + ".isms")).read_bytes()
