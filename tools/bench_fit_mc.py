#!/usr/bin/env python3
"""ISM fits against marching cubes at equal two-sided *true* error: the table of BENCHMARKS.md
(section fit, "Smaller than a mesh?").

Usage: ISM_BIN=target/release/ism python tools/bench_fit_mc.py [--out DIR] [--only NAME,...]
       [--rel 1e-3] [--timeout SECONDS] [--fit-arg=--no-topology ...] [--max-res N] [--reuse]

For every shape: `ism fit` at `rel` x the domain's longest side (the CLI default is 1e-3), CPU
time of the child process; then the fit's two-sided true error measured here, independently of
the fitter and its report:

- S -> Z (fit to target): `ism sample --surface` points of the written model (the sampler, not
  the fitter), and for each its distance to the true surface Z: closed form for the sphere and
  torus, the exact closest point on an ellipsoid (Eberly's root of the secular equation, by
  bisection) for the ellipsoid, and elsewhere the root of g found by bisection along the
  gradient line through the point (an upper bound of the distance; second-order exact where Z
  is smooth); for the mesh target the exact point-triangle distance to the mesh.
- Z -> S (target to fit): dense exact points of Z (roots of g by bisection on grid lines in all
  three axis directions, or points on the target mesh's triangles), each with its exact distance
  to the fit's own fine export (`ism export` at EXPORT_FRACTION of the tolerance, every triangle
  that can be nearer measured) plus that export's chordal tolerance: an upper bound of the
  distance to the fit within 5 % of the tolerance of the truth (the closest point may lie in any
  direction). The worst 2,000 are re-measured by two more upper bounds, a sign-change bracket
  on the model's F (along -grad F and the axes) and the distance to the nearest sample of the
  fit, and the smallest is kept. (stderr also prints the older estimate: the tangent plane of
  the nearest sample, off by about curvature x h^2 / 2 for samples of spacing h.)

Then scikit-image `marching_cubes` on a grid of the same function (for the mesh target the signed
distance, exact at the corners of the cells where it changes sign, clipped elsewhere: mesh_sdf),
the grid refined until the mesh's two-sided true error, measured the same way (mesh vertices,
edge midpoints and centroids to Z; Z points to the exact closest point on the triangles) is at
most the ISM's; the mesh is written as binary glTF (.glb, trimesh). 2D shapes use
`find_contours` and a .glb of line segments.

Prints one Markdown row per shape: tolerance, simplices, stored numbers, .ismb, .ismc (compact
binary), .ismz (compressed: the compact payload in xz, spec §7.4.2) and .isms (structured: face
records by the complex, control points on the 2^-24 lattice, spec §7.4.3) bytes, ISM two-sided true error (both directions), the report's own claim, topology, CPU
seconds; and the marching-cubes grid, vertices+faces numbers, .glb bytes, its error, topology, CPU
seconds; the ratios .glb / .ismb, .ismc, .ismz, .isms, and — for an honest comparison — the .glb
compressed by the same codec (xz preset 6, what `ism` writes) over the .ismz. Every fit is run with
`--lattice` (the control points on the lattice the structured encoding stores in 3 bytes per free
coordinate; each moves by at most 2^-25 of its face, and the error measured here is the written
model's, so every column describes the same model).
Needs numpy, scipy, scikit-image, trimesh (tools/requirements.txt); the mesh target needs the
bunny that ships in the pymeshlab wheel (skipped when pymeshlab is not installed); `--only bone`
(not in the default list) fits the wheel's second scanned mesh, a bone, the same way.
"""
import argparse
import json
import lzma
import math
import os
import resource
import struct
import subprocess
import sys
import tempfile
import time

import numpy as np
from scipy.spatial import cKDTree

ISM = os.environ.get("ISM_BIN", "target/release/ism")

# Bisection steps for roots of g: 2^-50 of the bracket, far below any error measured here.
BISECT = 50
# Surface samples of the fit drawn for the true error (uniform by curved area).
FIT_SAMPLES = 1_000_000
# Target points whose distance to the fit is re-measured by a certified bracket on the model's F.
WORST = 2000
# Z -> S against the fit's own fine export: `ism export` at this fraction of the fit's tolerance.
# dist(z, S) <= dist(z, export) + the export's chordal error, so the figure is an upper bound
# within this fraction of the tolerance (5 %) of the truth; finer exports grow as 1/fraction (the
# torus at 2e-4 gives ~3 M triangles at 1/20).
EXPORT_FRACTION = 1.0 / 20
# Edge halvings allowed in that export: enough that no patch edge stops at the depth limit (the
# default 8 stops ~400 edges of the bone at 2e-5); a depth-limited edge is reported, not hidden.
EXPORT_MAX_DEPTH = 16
# Grid-line spacing of the dense points on Z, as a fraction of the domain's longest side.
Z_SPACING = 1.0 / 400
# Points per batch of the exact point-to-mesh distance: about 0.4 GB of temporaries (16 nearest
# centroids per point and their point-triangle distances).
MESH_CHUNK = 250_000
# Point-triangle pairs per batch where the 16 nearest centroids do not certify the distance.
PAIR_CHUNK = 2_000_000
# Relative rounding bound of a 2D orientation determinant (b-a) x (p-a) evaluated in float64:
# Shewchuk's orient2d bound is (3 + 16 eps) eps ~ 3.3e-16 of |t1| + |t2|; 1e-15 is safely above
# it, and only the signs inside it are recomputed exactly (fractions).
ORIENT_ERR = 1e-15


# ---------------------------------------------------------------------------------------------
# Shapes: g for numpy, its gradient, the expression for `ism fit`, and the domain.


def sphere():
    r = 0.6
    return dict(
        name="sphere (preset)", fit=["--preset", "sphere"],
        domain=(-1, 1, -1, 1, -1, 1),
        g=lambda x, y, z: x * x + y * y + z * z - r * r,
        grad=lambda x, y, z: (2 * x, 2 * y, 2 * z),
        dist=lambda p: np.abs(np.linalg.norm(p, axis=1) - r),
        genus=0)


def torus():
    big, small = 0.6, 0.25
    return dict(
        name="torus (preset)", fit=["--preset", "torus"],
        domain=(-1, 1, -1, 1, -0.5, 0.5),
        g=lambda x, y, z: (x * x + y * y + z * z + big**2 - small**2) ** 2
        - 4 * big**2 * (x * x + y * y),
        grad=None,
        dist=lambda p: np.abs(np.hypot(np.hypot(p[:, 0], p[:, 1]) - big, p[:, 2]) - small),
        genus=1)


