"""The structured encoding's `complexForm` 1 (spec/ism-format.md §7.4.3, "The complex by its refinement") in ismpy,
the reader and writer written from the spec alone:

(a) a 2D example computed by hand from the spec's rules (grid ids and coordinates, the two slots of a square with
    the odd permutation's swap, one split of the diagonal, a kept mask, the renumbering), its payload written out
    byte by byte; the binary64 operation order of the grid coordinates and midpoints;
(b) 3D: the six slots of a cube listed by hand, and random refinements checked against a brute-force construction
    written differently here (orientation by the determinant instead of the permutation's parity, a scan of every
    slot per split, points instead of ids) and by geometry (every simplex positively oriented, conforming, the
    box's volume when everything is kept);
(c) round trips: form 1 -> model -> form 1 gives the same bytes (`refinement_of`, `write(..., refinement=)`); the
    writer refuses a refinement that does not give the model's complex bit for bit; `convert` writes form 0;
(d) every reader error of form 1 with the rule, pointer and file offset the spec gives, and the bound by the bytes
    present (a split sequence that would grow quadratically stops at the ⌈C/8⌉ rule, measured with tracemalloc);
    100k splits in seconds;
(e) differential: the Rust `ism` reads the same files to the same model (skipped when the binary is absent, set
    ISM_BIN).
"""

from __future__ import annotations

import math
import itertools
import json
import os
import random
import struct
import subprocess
import sys
import time
import tracemalloc
from fractions import Fraction
from pathlib import Path

import pytest

import ismpy
from test_structured import Payload, differences_from_the_reference, expect, mutants, varint

ROOT = Path(__file__).resolve().parents[2]
HEADER_LEN = ismpy.HEADER_LEN


def f64s(xs) -> bytes:
    return varint(len(xs)) + struct.pack(f"<{len(xs)}d", *xs)


def u32s(xs) -> bytes:
    return varint(len(xs)) + b"".join(varint(x) for x in xs)


