"""True two-sided error of `ism export` against the model's own surface, for one or two binaries
side by side (e.g. main's and a branch's), with triangles and CPU time; no number comes from the
exporter under test except its mesh.

For each model and tolerance T, each binary runs `ism export MODEL out.obj --tolerance T -j 1 -q
--json` (CPU time of the child from `resource.getrusage`, best of `--repeat`). Then, independently of
the exporter:

* **mesh → O**: probe points on every cell of the mesh (3D: vertices, edge midpoints and quarter
  points, centroids, points halfway between the centroid and each corner and each edge midpoint;
  2D: vertices and eighths of every segment) are moved onto O = {F = c} by Newton steps along ∇F
  (`p ← p − α (F − c) ∇F / |∇F|²`, α halved from 1 until |F − c| decreases; F and ∇F from `ism
  query`, a direct evaluation of F: no inversion, no refinement) until |F − c| / |∇F| < 1e-12 of
  the model's size; the displacement is the distance to a point of O, hence an upper bound of the
  distance to O. Probes whose iteration leaves the
  complex or does not converge are counted and reported (never silently dropped). The largest
  distances are then tightened (`tighten`): a sign change of F − c on a grid around the probe,
  bisected to a point of O, can be nearer than where Newton went; the table gives the tightened
  maximum and, in brackets, Newton's alone.
* **O → mesh**: `ism sample --surface N --seed 1` draws N points uniform by curved area, each on O to
  1e-12 (the sampler's contract, tested by its own suite); the distance from each to the mesh is the
  minimum over the cells nearest it (k-d tree of cell centroids, `--candidates` nearest), computed
  exactly per cell: again an upper bound of the true distance.
* for models with a known analytic shape (`--case NAME:MODEL:sphere:R` or `:torus:R:r`), also the
  largest distance from the probes to that shape (exact formula), which includes the fit's error.

The two-sided error is max(mesh → O, O → mesh). Prints a Markdown table.

Usage: ISM_BIN=target/release/ism [ISM_OLD=/path/to/other/ism] .venv/bin/python tools/bench_export_error.py
         [--case NAME:MODEL[:SHAPE...] ...] [--tolerance T ...] [--samples N] [--repeat R]
Default cases: every model in spec/examples (the .ism.json files).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
# Damped Newton (Model.distance): most steps per point, and most halvings of one step.
STEPS = 30
HALVINGS = 30


def child_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) and cells (m, 3) triangles or (m, 2) segments of an OBJ file."""
    verts, cells = [], []
    with open(path) as fh:
        for line in fh:
            if line.startswith("v "):
                verts.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("f ") or line.startswith("l "):
                cells.append([int(tok.split("/")[0]) - 1 for tok in line.split()[1:]])
    v = np.array(verts, dtype=np.float64)
    if v.shape[1] == 2:
        v = np.hstack([v, np.zeros((len(v), 1))])
    return v, np.array(cells, dtype=np.int64)