def ellipsoid():
    a = np.array([0.9, 0.3, 0.06])

    def dist(p):
        # Eberly: the closest point of the ellipsoid to q (first octant by symmetry) is
        # q_i a_i^2 / (t + a_i^2) with t the root of sum (a_i q_i / (t + a_i^2))^2 = 1.
        # A coordinate exactly 0 (fit vertices and patch corners on the grid plane z = 0) makes
        # 0/0 at t = -a_i^2; 1e-12 instead moves the point by at most 1.7e-12 and keeps the
        # degenerate case (closest point off the plane) as the limit of the root.
        q = np.maximum(np.abs(p), 1e-12)
        f = lambda t: (((a * q) / (t[:, None] + a * a)) ** 2).sum(axis=1) - 1
        lo = -np.full(len(q), a[2] ** 2) + a[2] * q[:, 2]
        hi = np.linalg.norm(a * q, axis=1)
        lo = np.minimum(lo, hi)
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            pos = f(mid) > 0
            lo = np.where(pos, mid, lo)
            hi = np.where(pos, hi, mid)
        t = 0.5 * (lo + hi)
        c = q * a * a / (t[:, None] + a * a)
        return np.linalg.norm(c - q, axis=1)

    return dict(
        name="thin ellipsoid 0.9 x 0.3 x 0.06",
        # The initial grid must see the thin shape: 16 cells along x put vertices inside it.
        fit=["--expr", "x^2/0.81 + y^2/0.09 + z^2/0.0036 - 1", "--resolution", "16"],
        domain=(-1, 1, -0.4, 0.4, -0.1, 0.1),
        g=lambda x, y, z: 1.2345679012345678 * x * x + 11.111111111111111 * y * y
        + 277.77777777777777 * z * z - 1,
        grad=None, dist=dist, genus=0)


def genus2():
    return dict(
        name="genus-2 (preset)", fit=["--preset", "genus2"],
        domain=(-1.2, 1.2, -0.7, 0.7, -0.3, 0.3),
        g=lambda x, y, z: (x * x * (1 - x * x) - y * y) ** 2 + z * z - 0.01,
        grad=None, dist=None, genus=2)


def tangle():
    return dict(
        name="tangle cube (genus 5)",
        fit=["--expr", "x^4 - 5*x^2 + y^4 - 5*y^2 + z^4 - 5*z^2 + 11.8"],
        domain=(-3, 3, -3, 3, -3, 3),
        g=lambda x, y, z: x**4 - 5 * x * x + y**4 - 5 * y * y + z**4 - 5 * z * z + 11.8,
        grad=None, dist=None, genus=5)


def heart():
    return dict(
        name="heart curve (cusps)", fit=["--expr", "(x^2+y^2-1)^3-x^2*y^3"],
        domain=(-1.5, 1.5, -1.5, 1.5),
        g=lambda x, y: (x * x + y * y - 1) ** 3 - x * x * y**3,
        grad=None, dist=None, genus=None)


SHAPES = {"sphere": sphere, "torus": torus, "ellipsoid": ellipsoid, "genus2": genus2,
          "tangle": tangle, "heart": heart}


# ---------------------------------------------------------------------------------------------
# Independent distances to Z = {g = 0}.


def num_grad(g, p, h=1e-7):
    out = []
    for k in range(p.shape[1]):
        e = np.zeros(p.shape[1])
        e[k] = h
        out.append((g(*(p + e).T) - g(*(p - e).T)) / (2 * h))
    return np.stack(out, axis=1)


def root_distance(g, p, reach):
    """Distance from p to a root of g along the gradient line (both ways) and, where that fails,
    the coordinate axes: each an upper bound of dist(p, Z)."""
    v = g(*p.T)
    best = np.full(len(p), np.inf)
    gr = num_grad(g, p)
    norm = np.linalg.norm(gr, axis=1)
    dirs = [-(np.sign(v) / np.where(norm > 0, norm, 1))[:, None] * gr]
    for k in range(p.shape[1]):
        for s in (-1.0, 1.0):
            d = np.zeros_like(p)
            d[:, k] = s
            dirs.append(d)
    for i, d in enumerate(dirs):
        todo = np.isfinite(best) if i > 0 else np.zeros(len(p), bool)
        # Axes only where the gradient line found nothing close (4x its first-order estimate).
        est = np.abs(v) / np.where(norm > 0, norm, np.inf)
        need = ~todo | (best > 4 * est) if i > 0 else np.ones(len(p), bool)
        idx = np.nonzero(need)[0]
        if len(idx) == 0:
            continue
        q, dq, sv = p[idx], d[idx], np.sign(v[idx])
        t = np.maximum(0.5 * est[idx], reach * 1e-9)
        t = np.where(np.isfinite(t), t, reach * 1e-6)
        lo = np.zeros(len(idx))
        found = np.zeros(len(idx), bool)
        hi = np.full(len(idx), np.inf)
        while True:
            act = ~found & (t <= reach)
            if not act.any():
                break
            x = g(*(q[act] + t[act, None] * dq[act]).T)
            changed = np.sign(x) != sv[act]
            ai = np.nonzero(act)[0]
            hi[ai[changed]] = t[ai[changed]]
            found[ai[changed]] = True
            lo[ai[~changed]] = t[ai[~changed]]
            t[ai[~changed]] *= 1.5
        f = np.nonzero(found)[0]
        a, b = lo[f], hi[f]
        for _ in range(BISECT):
            m = 0.5 * (a + b)
            x = g(*(q[f] + m[:, None] * dq[f]).T)
            same = np.sign(x) == sv[f]
            a = np.where(same, m, a)
            b = np.where(same, b, m)
        best[idx[f]] = np.minimum(best[idx[f]], b)
    best[v == 0] = 0.0
    return best


def surface_points(g, domain, spacing):
    """Roots of g on the grid lines (all axis directions) of spacing `spacing`: points of Z."""
    n = len(domain) // 2
    axes = [np.arange(domain[2 * k], domain[2 * k + 1] + 0.5 * spacing, spacing) for k in range(n)]
    out = []
    for k in range(n):
        # Lines along axis k: every combination of the other coordinates.
        others = [axes[j] for j in range(n) if j != k]
        mesh = np.meshgrid(*others, indexing="ij")
        base = np.stack([m.ravel() for m in mesh], axis=1)
        # Values along the line in chunks of lines (memory).
        for c0 in range(0, len(base), 20000):
            b = base[c0:c0 + 20000]
            pts = np.empty((len(b), len(axes[k]), n))
            pts[:, :, k] = axes[k][None, :]
            jj = 0
            for j in range(n):
                if j != k:
                    pts[:, :, j] = b[:, jj][:, None]
                    jj += 1
            v = g(*np.moveaxis(pts, 2, 0))
            s = np.sign(v)
            li, ti = np.nonzero(s[:, :-1] * s[:, 1:] < 0)
            if len(li) == 0:
                continue
            lo = axes[k][ti].copy()
            hi = axes[k][ti + 1].copy()
            slo = s[li, ti]
            for _ in range(BISECT):
                m = 0.5 * (lo + hi)
                q = pts[li, ti].copy()
                q[:, k] = m
                same = np.sign(g(*q.T)) == slo
                lo = np.where(same, m, lo)
                hi = np.where(same, hi, m)
            q = pts[li, ti].copy()
            q[:, k] = 0.5 * (lo + hi)
            out.append(q)
    return np.concatenate(out) if out else np.zeros((0, n))


def to_plane_distance(points, samples, normals):
    """Distance from each point to the fit: to the tangent plane of its nearest sample."""
    tree = cKDTree(samples)
    _, i = tree.query(points, k=1, workers=-1)
    return np.abs(((points - samples[i]) * normals[i]).sum(axis=1))


def read_export_obj(path):
    """Vertices and triangles (or 2D segments) of an OBJ written by `ism export` (`v x y z`, `f
    a//a b//b c//c` or `l a b`; one-based), parsed with numpy: the writer prints shortest
    round-trip numbers, so the coordinates are the exporter's float64 values bit for bit."""
    with open(path, "rb") as f:
        lines = f.read().split(b"\n")
    v = np.array(b" ".join(x[2:] for x in lines if x.startswith(b"v ")).split(), float)
    cells = [x[2:] for x in lines if x.startswith(b"f ") or x.startswith(b"l ")]
    idx = np.array(b" ".join(cells).replace(b"//", b" ").split(), np.int64)
    if cells and cells[0].count(b"//"):
        idx = idx[::2]  # `a//a`: the vertex and its normal share the index
    k = len(cells[0].split()) if cells else 3
    return v.reshape(-1, 3), idx.reshape(-1, k) - 1


