"""A generated corpus for the corpus pipeline (`python -m ism.batch`): its tests and its benchmark.

`make_corpus(folder)` writes, in one flat folder (so an item's id is its file name):

- good models: every spec example, in each variant translated by a vector and with its values
  scaled by a positive factor (the shape moves, validity is unchanged: stages are barycentric and
  the level scales with the values), written in rotating encodings (JSON, MessagePack, binary);
- good meshes: small closed ellipsoids (OBJ), fitted by the pipeline as `ism fit --mesh` does;
- bad inputs with what must be reported, known by construction: corrupt files (truncated, random
  bytes, cut JSON, empty), the reader vectors with huge declared lengths and a bit flip (their
  rule from `spec/vectors/reader/*.expect.json`), a complex with a facet shared by three
  simplices, a model whose stage folds (`validate` says invalid), a non-manifold mesh and an open
  mesh (both refused by the fit).

Returns a dict: `good` (ids), `meshes` (good mesh ids), `bad` {id: {"step", "rule"}} (rule None
where the input is not an ISM file) and `files` (all paths).

    python tools/batch_corpus.py OUT_FOLDER [VARIANTS] [MESHES]
"""

from __future__ import annotations

import json
import os
import sys
from typing import Any, Dict

import numpy as np

import ism

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EXAMPLES = os.path.join(ROOT, "spec", "examples")
READER = os.path.join(ROOT, "spec", "vectors", "reader")
VALIDATE = os.path.join(ROOT, "spec", "vectors", "validate")
SUFFIX = {"json": ".ism.json", "msgpack": ".ism.msgpack", "binary": ".ismb"}


def _ellipsoid_obj(path: str, radii: "tuple[float, float, float]", center: "tuple[float, float, float]") -> None:
    """An icosphere (one subdivision: 42 vertices, 80 triangles) stretched to ``radii``; every
    float written exactly (repr)."""
    t = (1 + 5**0.5) / 2
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
         (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]  # fmt: skip
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2), (10, 7, 6),
         (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10),
         (8, 6, 7), (9, 8, 1)]  # fmt: skip
    verts = [np.array(p, float) / np.linalg.norm(p) for p in v]
    mids: Dict[Any, int] = {}

    def mid(a: int, b: int) -> int:
        k = (min(a, b), max(a, b))
        if k not in mids:
            m = verts[a] + verts[b]
            verts.append(m / np.linalg.norm(m))
            mids[k] = len(verts) - 1
        return mids[k]

    faces = []
    for a, b, c in f:
        ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
        faces += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
    pts = np.array(verts) * np.array(radii) + np.array(center)
    with open(path, "w") as out:
        out.writelines(f"v {x!r} {y!r} {z!r}\n" for x, y, z in pts.tolist())
        out.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces)


def _copy(src: str, dest: str) -> None:
    with open(src, "rb") as f, open(dest, "wb") as g:
        g.write(f.read())


def make_corpus(folder: str, variants: int = 17, meshes: int = 8) -> Dict[str, Any]:
    os.makedirs(folder, exist_ok=True)
    good, mesh_ids, bad, files = [], [], {}, []
    names = sorted(f[: -len(".ismb")] for f in os.listdir(EXAMPLES) if f.endswith(".ismb"))
    k = 0
    for name in names:
        m = ism.read(os.path.join(EXAMPLES, name + ".ismb"))
        for v in range(variants):
            shift = np.array([0.013 * v, -0.007 * v, 0.011 * v][: m.dimension])
            scale = 1.0 + 0.125 * v  # exact in binary: values × scale round the same way everywhere
            moved = ism.Model(m.vertices + shift, m.simplices, m.values * scale, m.level * scale, list(m.stages),
                              metadata=dict(m.metadata, name=f"{name}-{v}"), extras=m.extras)  # fmt: skip
            enc = ("json", "msgpack", "binary")[k % 3]
            k += 1
            path = os.path.join(folder, f"{name}-v{v:02d}{SUFFIX[enc]}")
            moved.write(path, enc)
            good.append(os.path.basename(path))
            files.append(path)
    for i in range(meshes):
        path = os.path.join(folder, f"ellipsoid-{i:02d}.obj")
        _ellipsoid_obj(path, (0.5 + 0.03 * i, 0.4, 0.3 + 0.02 * i), (0.1 * i, 0.0, -0.05 * i))
        good.append(os.path.basename(path))
        mesh_ids.append(os.path.basename(path))
        files.append(path)

    def add_bad(name: str, step: str, rule: Any, data: bytes) -> None:
        path = os.path.join(folder, name)
        with open(path, "wb") as f:
            f.write(data)
        bad[name] = {"step": step, "rule": rule}
        files.append(path)

    with open(os.path.join(EXAMPLES, "sphere.ismb"), "rb") as f:
        sphere = f.read()
    add_bad("corrupt-truncated.ismb", "read", "ISM-", sphere[: len(sphere) // 2])
    add_bad("corrupt-random.ismb", "read", "ISM-", np.random.default_rng(1).bytes(3000))
    add_bad("corrupt-cut.ism.json", "read", "ISM-", b'{"version": "1.0", "dimension": 3, "vertices": [0.0, 1.0,')
    add_bad("corrupt-empty.ismb", "read", "ISM-", b"")
    for vec in ("huge-array-length.ism.msgpack", "huge-payload-length.ismb", "huge-sequence-length.ismb",
                "bit-flipped-payload-binary.ismb", "facet-shared-by-3.ism.json"):  # fmt: skip
        stem = vec.split(".")[0]
        with open(os.path.join(READER, stem + ".expect.json")) as f:
            rule = json.load(f)["rule"]
        with open(os.path.join(READER, vec), "rb") as f:
            add_bad("hostile-" + vec if "huge" in vec else "bad-" + vec, "read", rule, f.read())
    with open(os.path.join(VALIDATE, "fig2-exact-swap.expect.json")) as f:
        rule = json.load(f)["issues"][0]["code"]
    with open(os.path.join(VALIDATE, "fig2-exact-swap.ism.json"), "rb") as f:
        add_bad("invalid-fig2-exact-swap.ism.json", "validate", rule, f.read())
    # A tetrahedron's surface plus a fin on edge (0, 1): that edge has three triangles.
    tet = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv 0.5 -0.5 -0.5\n"
    add_bad("nonmanifold-fin.obj", "fit", None, (tet + "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\nf 1 2 5\n").encode())
    add_bad("open-mesh.obj", "fit", None, (tet + "f 1 3 2\nf 1 2 4\nf 1 4 3\n").encode())
    return {"good": good, "meshes": mesh_ids, "bad": bad, "files": files}


if __name__ == "__main__":
    out = sys.argv[1]
    c = make_corpus(out, *(int(a) for a in sys.argv[2:4]))
    print(f"{len(c['files'])} files in {out}: {len(c['good'])} good ({len(c['meshes'])} meshes), {len(c['bad'])} bad")
