#!/usr/bin/env python3
"""`ism fit --mesh` on generated closed meshes: the mesh table of BENCHMARKS.md (section fit).

Usage: ISM_BIN=target/release/ism python3 tools/bench_mesh_fit.py [OUTDIR]

Writes the meshes as OBJ into OUTDIR (default: a temporary directory), fits each with the
settings below, checks the model with `ism validate`, and prints one Markdown row per mesh.
Standard library only.
"""
import json
import math
import os
import subprocess
import sys
import tempfile
import time

ISM = os.environ.get("ISM_BIN", "target/release/ism")


def icosphere(level, r=1.0):
    t = (1 + 5 ** 0.5) / 2
    pts = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t),
           (0, -1, -t), (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    pts = [tuple(c / math.sqrt(sum(x * x for x in p)) for c in p) for p in pts]
    tris = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
            (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
            (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    for _ in range(level):
        mid = {}

        def midpoint(a, b):
            key = (min(a, b), max(a, b))
            if key not in mid:
                p = [(x + y) / 2 for x, y in zip(pts[a], pts[b])]
                n = math.sqrt(sum(x * x for x in p))
                pts.append(tuple(x / n for x in p))
                mid[key] = len(pts) - 1
            return mid[key]

        new = []
        for a, b, c in tris:
            ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        tris = new
    return [tuple(r * x for x in p) for p in pts], tris


def torus(big=1.0, small=0.4, nu=48, nv=24):
    pts = []
    for i in range(nu):
        u = 2 * math.pi * i / nu
        for j in range(nv):
            v = 2 * math.pi * j / nv
            pts.append(((big + small * math.cos(v)) * math.cos(u),
                        (big + small * math.cos(v)) * math.sin(u), small * math.sin(v)))
    tris = []
    for i in range(nu):
        for j in range(nv):
            a = i * nv + j
            b = ((i + 1) % nu) * nv + j
            c = ((i + 1) % nu) * nv + (j + 1) % nv
            d = i * nv + (j + 1) % nv
            tris += [(a, b, c), (a, c, d)]
    return pts, tris


def cube():
    pts = [(x, y, z) for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)]
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = []
    for a, b, c, d in quads:
        tris += [(a, b, c), (a, c, d)]
    return pts, tris


def write_obj(path, pts, tris):
    with open(path, "w") as f:
        for p in pts:
            f.write("v %.17g %.17g %.17g\n" % p)
        for t in tris:
            f.write("f %d %d %d\n" % tuple(i + 1 for i in t))


CASES = [
    ("icosahedron, 20 triangles", icosphere(0), ["--resolution", "4", "--tolerance", "2e-2"]),
    ("icosphere, 1,280 triangles", icosphere(3), ["--resolution", "4", "--tolerance", "1e-2"]),
    ("icosphere, 20,480 triangles", icosphere(5), ["--resolution", "4", "--tolerance", "5e-3"]),
    ("torus, 2,304 triangles", torus(), ["--resolution", "6", "--tolerance", "1e-2"]),
    ("cube, 12 triangles", cube(), ["--resolution", "6", "--tolerance", "1e-2"]),
]


def main():
    out = sys.argv[1] if len(sys.argv) > 1 else tempfile.mkdtemp(prefix="ism-mesh-fit-")
    os.makedirs(out, exist_ok=True)
    print("| mesh | settings | simplices | max / mean error | topology | time | ism validate |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for i, (name, (pts, tris), settings) in enumerate(CASES):
        obj = os.path.join(out, "mesh%d.obj" % i)
        model = os.path.join(out, "mesh%d.ismb" % i)
        write_obj(obj, pts, tris)
        start = time.time()
        run = subprocess.run([ISM, "fit", "--mesh", obj, *settings, "--json", "-q", "-o", model],
                             capture_output=True, text=True)
        seconds = time.time() - start
        if run.returncode not in (0, 1):
            print("| %s | %s | failed: %s | | | | |" % (name, " ".join(settings), run.stderr.strip()))
            continue
        r = json.loads(run.stdout)
        m = r["mesh"]
        check = subprocess.run([ISM, "validate", model], capture_output=True, text=True)
        verdict = check.stdout.split(":", 1)[1].split("—")[0].strip() if ":" in check.stdout else "?"
        topo = "χ = %d, %s" % (r["euler"], "as the mesh" if r["topologyMatchesPreset"] else "NOT as the mesh")
        print("| %s | %s | %d | %.1e / %.1e | %s | %.1f s%s | %s |" % (
            name, " ".join(settings), r["simplices"], m["maxDistanceRelative"],
            m["meanDistanceRelative"], topo, seconds,
            "" if r["toleranceMet"] else " (tolerance not met)", verdict))


if __name__ == "__main__":
    main()