def exported_distance(path, zpts, tol, out):
    """Z -> S against the fit's own fine export: `ism export` at EXPORT_FRACTION x tol, then the
    exact distance from every target point to that mesh (every triangle that can be nearer is
    measured: to_mesh_distance; 2D: the nearest segments). Returns (distance to the export, the
    export's chordal tolerance, triangles, depth-limited edges): dist(z, S) lies within the
    chordal tolerance of the first wherever the export meets its tolerance (no depth-limited
    edge). Unlike the tangent plane of the nearest sample or a bracket along a few directions
    (both loose on the scanned meshes: 1.18e-3 / 1.28e-3 where this gives 7.26e-4 on the bunny
    at 7.24e-4), the closest point of S may lie in any direction."""
    eps = EXPORT_FRACTION * tol
    obj = path + ".fine.obj"
    q = subprocess.run([ISM, "export", path, obj, "--tolerance", repr(eps), "--max-depth",
                        str(EXPORT_MAX_DEPTH), "-q", "--json"], capture_output=True, text=True)
    if q.returncode != 0:
        raise RuntimeError(f"ism export: {q.stderr}")
    summary = json.loads(q.stdout)
    v, cells = read_export_obj(obj)
    os.remove(obj)
    n = zpts.shape[1]
    if cells.shape[1] == 2:
        d, near = to_segments_distance(zpts, v[:, :n], cells), None
    else:
        d, near = to_mesh_distance(zpts, v, cells, closest=True)
    return d, near, eps, len(cells), summary.get("depth_limited_edges", 0)


def narrow_sign_change(path, p, d, sign, a, b, steps):
    """Bisects [a, b] along p + t d, where the model's F - c has sign `sign` at t = a and not at
    t = b, `steps` times by `ism query`; returns the narrowed (a, b) and whether every midpoint
    was inside |K| (where one was not, F is undefined there and [a, b] brackets nothing)."""
    ok = np.ones(len(p), bool)
    for _ in range(steps):
        m = 0.5 * (a + b)
        fv, sg, _ = ism_query(path, p + m[:, None] * d)
        same = sg == sign
        a = np.where(same, m, a)
        b = np.where(same, b, m)
        ok &= np.isfinite(fv)
    return a, b, ok


def projected_distance(path, z, q, reach):
    """An upper bound of dist(z, S) from a point q near S (the closest point of the fine export):
    along -sign(F) grad F from q, a sign change of the model's F - c is bracketed to [a, b] by
    `ism query` (40 bisections); S meets that segment (intermediate value theorem on F, which is
    continuous in |K|), so dist(z, S) <= max(|z - (q + a d)|, |z - (q + b d)|). Tight to second
    order where q is near S. Infinite where F is undefined along the way."""
    f, sign, grad = ism_query(path, q)
    norm = np.linalg.norm(grad, axis=1)
    d = -(sign / np.where(norm > 0, norm, np.inf))[:, None] * grad
    lo = np.zeros(len(q))
    t = np.maximum(0.5 * np.abs(f) / np.where(norm > 0, norm, np.inf), 1e-12)
    t = np.where(np.isfinite(t), t, 1e-12)
    hi = np.full(len(q), np.inf)
    act = (sign != 0) & np.isfinite(f) & (norm > 0)
    while act.any():
        fv, sg, _ = ism_query(path, q[act] + t[act, None] * d[act])
        ai = np.nonzero(act)[0]
        # `ism query` gives F NaN and sign 0 outside |K|: that ends the search there (no bound),
        # it is not a sign change; F exactly 0 is a point of S.
        inside = np.isfinite(fv)
        hit = inside & ((sg != sign[ai]) | (fv == 0))
        hi[ai[hit]] = t[ai[hit]]
        lo[ai[inside & ~hit]] = t[ai[inside & ~hit]]
        t[ai[~hit]] *= 2.0
        act[ai[hit | ~inside]] = False
        act &= t <= reach
    idx = np.nonzero(np.isfinite(hi))[0]
    a, b, ok = narrow_sign_change(path, q[idx], d[idx], sign[idx], lo[idx], hi[idx], 40)
    out = np.full(len(q), np.inf)
    ends = [np.linalg.norm(z[idx] - (q[idx] + x[:, None] * d[idx]), axis=1) for x in (a, b)]
    out[idx] = np.where(ok, np.maximum(*ends), np.inf)
    on = sign == 0
    out[on] = np.linalg.norm(z[on] - q[on], axis=1)
    return out


def ism_query(path, pts):
    """F and grad F of the model at pts (`ism query`); NaN outside |K|."""
    with tempfile.TemporaryDirectory() as d:
        src, dst = os.path.join(d, "p.npy"), os.path.join(d, "q.npy")
        np.save(src, np.ascontiguousarray(pts, dtype=np.float64))
        q = subprocess.run([ISM, "query", path, src, "-q", "-o", dst], capture_output=True,
                           text=True)
        if q.returncode != 0:
            raise RuntimeError(f"ism query: {q.stderr}")
        a = np.load(dst)
    n = pts.shape[1]
    grad = np.stack([a["g" + c] for c in "xyz"[:n]], axis=1)
    return a["f"], a["sign"], grad


def ism_bracket(path, pts, start, reach):
    """Distance from each point to a sign change of the model's F - c along -sign * grad F,
    then along the axes where that fails: a certified upper bound of the distance to the fit's
    shape S (by the intermediate value theorem on the model's own F, evaluated by `ism query`)."""
    f, sign, grad = ism_query(path, pts)
    n = pts.shape[1]
    norm = np.linalg.norm(grad, axis=1)
    d0 = -(sign / np.where(norm > 0, norm, 1))[:, None] * grad
    dirs = [d0] + [s * np.eye(n)[k][None, :].repeat(len(pts), 0) for k in range(n)
                   for s in (-1.0, 1.0)]
    best = np.full(len(pts), np.inf)
    for d in dirs:
        lo = np.zeros(len(pts))
        t = np.maximum(start, 1e-12)
        hi = np.full(len(pts), np.inf)
        act = np.ones(len(pts), bool)
        while act.any():
            _, sg, _ = ism_query(path, pts[act] + t[act, None] * d[act])
            ai = np.nonzero(act)[0]
            hit = (sg != sign[ai]) & (sg != 0)
            hi[ai[hit]] = t[ai[hit]]
            lo[ai[~hit]] = t[ai[~hit]]
            t[ai[~hit]] *= 1.5
            act[ai[hit]] = False
            act &= (t <= min(reach, 1.0)) & (t < best)
        idx = np.nonzero(np.isfinite(hi))[0]
        _, b, ok = narrow_sign_change(path, pts[idx], d[idx], sign[idx], lo[idx], hi[idx], 24)
        best[idx] = np.minimum(best[idx], np.where(ok, b, np.inf))
        if np.all(best <= 2 * start):
            break
    best[sign == 0] = np.nan
    return best