def probes(v: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Points on the mesh where its distance to O is measured (module doc)."""
    if c.shape[1] == 2:
        a, b = v[c[:, 0]], v[c[:, 1]]
        ts = np.arange(1, 8) / 8.0
        return np.concatenate([v] + [(1 - t) * a + t * b for t in ts])
    a, b, d = v[c[:, 0]], v[c[:, 1]], v[c[:, 2]]
    g = (a + b + d) / 3.0
    edges = np.unique(np.sort(np.concatenate([c[:, [0, 1]], c[:, [1, 2]], c[:, [2, 0]]]), axis=1), axis=0)
    ea, eb = v[edges[:, 0]], v[edges[:, 1]]
    out = [v, g, (ea + eb) / 2, 0.75 * ea + 0.25 * eb, 0.25 * ea + 0.75 * eb]
    for x in (a, b, d, (a + b) / 2, (b + d) / 2, (d + a) / 2):
        out.append((g + x) / 2)
    return np.concatenate(out)


class Model:
    def __init__(self, ism: str, path: str, tmp: Path):
        self.ism, self.path, self.tmp = ism, path, tmp
        info = json.loads(subprocess.run([ism, "info", path, "--json"], check=True, capture_output=True, text=True).stdout)
        self.level = float(info["level"])
        self.dim = int(info["dimension"])
        box = np.array(info["bounding_box"], dtype=np.float64)
        self.size = float(np.linalg.norm(box[:, 1] - box[:, 0]))

    def query(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        src, dst = self.tmp / "probe.npy", self.tmp / "probe-out.npy"
        np.save(src, np.ascontiguousarray(pts[:, : self.dim]))
        subprocess.run([self.ism, "query", self.path, str(src), "-o", str(dst), "-q"], check=True)
        out = np.load(dst)
        names = ["gx", "gy", "gz"][: self.dim]
        g = np.stack([out[n] for n in names], axis=1)
        if self.dim == 2:
            g = np.hstack([g, np.zeros((len(g), 1))])
        return out["f"] - self.level, g

    def distance(self, pts: np.ndarray) -> tuple[np.ndarray, int]:
        """Distance from each point to a point of O (damped Newton along ∇F), and how many did not converge.

        A full Newton step `(F − c) ∇F / |∇F|²` overshoots where |∇F| varies fast near O (fitted
        rational stages at their weight limits: |∇F| from 1.4 to 16 within 1e-3 on a fitted
        ellipsoid), and the iteration then lands on a far part of O: still an upper bound of the
        distance, but a loose one (5.4 × the tolerance reported where the nearest point of O was
        0.2 × it away). So a step is halved until |F − c| decreases (at most `HALVINGS` times;
        a point that cannot decrease it is counted as not converged).
        """
        q = pts.copy()
        f, g = self.query(q)
        g2 = np.einsum("ij,ij->i", g, g)
        alive = np.isfinite(f) & np.isfinite(g2) & (g2 > 0)
        done = np.zeros(len(q), dtype=bool)
        for _ in range(STEPS):
            done |= alive & (np.abs(f) < 1e-12 * self.size * np.sqrt(np.where(alive, g2, 1.0)))
            idx = np.nonzero(alive & ~done)[0]
            if len(idx) == 0:
                break
            step = (f[idx] / g2[idx])[:, None] * g[idx]
            alpha = np.ones(len(idx))
            pending = np.arange(len(idx))
            for _ in range(HALVINGS):
                trial = q[idx[pending]] - alpha[pending, None] * step[pending]
                ft, gt = self.query(trial)
                gt2 = np.einsum("ij,ij->i", gt, gt)
                ok = np.isfinite(ft) & np.isfinite(gt2) & (gt2 > 0) & (np.abs(ft) < np.abs(f[idx[pending]]))
                who = idx[pending[ok]]
                q[who], f[who], g[who], g2[who] = trial[ok], ft[ok], gt[ok], gt2[ok]
                pending = pending[~ok]
                if len(pending) == 0:
                    break
                alpha[pending] *= 0.5
            alive[idx[pending]] = False
        failed = int((~(alive & done)).sum())
        d = np.linalg.norm(q - pts, axis=1)
        d[~(alive & done)] = np.nan
        return d, failed


def tighten(model: Model, pts: np.ndarray, d: np.ndarray, top: int = 64, side: int = 17, rounds: int = 8) -> int:
    """Lowers the largest of the damped-Newton distances `d` (in place) where a nearer point of O
    exists: the damped iteration still follows ∇F to a far part of O where |∇F| varies fast (a probe
    of a fitted rational ellipsoid's 1e-4 export read 1.5e-4 where a sign change of F lay 4.6e-5
    away). For the `top` largest not yet tightened, F is evaluated on a grid of `side`ⁿ points filling
    the box of half-width d around the probe; each grid segment whose ends have opposite signs of
    F − c (both finite, so both in |K|) is bisected 40 times (a NaN midpoint, outside |K|, drops it),
    and the farther end of its final bracket from the probe bounds the distance to O from above: F
    is continuous on |K|, so a zero lies in every bracket that stayed in |K|. Repeated until the
    largest distance is one already tightened (at most `rounds` times). Returns how many probes were
    lowered. Still an upper bound of the true distance, only a tighter one."""
    done = np.zeros(len(d), dtype=bool)
    lowered = 0
    n = model.dim
    g = np.linspace(-1.0, 1.0, side)
    grid = np.stack(np.meshgrid(*[g] * n, indexing="ij"), axis=-1).reshape(-1, n)
    grid = np.hstack([grid, np.zeros((len(grid), 3 - n))])  # 2D: the plane z = 0
    # Grid segments along each axis, as index pairs into `grid`.
    idx = np.arange(side**n).reshape((side,) * n)
    pairs = np.concatenate(
        [
            np.stack([np.take(idx, range(side - 1), axis=a).ravel(), np.take(idx, range(1, side), axis=a).ravel()], axis=1)
            for a in range(n)
        ]
    )
    for _ in range(rounds):
        dd = np.where(np.isfinite(d), d, -np.inf)
        order = np.argsort(-dd)
        if done[order[0]] or not np.isfinite(d[order[0]]):
            break
        who = order[:top][~done[order[:top]]]
        done[who] = True
        q = pts[who, None, :] + d[who, None, None] * grid[None, :, :]
        f, _ = model.query(q.reshape(-1, 3))
        f = f.reshape(len(who), -1)
        fa, fb = f[:, pairs[:, 0]], f[:, pairs[:, 1]]
        cross = np.isfinite(fa) & np.isfinite(fb) & (np.sign(fa) != np.sign(fb))
        pi, si = np.nonzero(cross)
        if len(pi) == 0:
            continue
        a = q[pi, pairs[si, 0]]
        b = q[pi, pairs[si, 1]]
        fa = fa[pi, si]
        alive = np.ones(len(pi), dtype=bool)
        for _ in range(40):
            mid = 0.5 * (a + b)
            fm, _ = model.query(mid)
            alive &= np.isfinite(fm)
            left = np.sign(fm) == np.sign(fa)
            a = np.where(left[:, None], mid, a)
            fa = np.where(left, fm, fa)
            b = np.where(left[:, None], b, mid)
        bound = np.maximum(np.linalg.norm(a - pts[who[pi]], axis=1), np.linalg.norm(b - pts[who[pi]], axis=1))
        bound[~alive] = np.inf
        best = np.full(len(who), np.inf)
        np.minimum.at(best, pi, bound)
        better = best < d[who]
        d[who[better]] = best[better]
        lowered += int(better.sum())
    return lowered


def point_triangle(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Exact distance from p[i] to triangle (a[i], b[i], c[i]) (Ericson, vectorised)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = vb / denom
        w = vc / denom
        q = a + ab * v[:, None] + ac * w[:, None]  # interior
        # Edge regions.
        t_ab = np.clip(d1 / np.einsum("ij,ij->i", ab, ab), 0, 1)
        q_ab = a + ab * t_ab[:, None]
        t_ac = np.clip(d2 / np.einsum("ij,ij->i", ac, ac), 0, 1)
        q_ac = a + ac * t_ac[:, None]
        bc = c - b
        t_bc = np.clip(np.einsum("ij,ij->i", bc, bp) / np.einsum("ij,ij->i", bc, bc), 0, 1)
        q_bc = b + bc * t_bc[:, None]
    inside = (va >= 0) & (vb >= 0) & (vc >= 0) & np.isfinite(v) & np.isfinite(w)
    dist = np.full(len(p), np.inf)
    dist[inside] = np.linalg.norm(p[inside] - q[inside], axis=1)
    for qq in (q_ab, q_ac, q_bc):
        dd = np.linalg.norm(p - np.nan_to_num(qq, nan=np.inf), axis=1)
        dist = np.where(inside, dist, np.minimum(dist, dd))
    return dist


def point_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300), 0, 1)
    return np.linalg.norm(p - (a + ab * t[:, None]), axis=1)


def cell_distance(s: np.ndarray, v: np.ndarray, cell: np.ndarray) -> np.ndarray:
    if cell.shape[1] == 2:
        return point_segment(s, v[cell[:, 0]], v[cell[:, 1]])
    return point_triangle(s, v[cell[:, 0]], v[cell[:, 1]], v[cell[:, 2]])


def surface_to_mesh(s: np.ndarray, v: np.ndarray, c: np.ndarray, k: int) -> np.ndarray:
    """Exact distance from each point to the mesh. Candidates: every cell is covered by lattice points
    (spacing at most the median edge length L, so every point of a cell is within L of one of its
    lattice points); the cells owning the `k` nearest lattice points are measured exactly, and where
    the k-th lattice point is nearer than the best distance plus L (a cell not among them could be
    nearer), every cell with a lattice point within that radius is measured too."""
    corners = v[c]
    nv = c.shape[1]
    edge = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
    spacing = max(float(np.median(edge)), 1e-300)
    m = np.maximum(1, np.ceil(edge / spacing).astype(np.int64))
    pts, owner = [], []
    for level in np.unique(m):
        sel = np.nonzero(m == level)[0]
        if nv == 2:
            bary = np.stack([np.arange(level + 1)[::-1], np.arange(level + 1)], axis=1) / level
        else:
            bary = np.array([(i, j, level - i - j) for i in range(level + 1) for j in range(level + 1 - i)]) / level
        pts.append(np.einsum("lk,ckd->cld", bary, corners[sel]).reshape(-1, 3))
        owner.append(np.repeat(sel, len(bary)))
    pts, owner = np.concatenate(pts), np.concatenate(owner)
    cover = spacing  # sub-edges are at most `spacing` long, so a lattice point is within it
    tree = cKDTree(pts)
    k = min(k, len(pts))
    dk, nearest = tree.query(s, k=k)
    dk, nearest = dk.reshape(len(s), k), nearest.reshape(len(s), k)
    best = np.full(len(s), np.inf)

    def measure(who: np.ndarray, cells: np.ndarray) -> None:
        pair = np.unique(who * len(c) + cells)
        who, cells = pair // len(c), pair % len(c)
        np.minimum.at(best, who, cell_distance(s[who], v, c[cells]))

    measure(np.repeat(np.arange(len(s)), k), owner[nearest.ravel()])
    unsure = np.nonzero(dk[:, -1] < best + cover)[0] if k < len(pts) else np.array([], dtype=np.int64)
    for chunk in np.array_split(unsure, max(1, len(unsure) // 2000)):
        if len(chunk) == 0:
            continue
        lists = tree.query_ball_point(s[chunk], best[chunk] + cover)
        who = np.repeat(chunk, [len(x) for x in lists])
        if len(who):
            measure(who, owner[np.concatenate([np.asarray(x, dtype=np.int64) for x in lists])])
    return best


def analytic_distance(shape: list[str], q: np.ndarray) -> np.ndarray:
    p = [float(x) for x in shape[1:]]
    if shape[0] == "sphere":
        return np.abs(np.linalg.norm(q, axis=1) - p[0])
    if shape[0] == "circle":
        return np.abs(np.linalg.norm(q[:, :2], axis=1) - p[0])
    ring = np.sqrt(q[:, 0] ** 2 + q[:, 1] ** 2) - p[0]
    return np.abs(np.sqrt(ring * ring + q[:, 2] ** 2) - p[1])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--case", action="append", help="NAME:MODEL[:sphere:R|:torus:R:r|:circle:R]")
    ap.add_argument("--tolerance", action="append", type=float)
    ap.add_argument("--samples", type=int, default=200_000)
    ap.add_argument("--candidates", type=int, default=16)
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args()
    bins = [("new", os.environ.get("ISM_BIN", str(ROOT / "target" / "release" / "ism")))]
    if os.environ.get("ISM_OLD"):
        bins.insert(0, ("old", os.environ["ISM_OLD"]))
    cases = args.case or [f"{p.name[: -len('.ism.json')]}:{p}" for p in sorted((ROOT / "spec" / "examples").glob("*.ism.json"))]
    tolerances = args.tolerance or [1e-3]
    print(f"binaries: {bins}; load average {os.getloadavg()}", flush=True)
    print("| model | tolerance | binary | cells | CPU s | mesh→O max (damped Newton alone; probes tightened lower) | O→mesh max | two-sided / T | not converged | mesh→shape max |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for case in cases:
            name, path, *shape = case.split(":")
            ref = Model(bins[-1][1], path, tmp)
            spts = tmp / "surface.npy"
            subprocess.run([ref.ism, "sample", path, "--surface", str(args.samples), "--seed", "1", "-o", str(spts), "-q"], check=True)
            sa = np.load(spts)
            s = np.stack([sa[n] for n in ["x", "y", "z"][: ref.dim]], axis=1)
            if ref.dim == 2:
                s = np.hstack([s, np.zeros((len(s), 1))])
            for tol in tolerances:
                for label, ism in bins:
                    out = tmp / "out.obj"
                    best = float("inf")
                    for _ in range(args.repeat):
                        before = child_cpu()
                        r = subprocess.run(
                            [ism, "export", path, str(out), "--tolerance", str(tol), "-j", "1", "-q", "--json"],
                            capture_output=True,
                            text=True,
                        )
                        best = min(best, child_cpu() - before)
                    if r.returncode != 0:
                        print(f"| {name} | {tol:g} | {label} | export failed (exit {r.returncode}): {r.stderr.strip()[:200]} |", flush=True)
                        continue
                    v, c = read_obj(out)
                    pr = probes(v, c)
                    d, failed = ref.distance(pr)
                    newton = float(np.nanmax(d))
                    lowered = tighten(ref, pr, d)
                    m2o = float(np.nanmax(d))
                    o2m = float(surface_to_mesh(s, v, c, args.candidates).max())
                    two = max(m2o, o2m)
                    extra = f"{analytic_distance(shape, pr).max():.3e}" if shape else "–"
                    print(
                        f"| {name} | {tol:g} | {label} | {len(c):,} | {best:.3f} | {m2o:.3e} ({newton:.3e}; {lowered} lowered) | {o2m:.3e} | {two / tol:.2f} | {failed} of {len(pr):,} | {extra} |",
                        flush=True,
                    )


if __name__ == "__main__":
    main()
