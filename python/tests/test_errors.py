"""Bad input raises the typed exception with the rule and location the reader vectors name, by
every entry point; bad arguments raise TypeError/ValueError; nothing crashes the interpreter."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

import ism
from conftest import EXAMPLES, VECTORS

READER = sorted(p for p in (VECTORS / "reader").iterdir() if p.suffix in {".ismb", ".json", ".msgpack"} and not p.name.endswith(".expect.json"))


def stem(p):
    return p.name.split(".")[0]


def test_reader_vectors_exist():
    assert len(READER) > 50


@pytest.mark.parametrize("path", READER, ids=stem)
def test_reader_vector_raises_its_rule_and_location(path):
    expect = json.loads((path.parent / (stem(path) + ".expect.json")).read_text())
    data = path.read_bytes()
    for source in (path, data, io.BytesIO(data)):
        with pytest.raises(ism.ISMError) as info:
            ism.read(source)
        e = info.value
        assert isinstance(e, (ism.FormatError, ism.StructureError)), type(e)
        assert e.rule == expect["rule"], (e.rule, str(e))
        # The first diagnostic's location: exactly the members the vector names.
        assert e.location == expect["location"]
        assert e.pointer == expect["location"].get("pointer")
        assert e.offset == expect["location"].get("offset")
        assert e.diagnostics and e.diagnostics[0]["rule"] == expect["rule"]


def test_missing_file_is_a_file_error(tmp_path):
    with pytest.raises(ism.FileError) as info:
        ism.read(tmp_path / "absent.ismb")
    assert isinstance(info.value, OSError)


def test_truncations_never_crash():
    data = (EXAMPLES / "two-stage.ismb").read_bytes()
    for cut in range(0, len(data), 7):
        with pytest.raises(ism.ISMError):
            ism.loads(data[:cut])


def test_text_file_object_is_refused():
    with pytest.raises(TypeError):
        ism.read(io.StringIO("{}"))


def tri():
    return np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]), np.array([[0, 1, 2]]), np.array([-1.0, 1.0, 1.0])


def test_constructor_checks_arguments():
    v, s, f = tri()
    with pytest.raises(ValueError):
        ism.Model(v, [[0, 1, -2]], f)  # negative id never wraps around
    with pytest.raises(ValueError):
        ism.Model(v, [[0, 1, 2**32]], f)
    with pytest.raises(TypeError):
        ism.Model(v, [[0.0, 1.5, 2.0]], f)
    with pytest.raises(ValueError):
        ism.Model(np.zeros((3, 4)), s, f)
    with pytest.raises(ValueError):
        ism.Model(v, [[0, 1]], f)
    with pytest.raises(ValueError):
        ism.Model(v, s, f, metadata={"author": "x"})
    with pytest.raises(TypeError):
        ism.Model(v, s, f, extras={"x": float("nan")})
    with pytest.raises(ValueError):
        ism.Stage("spline", 2)
    with pytest.raises(ValueError):
        ism.Stage.from_tables("bezier", 2, face_offsets=[0, 5], face_vertices=[0, 1])


def test_structure_errors_are_listed():
    v, s, f = tri()
    with pytest.raises(ism.StructureError) as info:
        ism.Model(v, s, [0.0, 1.0, 0.0])
    rules = {d["rule"] for d in info.value.diagnostics}
    assert len(info.value.diagnostics) >= 2, info.value.diagnostics
    assert info.value.rule in rules
    # check=False builds it anyway, for the validator.
    m = ism.Model(v, s, [0.0, 1.0, 0.0], check=False)
    report = m.validate()
    assert report.verdict == "invalid"
    assert set(report.counts) >= rules


def test_writer_refuses_what_a_reader_refuses():
    v, s, f = tri()
    m = ism.Model(v, s, [np.inf, 1.0, 1.0], check=False)
    with pytest.raises(ism.FormatError) as info:
        m.to_bytes("json")
    assert info.value.rule is not None and info.value.pointer == "/values/0"


def test_bad_tool_arguments():
    m = ism.read(EXAMPLES / "sphere.ismb")
    with pytest.raises(ValueError):
        m.query(np.zeros((3, 2)))
    with pytest.raises(ValueError):
        m.sample_near_surface(10, -1.0)
    with pytest.raises(ValueError):
        m.extract_surface(0.0)
    with pytest.raises(ValueError):
        m.export("x.stl")
    with pytest.raises(ValueError):
        m.validate(max_pieces=0)
    with pytest.raises(ValueError):
        m.sample_volume(10, box=([0, 0], [1, 1]))