def point_triangle(p, a, b, c, closest=False):
    """Exact distances from points p to triangles (a, b, c), row by row (Ericson, RTCD 5.1.5);
    with `closest`, also the closest points."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(1), (ac * ap).sum(1)
    bp = p - b
    d3, d4 = (ab * bp).sum(1), (ac * bp).sum(1)
    cp = p - c
    d5, d6 = (ab * cp).sum(1), (ac * cp).sum(1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    denom = va + vb + vc
    with np.errstate(invalid="ignore", divide="ignore"):
        v = vb / denom
        w = vc / denom
    q = a + v[:, None] * ab + w[:, None] * ac
    # Regions outside the face: the closest point is on an edge or a vertex.
    def seg(x, y):
        d = y - x
        t = np.clip(((p - x) * d).sum(1) / np.maximum((d * d).sum(1), 1e-300), 0, 1)
        return x + t[:, None] * d
    inside = (va >= 0) & (vb >= 0) & (vc >= 0) & (denom > 0)
    cands = [seg(a, b), seg(b, c), seg(c, a)]
    ds = np.array([np.linalg.norm(p - x, axis=1) for x in cands])
    dist = np.where(inside, np.linalg.norm(p - q, axis=1), ds.min(axis=0))
    if not closest:
        return dist
    edge = np.array(cands)[ds.argmin(axis=0), np.arange(len(p))]
    return dist, np.where(inside[:, None], q, edge)


def split_large(tri):
    """Triangles (t, 3, 3) with those whose farthest corner from the centroid is above twice the
    median split into four at their edge midpoints until none is: the same set of points."""
    def radius(t):
        return np.linalg.norm(t - t.mean(axis=1)[:, None, :], axis=2).max(axis=1)
    limit = 2 * float(np.median(radius(tri))) if len(tri) else 0.0
    while True:
        big = radius(tri) > limit
        if not big.any():
            return tri
        t = tri[big]
        a, b, c = t[:, 0], t[:, 1], t[:, 2]
        ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
        tri = np.concatenate([tri[~big]] + [np.stack(x, axis=1) for x in
                                            ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])


def to_mesh_distance(points, verts, faces, k=16, closest=False):
    """Exact distance from points to a triangle mesh: the minimum over all its triangles of the
    exact point-triangle distance, in batches of MESH_CHUNK points.

    Candidates first: the k triangles with the nearest centroids. A triangle t not among them has
    its centroid at least d_k (the k-th nearest centroid's distance) from the point and all its
    points within R_t (its farthest corner) of the centroid, so its distance is at least
    d_k - max R_t; where the best candidate is not below that, every triangle whose centroid is
    within best + max R_t is measured too (a ball query), so the minimum is over all triangles
    that can be nearer. With `closest`, also the closest points of the mesh.

    An adaptive mesh (the fit's fine export) has a few large triangles in flat parts, and max R_t
    would send every point to the ball query; so triangles with R_t above twice the median are
    first split at their edge midpoints (4 each, repeatedly): the same point set, a small reach."""
    tri = split_large(verts[faces])
    cen = tri.mean(axis=1)
    reach = float(np.linalg.norm(tri - cen[:, None, :], axis=2).max())
    tree = cKDTree(cen)
    k = min(k, len(faces))
    out = np.empty(len(points))
    near = np.empty((len(points), 3))
    for c0 in range(0, len(points), MESH_CHUNK):
        p = points[c0:c0 + MESH_CHUNK]
        dk, ci = tree.query(p, k=k, workers=-1)
        dk, ci = dk.reshape(len(p), -1), ci.reshape(len(p), -1)
        best = np.full(len(p), np.inf)
        best_t = ci[:, 0].copy()
        for j in range(ci.shape[1]):
            t = tri[ci[:, j]]
            d = point_triangle(p, t[:, 0], t[:, 1], t[:, 2])
            better = d < best
            best_t[better] = ci[better, j]
            best = np.where(better, d, best)
        # Uncertified: some triangle outside the k could be nearer (with a margin for rounding).
        if k < len(faces):
            bad = np.nonzero(best >= (dk[:, -1] - reach) * (1 - 1e-9))[0]
        else:
            bad = np.zeros(0, int)
        for b0 in range(0, len(bad), 20000):
            idx = bad[b0:b0 + 20000]
            lists = tree.query_ball_point(p[idx], best[idx] + reach * (1 + 1e-9), workers=-1)
            lens = np.fromiter((len(x) for x in lists), int, len(lists))
            pi = np.repeat(idx, lens)
            ti = np.fromiter((i for x in lists for i in x), int, int(lens.sum()))
            for q0 in range(0, len(pi), PAIR_CHUNK):
                a, b = pi[q0:q0 + PAIR_CHUNK], ti[q0:q0 + PAIR_CHUNK]
                t = tri[b]
                d = point_triangle(p[a], t[:, 0], t[:, 1], t[:, 2])
                np.minimum.at(best, a, d)
                if closest:
                    # The triangle that attains the minimum (ties: any of them).
                    hit = d <= best[a]
                    best_t[a[hit]] = b[hit]
        out[c0:c0 + len(p)] = best
        if closest:
            t = tri[best_t]
            _, near[c0:c0 + len(p)] = point_triangle(p, t[:, 0], t[:, 1], t[:, 2], closest=True)
    return (out, near) if closest else out


def orient_sign(a, b, p):
    """Exact sign of the 2D orientation (b - a) x (p - a) (rows of (y, z) pairs), with the point
    perturbed to p + (e, e^2) for an infinitesimal e > 0 (simulation of simplicity): zero only
    where a = b. float64 with a rounding filter; the few signs inside the filter exactly."""
    t1 = (b[:, 0] - a[:, 0]) * (p[:, 1] - a[:, 1])
    t2 = (b[:, 1] - a[:, 1]) * (p[:, 0] - a[:, 0])
    det = t1 - t2
    sign = np.sign(det)
    unsure = np.nonzero(np.abs(det) <= ORIENT_ERR * (np.abs(t1) + np.abs(t2)))[0]
    if len(unsure):
        from fractions import Fraction as Q
        for i in unsure:
            ay, az, by, bz, py, pz = (Q(float(x)) for x in (a[i, 0], a[i, 1], b[i, 0], b[i, 1],
                                                            p[i, 0], p[i, 1]))
            e = (by - ay) * (pz - az) - (bz - az) * (py - ay)
            sign[i] = (e > 0) - (e < 0)
    # Zero: the e-term is -(bz - az), the e^2-term (by - ay) (signs of float differences are exact).
    zero = sign == 0
    tie = np.where(b[:, 1] != a[:, 1], np.sign(a[:, 1] - b[:, 1]), np.sign(b[:, 0] - a[:, 0]))
    return np.where(zero, tie, sign)


def mesh_inside(verts, faces, axes):
    """Inside (True) or outside of a closed triangle mesh at every point of the grid `axes`: the
    parity of the mesh's crossings of the grid line along x below the point. Whether a line
    (y, z) meets a triangle is decided by exact orientation signs with the line moved to
    (y + e, z + e^2), e infinitesimal, so it meets no edge or vertex and every crossing is
    counted once. The crossing's x is rounded: a grid point on the wrong side of it is within
    about 1e-16 x edge^3 / area of the triangle from the surface, where its sign does not
    matter (its distance, and so its value, is ~0 either way). Raises if a line crosses an odd
    number of times (the mesh is not closed)."""
    ax, ay, az = axes
    nx, ny, nz = len(ax), len(ay), len(az)
    tri = verts[faces]
    flat, lines = [], []
    for c0 in range(0, len(tri), 20000):
        t = tri[c0:c0 + 20000]
        j0 = np.searchsorted(ay, t[:, :, 1].min(1), "left")
        j1 = np.searchsorted(ay, t[:, :, 1].max(1), "right")
        k0 = np.searchsorted(az, t[:, :, 2].min(1), "left")
        k1 = np.searchsorted(az, t[:, :, 2].max(1), "right")
        nj, nk = np.maximum(j1 - j0, 0), np.maximum(k1 - k0, 0)
        cnt = nj * nk
        ti = np.repeat(np.arange(len(t)), cnt)
        if len(ti) == 0:
            continue
        local = np.arange(len(ti)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        j = j0[ti] + local // nk[ti]
        k = k0[ti] + local % nk[ti]
        p = np.stack([ay[j], az[k]], axis=1)
        a, b, c = t[ti, 0], t[ti, 1], t[ti, 2]
        s_a = orient_sign(b[:, 1:], c[:, 1:], p)
        s_b = orient_sign(c[:, 1:], a[:, 1:], p)
        s_c = orient_sign(a[:, 1:], b[:, 1:], p)
        hit = ((s_a > 0) & (s_b > 0) & (s_c > 0)) | ((s_a < 0) & (s_b < 0) & (s_c < 0))
        if not hit.any():
            continue
        a, b, c, p, j, k = a[hit], b[hit], c[hit], p[hit], j[hit], k[hit]
        # The crossing's x: barycentric weights are the sub-triangles' projected areas.
        def area(u, v):
            return ((v[:, 1] - u[:, 1]) * (p[:, 1] - u[:, 2])
                    - (v[:, 2] - u[:, 2]) * (p[:, 0] - u[:, 1]))
        w = np.stack([area(b, c), area(c, a), area(a, b)], axis=1)
        x = (w[:, 0] * a[:, 0] + w[:, 1] * b[:, 0] + w[:, 2] * c[:, 0]) / w.sum(axis=1)
        i0 = np.searchsorted(ax, x, "right")
        lines.append(j * nz + k)
        keep = i0 < nx
        flat.append((i0[keep] * ny + j[keep]) * nz + k[keep])
    lines = np.concatenate(lines) if lines else np.zeros(0, int)
    _, per_line = np.unique(lines, return_counts=True)
    if np.any(per_line % 2):
        raise RuntimeError(f"mesh_inside: {int(np.sum(per_line % 2))} grid lines cross the mesh "
                           "an odd number of times: the mesh is not closed")
    flip = np.zeros(nx * ny * nz, dtype=np.uint8)
    if flat:
        u, n = np.unique(np.concatenate(flat), return_counts=True)
        flip[u] = n & 1
    return np.bitwise_xor.accumulate(flip.reshape(nx, ny, nz), axis=0).astype(bool)


def sign_change_corners(vol):
    """Grid points that are corners of a cell whose corners are not all on one side of the level
    0, for either way of counting a value exactly 0 (> 0 or >= 0): the only values marching cubes
    reads for a cell that gives triangles (a cell with one class at all corners gives none)."""
    need = np.zeros(vol.shape, dtype=bool)
    for cls in (vol > 0, vol >= 0):
        some = np.zeros(tuple(n - 1 for n in vol.shape), dtype=bool)
        every = np.ones_like(some)
        corners = [(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)]
        for a, b, c in corners:
            part = cls[a:a + some.shape[0], b:b + some.shape[1], c:c + some.shape[2]]
            some |= part
            every &= part
        mixed = some & ~every
        del some, every
        for a, b, c in corners:
            need[a:a + mixed.shape[0], b:b + mixed.shape[1], c:c + mixed.shape[2]] |= mixed
    return need


def mesh_sdf(verts, faces, axes):
    """Signed distance to a closed triangle mesh on the grid `axes` (negative inside), exact
    where marching cubes reads it and clipped elsewhere. The sign is exact everywhere
    (mesh_inside: ray parity); every point then gets +-(one cell diagonal), and the corners of
    the cells whose corners change sign (sign_change_corners) the exact distance
    (to_mesh_distance), repeated until no new such corner appears (an exact distance 0 can change
    a cell's class). Marching cubes reads values only in cells whose corners change class, so its
    mesh is the one of the exact signed distance everywhere, while the exact distances cost
    ~ the surface's area / h^2 points, not the grid's volume, and memory is a few grid-sized
    arrays (the whole-grid distance with trimesh's `contains` was OOM-killed at 24 GB at 33^3
    points in session 22: its rays' bounding boxes meet most triangles)."""
    h = np.array([a[1] - a[0] for a in axes])
    clip = float(np.linalg.norm(h))
    vol = np.where(mesh_inside(verts, faces, axes), -clip, clip)
    exact = np.zeros(vol.shape, dtype=bool)
    while True:
        new = sign_change_corners(vol)
        new &= ~exact
        idx = np.flatnonzero(new)
        del new
        if len(idx) == 0:
            return vol
        exact.flat[idx] = True
        for c0 in range(0, len(idx), 4 * MESH_CHUNK):
            part = idx[c0:c0 + 4 * MESH_CHUNK]
            i, j, k = np.unravel_index(part, vol.shape)
            q = np.stack([axes[0][i], axes[1][j], axes[2][k]], axis=1)
            vol.flat[part] = np.sign(vol.flat[part]) * to_mesh_distance(q, verts, faces)


def mesh_samples(verts, faces):
    """Vertices, edge midpoints and centroids of a triangle mesh (where a flat triangle is
    farthest from a curved surface, and its corners)."""
    tri = verts[faces]
    mids = np.concatenate([(tri[:, 0] + tri[:, 1]) / 2, (tri[:, 1] + tri[:, 2]) / 2,
                           (tri[:, 2] + tri[:, 0]) / 2])
    return np.concatenate([verts, mids, tri.mean(axis=1)])


# ---------------------------------------------------------------------------------------------
# Runs.


def cpu_children():
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run(cmd, timeout=None):
    t0, c0 = time.time(), cpu_children()
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    return p, cpu_children() - c0, time.time() - t0


def fit_ism(shape, tol, out, timeout, extra=(), keep_unmet=False, reuse=False):
    path = os.path.join(out, shape["key"] + ".ismb")
    saved = os.path.join(out, shape["key"] + ".fit.json")
    cmd = [ISM, "fit", *shape["fit"], "--lattice", *extra, "--tolerance", repr(tol), "-q", "--json", "-o", path]
    if "--preset" not in shape["fit"] and "--mesh" not in shape["fit"]:
        cmd += ["--domain=" + ",".join(repr(float(x)) for x in shape["domain"])]
    if reuse and os.path.exists(path) and os.path.exists(saved):
        # --reuse: the fit written by an earlier run of this script with the same arguments (its
        # command, report and CPU time are saved beside it); everything after the fit is redone.
        with open(saved) as f:
            kept = json.load(f)
        if kept["command"][1:] != cmd[1:]:
            raise RuntimeError(f"--reuse: {saved} is for `{' '.join(kept['command'])}`")
        report, cpu, wall = kept["report"], kept["cpu"], kept["wall"]
        print(f"  reusing {path} ({cpu:.1f} CPU-s when fitted)", file=sys.stderr)
    else:
        p, cpu, wall = run(cmd, timeout)
        # Exit 1: the model is written but the tolerance (or the topology) was not met; its true
        # error is measured here all the same, and marching cubes is matched to that error.
        if p.returncode != 0 and not (keep_unmet and p.returncode == 1 and p.stdout.strip()):
            raise RuntimeError(f"{' '.join(cmd)}: exit {p.returncode}: {p.stderr[-2000:]}")
        report = json.loads(p.stdout)
        with open(saved, "w") as f:
            json.dump({"command": cmd, "report": report, "cpu": cpu, "wall": wall}, f)
    samples = os.path.join(out, shape["key"] + ".npy")
    q = subprocess.run([ISM, "sample", path, "--surface", str(FIT_SAMPLES), "-q", "-o", samples],
                       capture_output=True, text=True)
    if q.returncode != 0:
        raise RuntimeError(f"ism sample: {q.stderr}")
    a = np.load(samples)
    n = len(shape["domain"]) // 2
    cols = "xyz"[:n]
    pts = np.stack([a[c] for c in cols], axis=1)
    nrm = np.stack([a["n" + c] for c in cols], axis=1)
    return path, report, cpu, wall, pts, nrm


def compact_bytes(path):
    """Bytes of the same model in the compact binary encoding (spec ism-format.md §7.4.1: the
    binary grammar with variable-length integers), written by `ism convert`."""
    c = path[: -len(".ismb")] + ".ismc"
    subprocess.run([ISM, "convert", path, c, "-q"], check=True)
    return os.path.getsize(c)


def compressed_bytes(path):
    """Bytes of the same model in the compressed encoding (spec ism-format.md §7.4.2: the compact
    payload compressed by xz), written by `ism convert`."""
    z = path[: -len(".ismb")] + ".ismz"
    subprocess.run([ISM, "convert", path, z, "-q"], check=True)
    return os.path.getsize(z)


def structured_bytes(path):
    """Bytes of the same model in the structured encoding (spec ism-format.md §7.4.3: face records
    by the complex, points on a lattice when they lie on one), written by `ism convert`."""
    s = path[: -len(".ismb")] + ".isms"
    subprocess.run([ISM, "convert", path, s, "-q"], check=True)
    return os.path.getsize(s)


def xz_bytes(path):
    """Bytes of a file compressed by the codec of the compressed encoding at the writer's preset (xz
    preset 6, Python's lzma: the same liblzma), for the marching-cubes .glb beside the .ismz."""
    with open(path, "rb") as f:
        return len(lzma.compress(f.read(), format=lzma.FORMAT_XZ, preset=6))


def byte_parts(path):
    """Where the .ismb's bytes go (spec ism-format.md §7.4: u32 ids, f64 numbers, a u64 length
    before every array): from the model re-encoded as JSON by `ism convert`."""
    j = path + ".json"
    subprocess.run([ISM, "convert", path, j, "--to", "json", "-q"], check=True)
    with open(j) as f:
        m = json.load(f)
    os.remove(j)
    n = m["dimension"]
    parts = {"vertices+values": 8 * (len(m["vertices"]) + len(m["values"])),
             "simplex ids": 4 * len(m["simplices"])}
    for st in m["stages"]:
        for r in st.get("faces", []):
            key = f"{len(r['face']) - 1}-face records"
            parts[key] = parts.get(key, 0) + 24 + 4 * len(r["face"]) + 8 * (
                len(r["points"]) + len(r.get("weights", [])))
    vals, level = m["values"], m.get("level", 0.0)
    simp = [m["simplices"][i:i + n + 1] for i in range(0, len(m["simplices"]), n + 1)]
    crossed = sum(1 for s in simp if len({vals[v] < level for v in s}) == 2)
    total = os.path.getsize(path)
    return total, crossed, len(simp), parts


def dist_to_z(shape, p):
    if shape.get("mesh") is not None:
        v, f = shape["mesh"]
        return to_mesh_distance(p, v, f)
    if shape["dist"] is not None:
        return shape["dist"](p)
    d = np.asarray(shape["domain"])
    reach = float(np.linalg.norm(d[1::2] - d[0::2]))
    out = np.empty(len(p))
    for c0 in range(0, len(p), 200000):
        out[c0:c0 + 200000] = root_distance(shape["g"], p[c0:c0 + 200000], reach)
    return out


def grid_values(shape, res):
    d = shape["domain"]
    n = len(d) // 2
    longest = max(d[2 * k + 1] - d[2 * k] for k in range(n))
    h = longest / res
    axes = [np.linspace(d[2 * k], d[2 * k + 1], int(round((d[2 * k + 1] - d[2 * k]) / h)) + 1)
            for k in range(n)]
    if shape.get("sdf") is not None:
        return shape["sdf"](axes), axes
    if n == 2:
        x, y = np.meshgrid(*axes, indexing="ij")
        return shape["g"](x, y), axes
    vol = np.empty([len(a) for a in axes], dtype=np.float64)
    y, z = np.meshgrid(axes[1], axes[2], indexing="ij")
    for i, x in enumerate(axes[0]):
        vol[i] = shape["g"](x, y, z)
    return vol, axes


def marching(shape, res, out):
    """(verts, faces, cpu seconds, glb bytes, glb path) of marching cubes / squares at `res`
    grid cells along the longest side."""
    import skimage.measure
    c0 = time.process_time()
    vol, axes = grid_values(shape, res)
    spacing = [a[1] - a[0] for a in axes]
    origin = np.array([a[0] for a in axes])
    path = os.path.join(out, f"{shape['key']}_mc{res}.glb")
    if vol.ndim == 3:
        verts, faces, _, _ = skimage.measure.marching_cubes(vol, level=0.0, spacing=spacing)
        verts = verts + origin
        cpu = time.process_time() - c0
        import trimesh
        trimesh.Trimesh(verts.astype(np.float32), faces, process=False).export(path)
    else:
        contours = skimage.measure.find_contours(vol, 0.0)
        vs, segs, base = [], [], 0
        for c in contours:
            pts = origin + c * np.asarray(spacing)
            closed = np.allclose(pts[0], pts[-1])
            if closed:
                pts = pts[:-1]
            m = len(pts)
            idx = np.arange(m)
            e = np.stack([idx, (idx + 1) % m], axis=1) if closed else \
                np.stack([idx[:-1], idx[1:]], axis=1)
            vs.append(pts)
            segs.append(e + base)
            base += m
        verts, faces = np.concatenate(vs), np.concatenate(segs)
        cpu = time.process_time() - c0
        write_lines_glb(path, verts, faces)
    return verts, faces, cpu, os.path.getsize(path), path


def write_lines_glb(path, verts, segs):
    """A binary glTF of line segments (mode 1): trimesh writes 2D paths only as SVG/DXF, so this
    is written here (glTF 2.0 §4.4: a JSON chunk and a BIN chunk, 4-byte aligned)."""
    pos = np.zeros((len(verts), 3), np.float32)
    pos[:, :verts.shape[1]] = verts
    idx = segs.astype(np.uint32).ravel()
    pb, ib = pos.tobytes(), idx.tobytes()
    binary = pb + ib
    binary += b"\0" * (-len(binary) % 4)
    doc = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(binary)}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(pb), "target": 34962},
                        {"buffer": 0, "byteOffset": len(pb), "byteLength": len(ib),
                         "target": 34963}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": len(pos), "type": "VEC3",
                       "min": pos.min(0).tolist(), "max": pos.max(0).tolist()},
                      {"bufferView": 1, "componentType": 5125, "count": len(idx),
                       "type": "SCALAR"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "mode": 1}]}],
        "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}], "scene": 0,
    }
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    with open(path, "wb") as f:
        f.write(struct.pack("<III", 0x46546C67, 2, 12 + 8 + len(js) + 8 + len(binary)))
        f.write(struct.pack("<II", len(js), 0x4E4F534A) + js)
        f.write(struct.pack("<II", len(binary), 0x004E4942) + binary)


