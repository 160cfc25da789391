#!/usr/bin/env python3
"""ismpy: an independent ISM reader and writer, written from spec/ism-format.md alone.

It reads and writes all six encodings (JSON, MessagePack, binary, compact binary, compressed, structured) and the
container, and reports every reader rule of spec §9 (ISM-0xx, ISM-1xx) with the location of spec §7.8 and §9. No
Rust and no JSON or MessagePack library is used for reading (the compressed encoding's xz stream is decompressed by
the standard `lzma` module) (the standard `json` module is too lenient: it accepts NaN, duplicate keys and big
integers), so the spec, not a library, decides every byte. The structured encoding (spec §7.4.3, tag 6, `.isms`)
is the compact grammar with face records given by masks over the k-faces of the complex and control points on a
2^(-8w) lattice when they lie on one; `complex_faces` computes those k-face lists exactly as §7.4.3 defines them.
Its `complexForm` 1 (the complex as a Kuhn grid refined by edge bisections) is read by `KuhnRefinement`; the
canonical writer writes `complexForm` 0, and `write(model, "structured", refinement=...)` writes 1 for a refinement
(`refinement_of(data)` returns a form-1 file's) after checking that it rebuilds the model's complex bit for bit.

Command line (the protocol of tools/conformance):

    ismpy.py read FILE                 prints {"ok": true} (exit 0) or {"rule": ..., "location": {...}}
                                       (exit 1): the first error a reader reports
    ismpy.py convert IN OUT ENCODING   reads IN and writes OUT in ENCODING: json, json-pretty, msgpack,
                                       binary, compact, compressed, structured (exit 0), or prints the error as
                                       `read` does (exit 1)
"""

from __future__ import annotations

import itertools
import json
import lzma
import math
import struct
import sys
import zlib

MAGIC = b"\x89ISM\r\n\x1a\n"
HEADER_LEN = 32
MAJOR, MINOR = 1, 0
MAX_DEPTH = 64
MAX_DEGREE = 16
# The xz decoder's memory limit for the compressed encoding (spec §7.4.2): above what every xz preset needs
# (preset 9: 64 MiB dictionary), so a stream declaring a larger dictionary is refused (ISM-007) before allocating.
XZ_MEMORY_LIMIT = 128 << 20
DEFAULT_PAYLOAD_LIMIT = 8 << 30
KINDS = ["bezier", "rational", "monotonic"]
DIRECTIONS = ["implicit", "parametric"]


class IsmError(Exception):
    """A reader error: a rule id and a location (spec §9)."""

    def __init__(self, rule: str, message: str, pointer=None, offset=None, **extra):
        super().__init__(f"{rule}: {message}")
        self.rule = rule
        self.location = {}
        if pointer is not None:
            self.location["pointer"] = pointer
        if offset is not None:
            self.location["offset"] = offset
        self.location.update({k: v for k, v in extra.items() if v is not None})


def escape_token(token: str) -> str:
    return token.replace("~", "~0").replace("/", "~1")


def pointer_of(path: list) -> str:
    return "".join("/" + (escape_token(p) if isinstance(p, str) else str(p)) for p in path)


class Fail(Exception):
    """A tokenizer failure at a file offset; the decoder adds the pointer."""

    def __init__(self, offset: int, message: str):
        super().__init__(message)
        self.offset = offset


# ------------------------------------------------------------------------------------------ tokens
# A head is (kind, value): ("null", None), ("bool", b), ("int", i), ("float", x), ("str", s),
# ("array", count or None), ("object", count or None). JSON integer tokens are ("int", i) with the
# f64 value available by float(i) -- except that f64 members need correct rounding of huge integers,
# which float(int) gives (round-half-even).


class JsonTokens:
    """RFC 8259 text, strictly (spec §7.2): whitespace space/tab/LF/CR, no BOM."""

    WS = b" \t\n\r"

    def __init__(self, data: bytes, base: int):
        self.b = data
        self.at = 0
        self.base = base

    def fail(self, at: int, message: str) -> Fail:
        return Fail(self.base + at, message)

    def found(self, expected: str) -> Fail:
        return self.fail(self.at, f"expected {expected}")

    def peek(self):
        return self.b[self.at] if self.at < len(self.b) else None

    def ws(self):
        while self.at < len(self.b) and self.b[self.at] in self.WS:
            self.at += 1

    def string(self) -> str:
        self.at += 1
        out = []
        b = self.b
        while True:
            run = self.at
            while self.at < len(b) and b[self.at] != 0x22 and b[self.at] != 0x5C and b[self.at] >= 0x20:
                self.at += 1
            try:
                out.append(b[run : self.at].decode("utf-8"))
            except UnicodeDecodeError as e:
                raise self.fail(run + e.start, "invalid UTF-8")
            c = self.peek()
            if c is None:
                raise self.fail(self.at, "end of text in a string")
            if c == 0x22:
                self.at += 1
                return "".join(out)
            if c == 0x5C:
                esc = self.at
                self.at += 1
                e = self.peek()
                simple = {0x22: '"', 0x5C: "\\", 0x2F: "/", 0x62: "\b", 0x66: "\f", 0x6E: "\n", 0x72: "\r", 0x74: "\t"}
                if e in simple:
                    out.append(simple[e])
                    self.at += 1
                elif e == 0x75:
                    self.at += 1
                    hi = self.hex4(esc)
                    if 0xD800 <= hi < 0xDC00:
                        if b[self.at : self.at + 2] != b"\\u":
                            raise self.fail(esc, "unpaired surrogate")
                        self.at += 2
                        lo = self.hex4(esc)
                        if not 0xDC00 <= lo < 0xE000:
                            raise self.fail(esc, "unpaired surrogate")
                        out.append(chr(0x10000 + ((hi - 0xD800) << 10) + (lo - 0xDC00)))
                    elif 0xDC00 <= hi < 0xE000:
                        raise self.fail(esc, "unpaired surrogate")
                    else:
                        out.append(chr(hi))
                else:
                    raise self.fail(esc, "invalid escape")
            else:
                raise self.fail(self.at, "control character in a string")

    def hex4(self, esc: int) -> int:
        digits = self.b[self.at : self.at + 4]
        if len(digits) != 4 or not all(c in b"0123456789abcdefABCDEF" for c in digits):
            raise self.fail(esc, "invalid \\u escape")
        self.at += 4
        return int(digits, 16)

    def digits(self) -> int:
        start = self.at
        while self.at < len(self.b) and 0x30 <= self.b[self.at] <= 0x39:
            self.at += 1
        return self.at - start

    def number(self):
        start = self.at
        if self.peek() == 0x2D:
            self.at += 1
        c = self.peek()
        if c == 0x30:
            self.at += 1
        elif c is not None and 0x31 <= c <= 0x39:
            self.digits()
        else:
            raise self.found("a digit")
        integer = True
        if self.peek() == 0x2E:
            integer = False
            self.at += 1
            if self.digits() == 0:
                raise self.found("a digit")
        if self.peek() in (0x65, 0x45):
            integer = False
            self.at += 1
            if self.peek() in (0x2B, 0x2D):
                self.at += 1
            if self.digits() == 0:
                raise self.found("a digit")
        text = self.b[start : self.at].decode("ascii")
        value = float(text)  # correctly rounded, ties to even
        if not math.isfinite(value):
            raise self.fail(start, f"{text[:30]} does not round to a finite f64")
        if integer:
            return ("int", int(text), value)
        return ("float", value, value)

    def literal(self, word: bytes, head):
        if self.b[self.at : self.at + len(word)] == word:
            self.at += len(word)
            return head
        raise self.found("a value")

    def head(self):
        self.ws()
        start = self.at
        c = self.peek()
        if c == 0x7B:
            self.at += 1
            h = ("object", None)
        elif c == 0x5B:
            self.at += 1
            h = ("array", None)
        elif c == 0x22:
            h = ("str", self.string())
        elif c == 0x74:
            h = self.literal(b"true", ("bool", True))
        elif c == 0x66:
            h = self.literal(b"false", ("bool", False))
        elif c == 0x6E:
            h = self.literal(b"null", ("null", None))
        elif c is not None and (c == 0x2D or 0x30 <= c <= 0x39):
            kind, v, f = self.number()
            h = (kind, v) if kind == "float" else ("int", v, f)
        else:
            raise self.found("a value")
        return h, self.base + start

    def next_element(self, seq: dict) -> bool:
        self.ws()
        if seq["first"]:
            seq["first"] = False
            if self.peek() == 0x5D:
                self.at += 1
                return False
            return True
        c = self.peek()
        if c == 0x2C:
            self.at += 1
            return True
        if c == 0x5D:
            self.at += 1
            return False
        raise self.found("',' or ']'")

    def next_key(self, seq: dict):
        self.ws()
        if seq["first"]:
            seq["first"] = False
            if self.peek() == 0x7D:
                self.at += 1
                return None
        else:
            c = self.peek()
            if c == 0x2C:
                self.at += 1
                self.ws()
            elif c == 0x7D:
                self.at += 1
                return None
            else:
                raise self.found("',' or '}'")
        if self.peek() != 0x22:
            raise self.found("a string key")
        offset = self.base + self.at
        key = self.string()
        self.ws()
        if self.peek() != 0x3A:
            raise self.found("':'")
        self.at += 1
        return key, offset

    def end(self):
        self.ws()
        if self.at < len(self.b):
            raise self.fail(self.at, "only whitespace may follow the object")