def mask(bits) -> bytes:
    out = bytearray((len(bits) + 7) // 8)
    for i, bit in enumerate(bits):
        if bit:
            out[i // 8] |= 1 << (i % 8)
    return bytes(out)


def refined(n: int, box, cells, splits, kept: bytes, values=None, tail: bool = True, stages: bytes = b"\0", splits_bytes: bytes | None = None) -> Payload:
    """A payload with complexForm 1: `splits` a flat list of ids (or `splits_bytes` as they are)."""
    p = Payload()
    p.add("version", b"\x031.0").add("dimension", bytes([n])).add("metadata", b"\0\0\0\0").add("complexForm", b"\x01")
    p.add("box", f64s(box)).add("cells", u32s(cells))
    p.add("splits", u32s(splits) if splits_bytes is None else splits_bytes)
    p.add("kept", kept)
    if tail:
        p.add("values", f64s(values or [])).add("level", struct.pack("<d", 0.0)).add("stages", stages)
        p.add("model tail", b"\0\0\0\x04null")
    return p


def bits(xs) -> bytes:
    return struct.pack(f"<{len(xs)}d", *xs)


# ---------------------------------------------------------------- (a) a 2D example by hand
#
# box [0, 1] x [0, 1], cells [1, 1]. Grid ids (axis 0 fastest): 0 (0, 0), 1 (1, 0), 2 (0, 1), 3 (1, 1).
# One cube, lowest corner 0. Permutation 01 (even): 0, +axis 0 -> 1, +axis 1 -> 3: slot 0 = [0, 1, 3].
# Permutation 10 (odd): 0, +axis 1 -> 2, +axis 0 -> 3 = [0, 2, 3], last two swapped: slot 1 = [0, 3, 2].
# (Both positive: det((1,0),(1,1)) = 1, det((1,1),(0,1)) = 1.)
# Split (0, 3): m = 4 at ((0 + 1) * 0.5, (0 + 1) * 0.5) = (0.5, 0.5). Live slots containing 0 and 3: 0, then 1.
#   slot 0 [0, 1, 3] retired -> slot 2 [0, 1, 4] (3 replaced by 4), slot 3 [4, 1, 3] (0 replaced by 4);
#   slot 1 [0, 3, 2] retired -> slot 4 [0, 4, 2], slot 5 [4, 3, 2].
# Live slots: 2, 3, 4, 5 (C = 4): kept is 1 byte. Kept 0b1010: live slots 1 and 3, i.e. slots 3 and 5.
# Used vertices 1, 2, 3, 4 -> 0, 1, 2, 3: simplices [3, 0, 2], [3, 2, 1]; vertices (1,0) (0,1) (1,1) (0.5,0.5).

def from_listing(text: str) -> bytes:
    """The bytes of a listing: per line, hexadecimal bytes, then two spaces and what they are."""
    return bytes.fromhex("".join(line.strip().split("  ")[0] for line in text.strip().splitlines()))


EXAMPLE_2D = from_listing(
    """
    03 31 2e 30                   version "1.0"
    02                            dimension 2
    00 00 00 00                   metadata: no name, generator, units, description
    01                            complexForm 1
    04                            box: 4 numbers
    00 00 00 00 00 00 00 00       lo0 0.0
    00 00 00 00 00 00 f0 3f       hi0 1.0
    00 00 00 00 00 00 00 00       lo1 0.0
    00 00 00 00 00 00 f0 3f       hi1 1.0
    02 01 01                      cells: 2 numbers, 1, 1
    02 00 03                      splits: 2 ids, the pair (0, 3)
    0a                            kept: live slots 1 and 3 (bits 1 and 3)
    04                            values: 4 numbers
    00 00 00 00 00 00 f0 bf       -1.0
    00 00 00 00 00 00 f0 3f       1.0
    00 00 00 00 00 00 f0 3f       1.0
    00 00 00 00 00 00 e0 bf       -0.5
    00 00 00 00 00 00 00 00       level 0.0
    00                            stages: 0
    00 00 00                      extensionsUsed, extensionsRequired, extensions: empty
    04 6e 75 6c 6c                extras: "null"
    """
)
EXAMPLE_2D_VERTICES = [1.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.5, 0.5]
EXAMPLE_2D_SIMPLICES = [3, 0, 2, 3, 2, 1]


def test_the_2d_example_payload_is_its_parts():
    p = refined(2, [0.0, 1.0, 0.0, 1.0], [1, 1], [0, 3], b"\x0a", [-1.0, 1.0, 1.0, -0.5])
    assert bytes(p.b) == EXAMPLE_2D
    assert len(EXAMPLE_2D) == 4 + 1 + 4 + 1 + 33 + 3 + 3 + 1 + 33 + 8 + 1 + 3 + 5


def test_the_2d_example_decodes_to_the_hand_computed_complex():
    model = ismpy.read(ismpy.container(EXAMPLE_2D, 6))
    assert bits(model["vertices"]) == bits(EXAMPLE_2D_VERTICES)
    assert model["simplices"] == EXAMPLE_2D_SIMPLICES
    assert model["values"] == [-1.0, 1.0, 1.0, -0.5]
    assert ismpy.refinement_of(ismpy.container(EXAMPLE_2D, 6)) == {
        "box": [0.0, 1.0, 0.0, 1.0], "cells": [1, 1], "splits": [[0, 3]], "kept": [False, True, False, True]}


@pytest.mark.parametrize("kept, vertices, simplices", [
    # Every live slot: slots 2 [0,1,4], 3 [4,1,3], 4 [0,4,2], 5 [4,3,2]; all five vertices in id order.
    (0b1111, [0, 0, 1, 0, 0, 1, 1, 1, 0.5, 0.5], [0, 1, 4, 4, 1, 3, 0, 4, 2, 4, 3, 2]),
    # Slot 2 alone: vertices 0, 1, 4.
    (0b0001, [0, 0, 1, 0, 0.5, 0.5], [0, 1, 2]),
    # Slots 4 and 2 kept (bits 2 and 0), listed in slot order: [0,1,4], [0,4,2] -> vertices 0, 1, 2, 4.
    (0b0101, [0, 0, 1, 0, 0, 1, 0.5, 0.5], [0, 1, 3, 0, 3, 2]),
    # Slots 2, 4, 5: [0,1,4], [0,4,2], [4,3,2]; all five vertices.
    (0b1101, [0, 0, 1, 0, 0, 1, 1, 1, 0.5, 0.5], [0, 1, 4, 0, 4, 2, 4, 3, 2]),
    # Slots 4, 5: [0,4,2], [4,3,2]; vertices 0, 2, 3, 4 -> 0, 1, 2, 3.
    (0b1100, [0, 0, 0, 1, 1, 1, 0.5, 0.5], [0, 3, 1, 3, 2, 1]),
    # Nothing kept: an empty complex.
    (0b0000, [], []),
])
def test_the_2d_example_with_other_kept_masks(kept, vertices, simplices):
    values = [1.0] * (len(vertices) // 2)
    model, _ = ismpy.decode(refined(2, [0.0, 1.0, 0.0, 1.0], [1, 1], [0, 3], bytes([kept]), values).file())
    assert bits(model["vertices"]) == bits([float(x) for x in vertices])
    assert model["simplices"] == simplices


def test_the_grid_without_splits_is_the_two_slots():
    # Slots [0, 1, 3] and [0, 3, 2], both kept: the odd permutation's slot has its last two vertices swapped.
    model = ismpy.read(refined(2, [0.0, 1.0, 0.0, 1.0], [1, 1], [], b"\x03", [1.0] * 4).file())
    assert model["simplices"] == [0, 1, 3, 0, 3, 2]
    assert model["vertices"] == [0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 1.0, 1.0]


def test_two_cubes_are_in_the_order_of_their_lowest_corners():
    # cells [2, 1]: ids 0 (0,0) 1 (1,0) 2 (2,0) 3 (0,1) 4 (1,1) 5 (2,1). Cube at 0: [0,1,4], [0,4,3]; cube at 1:
    # [1,2,5], [1,5,4]. Keep slots 1 and 2: [0,4,3], [1,2,5] -> vertices 0 1 2 3 4 5 all used.
    model = ismpy.read(refined(2, [0.0, 2.0, 0.0, 1.0], [2, 1], [], b"\x06", [1.0] * 6).file())
    assert model["simplices"] == [0, 4, 3, 1, 2, 5]
    assert model["vertices"] == [0.0, 0.0, 1.0, 0.0, 2.0, 0.0, 0.0, 1.0, 1.0, 1.0, 2.0, 1.0]


def test_grid_coordinates_and_midpoints_in_binary64_operation_order():
    # Axis 0: lo -0.7, hi 0.3, 7 cells: x_i = -0.7 + i * ((0.3 - -0.7) / 7), and 0.3 itself at i = 7. Axis 1:
    # lo -1, hi 2, 1 cell. Chosen so that each rule decides some bits:
    lo, hi, c = -0.7, 0.3, 7
    step = (hi - lo) / c
    xs = [lo + i * step for i in range(c)] + [hi]
    assert lo + c * step != hi  # "hi exactly at i = c"
    assert any(lo + i * step != lo + (i * (hi - lo)) / c for i in range(c))  # the quotient first
    grid = [(x, y) for y in (-1.0, 2.0) for x in xs]  # ids 0..15, axis 0 fastest
    # Slots: cube i (lowest corner id i) gives 2i = [i, i+1, i+9] and 2i+1 = [i, i+9, i+8]. Split (3, 12), m = 16:
    # slots 6 [3,4,12] and 7 [3,12,11] retired; 14 [3,4,16], 15 [16,4,12], 16 [3,16,11], 17 [16,12,11].
    m = ((xs[3] + xs[4]) * 0.5, (-1.0 + 2.0) * 0.5)
    slots = [[i, i + 1, i + 9, i, i + 9, i + 8] for i in range(7)]
    expected_simplices = [v for i, pair in enumerate(slots) if i != 3 for v in pair]
    expected_simplices += [3, 4, 16, 16, 4, 12, 3, 16, 11, 16, 12, 11]
    model = ismpy.read(refined(2, [lo, hi, -1.0, 2.0], [c, 1], [3, 12], b"\xff\xff", [1.0] * 17).file())
    assert bits(model["vertices"]) == bits([v for point in grid + [m] for v in point])
    assert model["simplices"] == expected_simplices


# ---------------------------------------------------------------- (b) 3D: by hand, and a brute force written differently

# The unit cube: ids 0 (0,0,0) 1 (1,0,0) 2 (0,1,0) 3 (1,1,0) 4 (0,0,1) 5 (1,0,1) 6 (0,1,1) 7 (1,1,1).
# Permutations 012 (even) 0-1-3-7; 021 (odd) 0-1-5-7 -> 0,1,7,5; 102 (odd) 0-2-3-7 -> 0,2,7,3; 120 (even) 0-2-6-7;
# 201 (even) 0-4-5-7; 210 (odd) 0-4-6-7 -> 0,4,7,6.
CUBE_SLOTS = [0, 1, 3, 7, 0, 1, 7, 5, 0, 2, 7, 3, 0, 2, 6, 7, 0, 4, 5, 7, 0, 4, 7, 6]


def test_the_six_slots_of_a_cube():
    model = ismpy.read(refined(3, [0.0, 1.0, 0.0, 1.0, 0.0, 1.0], [1, 1, 1], [], b"\x3f", [1.0] * 8).file())
    assert model["simplices"] == CUBE_SLOTS
    assert model["vertices"] == [float(v) for i in range(8) for v in (i & 1, i >> 1 & 1, i >> 2 & 1)]


def det3(p, q, r, s) -> Fraction:
    a = [Fraction(q[k]) - Fraction(p[k]) for k in range(3)]
    b = [Fraction(r[k]) - Fraction(p[k]) for k in range(3)]
    c = [Fraction(s[k]) - Fraction(p[k]) for k in range(3)]
    return a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0]) + a[2] * (b[0] * c[1] - b[1] * c[0])


class BruteForce3D:
    """§7.4.3's construction in 3D written another way: points by their index triples and a dict id -> point,
    each cube's six monotone paths put in positive orientation by the sign of their determinant (not by the
    permutation's parity), and each split scanning every slot."""

    def __init__(self, box, cells):
        self.points = {}
        nx, ny, nz = cells
        for k in range(nz + 1):
            for j in range(ny + 1):
                for i in range(nx + 1):
                    ident = i + (nx + 1) * (j + (ny + 1) * k)
                    point = []
                    for axis, index in enumerate((i, j, k)):
                        lo, hi, c = box[2 * axis], box[2 * axis + 1], cells[axis]
                        point.append(hi if index == c else lo + index * ((hi - lo) / c))
                    self.points[ident] = tuple(point)
        self.grid = len(self.points)
        self.slots = []  # [simplex or None]
        ident = lambda i, j, k: i + (nx + 1) * (j + (ny + 1) * k)
        for k in range(nz):
            for j in range(ny):
                for i in range(nx):
                    for order in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
                        at = [i, j, k]
                        path = [ident(*at)]
                        for axis in order:
                            at[axis] += 1
                            path.append(ident(*at))
                        if det3(*(self.points[v] for v in path)) < 0:
                            path[2], path[3] = path[3], path[2]
                        self.slots.append(path)

    def live(self):
        return [s for s in self.slots if s is not None]

    def split(self, a, b):
        m = len(self.points)
        pa, pb = self.points[a], self.points[b]
        self.points[m] = tuple((x + y) * 0.5 for x, y in zip(pa, pb))
        hit = [i for i, s in enumerate(self.slots) if s is not None and a in s and b in s]
        assert hit
        for i in hit:
            s = self.slots[i]
            self.slots[i] = None
            self.slots.append([m if v == b else v for v in s])
            self.slots.append([m if v == a else v for v in s])

    def model(self, kept):
        chosen = [s for s, keep in zip(self.live(), kept) if keep]
        used = sorted(set(v for s in chosen for v in s))
        new = {v: i for i, v in enumerate(used)}
        return [x for v in used for x in self.points[v]], [new[v] for s in chosen for v in s]


def random_refinement_3d(seed: int, box, cells, count: int):
    rnd = random.Random(seed)
    brute = BruteForce3D(box, cells)
    splits = []
    for _ in range(count):
        s = rnd.choice(brute.live())
        a, b = sorted(rnd.sample(s, 2))
        brute.split(a, b)
        splits.append((a, b))
    return brute, splits


def check_geometry(vertices, simplices, box, whole: bool):
    """Every simplex positively oriented, every triangle in at most two tetrahedra (in exactly two unless it lies
    on the box's boundary, when everything is kept), and the volumes summing to the box's."""
    point = lambda v: vertices[3 * v : 3 * v + 3]
    volume = Fraction(0)
    facets = {}
    for t in range(len(simplices) // 4):
        ids = simplices[4 * t : 4 * t + 4]
        d = det3(*(point(v) for v in ids))
        assert d > 0, f"simplex {t} {ids} is not positively oriented"
        volume += d / 6
        for facet in itertools.combinations(sorted(ids), 3):
            facets[facet] = facets.get(facet, 0) + 1
    assert max(facets.values()) <= 2
    if whole:
        box_volume = Fraction(1)
        for k in range(3):
            box_volume *= Fraction(box[2 * k + 1]) - Fraction(box[2 * k])
        assert volume == box_volume
        for facet, count in facets.items():
            if count == 1:
                on = [all(point(v)[k] == box[2 * k + side] for v in facet) for k in range(3) for side in (0, 1)]
                assert any(on), f"the facet {facet} is in one simplex inside the box"


@pytest.mark.parametrize("seed", range(4))
def test_random_3d_refinements_match_the_brute_force(seed):
    box = [-1.0, 3.0, 0.0, 2.0, 0.5, 1.5]  # steps 1, 1, 0.5: exact coordinates, so Fraction geometry is exact
    cells = [4, 2, 2]
    brute, splits = random_refinement_3d(seed, box, cells, 60)
    live = len(brute.live())
    rnd = random.Random(100 + seed)
    for kept in ([True] * live, [rnd.random() < 0.5 for _ in range(live)]):
        vertices, simplices = brute.model(kept)
        p = refined(3, box, cells, [x for pair in splits for x in pair], mask(kept), [1.0] * (len(vertices) // 3))
        model, _ = ismpy.decode(p.file())
        assert bits(model["vertices"]) == bits(vertices)
        assert model["simplices"] == simplices
        check_geometry(model["vertices"], model["simplices"], box, whole=all(kept))


def test_bisections_with_non_dyadic_coordinates_match_the_brute_force():
    box = [0.1, 0.7, -0.3, 0.2, 1.0, 1.0 + 1e-9]
    cells = [3, 5, 2]
    brute, splits = random_refinement_3d(7, box, cells, 40)
    kept = [True] * len(brute.live())
    vertices, simplices = brute.model(kept)
    model, _ = ismpy.decode(refined(3, box, cells, [x for pair in splits for x in pair], mask(kept), [1.0] * (len(vertices) // 3)).file())
    assert bits(model["vertices"]) == bits(vertices)
    assert model["simplices"] == simplices


# ---------------------------------------------------------------- (c) round trips and the writer


def a_stage_on(model: dict) -> dict:
    """A degree-2 Bézier stage with a record on the first edge of the complex (recordForm 1 on the way out)."""
    edge = ismpy.complex_faces(model["simplices"], model["dimension"], 1)[0]
    return {"kind": "bezier", "degree": 2, "direction": "implicit", "name": None, "faces": [{"face": list(edge), "points": [0.5, 0.5], "weights": []}], "vertexMaps": [], "extras": None}


def test_form_1_round_trips_to_the_same_bytes():
    data = ismpy.container(EXAMPLE_2D, 6)
    model = ismpy.read(data)
    assert ismpy.write(model, "structured", refinement=ismpy.refinement_of(data)) == data
    # The canonical writer keeps complexForm 0, and its file reads to the same model.
    canonical = ismpy.write(model, "structured")
    assert canonical[HEADER_LEN + 9] == 0 and canonical != data
    assert ismpy.BinaryWriter().model(ismpy.read(canonical)) == ismpy.BinaryWriter().model(model)


@pytest.mark.parametrize("seed", range(3))
def test_random_3d_form_1_files_round_trip(seed):
    box = [-1.0, 3.0, 0.0, 2.0, 0.5, 1.5]
    brute, splits = random_refinement_3d(seed, box, [4, 2, 2], 50)
    kept = [i % 3 != 1 for i in range(len(brute.live()))]
    vertices, _ = brute.model(kept)
    data = refined(3, box, [4, 2, 2], [x for pair in splits for x in pair], mask(kept), [float(i % 5 - 2) or 0.5 for i in range(len(vertices) // 3)]).file()
    model = ismpy.read(data)
    model["stages"] = [a_stage_on(model)]
    with_stage = ismpy.write(model, "structured", refinement=ismpy.refinement_of(data))
    assert ismpy.refinement_of(with_stage) == ismpy.refinement_of(data)
    back = ismpy.read(with_stage)
    assert ismpy.BinaryWriter().model(back) == ismpy.BinaryWriter().model(model)
    assert ismpy.write(back, "structured", refinement=ismpy.refinement_of(with_stage)) == with_stage


def test_refinement_of_other_files_is_none():
    model = ismpy.read(ismpy.container(EXAMPLE_2D, 6))
    for encoding in ("structured", "compact", "binary", "json"):
        assert ismpy.refinement_of(ismpy.write(model, encoding)) is None


def example_refinement() -> dict:
    return {"box": [0.0, 1.0, 0.0, 1.0], "cells": [1, 1], "splits": [[0, 3]], "kept": [False, True, False, True]}


@pytest.mark.parametrize("change, message", [
    (lambda m, r: m["vertices"].__setitem__(6, 0.5000000000000001), "vertices"),
    (lambda m, r: m["vertices"].__setitem__(1, -0.0), "vertices"),  # 0.0 == -0.0, but not bit for bit
    (lambda m, r: m["vertices"].extend([0.0, 0.0]), "vertices"),
    (lambda m, r: m["simplices"].reverse(), "simplices"),
    (lambda m, r: r.__setitem__("kept", [True, True, False, True]), "vertices"),
    (lambda m, r: r.__setitem__("kept", [False, True, False]), "kept"),
    (lambda m, r: r.__setitem__("splits", [[3, 0]]), "split 0"),
    (lambda m, r: r.__setitem__("splits", [[1, 2]]), "split 0"),
    (lambda m, r: r.__setitem__("box", [0.0, 1.0, 1.0, 1.0]), "box"),
    (lambda m, r: r.__setitem__("box", [0.0, 1.0, 0.0]), "box"),
    (lambda m, r: r.__setitem__("cells", [1, 0]), "cell"),
    (lambda m, r: r.__setitem__("cells", [1 << 31, 1]), r"2\^32"),
    (lambda m, r: m.__setitem__("dimension", 4), "dimension"),
])
def test_the_writer_refuses_a_refinement_that_does_not_give_the_model(change, message):
    data = ismpy.container(EXAMPLE_2D, 6)
    model = ismpy.read(data)
    refinement = example_refinement()
    change(model, refinement)
    with pytest.raises(ValueError, match=message):
        ismpy.write(model, "structured", refinement=refinement)


def test_a_refinement_only_in_the_structured_encoding():
    model = ismpy.read(ismpy.container(EXAMPLE_2D, 6))
    with pytest.raises(ValueError):
        ismpy.write(model, "compact", refinement=example_refinement())


def test_convert_writes_form_0(tmp_path):
    source = tmp_path / "in.isms"
    source.write_bytes(ismpy.container(EXAMPLE_2D, 6))
    target = tmp_path / "out.isms"
    done = subprocess.run([sys.executable, str(Path(ismpy.__file__)), "convert", str(source), str(target), "structured"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    assert target.read_bytes()[HEADER_LEN + 9] == 0
    assert ismpy.refinement_of(target.read_bytes()) is None
    assert ismpy.read(target.read_bytes())["simplices"] == EXAMPLE_2D_SIMPLICES


# ---------------------------------------------------------------- (d) reader errors


def example(**changes) -> Payload:
    args = dict(n=2, box=[0.0, 1.0, 0.0, 1.0], cells=[1, 1], splits=[0, 3], kept=b"\x0a", values=[-1.0, 1.0, 1.0, -0.5])
    args.update(changes)
    return refined(**args)


def test_the_example_reads():
    assert ismpy.read(example().file())["simplices"] == EXAMPLE_2D_SIMPLICES


@pytest.mark.parametrize("dimension", [0, 1, 4, 15])
def test_form_1_outside_2d_and_3d(dimension):
    p = example(n=dimension)
    expect(p.file(), "/vertices", p.at["complexForm"])


@pytest.mark.parametrize("box", [
    [0.0, 1.0, 0.0],  # 2n - 1 numbers
    [0.0, 1.0, 0.0, 1.0, 0.0, 1.0],  # 2n + 2
    [],
    [float("nan"), 1.0, 0.0, 1.0],
    [0.0, float("inf"), 0.0, 1.0],
    [0.0, 1.0, float("-inf"), 1.0],
    [0.0, 1.0, 1.0, 1.0],  # lo = hi
    [1.0, 0.0, 0.0, 1.0],  # lo > hi
    [0.0, 1.0, -1.5e308, 1.5e308],  # hi - lo overflows
])
def test_box_errors_at_its_first_byte(box):
    p = example(box=box)
    expect(p.file(), "/vertices", p.at["box"])


def test_a_box_longer_than_the_payload_at_its_length():
    p = Payload().add("head", b"\x031.0\x02\0\0\0\0\x01").add("box", b"\x05" + bytes(32))
    expect(p.file(), "/vertices", p.at["box"])


@pytest.mark.parametrize("cells", [[1], [1, 1, 1], [], [0, 1], [1, 0]])
def test_cells_errors_at_its_first_byte(cells):
    p = example(cells=cells)
    expect(p.file(), "/vertices", p.at["cells"])


def test_a_cell_count_not_minimal_at_its_byte():
    p = example()
    data = bytearray(p.b)
    at = p.at["cells"] - HEADER_LEN
    data[at : at + 3] = b"\x02\x01\xfb\x01\x00"
    expect(ismpy.container(bytes(data), 6), "/vertices", p.at["cells"] + 2)


def test_the_grid_cells_need_their_kept_bytes_before_the_grid_is_built():
    # cells [100, 100]: C0 = 2 * 10000, kept needs 2500 bytes. Right after cells the payload must hold them
    # (here: splits' one-byte length, then `after` bytes); the mask itself then needs them after splits.
    for after, where in ((2498, "cells"), (2499, "kept"), (2500, None)):
        p = refined(2, [0.0, 1.0, 0.0, 1.0], [100, 100], [], bytes(after), tail=False)
        if where == "cells":
            expect(p.file(), "/vertices", p.at["cells"])
        elif where == "kept":
            expect(p.file(), "/simplices", p.at["kept"])
        else:
            # The mask is there (all zero): the model ends at values, missing.
            expect(p.file(), "/values", HEADER_LEN + len(p.b))
    # A huge grid in a small file: refused at cells, nothing allocated.
    p = refined(3, [0.0, 1.0] * 3, [1 << 31, 1 << 31, 1 << 31], [], bytes(100))
    tracemalloc.start()
    expect(p.file(), "/vertices", p.at["cells"])
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 1 << 20


def test_the_kept_bytes_are_counted_after_splits():
    # Two splits take 5 bytes after cells, enough for the grid's 1-byte mask; but after the first split the 4 live
    # slots need 1 byte after splits, and nothing follows: refused at that pair (its first byte, after the length).
    p = refined(2, [0.0, 1.0, 0.0, 1.0], [1, 1], [0, 3, 0, 4], b"", tail=False)
    expect(p.file(), "/simplices", p.at["splits"] + 1)


def test_a_grid_of_2_to_the_32_vertices_is_ism_007():
    # cells [2^31 - 1, 1]: (2^31) * 2 = 2^32 grid vertices, C0 = 2^32 - 2 slots; the kept mask's 2^29 bytes are
    # present, so the bytes check passes and the vertex count is refused, before anything is built. The
    # decoder runs on the payload itself (a container would copy its 512 MiB twice).
    cells = [(1 << 31) - 1, 1]
    head = refined(2, [0.0, 1.0, 0.0, 1.0], cells, [], b"", tail=False)
    payload = bytes(head.b) + bytes(((1 << 32) - 2 + 7) // 8)
    with pytest.raises(ismpy.IsmError) as error:
        ismpy.BinaryDecoder(payload, HEADER_LEN, structured=True).model(allow_trailing=False)
    del payload
    assert (error.value.rule, error.value.location) == ("ISM-007", {"pointer": "/vertices", "offset": head.at["cells"]})


def test_a_large_grid_below_the_limit_is_refused_by_the_bytes():
    # The same grid with one byte missing: ISM-006 at cells (the bytes come first).
    p = refined(2, [0.0, 1.0, 0.0, 1.0], [(1 << 31) - 1, 1], [], bytes(1000))
    expect(p.file(), "/vertices", p.at["cells"])


@pytest.mark.parametrize("count", [1, 3])
def test_an_odd_splits_length_at_its_length(count):
    p = example(splits_bytes=varint(count) + b"\x00\x03\x01")
    expect(p.file(), "/simplices", p.at["splits"])


def test_splits_longer_than_the_payload_at_its_length():
    p = refined(2, [0.0, 1.0, 0.0, 1.0], [1, 1], [], b"", tail=False, splits_bytes=b"\x08\x00\x03")
    expect(p.file(), "/simplices", p.at["splits"])


def test_a_split_id_not_minimal_at_its_byte():
    p = example(splits_bytes=b"\x02\x00\xfb\x03\x00")
    expect(p.file(), "/simplices", p.at["splits"] + 2)


def test_a_split_id_of_253_at_its_byte():
    p = example(splits_bytes=b"\x02\x00\xfd" + bytes(8))
    expect(p.file(), "/simplices", p.at["splits"] + 2)


@pytest.mark.parametrize("pairs, bad", [
    ([(3, 0)], 0),  # a > b
    ([(3, 3)], 0),  # a = b
    ([(0, 5)], 0),  # 5 does not exist yet (the first midpoint is 4)
    ([(0, 4)], 0),  # nor does 4
    ([(1, 2)], 0),  # both exist, no slot holds both
    ([(0, 3), (0, 3)], 1),  # the edge is gone after its split
    ([(0, 3), (1, 2)], 1),
    ([(0, 3), (0, 4), (4, 1)], 2),  # after two good splits, a > b
    ([(0, 1 << 20)], 0),
])
def test_a_bad_pair_at_its_first_byte(pairs, bad):
    flat = [x for pair in pairs for x in pair]
    p = example(splits=flat, kept=b"\0\0\0")
    at = p.at["splits"] + len(varint(len(flat))) + sum(len(varint(x)) for x in flat[: 2 * bad])
    expect(p.file(), "/simplices", at)


def test_splits_through_midpoints_by_hand():
    # (0,3) -> 4: slot 0 [0,1,3] -> 2 [0,1,4], 3 [4,1,3]; slot 1 [0,3,2] -> 4 [0,4,2], 5 [4,3,2].
    # (0,4) -> 5: slots 2, 4: 2 -> 6 [0,1,5], 7 [5,1,4]; 4 -> 8 [0,5,2], 9 [5,4,2].
    # (0,1) -> 6: slot 6 only (slot 3 [4,1,3] lacks 0): 10 [0,6,5], 11 [6,1,5].
    # (1,6) -> 7: slot 11 [6,1,5], a = 1, b = 6: 12 [7,1,5] (b replaced), 13 [6,7,5] (a replaced).
    # Live: 3 5 7 8 9 10 12 13, all kept; every vertex 0..7 used, so no renumbering.
    p = example(splits=[0, 3, 0, 4, 0, 1, 1, 6], kept=b"\xff", values=[1.0] * 8)
    model = ismpy.read(p.file())
    assert model["simplices"] == [4, 1, 3, 4, 3, 2, 5, 1, 4, 0, 5, 2, 5, 4, 2, 0, 6, 5, 7, 1, 5, 6, 7, 5]
    assert model["vertices"] == [0, 0, 1, 0, 0, 1, 1, 1, 0.5, 0.5, 0.25, 0.25, 0.5, 0, 0.75, 0]


def test_kept_padding_bits_at_their_byte():
    # C = 4 live slots: bits 4..7 of the one byte must be zero.
    for byte in (0x10, 0x80, 0xFA):
        p = example(kept=bytes([byte]))
        expect(p.file(), "/simplices", p.at["kept"])
    # C = 12 (a 3 x 1 grid's 6 slots, three diagonals split): two bytes, padding bits in the second.
    p = refined(2, [0.0, 3.0, 0.0, 1.0], [3, 1], [0, 5, 1, 6, 2, 7], b"\xff\x1f", [1.0] * 11)
    expect(p.file(), "/simplices", p.at["kept"] + 1)
    p = refined(2, [0.0, 3.0, 0.0, 1.0], [3, 1], [0, 5, 1, 6, 2, 7], b"\xff\x0f", [1.0] * 11)
    assert len(ismpy.read(p.file())["simplices"]) == 3 * 12


def quadratic_splits(ring: int, axis: int):
    """Splits of the unit cube that grow the slots quadratically: `ring` splits (1, 3), (1, 8), (1, 9), ... each
    add one tetrahedron around the diagonal (0, 7) (the edge (1, m) lies on one slot, [0, 1, m, 7]); then the
    diagonal's splits (0, 7), (0, M), (0, M + 1), ... each retire the 6 + ring tetrahedra around it and add
    twice as many. Returns the pairs and the number of live slots after each."""
    pairs = [(1, 3)] + [(1, 8 + i) for i in range(ring - 1)]
    live = [6 + i + 1 for i in range(ring)]
    first = 8 + ring
    pairs += [(0, 7)] + [(0, first + i) for i in range(axis - 1)]
    live += [live[ring - 1] + (6 + ring) * (i + 1) for i in range(axis)]
    return pairs, live


def test_the_quadratic_split_sequence_is_what_it_says():
    pairs, live = quadratic_splits(5, 4)
    brute = BruteForce3D([0.0, 1.0] * 3, [1, 1, 1])
    for (a, b), count in zip(pairs, live):
        brute.split(a, b)
        assert len(brute.live()) == count


def test_a_quadratic_split_sequence_stops_at_the_bound():
    # 300 ring splits, then 3000 on the diagonal: unbounded, 306 + 3000 * 306 ~ 920 000 slots. With 500 bytes
    # after splits, C may reach 4000: the first split past it is refused, having built at most that many slots.
    pairs, live = quadratic_splits(300, 3000)
    after = 500
    bad = next(i for i, c in enumerate(live) if (c + 7) // 8 > after)
    assert bad > 300 and live[-1] > 900_000
    flat = [x for pair in pairs for x in pair]
    p = refined(3, [0.0, 1.0] * 3, [1, 1, 1], flat, bytes(after), tail=False)
    at = p.at["splits"] + len(varint(len(flat))) + sum(len(varint(x)) for x in flat[: 2 * bad])
    data = p.file()
    tracemalloc.start()
    start = time.perf_counter()
    expect(data, "/simplices", at)
    elapsed = time.perf_counter() - start
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 16 << 20, f"{peak} bytes"
    assert elapsed < 10
    # One byte more after splits and that split passes (it is the next one that fails, if any).
    p = refined(3, [0.0, 1.0] * 3, [1, 1, 1], flat[: 2 * (bad + 1)], bytes((live[bad] + 7) // 8), tail=False)
    expect(p.file(), "/values", HEADER_LEN + len(p.b))


def test_100k_splits_in_seconds():
    # 2D, a 16 x 16 grid, 100 000 bisections of the longest edge of random live slots (chosen with ismpy's own
    # construction, which only picks them: the file is then read back from bytes).
    rnd = random.Random(5)
    box, cells = [0.0, 1.0, 0.0, 1.0], [16, 16]
    grid = ismpy.KuhnRefinement(2, box, cells)
    splits = []
    while len(splits) < 100_000:
        s = rnd.randrange(len(grid.slots))
        simplex = grid.slots[s]
        if simplex is None:
            continue
        points = [grid.coordinates(v) for v in simplex]
        longest = max(itertools.combinations(range(3), 2), key=lambda e: (points[e[0]][0] - points[e[1]][0]) ** 2 + (points[e[0]][1] - points[e[1]][1]) ** 2)
        a, b = sorted(simplex[i] for i in longest)
        grid.split(len(splits), a, b)
        splits.append((a, b))
    live = len(grid.live_slots())
    kept = [True] * live
    used = (cells[0] + 1) * (cells[1] + 1) + len(splits)
    data = refined(2, box, cells, [x for pair in splits for x in pair], mask(kept), [1.0] * used).file()
    start = time.perf_counter()
    model, _ = ismpy.decode(data)
    elapsed = time.perf_counter() - start
    assert len(model["simplices"]) == 3 * live and len(model["vertices"]) == 2 * used
    assert elapsed < 20, f"{elapsed:.1f} s"
    # Area: every triangle positive, the unit square's area in all (exact: the coordinates are dyadic).
    v, t = model["vertices"], model["simplices"]
    area = Fraction(0)
    for i in range(0, len(t), 3):
        (x0, y0), (x1, y1), (x2, y2) = ((Fraction(v[2 * j]), Fraction(v[2 * j + 1])) for j in t[i : i + 3])
        d = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
        assert d > 0
        area += d / 2
    assert area == 1
    start = time.perf_counter()
    again = ismpy.write(model, "structured", refinement=ismpy.refinement_of(data))
    assert again == data
    assert time.perf_counter() - start < 30


# ---------------------------------------------------------------- (e) differential, against the Rust `ism`


def ism_bin() -> str:
    path = os.environ.get("ISM_BIN") or str(ROOT / "target" / "debug" / "ism")
    if not Path(path).is_file():
        pytest.skip(f"the Rust `ism` binary is absent ({path}): build it with `cargo build -p ism-cli` or set ISM_BIN")
    return path


def differential_files() -> dict:
    files = {"example-2d": ismpy.container(EXAMPLE_2D, 6)}
    box = [-1.0, 3.0, 0.0, 2.0, 0.5, 1.5]
    for seed in range(3):
        brute, splits = random_refinement_3d(seed, box, [4, 2, 2], 50)
        kept = [i % 4 != 1 for i in range(len(brute.live()))]
        vertices, _ = brute.model(kept)
        files[f"random-3d-{seed}"] = refined(3, box, [4, 2, 2], [x for pair in splits for x in pair], mask(kept), [float(i % 3 - 1) or 0.5 for i in range(len(vertices) // 3)]).file()
    box = [0.1, 0.7, -0.3, 0.2, 1.0, 1.0 + 1e-9]
    brute, splits = random_refinement_3d(7, box, [3, 5, 2], 40)
    kept = [True] * len(brute.live())
    vertices, _ = brute.model(kept)
    files["non-dyadic-3d"] = refined(3, box, [3, 5, 2], [x for pair in splits for x in pair], mask(kept), [1.0] * (len(vertices) // 3)).file()
    return files


def test_the_reference_reads_form_1_to_the_same_model(tmp_path):
    binary = ism_bin()
    for name, data in differential_files().items():
        source = tmp_path / f"{name}.isms"
        source.write_bytes(data)
        target = tmp_path / f"{name}.ismb"
        done = subprocess.run([binary, "convert", str(source), str(target)], capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stdout + done.stderr
        assert target.read_bytes() == ismpy.write(ismpy.read(data), "binary"), name


def form_1_reader_cases() -> dict:
    """Files of each form-1 reader error above (and some that read), by name."""
    cases = dict(differential_files())
    cases["dimension-4"] = example(n=4).file()
    cases["box-short"] = example(box=[0.0, 1.0, 0.0]).file()
    cases["box-nan"] = example(box=[float("nan"), 1.0, 0.0, 1.0]).file()
    cases["box-lo-equals-hi"] = example(box=[0.0, 1.0, 1.0, 1.0]).file()
    cases["box-extent-overflows"] = example(box=[0.0, 1.0, -1.5e308, 1.5e308]).file()
    cases["cells-three"] = example(cells=[1, 1, 1]).file()
    cases["cells-zero"] = example(cells=[1, 0]).file()
    cases["cells-not-minimal"] = example(cells=[1, 1]).file().replace(b"\x02\x01\x01\x02\x00\x03", b"\x02\x01\xfb\x01\x00\x02\x00\x03")
    cases["cells-not-minimal"] = ismpy.container(cases["cells-not-minimal"][HEADER_LEN:], 6)
    cases["kept-bytes-missing"] = refined(2, [0.0, 1.0, 0.0, 1.0], [100, 100], [], bytes(2499), tail=False).file()
    cases["kept-bytes-present"] = refined(2, [0.0, 1.0, 0.0, 1.0], [100, 100], [], bytes(2500), tail=False).file()
    cases["huge-grid-few-bytes"] = refined(3, [0.0, 1.0] * 3, [1 << 31, 1 << 31, 1 << 31], [], bytes(100)).file()
    cases["splits-odd"] = example(splits_bytes=b"\x03\x00\x03\x01").file()
    cases["split-not-minimal"] = example(splits_bytes=b"\x02\x00\xfb\x03\x00").file()
    for name, pairs in {"a-above-b": [3, 0], "a-equals-b": [3, 3], "unknown-id": [0, 5], "no-common-slot": [1, 2], "edge-gone": [0, 3, 0, 3]}.items():
        cases[f"pair-{name}"] = example(splits=pairs, kept=b"\0\0\0").file()
    cases["kept-padding"] = example(kept=b"\x1a").file()
    cases["kept-padding-second-byte"] = refined(2, [0.0, 3.0, 0.0, 1.0], [3, 1], [0, 5, 1, 6, 2, 7], b"\xff\x1f", [1.0] * 11).file()
    cases["by-hand-midpoints"] = example(splits=[0, 3, 0, 4, 0, 1, 1, 6], kept=b"\xff", values=[1.0] * 8).file()
    pairs, live = quadratic_splits(300, 3000)
    cases["quadratic-bound"] = refined(3, [0.0, 1.0] * 3, [1, 1, 1], [x for pair in pairs for x in pair], bytes(500), tail=False).file()
    return cases


def test_form_1_reader_cases_are_what_the_reference_reports(tmp_path):
    differ = differences_from_the_reference(form_1_reader_cases(), tmp_path)
    assert not differ, "\n".join(differ)


def mutated_form_1_files(count: int, seed: int = 29) -> list[bytes]:
    """Mutants of the form-1 cases above (not the three large ones)."""
    seeds = [data for name, data in form_1_reader_cases().items() if name not in ("quadratic-bound", "kept-bytes-present", "kept-bytes-missing")]
    return mutants(seeds, count, seed)


def test_mutated_form_1_files_read_or_fail_with_a_rule():
    # No mutation makes the reader fail other than with a rule of §9 (no KeyError, IndexError, MemoryError ...),
    # and none takes long or much memory.
    tracemalloc.start()
    start = time.perf_counter()
    rules = {}
    for data in mutated_form_1_files(1000):
        try:
            ismpy.read(data)
            rules["ok"] = rules.get("ok", 0) + 1
        except ismpy.IsmError as e:
            rules[e.rule] = rules.get(e.rule, 0) + 1
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert time.perf_counter() - start < 120
    assert peak < 64 << 20
    assert rules.get("ISM-006", 0) > 100 and rules.get("ok", 0) > 10, rules


def test_a_box_whose_midpoints_could_overflow_is_refused_at_box():
    # (x_a + x_b) * 0.5 would overflow when both coordinates are near the largest float although hi - lo is
    # finite: §7.4.3 asks 2 lo and 2 hi finite, so such a box is ISM-006 at `box` and no coordinate is infinite.
    p = refined(2, [1e308, 1.7e308, 0.0, 1.0], [1, 1], [1, 3], b"\x07", [1.0] * 5)
    expect(p.file(), "/vertices", p.at["box"])
    # Just inside: 2 hi finite.
    p = refined(2, [0.8e308, 0.85e308, 0.0, 1.0], [1, 1], [1, 3], b"\x07", [1.0] * 5)
    model, _ = ismpy.decode(p.file())
    assert all(math.isfinite(x) for x in model["vertices"])


def test_mutated_form_1_files_read_alike(tmp_path):
    # Every mutated form-1 file: accepted by both, or the same first rule at the same location.
    named = {f"mutant {i}": data for i, data in enumerate(mutated_form_1_files(1500))}
    differ = differences_from_the_reference(named, tmp_path)
    assert not differ, f"{len(differ)} of {len(named)} differ:\n" + "\n".join(differ[:10])