def segment_samples(verts, segs, k=8):
    a, b = verts[segs[:, 0]], verts[segs[:, 1]]
    t = np.linspace(0, 1, k + 1)
    return (a[:, None, :] + t[None, :, None] * (b - a)[:, None, :]).reshape(-1, verts.shape[1])


def to_segments_distance(points, verts, segs):
    a, b = verts[segs[:, 0]], verts[segs[:, 1]]
    _, ci = cKDTree((a + b) / 2).query(points, k=min(8, len(segs)), workers=-1)
    best = np.full(len(points), np.inf)
    for j in range(ci.shape[1]):
        x, y = a[ci[:, j]], b[ci[:, j]]
        d = y - x
        t = np.clip(((points - x) * d).sum(1) / np.maximum((d * d).sum(1), 1e-300), 0, 1)
        best = np.minimum(best, np.linalg.norm(points - x - t[:, None] * d, axis=1))
    return best


def mc_error(shape, verts, faces, zpts):
    if faces.shape[1] == 2:
        s = segment_samples(verts, faces)
        back = to_segments_distance(zpts, verts, faces)
    else:
        s = mesh_samples(verts, faces)
        back = to_mesh_distance(zpts, verts, faces)
    fwd = dist_to_z(shape, s)
    return float(fwd.max()), float(back.max())