class MsgpackTokens:
    """MessagePack, strictly (spec §7.3): maps with str keys, str strings, no bin/ext."""

    def __init__(self, data: bytes, base: int):
        self.b = data
        self.at = 0
        self.base = base

    def fail(self, at: int, message: str) -> Fail:
        return Fail(self.base + at, message)

    def take(self, n: int, start: int) -> bytes:
        if len(self.b) - self.at < n:
            raise self.fail(start, "value runs past the payload")
        out = self.b[self.at : self.at + n]
        self.at += n
        return out

    def uint(self, n: int, start: int) -> int:
        return int.from_bytes(self.take(n, start), "big")

    def count(self, n: int, per: int, start: int) -> int:
        count = self.uint(n, start)
        if count > (len(self.b) - self.at) // per:
            raise self.fail(start, f"declares {count} entries; too few bytes remain")
        return count

    def str_of(self, n: int, start: int) -> str:
        if n > len(self.b) - self.at:
            raise self.fail(start, "str runs past the payload")
        data_at = self.at
        data = self.take(n, start)
        try:
            return data.decode("utf-8")
        except UnicodeDecodeError as e:
            raise self.fail(data_at + e.start, "invalid UTF-8")

    def head(self):
        start = self.at
        if self.at >= len(self.b):
            raise self.fail(start, "end of payload; expected a value")
        m = self.b[self.at]
        self.at += 1
        if m <= 0x7F:
            h = ("int", m, float(m))
        elif m <= 0x8F:
            h = ("object", m & 0x0F)
        elif m <= 0x9F:
            h = ("array", m & 0x0F)
        elif m <= 0xBF:
            h = ("str", self.str_of(m & 0x1F, start))
        elif m == 0xC0:
            h = ("null", None)
        elif m == 0xC2:
            h = ("bool", False)
        elif m == 0xC3:
            h = ("bool", True)
        elif m == 0xCA:
            h = ("float", struct.unpack(">f", self.take(4, start))[0])
        elif m == 0xCB:
            h = ("float", struct.unpack(">d", self.take(8, start))[0])
        elif 0xCC <= m <= 0xCF:
            v = self.uint(1 << (m - 0xCC), start)
            h = ("int", v, float(v))
        elif 0xD0 <= m <= 0xD3:
            n = 1 << (m - 0xD0)
            v = int.from_bytes(self.take(n, start), "big", signed=True)
            h = ("int", v, float(v))
        elif 0xD9 <= m <= 0xDB:
            h = ("str", self.str_of(self.uint(1 << (m - 0xD9), start), start))
        elif m in (0xDC, 0xDD):
            h = ("array", self.count(2 if m == 0xDC else 4, 1, start))
        elif m in (0xDE, 0xDF):
            h = ("object", self.count(2 if m == 0xDE else 4, 2, start))
        elif m >= 0xE0:
            h = ("int", m - 256, float(m - 256))
        else:  # bin, ext, fixext, 0xc1
            raise self.fail(start, f"format 0x{m:02x} is not allowed")
        return h, self.base + start

    def next_element(self, seq: dict) -> bool:
        if seq["left"] == 0:
            return False
        seq["left"] -= 1
        return True

    def next_key(self, seq: dict):
        if not self.next_element(seq):
            return None
        h, offset = self.head()
        if h[0] != "str":
            raise Fail(offset, "map keys must be str")
        return h[1], offset

    def end(self):
        if self.at < len(self.b):
            raise self.fail(self.at, "bytes follow the MessagePack value")


# ------------------------------------------------------------------------------------------ decoder


class Decoder:
    """The typed model decoder over either tokenizer (spec §7.2, §7.3, §7.8)."""

    def __init__(self, tok, path=None, depth=0):
        self.tok = tok
        self.path = list(path or [])
        self.depth = depth

    def at(self, offset, message) -> IsmError:
        return IsmError("ISM-006", message, pointer=pointer_of(self.path), offset=offset)

    def call(self, f, *args):
        try:
            return f(*args)
        except Fail as e:
            raise self.at(e.offset, str(e)) from None

    def head(self):
        return self.call(self.tok.head)

    def enter(self, offset):
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise self.at(offset, "nested too deep")

    @staticmethod
    def seq(head) -> dict:
        return {"first": True, "left": head[1]}

    def obj(self, member):
        h, offset = self.head()
        if h[0] != "object":
            raise self.at(offset, f"expected an object, found {h[0]}")
        self.enter(offset)
        seq = self.seq(h)
        seen = set()
        while True:
            nk = self.call(self.tok.next_key, seq)
            if nk is None:
                break
            key, key_offset = nk
            self.path.append(key)
            if key in seen:
                raise self.at(key_offset, f"{key!r} given twice")
            seen.add(key)
            member(key)
            self.path.pop()
        self.depth -= 1
        return offset

    def array(self, element):
        h, offset = self.head()
        if h[0] != "array":
            raise self.at(offset, f"expected an array, found {h[0]}")
        self.enter(offset)
        seq = self.seq(h)
        i = 0
        while self.call(self.tok.next_element, seq):
            self.path.append(i)
            element()
            self.path.pop()
            i += 1
        self.depth -= 1

    def string_at(self):
        h, offset = self.head()
        if h[0] != "str":
            raise self.at(offset, f"expected a string, found {h[0]}")
        return h[1], offset

    def uint(self, top: int) -> int:
        h, offset = self.head()
        if h[0] != "int" or not 0 <= h[1] <= top or math.copysign(1.0, h[2]) < 0:  # `-0` has a sign
            raise self.at(offset, f"expected an integer from 0 to {top}")
        return h[1]

    def f64(self) -> float:
        h, offset = self.head()
        if h[0] == "int":
            return h[2]
        if h[0] == "float":
            return h[1]
        raise self.at(offset, f"expected a number, found {h[0]}")

    def list_of(self, read) -> list:
        out = []
        self.array(lambda: out.append(read()))
        return out

    def data(self):
        """JSON data (spec §2): extras, extension payloads, unknown members."""
        h, offset = self.head()
        kind = h[0]
        if kind in ("null", "bool", "str"):
            return h[1]
        if kind == "int":
            if not -(1 << 63) <= h[1] <= (1 << 64) - 1:
                raise self.at(offset, "integer outside the range of JSON data")
            return h[1]
        if kind == "float":
            if not math.isfinite(h[1]):
                raise self.at(offset, "non-finite number in JSON data")
            return h[1]
        self.enter(offset)
        seq = self.seq(h)
        if kind == "array":
            out = []
            while self.call(self.tok.next_element, seq):
                self.path.append(len(out))
                out.append(self.data())
                self.path.pop()
        else:
            out = {}
            while True:
                nk = self.call(self.tok.next_key, seq)
                if nk is None:
                    break
                key, key_offset = nk
                self.path.append(key)
                if key in out:
                    raise self.at(key_offset, f"{key!r} given twice")
                out[key] = self.data()
                self.path.pop()
        self.depth -= 1
        return out

    def missing(self, offset, members):
        for name, present in members:
            if not present:
                raise self.at(offset, f"missing required member {name!r}")

    def metadata(self) -> dict:
        m = {}

        def member(key):
            if key in ("name", "generator", "units", "description"):
                m[key] = self.string_at()[0]
            else:
                self.data()

        self.obj(member)
        return {k: m[k] for k in ("name", "generator", "units", "description") if k in m}

    def face_record(self) -> dict:
        r = {"points": [], "weights": []}

        def member(key):
            if key == "face":
                r["face"] = self.list_of(lambda: self.uint(0xFFFFFFFF))
            elif key in ("points", "weights"):
                r[key] = self.list_of(self.f64)
            else:
                self.data()

        offset = self.obj(member)
        self.missing(offset, [("face", "face" in r)])
        return {"face": r["face"], "points": r["points"], "weights": r["weights"]}

    def vertex_map(self) -> dict:
        r = {}

        def member(key):
            if key == "vertex":
                r[key] = self.uint(0xFFFFFFFF)
            elif key == "coefficients":
                r[key] = self.list_of(self.f64)
            else:
                self.data()

        offset = self.obj(member)
        self.missing(offset, [("vertex", "vertex" in r), ("coefficients", "coefficients" in r)])
        return {"vertex": r["vertex"], "coefficients": r["coefficients"]}

    def stage(self) -> dict:
        s = {"direction": "implicit", "name": None, "faces": [], "vertexMaps": [], "extras": None}

        def member(key):
            if key in ("kind", "direction"):
                value, offset = self.string_at()
                allowed = KINDS if key == "kind" else DIRECTIONS
                if value not in allowed:
                    raise self.at(offset, f"{key} {value!r} not one of {allowed}")
                s[key] = value
            elif key == "degree":
                s[key] = self.uint(0xFFFFFFFF)
            elif key == "name":
                s[key] = self.string_at()[0]
            elif key == "faces":
                s[key] = self.list_of(self.face_record)
            elif key == "vertexMaps":
                s[key] = self.list_of(self.vertex_map)
            elif key == "extras":
                s[key] = self.data()
            else:
                self.data()

        offset = self.obj(member)
        self.missing(offset, [("kind", "kind" in s), ("degree", "degree" in s)])
        return s

    def model(self) -> dict:
        m = new_model()
        present = set()

        def member(key):
            present.add(key)
            if key == "version":
                m[key] = self.string_at()[0]
            elif key == "dimension":
                m[key] = self.uint(255)
            elif key == "metadata":
                m[key] = self.metadata()
            elif key in ("vertices", "values"):
                m[key] = self.list_of(self.f64)
            elif key == "simplices":
                m[key] = self.list_of(lambda: self.uint(0xFFFFFFFF))
            elif key == "level":
                m[key] = self.f64()
            elif key == "stages":
                m[key] = self.list_of(self.stage)
            elif key in ("extensionsUsed", "extensionsRequired"):
                m[key] = self.list_of(lambda: self.string_at()[0])
            elif key == "extensions":
                ext = {}

                def entry(name):
                    ext[name] = self.data()

                self.obj(entry)
                m[key] = ext
            elif key == "extras":
                m[key] = self.data()
            else:
                self.data()

        offset = self.obj(member)
        self.missing(offset, [(k, k in present) for k in ("version", "dimension", "vertices", "simplices", "values")])
        self.call(self.tok.end)
        return m


def new_model() -> dict:
    return {
        "version": "",
        "dimension": 0,
        "metadata": {},
        "vertices": [],
        "simplices": [],
        "values": [],
        "level": 0.0,
        "stages": [],
        "extensionsUsed": [],
        "extensionsRequired": [],
        "extensions": {},
        "extras": None,
    }


def probe_version(tok):
    """The top-level `version` of a well-formed payload (spec §7.8, last paragraph), else None."""
    try:
        d = Decoder(tok)
        value = d.data()
        d.call(tok.end)
    except IsmError:
        return None
    if isinstance(value, dict) and isinstance(value.get("version"), str):
        return value["version"]
    return None


# ------------------------------------------------------------------------------------------ the complex's faces (§7.4.3)


def complex_faces(simplices, n: int, k: int, limit=None):
    """The k-faces of the complex (spec §7.4.3): the sorted tuples of k + 1 distinct ids taken from one top
    simplex of `simplices` as decoded (n + 1 ids each; a trailing incomplete group is no top simplex), each
    tuple once, in increasing lexicographic order. Computed before any structural check, so ids out of range or
    repeated in a simplex still give a well-defined list (a repeated id counts once).

    With `limit`, returns None as soon as the list is known to hold more than `limit` faces, having held at
    most about 2 * limit of them (a reader's bound on memory: a mask of more faces than the payload's bytes
    can hold is an error whatever its exact length)."""
    m = n + 1
    out = set()
    seen = set()
    for s in range(len(simplices) // m):
        ids = tuple(sorted(set(simplices[s * m : s * m + m])))
        if len(ids) <= k or ids in seen:
            continue
        seen.add(ids)
        if limit is not None and math.comb(len(ids), k + 1) > limit:
            return None
        out.update(itertools.combinations(ids, k + 1))
        if limit is not None and len(out) > limit:
            return None
    return sorted(out)


class ComplexFaces:
    """The k-face lists of one complex, computed once per k: `faces(k)` the list, `index(k)` face -> position."""

    def __init__(self, simplices, n: int):
        self.simplices = simplices
        self.n = n
        self.lists = {}
        self.indices = {}

    def faces(self, k: int, limit=None):
        if k not in self.lists:
            faces = complex_faces(self.simplices, self.n, k, limit)
            if faces is None:
                return None
            self.lists[k] = faces
        return self.lists[k]

    def index(self, k: int) -> dict:
        if k not in self.indices:
            self.indices[k] = {face: i for i, face in enumerate(self.faces(k))}
        return self.indices[k]


def owned_count(degree: int, k: int) -> int:
    """C(d - 1, k): the multi-indices a k-face owns at degree d (spec §2.5, §4.4); none when d <= k. Exact for
    every u32 degree (Python integers do not overflow, so no count saturates)."""
    return math.comb(degree - 1, k) if degree > k else 0


LATTICE_MAX_WIDTH = 4


def point_lattice_width(coords) -> int:
    """The smallest w >= 1 at which the point `coords` = (c0, ..., ck) is exactly n_j * 2^(-8w) (j >= 1) with
    integers 0 <= n_j < 2^(8w) and c0 = (2^(8w) - n_1 - ... - n_k) * 2^(-8w), compared bit for bit (a -0.0
    coordinate is on no lattice), or 0 when no w <= 4 does (spec §7.4.3)."""
    top = 1 << (8 * LATTICE_MAX_WIDTH)
    total = 0
    exponent = 0
    for c in coords[1:]:
        if not (0.0 <= c < 1.0) or (c == 0.0 and math.copysign(1.0, c) < 0):
            return 0
        p, q = c.as_integer_ratio()
        if q > top:
            return 0
        e = q.bit_length() - 1
        exponent = max(exponent, e)
        total += p << (8 * LATTICE_MAX_WIDTH - e)
    c0 = coords[0]
    if not math.isfinite(c0) or (c0 == 0.0 and math.copysign(1.0, c0) < 0):
        return 0
    p0, q0 = c0.as_integer_ratio()
    if q0 > top or p0 * (top // q0) != top - total:
        return 0
    return max(1, (exponent + 7) // 8)


# ------------------------------------------------------------------------------------------ the complex by its refinement (§7.4.3)


class RefinementRefused(Exception):
    """A rule of `complexForm` 1 broken while building (§7.4.3): `what` is "pair" (a pair that is not a < b of
    existing ids on a common live slot), "ids" (a midpoint id of 2^32 - 1 or more: ISM-007) or "bound" (⌈C/8⌉
    past the bytes after `splits`); `index` the pair."""

    def __init__(self, what: str, index: int, message: str):
        super().__init__(message)
        self.what = what
        self.index = index


class KuhnRefinement:
    """The complex of `complexForm` 1 (spec §7.4.3): the Kuhn grid of `box` and `cells`, refined by edge
    bisections, computed in binary64 (Python floats: round-to-nearest-even, no fused multiply-add).

    Slots are kept in a list in slot order (a retired slot is None); `edges` maps each edge (a, b), a < b, of a
    live slot to the live slots containing it, as an insertion-ordered dict: a slot enters its edges' dicts when
    it is created, with the largest slot id so far, so each dict lists its slots in increasing slot order. A
    split costs the slots it retires, never a scan of the list."""

    def __init__(self, n: int, box, cells):
        self.n = n
        self.box = list(box)
        self.cells = list(cells)
        self.strides = []
        stride = 1
        for c in self.cells:
            self.strides.append(stride)
            stride *= c + 1
        self.grid_count = stride
        self.steps = [(self.box[2 * k + 1] - self.box[2 * k]) / self.cells[k] for k in range(n)]
        self.mids = []  # coordinates of the midpoints, ids grid_count, grid_count + 1, ...
        self.slots = []
        self.edges = {}
        self.live = 0
        pairs = list(itertools.combinations(range(n + 1), 2))
        self.pairs = pairs
        # Per permutation of the axes in lexicographic order: the offsets of the monotone path's vertices from
        # the cube's lowest corner, the last two swapped when the permutation is odd.
        paths = []
        for perm in itertools.permutations(range(n)):
            offsets = [0]
            for axis in perm:
                offsets.append(offsets[-1] + self.strides[axis])
            inversions = sum(1 for i in range(n) for j in range(i + 1, n) if perm[i] > perm[j])
            if inversions % 2:
                offsets[-1], offsets[-2] = offsets[-2], offsets[-1]
            paths.append(offsets)
        # Cubes by their lowest corner's id (axis 0 fastest).
        for corner in itertools.product(*[range(c) for c in reversed(self.cells)]):
            base = sum(i * s for i, s in zip(reversed(corner), self.strides))
            for offsets in paths:
                self.add(tuple(base + o for o in offsets))

    def add(self, simplex: tuple):
        s = len(self.slots)
        self.slots.append(simplex)
        self.live += 1
        edges = self.edges
        for i, j in self.pairs:
            a, b = simplex[i], simplex[j]
            key = (a, b) if a < b else (b, a)
            group = edges.get(key)
            if group is None:
                edges[key] = {s: None}
            else:
                group[s] = None

    def coordinates(self, v: int) -> list:
        if v < self.grid_count:
            out = []
            for k in range(self.n):
                size = self.cells[k] + 1
                i = v % size
                v //= size
                # The quotient, then the product, then the sum; hi exactly at i = c.
                out.append(self.box[2 * k + 1] if i == self.cells[k] else self.box[2 * k] + i * self.steps[k])
            return out
        return self.mids[v - self.grid_count]

    def split(self, index: int, a: int, b: int, byte_limit=None):
        """Applies the split (a, b), the `index`-th pair; with `byte_limit`, refuses it when ⌈C/8⌉ after it
        would exceed that many bytes (checked before anything is allocated)."""
        group = self.edges.get((a, b)) if a < b else None
        if not group:
            why = "a >= b" if a >= b else "no live slot contains both"
            raise RefinementRefused("pair", index, f"split {index} ({a}, {b}): {why}")
        k = len(group)
        if self.grid_count + len(self.mids) >= (1 << 32) - 1:
            raise RefinementRefused("ids", index, f"split {index} ({a}, {b}): the midpoint's id would be 2^32 - 1 or more")
        if byte_limit is not None and (self.live + k + 7) // 8 > byte_limit:
            raise RefinementRefused("bound", index, f"split {index} ({a}, {b}): {self.live + k} live slots need more than the {byte_limit} bytes after splits")
        m = self.grid_count + len(self.mids)
        self.mids.append([(xa + xb) * 0.5 for xa, xb in zip(self.coordinates(a), self.coordinates(b))])
        edges = self.edges
        for s in list(group):
            simplex = self.slots[s]
            self.slots[s] = None
            self.live -= 1
            for i, j in self.pairs:
                u, v = simplex[i], simplex[j]
                key = (u, v) if u < v else (v, u)
                g = edges[key]
                del g[s]
                if not g:
                    del edges[key]
            self.add(tuple(m if x == b else x for x in simplex))
            self.add(tuple(m if x == a else x for x in simplex))

    def live_slots(self) -> list:
        return [s for s, simplex in enumerate(self.slots) if simplex is not None]

    def complex(self, kept_slots) -> tuple:
        """(vertices, simplices) of the model: the constructed vertices some kept simplex uses, in increasing
        id, and the kept simplices in slot order, renumbered to those positions."""
        simplices = [self.slots[s] for s in kept_slots]
        used = sorted({v for simplex in simplices for v in simplex})
        position = {v: i for i, v in enumerate(used)}
        vertices = []
        for v in used:
            vertices.extend(self.coordinates(v))
        return vertices, [position[v] for simplex in simplices for v in simplex]


def box_problem(n: int, box):
    """Why `box` is not that of §7.4.3 step 1 in dimension n (a message), or None."""
    if len(box) != 2 * n:
        return f"box holds {len(box)} numbers, not {2 * n}"
    for k in range(n):
        lo, hi = box[2 * k], box[2 * k + 1]
        if not (math.isfinite(lo) and math.isfinite(hi)):
            return f"box axis {k} is not finite"
        if not lo < hi:
            return f"box axis {k}: lo {lo!r} is not below hi {hi!r}"
        if not math.isfinite(hi - lo):
            return f"box axis {k}: hi - lo is not finite"
        if not (math.isfinite(lo + lo) and math.isfinite(hi + hi)):
            return f"box axis {k}: 2 lo or 2 hi is not finite (a midpoint's sum could overflow)"
    return None


def cells_problem(n: int, cells):
    """Why `cells` is not that of §7.4.3 step 1 in dimension n (a message), or None."""
    if len(cells) != n:
        return f"cells holds {len(cells)} numbers, not {n}"
    if any(c < 1 for c in cells):
        return "a cell count is 0"
    return None


def kuhn_slot_count(n: int, cells) -> int:
    """C₀ = n! · Π c_k, the grid cells of §7.4.3."""
    return math.factorial(n) * math.prod(cells)


def build_refinement(n: int, refinement: dict):
    """The model's (vertices, simplices) given by a refinement {"box", "cells", "splits", "kept"} (§7.4.3),
    with `kept` one bool per live slot; ValueError when it is not one a writer may write."""
    if n not in (2, 3):
        raise ValueError(f"complexForm 1 is only for dimension 2 or 3, not {n}")
    box = [float(x) for x in refinement["box"]]
    cells = [int(c) for c in refinement["cells"]]
    problem = box_problem(n, box) or cells_problem(n, cells)
    if problem is None and any(c >= 1 << 32 for c in cells):
        problem = "a cell count is not a u32"
    if problem:
        raise ValueError(problem)
    if math.prod(c + 1 for c in cells) >= 1 << 32:
        raise ValueError("the grid has 2^32 vertices or more")
    grid = KuhnRefinement(n, box, cells)
    for index, pair in enumerate(refinement["splits"]):
        a, b = (int(x) for x in pair)
        if not (0 <= a and b < 1 << 32):
            raise ValueError(f"split {index} ({a}, {b}): ids are u32")
        try:
            grid.split(index, a, b)
        except RefinementRefused as e:
            raise ValueError(str(e)) from None
    kept = list(refinement["kept"])
    live = grid.live_slots()
    if len(kept) != len(live):
        raise ValueError(f"kept has {len(kept)} entries for {len(live)} live slots")
    return grid.complex([s for s, keep in zip(live, kept) if keep]), len(live)


def write_refinement(w, n: int, refinement: dict, live: int):
    """complexForm 1 and its members (§7.4.3) into BinaryWriter `w` (structured)."""
    w.put("<B", 1)
    w.f64s([float(x) for x in refinement["box"]])
    w.u32s([int(c) for c in refinement["cells"]])
    w.u32s([int(x) for pair in refinement["splits"] for x in pair])
    mask = bytearray((live + 7) // 8)
    for i, keep in enumerate(refinement["kept"]):
        if keep:
            mask[i >> 3] |= 1 << (i & 7)
    w.out += mask


# ------------------------------------------------------------------------------------------ binary


class BinaryDecoder:
    """The binary grammar of spec §7.4; with `compact`, the compact binary encoding of §7.4.1 (every
    length, u32 and enumeration index a minimal varint); with `structured` (and `compact`), the structured
    encoding of §7.4.3 (`complexForm`, and a stage's records by `recordForm`)."""

    def __init__(self, data: bytes, base: int, compact: bool = False, structured: bool = False):
        self.b = data
        self.at = 0
        self.base = base
        self.path = []
        self.compact = compact or structured
        self.structured = structured
        self.complex = None
        self.refinement = None  # {"box", "cells", "splits", "kept"} of a complexForm 1 payload
        # Smallest element sizes (§7.4, §7.4.1; §7.4.3 keeps the compact ones: "Errors are those of §7.4.1").
        if self.compact:
            self.MIN = {"f64": 8, "u32": 1, "string": 1, "stage": 7, "record": 3, "vmap": 2, "ext": 2}
        else:
            self.MIN = {"f64": 8, "u32": 4, "string": 8, "stage": 37, "record": 24, "vmap": 12, "ext": 16}

    def varint(self, wide: bool) -> int:
        """A minimal varint (§7.4.1) of a u64 (`wide`) or u32 member; errors at its first byte."""
        start = self.at
        first = self.take(1)[0]
        if first <= 250:
            return first
        sizes = {251: (2, "<H", 251), 252: (4, "<I", 1 << 16)}
        if wide:
            sizes[253] = (8, "<Q", 1 << 32)
        if first not in sizes:
            raise self.fail(start, f"varint first byte {first}")
        n, fmt, least = sizes[first]
        if len(self.b) - self.at < n:
            raise self.fail(start, "varint runs past the payload")
        (value,) = struct.unpack(fmt, self.take(n))
        if value < least:
            raise self.fail(start, "varint not minimal")
        return value

    def fail(self, at, message) -> IsmError:
        return IsmError("ISM-006", message, pointer=pointer_of(self.path), offset=self.base + at)

    def take(self, n: int) -> bytes:
        if len(self.b) - self.at < n:
            raise self.fail(self.at, "field runs past the payload")
        out = self.b[self.at : self.at + n]
        self.at += n
        return out

    def u8(self):
        return self.take(1)[0]

    def u32(self):
        if self.compact:
            return self.varint(False)
        return struct.unpack("<I", self.take(4))[0]

    def f64(self):
        return struct.unpack("<d", self.take(8))[0]

    def length(self, minimum: int) -> int:
        start = self.at
        (n,) = (self.varint(True),) if self.compact else struct.unpack("<Q", self.take(8))
        if n > (len(self.b) - self.at) // minimum:
            raise self.fail(start, f"declares {n} elements; too few bytes remain")
        return n

    def string(self) -> str:
        n = self.length(1)
        at = self.at
        data = self.take(n)
        try:
            return data.decode("utf-8")
        except UnicodeDecodeError as e:
            raise self.fail(at + e.start, "invalid UTF-8")

    def optional_string(self):
        start = self.at
        tag = self.u8()
        if tag == 0:
            return None
        if tag == 1:
            return self.string()
        raise self.fail(start, f"presence tag {tag}")

    def member(self, name, read):
        self.path.append(name)
        value = read()
        self.path.pop()
        return value

    def f64s(self):
        n = self.length(8)
        return list(struct.unpack(f"<{n}d", self.take(8 * n)))

    def u32s(self):
        n = self.length(self.MIN["u32"])
        if self.compact:
            return [self.u32() for _ in range(n)]
        return list(struct.unpack(f"<{n}I", self.take(4 * n)))

    def seq(self, minimum, read):
        n = self.length(minimum)
        out = []
        for i in range(n):
            self.path.append(i)
            out.append(read())
            self.path.pop()
        return out

    def data(self, depth: int):
        start = self.at
        self.length(1)
        text_at = self.at
        self.at = start
        text = self.string()
        d = Decoder(JsonTokens(text.encode("utf-8"), self.base + text_at), self.path, depth)
        value = d.data()
        d.call(d.tok.end)
        if json_text(value) != text:
            raise self.fail(start, "JSON text is not canonical")
        return value

    def enum(self, name, names):
        start = self.at
        self.path.append(name)
        i = self.u32()
        if i >= len(names):
            raise self.fail(start, f"{name} {i} out of range")
        self.path.pop()
        return names[i]

    def stage(self) -> dict:
        s = {"kind": self.enum("kind", KINDS)}
        s["degree"] = self.member("degree", self.u32)
        s["direction"] = self.enum("direction", DIRECTIONS)
        s["name"] = self.member("name", self.optional_string)

        def record():
            return {
                "face": self.member("face", self.u32s),
                "points": self.member("points", self.f64s),
                "weights": self.member("weights", self.f64s),
            }

        def vmap():
            return {"vertex": self.member("vertex", self.u32), "coefficients": self.member("coefficients", self.f64s)}

        if self.structured:
            s["faces"] = self.member("faces", lambda: self.records(s, record))
        else:
            s["faces"] = self.member("faces", lambda: self.seq(self.MIN["record"], record))
        s["vertexMaps"] = self.member("vertexMaps", lambda: self.seq(self.MIN["vmap"], vmap))
        s["extras"] = self.member("extras", lambda: self.data(3))
        return s

    def records(self, stage: dict, record) -> list:
        """A stage's records in the structured encoding (§7.4.3), at pointer /stages/s/faces: `recordForm` 0, the
        compact sequence; 1, masks over the complex's k-faces, `width`, the points, the weights."""
        start = self.at
        form = self.u8()
        if form == 0:
            return self.seq(self.MIN["record"], record)
        if form != 1:
            raise self.fail(start, f"recordForm {form}")
        if self.dimension not in (2, 3):
            # §7.4.3: recordForm 1 only in 2D and 3D, so no reader lists the faces of an impossible complex.
            raise self.fail(start, f"recordForm 1 in dimension {self.dimension} (only 2 or 3)")
        dims_at = self.at
        dims = self.u8()
        n = self.dimension
        if dims >> (n + 1):
            raise self.fail(dims_at, f"dims 0x{dims:02x} has bits above the dimension {n}")
        if dims and stage["kind"] == "monotonic":
            raise self.fail(dims_at, "a monotonic stage's dims is not 0")
        chosen = []  # (k, face) in record order
        for k in range(8):
            if not dims >> k & 1:
                continue
            mask_at = self.at
            left = len(self.b) - self.at
            faces = self.complex.faces(k, limit=8 * left)
            if faces is None or (len(faces) + 7) // 8 > left:
                raise self.fail(mask_at, f"the mask of the {k}-faces runs past the payload")
            size = (len(faces) + 7) // 8
            mask = self.take(size)
            if len(faces) % 8 and mask[-1] >> (len(faces) % 8):
                raise self.fail(mask_at + size - 1, f"mask bits beyond the {len(faces)} {k}-faces are set")
            for j, byte in enumerate(mask):
                while byte:
                    low = byte & -byte
                    chosen.append((k, faces[8 * j + low.bit_length() - 1]))
                    byte ^= low
        width_at = self.at
        width = self.u8()
        if width > LATTICE_MAX_WIDTH:
            raise self.fail(width_at, f"width {width}")
        rational = stage["kind"] == "rational"
        counts = {}
        for k, _ in chosen:
            counts[k] = counts.get(k, 0) + 1
        owned = {k: owned_count(stage["degree"], k) for k in counts}
        needed = 0
        for k, count in counts.items():
            point_bytes = 8 * (k + 1) if width == 0 else k * width
            needed += count * owned[k] * (point_bytes + (8 if rational else 0))
        if needed > len(self.b) - self.at:
            raise self.fail(width_at, f"the records need {needed} bytes; {len(self.b) - self.at} remain")
        out = []
        b = self.b
        if width:
            scale = 2.0 ** (-8 * width)
            top = 1 << (8 * width)
        for k, face in chosen:
            count = owned[k]
            if width == 0:
                points = list(struct.unpack_from(f"<{count * (k + 1)}d", b, self.at))
                self.at += 8 * count * (k + 1)
            else:
                points = []
                for _ in range(count):
                    ns = [int.from_bytes(b[self.at + width * j : self.at + width * j + width], "little") for j in range(k)]
                    self.at += width * k
                    points.append((top - sum(ns)) * scale)
                    points.extend(x * scale for x in ns)
            out.append({"face": list(face), "points": points, "weights": []})
        if rational:
            for r, (k, _) in enumerate(chosen):
                count = owned[k]
                out[r]["weights"] = list(struct.unpack_from(f"<{count}d", b, self.at))
                self.at += 8 * count
        return out

    def refined_complex(self, n: int):
        """`complexForm` 1 (§7.4.3), after its byte: `box`, `cells` (at /vertices), `splits`, `kept` (at
        /simplices); the model's vertices and simplices by the construction. The grid is built only once the
        payload is known to hold its kept mask, and each split only while the mask after it fits the bytes left
        after `splits`, so the slots stay below 16 per byte of input."""
        self.path.append("vertices")
        box_at = self.at
        # Each array is decoded (its grammar's errors at their bytes) and then checked (at its first byte); box
        # before cells is decoded, so a bad box is reported before a bad varint in cells (front to back, §7.8).
        box = self.f64s()
        problem = box_problem(n, box)
        if problem is not None:
            raise self.fail(box_at, problem)
        cells_at = self.at
        cells = self.u32s()
        problem = cells_problem(n, cells)
        if problem is not None:
            raise self.fail(cells_at, problem)
        # Right after `cells` (§7.4.3, front to back): the kept mask of the grid's cells must fit the bytes left
        # (ISM-006; splits only add slots), then the grid's vertex count must fit u32 (ISM-007), both at `cells`.
        grid_cells = kuhn_slot_count(n, cells)
        left = len(self.b) - self.at
        if (grid_cells + 7) // 8 > left:
            raise self.fail(cells_at, f"the {grid_cells} grid cells need a kept mask of {(grid_cells + 7) // 8} bytes; {left} follow cells")
        if math.prod(c + 1 for c in cells) >= 1 << 32:
            raise IsmError("ISM-007", "the grid has 2^32 vertices or more", pointer="/vertices", offset=self.base + cells_at)
        self.path[-1] = "simplices"
        splits_at = self.at
        count = self.length(self.MIN["u32"])
        pairs = []
        for _ in range(count // 2):
            at = self.at
            a = self.u32()
            pairs.append((at, a, self.u32()))
        if count % 2:
            self.u32()
            raise self.fail(splits_at, f"splits holds {count} ids, an odd number")
        after = len(self.b) - self.at
        grid = KuhnRefinement(n, box, cells)
        for index, (at, a, b) in enumerate(pairs):
            try:
                grid.split(index, a, b, byte_limit=after)
            except RefinementRefused as e:
                if e.what == "ids":
                    raise IsmError("ISM-007", str(e), pointer="/simplices", offset=self.base + at) from None
                raise self.fail(at, str(e)) from None
        live = grid.live_slots()
        kept_at = self.at
        size = (len(live) + 7) // 8
        mask = self.take(size)
        if len(live) % 8 and mask[-1] >> (len(live) % 8):
            raise self.fail(kept_at + size - 1, f"kept bits beyond the {len(live)} live slots are set")
        kept = [s for i, s in enumerate(live) if mask[i >> 3] >> (i & 7) & 1]
        self.path.pop()
        self.refinement = {
            "box": box,
            "cells": cells,
            "splits": [[a, b] for _, a, b in pairs],
            "kept": [bool(mask[i >> 3] >> (i & 7) & 1) for i in range(len(live))],
        }
        return grid.complex(kept)

    def extensions(self) -> dict:
        n = self.length(self.MIN["ext"])
        out = {}
        previous = None
        for _ in range(n):
            key_at = self.at
            key = self.string()
            self.path.append(key)
            if previous is not None and key.encode("utf-8") <= previous.encode("utf-8"):
                raise self.fail(key_at, "extension names not strictly increasing")
            out[key] = self.data(2)
            self.path.pop()
            previous = key
        return out

    def model(self, allow_trailing: bool) -> dict:
        m = new_model()
        m["version"] = self.member("version", self.string)
        m["dimension"] = self.member("dimension", self.u8)

        def metadata():
            meta = {}
            for key in ("name", "generator", "units", "description"):
                value = self.member(key, self.optional_string)
                if value is not None:
                    meta[key] = value
            return meta

        m["metadata"] = self.member("metadata", metadata)
        form = 0
        if self.structured:
            self.path.append("vertices")
            start = self.at
            form = self.u8()
            if form == 1 and m["dimension"] not in (2, 3):
                raise self.fail(start, f"complexForm 1 in dimension {m['dimension']} (only 2 or 3)")
            if form not in (0, 1):
                raise self.fail(start, f"complexForm {form}")
            self.path.pop()
        if form == 1:
            m["vertices"], m["simplices"] = self.refined_complex(m["dimension"])
        else:
            m["vertices"] = self.member("vertices", self.f64s)
            m["simplices"] = self.member("simplices", self.u32s)
        self.dimension = m["dimension"]
        self.complex = ComplexFaces(m["simplices"], m["dimension"])
        m["values"] = self.member("values", self.f64s)
        m["level"] = self.member("level", self.f64)
        m["stages"] = self.member("stages", lambda: self.seq(self.MIN["stage"], self.stage))
        for key in ("extensionsUsed", "extensionsRequired"):
            m[key] = self.member(key, lambda: self.seq(self.MIN["string"], self.string))
        m["extensions"] = self.member("extensions", self.extensions)
        m["extras"] = self.member("extras", lambda: self.data(1))
        if self.at < len(self.b) and not allow_trailing:
            raise self.fail(self.at, "bytes follow the model")
        return m


# ------------------------------------------------------------------------------------------ reading


def parse_version(text: str):
    parts = text.split(".")
    if len(parts) != 2:
        return None
    out = []
    for p in parts:
        if not (1 <= len(p) <= 5 and p.isascii() and p.isdigit()) or (len(p) > 1 and p[0] == "0") or int(p) > 65535:
            return None
        out.append(int(p))
    return tuple(out)


def check_version(text: str):
    version = parse_version(text)
    if version is None:
        raise IsmError("ISM-006", f"version {text!r} is not major.minor", pointer="/version")
    if version[0] != MAJOR:
        raise IsmError("ISM-002", f"version {text}; this reader implements {MAJOR}", pointer="/version")
    return version


def decode_map_encoding(tokens_of, payload: bytes, base: int) -> dict:
    try:
        return Decoder(tokens_of(payload, base)).model()
    except IsmError as error:
        probed = probe_version(tokens_of(payload, base))
        if probed is not None:
            try:
                check_version(probed)
            except IsmError as e:
                if e.rule == "ISM-002":
                    raise e from None
        raise


def decompress(payload: bytes, payload_limit: int) -> bytes:
    """The compact payload inside a compressed one (spec §7.4.2), with the checks in the spec's order; never
    decompresses more than the declared length plus one byte."""
    end = HEADER_LEN + len(payload)
    if len(payload) < 8:
        raise IsmError("ISM-006", "compressed payload shorter than its length", offset=end)
    (length,) = struct.unpack_from("<Q", payload, 0)
    if length > payload_limit:
        raise IsmError("ISM-007", "uncompressed length above the limit", offset=HEADER_LEN)
    stream = payload[8:]
    d = lzma.LZMADecompressor(format=lzma.FORMAT_XZ, memlimit=XZ_MEMORY_LIMIT)
    try:
        out = d.decompress(stream, max_length=length + 1)
    except lzma.LZMAError as e:
        rule = "ISM-007" if "Memory usage limit" in str(e) else "ISM-006"
        raise IsmError(rule, f"xz: {e}", offset=HEADER_LEN + 8) from None
    if len(out) <= length and not d.eof:
        # All input consumed without the stream's end: it is cut short.
        raise IsmError("ISM-006", "truncated xz stream", offset=end)
    if len(out) != length:
        raise IsmError("ISM-006", f"xz stream holds other than {length} bytes", offset=HEADER_LEN)
    if d.unused_data:
        raise IsmError("ISM-006", "bytes after the xz stream", offset=end - len(d.unused_data))
    return out


def decode(data: bytes, payload_limit: int = DEFAULT_PAYLOAD_LIMIT, refinement_out: dict | None = None):
    """Container, encoding and version (spec §7.1, §7.5): returns (model, encoding)."""
    if data[:8] == MAGIC:
        if len(data) < HEADER_LEN:
            raise IsmError("ISM-004", "truncated header", offset=len(data))
        if zlib.crc32(data[:28]) != struct.unpack_from("<I", data, 28)[0]:
            raise IsmError("ISM-003", "header CRC", offset=28)
        major, minor, tag = struct.unpack_from("<HHB", data, 8)
        if major != MAJOR:
            raise IsmError("ISM-002", f"major version {major}", offset=8)
        if tag not in (1, 2, 3, 4, 5, 6):
            raise IsmError("ISM-005", f"encoding tag {tag}", offset=12)
        if data[13:16] != b"\0\0\0":
            raise IsmError("ISM-006", "reserved bytes", offset=13)
        (length,) = struct.unpack_from("<Q", data, 16)
        if length > payload_limit:
            raise IsmError("ISM-007", "payload length above the limit", offset=16)
        if len(data) - HEADER_LEN < length:
            raise IsmError("ISM-004", "truncated payload", offset=len(data))
        if len(data) > HEADER_LEN + length:
            raise IsmError("ISM-010", "trailing data", offset=HEADER_LEN + length)
        payload = data[HEADER_LEN:]
        if zlib.crc32(payload) != struct.unpack_from("<I", data, 24)[0]:
            raise IsmError("ISM-003", "payload CRC", offset=24)
        if tag == 1:
            model = decode_map_encoding(JsonTokens, payload, HEADER_LEN)
        elif tag == 2:
            model = decode_map_encoding(MsgpackTokens, payload, HEADER_LEN)
        elif tag == 5:
            compact = decompress(payload, payload_limit)
            model = BinaryDecoder(compact, HEADER_LEN, compact=True).model(allow_trailing=minor > MINOR)
        else:
            decoder = BinaryDecoder(payload, HEADER_LEN, compact=tag == 4, structured=tag == 6)
            model = decoder.model(allow_trailing=minor > MINOR)
            if refinement_out is not None and decoder.refinement is not None:
                refinement_out["refinement"] = decoder.refinement
        version = check_version(model["version"])
        if version != (major, minor):
            raise IsmError("ISM-009", "header and payload versions differ", pointer="/version")
        return model, {1: "json", 2: "msgpack", 3: "binary", 4: "compact", 5: "compressed", 6: "structured"}[tag]
    stripped = data.lstrip(b" \t\n\r")
    if stripped[:1] != b"{":
        raise IsmError("ISM-001", "not an ISM file", offset=0)
    model = decode_map_encoding(JsonTokens, data, 0)
    check_version(model["version"])
    return model, "json"


def refinement_of(data: bytes):
    """The refinement a structured file's `complexForm` 1 holds ({"box", "cells", "splits": [[a, b], ...],
    "kept": [bool per live slot]}, what `write(..., refinement=)` takes), or None for any other file. Raises
    IsmError as `decode` does."""
    found = {}
    decode(data, refinement_out=found)
    return found.get("refinement")


def read(data: bytes, supported_extensions=()) -> dict:
    """Reads a file: every reader rule of spec §9; raises IsmError with the first error."""
    model, _ = decode(data)
    for i, name in enumerate(model["extensionsRequired"]):
        if name not in supported_extensions:
            raise IsmError("ISM-008", f"extension {name} not supported", pointer=f"/extensionsRequired/{i}")
    errors = structural_errors(model)
    if errors:
        raise errors[0]
    return model


# ------------------------------------------------------------------------------------------ structure (§3, §5, §9)


def orientation(model, ids):
    n = model["dimension"]
    v = model["vertices"]
    p = [v[i * n : i * n + n] for i in ids]
    e = [[p[k + 1][c] - p[0][c] for c in range(n)] for k in range(n)]
    if n == 2:
        det = e[0][0] * e[1][1] - e[0][1] * e[1][0]
    else:
        det = (
            e[0][0] * (e[1][1] * e[2][2] - e[1][2] * e[2][1])
            - e[0][1] * (e[1][0] * e[2][2] - e[1][2] * e[2][0])
            + e[0][2] * (e[1][0] * e[2][1] - e[1][1] * e[2][0])
        )
    longest = 0.0
    for a in range(n + 1):
        for b in range(a + 1, n + 1):
            d2 = 0.0
            for c in range(n):
                d = p[a][c] - p[b][c]
                d2 += d * d  # not ** 2, which raises OverflowError instead of giving inf
            longest = max(longest, math.sqrt(d2))
    return det, longest


def structural_errors(model: dict) -> list:
    """The structural errors (not warnings) of spec §9 in the reader's order."""
    out = []
    n = model["dimension"]
    if n not in (2, 3):
        return [IsmError("ISM-101", "dimension", pointer="/dimension")]
    verts, sims, vals = model["vertices"], model["simplices"], model["values"]
    if len(verts) % n:
        out.append(IsmError("ISM-102", "vertex count", pointer="/vertices"))
    for i, x in enumerate(verts):
        if not math.isfinite(x):
            out.append(IsmError("ISM-102", "non-finite coordinate", pointer=f"/vertices/{i}", vertex=i // n))
    m = n + 1
    if len(sims) % m or not sims:
        out.append(IsmError("ISM-103", "simplex array", pointer="/simplices"))
        return out
    nv = len(verts) // n
    for i, idx in enumerate(sims):
        if idx >= nv:
            out.append(IsmError("ISM-104", "index range", pointer=f"/simplices/{i}", simplex=i // m))
    if out:
        return out
    simplices = [sims[s * m : s * m + m] for s in range(len(sims) // m)]

    def at_simplex(rule, s, **extra):
        return IsmError(rule, rule, pointer=f"/simplices/{m * s}", simplex=s, **extra)

    repeated = set()
    for s, ids in enumerate(simplices):
        if len(set(ids)) < m:
            repeated.add(s)
            out.append(at_simplex("ISM-105", s))
            continue
        det, longest = orientation(model, ids)
        scale = longest * longest * (longest if n == 3 else 1.0)
        if abs(det) <= 1e-12 * scale or not math.isfinite(det):
            out.append(at_simplex("ISM-107", s))
        elif det < 0:
            out.append(at_simplex("ISM-106", s))
    keys = sorted((tuple(sorted(ids)), s) for s, ids in enumerate(simplices) if s not in repeated)
    for (k0, _), (k1, s1) in zip(keys, keys[1:]):
        if k0 == k1:
            out.append(at_simplex("ISM-108", s1))
    facets = []
    for s, ids in enumerate(simplices):
        if s in repeated:
            continue
        for skip in range(m):
            rest = [x for j, x in enumerate(ids) if j != skip]
            inversions = sum(1 for a in range(len(rest)) for b in range(a + 1, len(rest)) if rest[a] > rest[b])
            odd = (skip % 2 == 1) != (inversions % 2 == 1)
            facets.append((tuple(sorted(rest)), odd, s))  # side +1 (odd False) sorts first
    facets.sort()
    i = 0
    while i < len(facets):
        j = i + 1
        while j < len(facets) and facets[j][0] == facets[i][0]:
            j += 1
        group = facets[i:j]
        face = list(group[0][0])
        if len(group) > 2:
            out.append(at_simplex("ISM-109", group[2][2], face=face))
        elif len(group) == 2 and group[0][1] == group[1][1] and group[0][2] != group[1][2]:
            out.append(at_simplex("ISM-110", group[1][2], face=face))
        i = j
    level = model["level"]
    if not math.isfinite(level):
        out.append(IsmError("ISM-114", "level", pointer="/level"))
    if len(vals) != nv:
        out.append(IsmError("ISM-111", "value count", pointer="/values"))
    for v, x in enumerate(vals):
        if not math.isfinite(x):
            out.append(IsmError("ISM-111", "non-finite value", pointer=f"/values/{v}", vertex=v))
        elif x == 0:
            out.append(IsmError("ISM-112", "zero value", pointer=f"/values/{v}", vertex=v))
        elif x == level:
            out.append(IsmError("ISM-113", "value at level", pointer=f"/values/{v}", vertex=v))
    used = model["extensionsUsed"]
    for member in ("extensionsUsed", "extensionsRequired"):
        seen = set()
        for i, name in enumerate(model[member]):
            if name in seen:
                out.append(IsmError("ISM-152", "listed twice", pointer=f"/{member}/{i}"))
            seen.add(name)
    for i, name in enumerate(model["extensionsRequired"]):
        if name not in used:
            out.append(IsmError("ISM-152", "not listed", pointer=f"/extensionsRequired/{i}"))
    for name in sorted(model["extensions"], key=lambda k: k.encode("utf-8")):
        if name not in used:
            out.append(IsmError("ISM-152", "not listed", pointer=f"/extensions/{escape_token(name)}"))
    complex_ = ComplexFaces(sims, n)  # a face of K: its ids, sorted, all in one top simplex
    for k, stage in enumerate(model["stages"]):
        base = f"/stages/{k}"
        d = stage["degree"]
        if not 1 <= d <= MAX_DEGREE:
            out.append(IsmError("ISM-120", "degree", pointer=f"{base}/degree", stage=k))
            continue
        if stage["kind"] == "monotonic":
            if stage["faces"]:
                out.append(IsmError("ISM-127", "kind", pointer=f"{base}/faces", stage=k))
            seen = set()
            for r, vm in enumerate(stage["vertexMaps"]):
                loc = {"stage": k, "vertex": vm["vertex"]}
                if vm["vertex"] >= nv or vm["vertex"] in seen:
                    out.append(IsmError("ISM-128", "vertex map", pointer=f"{base}/vertexMaps/{r}/vertex", **loc))
                seen.add(vm["vertex"])
                coefficients = vm["coefficients"]
                if len(coefficients) != d + 1:
                    out.append(IsmError("ISM-129", "count", pointer=f"{base}/vertexMaps/{r}/coefficients", **loc))
                bad = [j for j, x in enumerate(coefficients) if not math.isfinite(x)]
                if bad:
                    out.append(IsmError("ISM-126", "non-finite", pointer=f"{base}/vertexMaps/{r}/coefficients/{bad[0]}", **loc))
            continue
        if stage["vertexMaps"]:
            out.append(IsmError("ISM-127", "kind", pointer=f"{base}/vertexMaps", stage=k))
        first_record = {}
        for r, rec in enumerate(stage["faces"]):
            face = rec["face"]
            loc = {"stage": k, "face": list(face)}
            where = f"{base}/faces/{r}"
            size = len(face)
            if not 1 <= size <= n + 1:
                out.append(IsmError("ISM-122", "not a face", pointer=f"{where}/face", **loc))
                continue
            if any(a >= b for a, b in zip(face, face[1:])):
                out.append(IsmError("ISM-121", "not sorted", pointer=f"{where}/face", **loc))
                continue
            if any(v >= nv for v in face) or tuple(face) not in complex_.index(size - 1):
                out.append(IsmError("ISM-122", "not a face", pointer=f"{where}/face", **loc))
                continue
            key = tuple(face)
            if key in first_record:
                out.append(IsmError("ISM-123", "duplicate", pointer=f"{where}/face", **loc))
            else:
                first_record[key] = r
            owned = math.comb(d - 1, size - 1) if d >= size else 0
            if owned == 0:
                out.append(IsmError("ISM-124", "owns nothing", pointer=f"{where}/points", **loc))
                continue
            if len(rec["points"]) != owned * size:
                out.append(IsmError("ISM-124", "point count", pointer=f"{where}/points", **loc))
            if len(rec["weights"]) != (owned if stage["kind"] == "rational" else 0):
                out.append(IsmError("ISM-125", "weight count", pointer=f"{where}/weights", **loc))
            for what in ("points", "weights"):
                bad = [j for j, x in enumerate(rec[what]) if not math.isfinite(x)]
                if bad:
                    out.append(IsmError("ISM-126", "non-finite", pointer=f"{where}/{what}/{bad[0]}", **loc))
    return out


# ------------------------------------------------------------------------------------------ writing (§7.7)


def format_f64(x: float) -> str:
    """The canonical spelling of spec §7.7, from Python's shortest round-trip repr."""
    if x == 0:
        return "-0.0" if math.copysign(1.0, x) < 0 else "0.0"
    sign = "-" if x < 0 else ""
    r = repr(abs(x))
    mantissa, _, exp = r.partition("e")
    whole, _, frac = mantissa.partition(".")
    digits = whole + frac
    point = len(whole) + (int(exp) if exp else 0)
    stripped = digits.lstrip("0")
    point -= len(digits) - len(stripped)
    digits = stripped.rstrip("0")
    length = len(digits)
    if 0 < point <= 16:
        body = digits + "0" * (point - length) + ".0" if length <= point else digits[:point] + "." + digits[point:]
    elif -5 < point <= 0:
        body = "0." + "0" * -point + digits
    else:
        body = digits[0] + ("." + digits[1:] if length > 1 else "") + "e" + str(point - 1)
    return sign + body


ESCAPES = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r"}


def json_string(s: str) -> str:
    return '"' + "".join(ESCAPES.get(c, f"\\u{ord(c):04x}" if ord(c) < 0x20 else c) for c in s) + '"'


def to_json(value, indent=None, level=0) -> str:
    """Canonical JSON text: compact (indent None) or pretty (two spaces per level)."""
    if value is None:
        return "null"
    if value is True:
        return "true"
    if value is False:
        return "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return format_f64(value)
    if isinstance(value, str):
        return json_string(value)
    if isinstance(value, list):
        items = [to_json(v, indent, level + 1) for v in value]
        open_, close = "[", "]"
    else:
        items = [json_string(k) + (": " if indent else ":") + to_json(v, indent, level + 1) for k, v in value.items()]
        open_, close = "{", "}"
    if not items:
        return open_ + close
    if indent is None:
        return open_ + ",".join(items) + close
    pad = "\n" + "  " * (level + 1)
    return open_ + pad + ("," + pad).join(items) + "\n" + "  " * level + close


def json_text(value) -> str:
    return to_json(value)


def canonical_members(model: dict) -> dict:
    """The model as the ordered members a writer writes (§7.7), f64 members as floats."""
    fl = lambda xs: [float(x) for x in xs]  # noqa: E731
    out = {
        "version": f"{MAJOR}.{MINOR}",
        "dimension": model["dimension"],
        "metadata": {k: model["metadata"][k] for k in ("name", "generator", "units", "description") if model["metadata"].get(k) is not None},
        "vertices": fl(model["vertices"]),
        "simplices": list(model["simplices"]),
        "values": fl(model["values"]),
        "level": float(model["level"]),
        "stages": [],
    }
    for s in model["stages"]:
        stage = {"kind": s["kind"], "degree": s["degree"], "direction": s.get("direction", "implicit")}
        if s.get("name") is not None:
            stage["name"] = s["name"]
        if s.get("faces"):
            stage["faces"] = []
            for r in s["faces"]:
                rec = {"face": list(r["face"]), "points": fl(r.get("points", []))}
                if r.get("weights"):
                    rec["weights"] = fl(r["weights"])
                stage["faces"].append(rec)
        if s.get("vertexMaps"):
            stage["vertexMaps"] = [{"vertex": v["vertex"], "coefficients": fl(v["coefficients"])} for v in s["vertexMaps"]]
        if s.get("extras") is not None:
            stage["extras"] = s["extras"]
        out["stages"].append(stage)
    for key in ("extensionsUsed", "extensionsRequired"):
        if model.get(key):
            out[key] = list(model[key])
    if model.get("extensions"):
        out["extensions"] = {k: model["extensions"][k] for k in sorted(model["extensions"], key=lambda k: k.encode("utf-8"))}
    if model.get("extras") is not None:
        out["extras"] = model["extras"]
    return out


def check_writable(model: dict):
    """Writers refuse what readers refuse (§7.7): non-finite numbers, data nested too deep."""
    n = max(model["dimension"], 1)
    for i, x in enumerate(model["vertices"]):
        if not math.isfinite(x):
            raise IsmError("ISM-102", "non-finite", pointer=f"/vertices/{i}", vertex=i // n)
    for i, x in enumerate(model["values"]):
        if not math.isfinite(x):
            raise IsmError("ISM-111", "non-finite", pointer=f"/values/{i}", vertex=i)
    if not math.isfinite(model["level"]):
        raise IsmError("ISM-114", "non-finite", pointer="/level")
    for k, s in enumerate(model["stages"]):
        for r, rec in enumerate(s.get("faces", [])):
            for what in ("points", "weights"):
                for j, x in enumerate(rec.get(what, [])):
                    if not math.isfinite(x):
                        raise IsmError("ISM-126", "non-finite", pointer=f"/stages/{k}/faces/{r}/{what}/{j}", stage=k, face=list(rec["face"]))
        for r, vm in enumerate(s.get("vertexMaps", [])):
            for j, x in enumerate(vm["coefficients"]):
                if not math.isfinite(x):
                    raise IsmError("ISM-126", "non-finite", pointer=f"/stages/{k}/vertexMaps/{r}/coefficients/{j}", stage=k, vertex=vm["vertex"])

    def depth(value, above, pointer):
        if isinstance(value, (list, dict)):
            if above + 1 > MAX_DEPTH:
                raise IsmError("ISM-006", "nested too deep", pointer=pointer)
            items = enumerate(value) if isinstance(value, list) else value.items()
            for k, v in items:
                depth(v, above + 1, f"{pointer}/{escape_token(str(k))}")

    for k, s in enumerate(model["stages"]):
        depth(s.get("extras"), 3, f"/stages/{k}/extras")
    for name, value in model["extensions"].items():
        depth(value, 2, f"/extensions/{escape_token(name)}")
    depth(model["extras"], 1, "/extras")


def msgpack(value, out: bytearray):
    """The canonical MessagePack of §7.7: smallest formats, floats as float 64."""
    if value is None:
        out.append(0xC0)
    elif value is True or value is False:
        out.append(0xC3 if value else 0xC2)
    elif isinstance(value, int):
        if 0 <= value < 128:
            out.append(value)
        elif value >= 0:
            for fmt, marker, top in (("B", 0xCC, 1 << 8), (">H", 0xCD, 1 << 16), (">I", 0xCE, 1 << 32), (">Q", 0xCF, 1 << 64)):
                if value < top:
                    out.append(marker)
                    out += struct.pack(fmt, value)
                    break
        elif value >= -32:
            out.append(value + 256)
        else:
            for fmt, marker, low in (("b", 0xD0, -(1 << 7)), (">h", 0xD1, -(1 << 15)), (">i", 0xD2, -(1 << 31)), (">q", 0xD3, -(1 << 63))):
                if value >= low:
                    out.append(marker)
                    out += struct.pack(fmt, value)
                    break
    elif isinstance(value, float):
        out.append(0xCB)
        out += struct.pack(">d", value)
    elif isinstance(value, str):
        data = value.encode("utf-8")
        header(len(data), 0xA0, 32, (0xD9, 0xDA, 0xDB), out, allow8=True)
        out += data
    elif isinstance(value, list):
        header(len(value), 0x90, 16, (None, 0xDC, 0xDD), out)
        for v in value:
            msgpack(v, out)
    else:
        header(len(value), 0x80, 16, (None, 0xDE, 0xDF), out)
        for k, v in value.items():
            msgpack(k, out)
            msgpack(v, out)


def header(n: int, fix: int, fix_limit: int, markers, out: bytearray, allow8=False):
    if n < fix_limit:
        out.append(fix | n)
    elif allow8 and n < 256:
        out += bytes([markers[0], n])
    elif n < 1 << 16:
        out.append(markers[1])
        out += struct.pack(">H", n)
    else:
        out.append(markers[2])
        out += struct.pack(">I", n)


class BinaryWriter:
    """The binary grammar of §7.4; with `compact`, §7.4.1 (lengths, u32s and enumeration indices as
    minimal varints); with `structured`, §7.4.3 in its canonical form (`recordForm` 1 whenever the records
    allow it, the smallest lattice `width`)."""

    def __init__(self, compact: bool = False, structured: bool = False, refinement=None, live: int = 0):
        self.out = bytearray()
        self.compact = compact or structured
        self.structured = structured
        # complexForm 1 (§7.4.3): a refinement already checked to give the model's complex, and its live slots.
        self.refinement = refinement
        self.live = live

    def put(self, fmt, *values):
        self.out += struct.pack(fmt, *values)

    def varint(self, n: int):
        if n <= 250:
            self.put("<B", n)
        elif n < 1 << 16:
            self.put("<BH", 251, n)
        elif n < 1 << 32:
            self.put("<BI", 252, n)
        else:
            self.put("<BQ", 253, n)

    def length(self, n: int):
        if self.compact:
            self.varint(n)
        else:
            self.put("<Q", n)

    def u32(self, n: int):
        if self.compact:
            self.varint(n)
        else:
            self.put("<I", n)

    def string(self, s: str):
        data = s.encode("utf-8")
        self.length(len(data))
        self.out += data

    def optional(self, value):
        if value is None:
            self.put("<B", 0)
        else:
            self.put("<B", 1)
            self.string(value)

    def f64s(self, xs):
        self.length(len(xs))
        self.put(f"<{len(xs)}d", *xs)

    def u32s(self, xs):
        self.length(len(xs))
        for x in xs:
            self.u32(x)

    def records_by_complex(self, stage: dict, n: int, complex_: ComplexFaces) -> bool:
        """Writes the stage's records in `recordForm` 1 when they allow it (§7.4.3); False when they do not."""
        masks = stage_record_masks(stage, n, complex_)
        if masks is None:
            return False
        width = stage_lattice_width(stage)
        self.put("<BB", 1, sum(1 << k for k in masks))  # recordForm 1, dims
        for k in sorted(masks):
            mask = bytearray((len(complex_.faces(k)) + 7) // 8)
            for i in masks[k]:
                mask[i >> 3] |= 1 << (i & 7)
            self.out += mask
        self.put("<B", width)
        records = stage.get("faces", [])
        if width == 0:
            for r in records:
                self.put(f"<{len(r.get('points', []))}d", *r.get("points", []))
        else:
            shift = 8 * width
            for r in records:
                size = len(r["face"])
                points = r["points"]
                for at in range(0, len(points), size):
                    for c in points[at + 1 : at + size]:
                        p, q = c.as_integer_ratio()
                        self.out += (p << (shift - (q.bit_length() - 1))).to_bytes(width, "little")
        for r in records:
            weights = r.get("weights", [])
            self.put(f"<{len(weights)}d", *weights)
        return True

    def model(self, m: dict) -> bytes:
        self.string(f"{MAJOR}.{MINOR}")
        self.put("<B", m["dimension"])
        for key in ("name", "generator", "units", "description"):
            self.optional(m["metadata"].get(key))
        complex_ = None
        if self.structured:
            complex_ = ComplexFaces(m["simplices"], m["dimension"])
        if self.structured and self.refinement is not None:
            write_refinement(self, m["dimension"], self.refinement, self.live)
        else:
            if self.structured:
                self.put("<B", 0)  # complexForm 0
            self.f64s(m["vertices"])
            self.u32s(m["simplices"])
        self.f64s(m["values"])
        self.put("<d", m["level"])
        self.length(len(m["stages"]))
        for s in m["stages"]:
            for x in (KINDS.index(s["kind"]), s["degree"], DIRECTIONS.index(s.get("direction", "implicit"))):
                self.u32(x)
            self.optional(s.get("name"))
            if self.structured and self.records_by_complex(s, m["dimension"], complex_):
                pass
            else:
                if self.structured:
                    self.put("<B", 0)  # recordForm 0
                self.length(len(s.get("faces", [])))
                for r in s.get("faces", []):
                    self.u32s(r["face"])
                    self.f64s(r.get("points", []))
                    self.f64s(r.get("weights", []))
            self.length(len(s.get("vertexMaps", [])))
            for v in s.get("vertexMaps", []):
                self.u32(v["vertex"])
                self.f64s(v["coefficients"])
            self.string(json_text(s.get("extras")))
        for key in ("extensionsUsed", "extensionsRequired"):
            self.length(len(m[key]))
            for name in m[key]:
                self.string(name)
        names = sorted(m["extensions"], key=lambda k: k.encode("utf-8"))
        self.length(len(names))
        for name in names:
            self.string(name)
            self.string(json_text(m["extensions"][name]))
        self.string(json_text(m["extras"]))
        return bytes(self.out)


def stage_record_masks(stage: dict, n: int, complex_: ComplexFaces):
    """The canonical `recordForm` 1 of a stage (§7.4.3): {k: [face positions]} when its records are exactly, in
    order, the records of some masks over the k-faces of the complex (k ascending, face order within a k, no face
    twice), each with C(d - 1, k) points of k + 1 coordinates and, in a rational stage, as many weights (none in
    other kinds), and a monotonic stage has none; else None (`recordForm` 0)."""
    records = stage.get("faces", [])
    if n not in (2, 3):
        return None
    if stage["kind"] == "monotonic":
        return {} if not records else None
    rational = stage["kind"] == "rational"
    masks = {}
    previous = (-1, -1)
    for r in records:
        face = tuple(r["face"])
        k = len(face) - 1
        if not 0 <= k <= min(n, 7):
            return None
        position = complex_.index(k).get(face)
        if position is None or (k, position) <= previous:
            return None
        owned = owned_count(stage["degree"], k)
        if len(r.get("points", [])) != owned * (k + 1) or len(r.get("weights", [])) != (owned if rational else 0):
            return None
        previous = (k, position)
        masks.setdefault(k, []).append(position)
    return masks


def stage_lattice_width(stage: dict) -> int:
    """The canonical `width` of a `recordForm` 1 stage (§7.4.3): the smallest w >= 1 at which every point of the
    stage lies on the 2^(-8w) lattice (1 when it has no points), else 0."""
    width = 1
    for r in stage.get("faces", []):
        size = len(r["face"])
        points = r.get("points", [])
        for at in range(0, len(points), size):
            w = point_lattice_width(points[at : at + size])
            if w == 0:
                return 0
            width = max(width, w)
    return width


def structured_choices(model: dict) -> list:
    """Per stage, the canonical structured form (§7.4.3): (1, dims, width) for `recordForm` 1, (0, None, None)
    for `recordForm` 0."""
    complex_ = ComplexFaces(model["simplices"], model["dimension"])
    out = []
    for stage in model["stages"]:
        masks = stage_record_masks(stage, model["dimension"], complex_)
        out.append((0, None, None) if masks is None else (1, sum(1 << k for k in masks), stage_lattice_width(stage)))
    return out


def container(payload: bytes, tag: int, major: int = MAJOR, minor: int = MINOR) -> bytes:
    head = MAGIC + struct.pack("<HHB3xQI", major, minor, tag, len(payload), zlib.crc32(payload))
    return head + struct.pack("<I", zlib.crc32(head)) + payload


def write(model: dict, encoding: str, refinement: dict | None = None) -> bytes:
    """The canonical file of `model` in `encoding`: json, json-pretty, msgpack, binary, compact, structured or
    compressed (whose compressed bytes depend on the xz encoder: preset 6, CRC64, like the reference writer).

    With `refinement` ({"box": [lo0, hi0, ...], "cells": [c0, ...], "splits": [[a, b], ...], "kept": [bool per
    live slot]}, as `refinement_of` returns it), only in the structured encoding: the complex as `complexForm` 1
    (§7.4.3) instead of the canonical 0, after rebuilding it; ValueError unless it gives exactly the model's
    `vertices` (every bit, in order) and `simplices`."""
    check_writable(model)
    if refinement is not None:
        if encoding != "structured":
            raise ValueError("a refinement is written only in the structured encoding (complexForm 1)")
        (vertices, simplices), live = build_refinement(model["dimension"], refinement)
        if len(vertices) != len(model["vertices"]) or struct.pack(f"<{len(vertices)}d", *vertices) != struct.pack(f"<{len(vertices)}d", *model["vertices"]):
            raise ValueError("the refinement does not give the model's vertices bit for bit")
        if simplices != list(model["simplices"]):
            raise ValueError("the refinement does not give the model's simplices")
        return container(BinaryWriter(structured=True, refinement=refinement, live=live).model(model), 6)
    if encoding in ("json", "json-pretty"):
        return to_json(canonical_members(model), indent=2 if encoding == "json-pretty" else None).encode("utf-8")
    if encoding == "msgpack":
        out = bytearray()
        msgpack(canonical_members(model), out)
        return container(bytes(out), 2)
    if encoding == "binary":
        return container(BinaryWriter().model(model), 3)
    if encoding == "compact":
        return container(BinaryWriter(compact=True).model(model), 4)
    if encoding == "structured":
        return container(BinaryWriter(structured=True).model(model), 6)
    if encoding == "compressed":
        compact = BinaryWriter(compact=True).model(model)
        xz = lzma.compress(compact, format=lzma.FORMAT_XZ, check=lzma.CHECK_CRC64, preset=6)
        return container(struct.pack("<Q", len(compact)) + xz, 5)
    raise ValueError(f"unknown encoding {encoding}")


# ------------------------------------------------------------------------------------------ command line


def main(argv: list) -> int:
    if len(argv) >= 2 and argv[0] == "read":
        try:
            with open(argv[1], "rb") as f:
                read(f.read())
        except IsmError as e:
            print(json.dumps({"rule": e.rule, "location": e.location, "message": str(e)}))
            return 1
        print(json.dumps({"ok": True}))
        return 0
    if len(argv) >= 4 and argv[0] == "convert":
        try:
            with open(argv[1], "rb") as f:
                model = read(f.read())
            data = write(model, argv[3])
        except IsmError as e:
            print(json.dumps({"rule": e.rule, "location": e.location, "message": str(e)}))
            return 1
        with open(argv[2], "wb") as f:
            f.write(data)
        return 0
    print(__doc__, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