def euler(verts, faces):
    if faces.shape[1] == 2:
        return None
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
    e = len(np.unique(edges, axis=0))
    return len(verts) - e + len(faces)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=None)
    ap.add_argument("--only", default=",".join(list(SHAPES) + ["bunny"]))
    ap.add_argument("--rel", type=float, default=1e-3)
    ap.add_argument("--timeout", type=float, default=900)
    ap.add_argument("--max-res", type=int, default=640, help="largest 3D grid (cells per side)")
    ap.add_argument("--fit-arg", action="append", default=[],
                    help="extra `ism fit` argument (repeatable), e.g. --fit-arg=--no-topology")
    ap.add_argument("--reuse", action="store_true",
                    help="take the fit from an earlier run's --out DIR (KEY.ismb and KEY.fit.json, "
                    "same fit command) instead of fitting again; the measures are redone")
    ap.add_argument("--keep-unmet", action="store_true",
                    help="measure a fit that exits 1 (model written, tolerance or topology not "
                    "met) instead of giving a failed row; its row says `met False`")
    args = ap.parse_args()
    out = args.out or tempfile.mkdtemp(prefix="ism_mc_")
    os.makedirs(out, exist_ok=True)
    print(f"ism: {ISM}; output in {out}", file=sys.stderr)
    rows = []
    for key in args.only.split(","):
        shape = scanned(key, out) if key in SCANNED else SHAPES[key]()
        if shape is None:
            print(f"{key}: pymeshlab not installed, skipped", file=sys.stderr)
            continue
        shape["key"] = key
        d = shape["domain"]
        n = len(d) // 2
        longest = max(d[2 * k + 1] - d[2 * k] for k in range(n))
        tol = args.rel * longest
        try:
            path, report, cpu, wall, pts, nrm = fit_ism(shape, tol, out, args.timeout,
                                                        args.fit_arg, args.keep_unmet, args.reuse)
        except (RuntimeError, subprocess.TimeoutExpired) as e:
            print(f"{key}: fit failed: {e}", file=sys.stderr)
            rows.append(f"| {shape['name']} | {tol:.1e} | fit failed: {str(e)[:120]} |")
            continue
        if shape.get("zpts") is not None:
            zpts = shape["zpts"]
        else:
            zpts = surface_points(shape["g"], d, Z_SPACING * longest)
        fwd = dist_to_z(shape, pts)
        plane = to_plane_distance(zpts, pts, nrm)
        # Z -> S: the exact distance to the fit's fine export plus its chordal tolerance, an
        # upper bound of dist(z, S) (up to the exporter's chordal test) for every target point.
        near_export, near_q, eps, ntri, limited = exported_distance(path, zpts, tol, out)
        back = near_export + eps
        print(f"  Z->S: to the fit's export at {eps:.2e} ({ntri} cells, {limited} depth-limited "
              f"edges) {near_export.max():.4e} (+/- {eps:.1e}); tangent planes of the nearest "
              f"sample {plane.max():.3e}", file=sys.stderr)
        # The worst target points again with a certified bracket on the model's own F: a second
        # upper bound, taken where it is smaller.
        worst = np.argsort(back)[-WORST:]
        longest_side = max(d[2 * k + 1] - d[2 * k] for k in range(n))
        bracket = ism_bracket(path, zpts[worst], 0.5 * back[worst], longest_side)
        # Both the bracket (along -grad F and the axes) and the distance to the nearest sample
        # of the fit are upper bounds of dist(z, S); the bracket can be far from tight where the
        # closest point is in none of its directions (near the heart's cusp (0, 1): 2.54e-3
        # against 1.69e-3 to a sample), so the smaller is taken.
        nearest, near_i = cKDTree(pts).query(zpts[worst], k=1, workers=-1)
        # Where F is undefined at the target point (it lies just outside the written shell |K|,
        # e.g. the torus's lowest circle on a grid plane), bracket from a point 1e-7 towards the
        # nearest sample instead, plus that step (dist is 1-Lipschitz). In 3D the nearest of 1M
        # samples alone is loose (about their spacing, 2.4e-3 on the torus).
        undef = np.nonzero(np.isnan(bracket))[0]
        if len(undef):
            w = zpts[worst][undef]
            step = pts[near_i[undef]] - w
            step *= 1e-7 / np.maximum(np.linalg.norm(step, axis=1), 1e-300)[:, None]
            again = ism_bracket(path, w + step, 0.5 * back[worst][undef], longest_side)
            bracket[undef] = again + 1e-7
        bracket = np.fmin(bracket, nearest)
        rest = np.delete(back, worst)
        print(f"  Z->S: bracket on the worst {len(worst)} {np.nanmax(bracket):.3e}; the smaller "
              f"upper bound {max(np.nanmax(np.fmin(bracket, back[worst])), 0):.4e}",
              file=sys.stderr)
        bracket = np.fmin(bracket, back[worst])
        if near_q is not None:
            # A third: the export's closest point carried onto S along grad F (tight).
            proj = projected_distance(path, zpts[worst], near_q[worst], longest_side)
            print(f"  Z->S: the export's closest points projected onto S: worst "
                  f"{np.max(np.fmin(proj, bracket)):.4e} ({int(np.sum(~np.isfinite(proj)))} not "
                  f"projected)", file=sys.stderr)
            bracket = np.fmin(bracket, proj)
        back = np.append(rest, bracket)
        # The largest of the final upper bounds (after all three re-measures of the worst; an
        # infinite one stays infinite: it is not dropped).
        back_max = float(np.nanmax(back)) if len(back) else 0.0
        back = back[np.isfinite(back)]
        ism_err = max(fwd.max(), back_max)
        ism_bytes = os.path.getsize(path)
        ismc_bytes = compact_bytes(path)
        ismz_bytes = compressed_bytes(path)
        isms_bytes = structured_bytes(path)
        total, crossed, simplices, parts = byte_parts(path)
        print(f"  .ismb {total} B: {simplices} simplices ({crossed} crossed); " + ", ".join(
            f"{k} {v} B ({100 * v / total:.0f} %)" for k, v in parts.items()), file=sys.stderr)
        print(f"{key}: ISM tol {tol:.2e}: {report['simplices']} simplices, "
              f"{report['storedNumbers']} numbers, {ism_bytes} B (.ismc {ismc_bytes} B, .ismz {ismz_bytes} B, .isms {isms_bytes} B), true S->Z {fwd.max():.3e} "
              f"Z->S {back.max():.3e} (report {report['shapeToTarget']:.3e} / "
              f"{report['targetToShape']:.3e}, met {report['toleranceMet']}), {cpu:.1f} CPU-s",
              file=sys.stderr)
        # Marching cubes: from a coarse grid up, by the error's h^2 law, until at most the ISM's,
        # then down by bisection to the coarsest grid (cells per side) that still meets it.
        res, best = 16, None
        tried = {}

        def meets(x):
            return not any(math.isnan(v) for v in x) and max(x) <= ism_err

        max_res = args.max_res if n == 3 else 16 * args.max_res
        while res <= max_res and res not in tried:
            verts, faces, mcpu, glb, gpath = marching(shape, res, out)
            e = mc_error(shape, verts, faces, zpts)
            tried[res] = e
            print(f"  mc {res}: {len(verts)} verts {len(faces)} faces {glb} B err {e[0]:.3e} / "
                  f"{e[1]:.3e} ({mcpu:.1f} CPU-s)", file=sys.stderr)
            err = max(e) if not any(math.isnan(x) for x in e) else math.inf
            passing = [r for r, x in tried.items() if meets(x)]
            failing = [r for r, x in tried.items() if not meets(x)]
            if meets(e):
                best = (res, verts, faces, mcpu, glb, e, gpath)
            if best is not None:
                # The coarsest grid that meets it: bisect between the finest failing grid below
                # the coarsest passing one and that one (one step down by 8 % when none failed).
                top = min(passing)
                below = [r for r in failing if r < top]
                low = max(below) if below else int(top / 1.08)
                if top - low <= 1 or low < 8:
                    break
                res = low if not below else (low + top) // 2
                continue
            grow = math.sqrt(err / ism_err) * 1.03 if math.isfinite(err) else 2.0
            res = max(res + 1, int(math.ceil(res * min(2.0, grow))))
        topo = f"genus {shape['genus']}" if shape.get("genus") is not None else "—"
        ism_topo = f"{report.get('components')} comp., χ {report.get('euler')}"
        if best is None:
            mc = f"not reached by {max_res} cells | — | — | — | — | — | — | — | — | — | — |"
        else:
            r, v, f, mcpu, glb, e, gpath = best
            glb_xz = xz_bytes(gpath)
            chi = euler(v, f)
            nums = v.size + f.size
            mc = (f"{r} | {nums:,} | {glb:,} | {max(e):.2e} ({e[0]:.1e}/{e[1]:.1e}) | "
                  f"{'χ ' + str(chi) if chi is not None else str(len(f)) + ' segments'}, "
                  f"{mcpu:.1f} CPU-s | {glb / ism_bytes:.2f} | {glb / ismc_bytes:.2f} | {glb / ismz_bytes:.2f} | "
                  f"{glb / isms_bytes:.2f} | {glb_xz:,} | {glb_xz / ismz_bytes:.2f} |")
        rows.append(
            f"| {shape['name']} ({topo}) | {tol:.1e} | {report['simplices']:,} | "
            f"{report['storedNumbers']:,} | {ism_bytes:,} | {ismc_bytes:,} | {ismz_bytes:,} | {isms_bytes:,} | {ism_err:.2e} ({fwd.max():.1e}/"
            f"{back.max():.1e}) | {report['maxDistance']:.2e}, met {report['toleranceMet']} | "
            f"{ism_topo}, {cpu:.1f} CPU-s | {mc}")
    print("| shape | tolerance | ISM simplices | stored numbers | .ismb bytes | .ismc bytes | .ismz bytes | .isms bytes | true "
          "two-sided error (S→Z/Z→S) | report's claim | ISM topology, CPU | MC grid | MC numbers | "
          ".glb bytes | MC true error | MC topology, CPU | .glb / .ismb | .glb / .ismc | .glb / .ismz | .glb / .isms | "
          ".glb.xz bytes | .glb.xz / .ismz |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(r)


# Scanned meshes in the pymeshlab wheel's tests/sample_meshes: key -> (file, row name). Both are
# closed (watertight, consistently wound) after trimesh's merge of duplicate vertices.
SCANNED = {"bunny": ("bunny.obj", "Stanford bunny (pymeshlab wheel, closed)"),
           "bone": ("bone.ply", "bone (pymeshlab wheel, closed)")}


def scanned(key, out):
    """A scanned mesh from the pymeshlab wheel (SCANNED): fitted with `ism fit --mesh` (written
    as OBJ, the reader `ism fit` has); Z is the mesh, its grid function for marching cubes the
    signed distance (mesh_sdf: the sign by ray parity along grid lines, the distance exact at
    every value marching cubes reads)."""
    try:
        import pymeshlab
    except ImportError:
        return None
    import trimesh
    file, name = SCANNED[key]
    src = os.path.join(os.path.dirname(pymeshlab.__file__), "tests", "sample_meshes", file)
    m = trimesh.load(src, process=True, force="mesh")
    v, f = np.asarray(m.vertices, float), np.asarray(m.faces)
    obj = os.path.join(out, key + ".obj")
    m.export(obj)
    lo, hi = v.min(0), v.max(0)
    diag = float(np.linalg.norm(hi - lo))
    pad = 0.05 * diag
    domain = tuple(float(x) for pair in zip(lo - pad, hi + pad) for x in pair)
    # Dense points on the triangles: a barycentric lattice fine enough for spacing Z_SPACING.
    tri = v[f]
    longest = max(domain[1] - domain[0], domain[3] - domain[2], domain[5] - domain[4])
    edge = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)
    zs = []
    for lev in np.unique(np.ceil(edge / (Z_SPACING * longest)).astype(int).clip(1, 64)):
        sel = np.ceil(edge / (Z_SPACING * longest)).astype(int).clip(1, 64) == lev
        bary = np.array([(i, j, lev - i - j) for i in range(lev + 1) for j in range(lev + 1 - i)],
                        float) / lev
        zs.append(np.einsum("kb,tbd->tkd", bary, tri[sel]).reshape(-1, 3))
    zpts = np.concatenate(zs)

    def sdf(axes):
        # Exact only where marching cubes reads it (mesh_sdf): trimesh's `contains` ray tests on
        # the whole grid took 17 CPU-s at 16 cells and were OOM-killed at 24 GB at 32 (session 22).
        return mesh_sdf(v, f, axes)

    return dict(name=name, fit=["--mesh", obj],
                domain=domain, g=None, grad=None, dist=None, mesh=(v, f), zpts=zpts,
                genus=(2 - m.euler_number) // 2 if m.body_count == 1 else None,
                sdf=sdf)


if __name__ == "__main__":
    main()
