"""Peer benchmark of `ism export` (the curved surface as triangles): scikit-image `marching_cubes`
on a grid of the analytic implicit function of the same shape, at equal true error, in one run.

For each model and chordal tolerance T:
  1. `ism export MODEL out.glb --tolerance T -j 1 -q --json` (best of 3, CPU time of the child from
     `resource.getrusage`; the whole command: read, extract, write, topology summary).
  2. The export's **true two-sided** error, measured here and not by the exporter: mesh → surface
     at every vertex, edge midpoint, centroid and the three points halfway between the centroid and
     the corners (distance to the model's own surface, below), and surface → mesh from `--samples`
     points of `ism sample --surface` (exactly on the surface) to the mesh (exact point–triangle
     distance, `bench_export_error.surface_to_mesh`); the larger of the two.
  3. scikit-image `marching_cubes` at level c over the model's box, the grid refined by the error's
     h² law until its true error, measured the same way, is at most the export's (the smallest
     such grid is kept; its error is two-sided the same way, with points exactly on the shape it
     approximates: the model's samples, or uniform-by-area points of the analytic shape). SHAPE
     `model`: the grid holds the model's own F (from
     `ism query`), so both meshes approximate the same surface and are measured against it —
     the issue's "marching cubes on a grid of the same implicit function". F exists only on |K|,
     which need not cover the box (a fit's complex misses the box's corners): grid points outside
     |K| get a value of the sign F − c has on all of ∂|K|, and only when that sign is proved from
     the model (every vertex of ∂K has f on one side of c; `boundary_sign` gives the argument);
     otherwise the case is refused. The count of such points is printed. Marching cubes' vertices
     on grid edges that leave |K| are then moved to F's exact crossing on the edge (bisection;
     `exact_boundary_crossings`, `--plain-fill` keeps the interpolated ones): with only a sign
     outside |K|, interpolation puts them up to h off the surface, which dominated MC's error on
     the fitted torus (its surface runs within 1e-2 of ∂|K|). SHAPE sphere:R or
     torus:R:r: the grid holds that analytic g and the error is the exact distance to it (for
     fitted models, whose surface is within the fit tolerance of the analytic shape).
     CPU time: marching cubes itself (`time.process_time`, best of 3); the grid's evaluation is
     printed apart (numpy for analytic g; `ism query`'s CPU for F, which locates every grid point
     in the complex and is not a grid evaluator).
Prints triangles and CPU time of both and the ratios.

Distances to the model's surface: from each probe point Newton steps along ∇F
(`p ← p − (F − c) ∇F / |∇F|²`, F and ∇F from `ism query`, a direct evaluation of F with no
inversion or refinement) until they are below 1e-13, a step that would leave |K| halved until it
stays in; the displacement to the point reached (|F − c| / |∇F| ≤ 1e-12 there, else the case is
refused) is an upper bound of the distance, within ~2 % of the first-order |F − c| / |∇F| at these
distances.

Usage: ISM_BIN=target/release/ism .venv/bin/python tools/bench_export_mc.py
         [--case NAME:MODEL[:SHAPE] ...] [--tolerance T ...] [--max-cells 640]
  Needs numpy, scikit-image, trimesh (tools/requirements.txt).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh
from skimage.measure import marching_cubes

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_export_error import surface_to_mesh  # noqa: E402  (exact point-to-mesh distance)

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "spec" / "examples"

# Fitted presets (`ism fit --preset sphere --resolution 6 --tolerance 4e-3 -o fsphere.ismb`,
# `ism fit --preset torus --tolerance 2e-3 -o ftorus.ismb`): their surfaces are within the fit
# tolerance of the analytic shapes and smooth like them. The spec examples are not: their surfaces
# meet the analytic sphere/torus only along the crossed edges (the sphere example's vertices are up
# to 3.6e-2 off |p| = 0.7), so they are flatter between and need fewer triangles than the analytic
# shape; and marching cubes on their own F converges only like O(h) (F is steep and only C⁰ across
# simplices: grid 32 → 145 took the error from 2.0e-2 to 3.9e-3), so SHAPE `model` on them asks
# for grids of 10⁸ points.
DEFAULT_CASES = [
    "fitted-sphere:fsphere.ismb:sphere:0.6",
    "fitted-torus:ftorus.ismb:torus:0.6:0.25",
]


def child_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def probe_points(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Vertices, edge midpoints, centroids and centroid–corner midpoints of a triangle mesh."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    g = (a + b + c) / 3.0
    return np.concatenate([v, (a + b) / 2, (b + c) / 2, (c + a) / 2, g, (g + a) / 2, (g + b) / 2, (g + c) / 2])


class Shape:
    def __init__(self, spec: list[str]):
        self.kind = spec[0]
        self.p = [float(x) for x in spec[1:]]

    def g(self, x, y, z):
        if self.kind == "sphere":
            return x * x + y * y + z * z - self.p[0] ** 2
        ring = np.sqrt(x * x + y * y) - self.p[0]
        return ring * ring + z * z - self.p[1] ** 2

    def samples(self, n: int) -> np.ndarray:
        """n points uniform by area on the analytic surface (exactly on it, to rounding)."""
        rng = np.random.default_rng(1)
        if self.kind == "sphere":
            x = rng.normal(size=(n, 3))
            return self.p[0] * x / np.linalg.norm(x, axis=1)[:, None]
        big, small = self.p
        out = []
        while sum(len(o) for o in out) < n:
            th, ph = rng.uniform(0, 2 * np.pi, size=(2, 2 * n))
            keep = rng.uniform(size=2 * n) < (big + small * np.cos(ph)) / (big + small)
            th, ph = th[keep], ph[keep]
            ring = big + small * np.cos(ph)
            out.append(np.stack([ring * np.cos(th), ring * np.sin(th), small * np.sin(ph)], axis=1))
        return np.concatenate(out)[:n]

    def distance(self, q: np.ndarray) -> np.ndarray:
        if self.kind == "sphere":
            return np.abs(np.linalg.norm(q, axis=1) - self.p[0])
        ring = np.sqrt(q[:, 0] ** 2 + q[:, 1] ** 2) - self.p[0]
        return np.abs(np.sqrt(ring * ring + q[:, 2] ** 2) - self.p[1])


def ism_export(ism: str, model: str, tol: float, out: Path) -> tuple[float, dict]:
    best = float("inf")
    summary = {}
    for _ in range(3):
        before = child_cpu()
        r = subprocess.run(
            [ism, "export", model, str(out), "--tolerance", str(tol), "-j", "1", "-q", "--json"],
            check=True,
            capture_output=True,
            text=True,
            env=dict(os.environ, RAYON_NUM_THREADS="1"),
        )
        best = min(best, child_cpu() - before)
        summary = json.loads(r.stdout)
    return best, summary


def query(ism: str, model: str, pts: np.ndarray, tmp: Path, with_simplex: bool = False):
    """F, ∇F at `pts` from `ism query`, the child's CPU seconds (and the containing simplex, −1
    outside |K|, when `with_simplex`)."""
    src, dst = tmp / "probe.npy", tmp / "probe-out.npy"
    np.save(src, pts)
    before = child_cpu()
    subprocess.run([ism, "query", model, str(src), "-o", str(dst), "-q", "-j", "1"], check=True)
    cpu = child_cpu() - before
    out = np.load(dst)
    g = np.stack([out["gx"], out["gy"], out["gz"]], axis=1)
    if with_simplex:
        return out["f"].copy(), g, cpu, np.asarray(out["simplex"])
    return out["f"], g, cpu


_BOUNDARY_SIGN: dict[str, int] = {}


def boundary_sign(ism: str, model: str, tmp: Path) -> int:
    """The sign of F − c on all of ∂|K|, proved from the model, or SystemExit.

    X maps every face of K onto itself (spec/mathematics.md §1), so on a boundary triangle τ of K
    F = Σ f(vᵢ) X_σ(w)ᵢ is a convex combination of f at τ's three vertices. Hence if f − c has one
    strict sign s at every vertex of every boundary triangle (triangles in exactly one tetrahedron),
    F − c has sign s on all of ∂|K|: the level set lies in the interior of |K|, and every point
    outside |K| is on the side s of the shape (s = +1: outside the solid). Giving grid points
    outside |K| any value of sign s then keeps every grid point's sign right, and no grid edge
    gets a sign change that the surface does not cause. (Where the assigned magnitude places
    marching cubes' vertex on such an edge is not exact; those vertices are measured like every
    other one.) The comparisons are exact (stored values against the stored level)."""
    if model in _BOUNDARY_SIGN:
        return _BOUNDARY_SIGN[model]
    js = tmp / "model.ism.json"
    subprocess.run([ism, "convert", model, str(js)], check=True, capture_output=True)
    doc = json.loads(js.read_text())
    js.unlink()
    if doc["dimension"] != 3:
        raise SystemExit(f"{model}: grid points outside |K| are only handled for 3D models")
    tets = np.asarray(doc["simplices"], dtype=np.int64).reshape(-1, 4)
    f = np.asarray(doc["values"], dtype=np.float64)
    c = float(doc.get("level", 0.0))
    tris = np.sort(np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 2, 3]], tets[:, [0, 1, 3]], tets[:, [0, 1, 2]]]), axis=1)
    uniq, count = np.unique(tris, axis=0, return_counts=True)
    bverts = np.unique(uniq[count == 1])
    d = f[bverts] - c
    if np.all(d > 0):
        s = 1
    elif np.all(d < 0):
        s = -1
    else:
        raise SystemExit(
            f"{model}: grid points lie outside |K| and f − c changes sign on ∂K "
            f"({int((d > 0).sum())} of {len(d)} boundary vertices above the level): the shape may "
            "reach the complex's boundary, so no sign outside |K| is provably right; refusing this case"
        )
    print(f"  {model}: ∂K has {int((count == 1).sum()):,} triangles, {len(bverts):,} vertices, "
          f"all with f {'>' if s > 0 else '<'} c: F − c {'>' if s > 0 else '<'} 0 on ∂|K|",
          file=sys.stderr, flush=True)
    _BOUNDARY_SIGN[model] = s
    return s


def model_distance(ism: str, model: str, level: float, pts: np.ndarray, tmp: Path) -> float:
    """Largest distance from `pts` to the model's surface (module doc: Newton along ∇F).

    A step that would leave |K| (`ism query` gives no F there: the fitted torus's surface runs
    within 1e-2 of ∂|K|, whose z-extent is the torus's height) is halved until its end is in |K|,
    so the walk stays where F exists. The walk ends on the surface (|F − c| / |∇F| ≤ 1e-12, else
    the case is refused), so the displacement is an upper bound of the distance, whatever the path;
    the halved steps only make it less tight (their count is printed). A probe point outside |K|
    (no F to start from) is refused."""
    q = pts.copy()
    f, g, _ = query(ism, model, q, tmp)
    bad = ~(np.isfinite(f) & np.all(np.isfinite(g), axis=1))
    if bad.any():
        raise SystemExit(f"{model}: {int(bad.sum())} probe points lie outside the complex (no F to start from)")
    halved = 0
    for _ in range(20):
        gg = np.einsum("ij,ij->i", g, g)
        step = -((f - level) / gg)[:, None] * g
        move = np.linalg.norm(step, axis=1) > 1e-13
        if not move.any():
            break
        idx = np.flatnonzero(move)
        t = np.ones(len(idx))
        for _ in range(40):
            cand = q[idx] + t[:, None] * step[idx]
            fc, gc, _ = query(ism, model, cand, tmp)
            ok = np.isfinite(fc) & np.all(np.isfinite(gc), axis=1)
            q[idx[ok]], f[idx[ok]], g[idx[ok]] = cand[ok], fc[ok], gc[ok]
            if ok.all():
                break
            halved += int((~ok).sum())
            idx, t = idx[~ok], t[~ok] / 2
        else:
            raise SystemExit(f"{model}: a Newton step stays outside the complex after 40 halvings")
    residual = np.abs(f - level) / np.sqrt(np.einsum("ij,ij->i", g, g))
    if not residual.max() <= 1e-12:
        raise SystemExit(f"{model}: the Newton walk did not reach the surface (|F − c|/|∇F| = {residual.max():.1e})")
    if halved:
        print(f"  {halved} Newton steps halved to stay in |K|", file=sys.stderr, flush=True)
    return float(np.linalg.norm(q - pts, axis=1).max())


class Grid:
    """The sampled function on a grid with `cells` cells along the box's longest side."""

    def __init__(self, box: list[list[float]], cells: int):
        self.lo = np.array([b[0] for b in box], dtype=np.float64)
        hi = np.array([b[1] for b in box], dtype=np.float64)
        self.h = float((hi - self.lo).max() / cells)
        # Rounded up, so the grid covers the box: rounded to nearest it stopped up to h/2 short
        # of a shorter side (the fitted torus's top, 0.242 of 0.25 at 96 cells), and marching
        # cubes missed the surface beyond (errors of 6e-2 at 96 cells, 1e-2 at 256).
        counts = [int(np.ceil((hi[k] - self.lo[k]) / self.h - 1e-9)) + 1 for k in range(3)]
        self.axes = [self.lo[k] + self.h * np.arange(counts[k]) for k in range(3)]


def mc(grid: Grid, vol: np.ndarray, level: float):
    """Marching cubes (best CPU of 3): vertices in model coordinates, faces, CPU seconds."""
    best = float("inf")
    for _ in range(3):
        t = time.process_time()
        v, f, _, _ = marching_cubes(vol, level, spacing=(grid.h,) * 3)
        best = min(best, time.process_time() - t)
    return v + grid.lo, f, best


def sample(shape, ism, model, level: float, grid: Grid, tmp: Path):
    """The grid's values, the CPU seconds of computing them, and which grid points lie outside |K|
    (SHAPE `model`; None otherwise)."""
    if shape is None:
        x, y, z = np.meshgrid(*grid.axes, indexing="ij")
        pts = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
        del x, y, z
        f, _, cpu, simplex = query(ism, model, pts, tmp, with_simplex=True)
        out = simplex < 0
        if not np.all(np.isfinite(f[~out])):
            raise SystemExit(f"{model}: `ism query` gave no F at a grid point inside |K|")
        if out.any():
            # Grid points outside |K| (`ism query`: simplex -1): give them the sign F − c has on all
            # of ∂|K| — only when that sign is proved constant (`boundary_sign`, refuses otherwise).
            s = boundary_sign(ism, model, tmp)
            # The magnitude (the largest |F − c| inside) only places marching cubes' vertices on
            # edges leaving |K|; they are measured like every other vertex.
            f[out] = level + s * float(np.abs(f[~out] - level).max(initial=0.0) or 1.0)
            print(f"  {int(out.sum()):,} of {len(f):,} grid points outside |K|: set to F − c "
                  f"{'>' if s > 0 else '<'} 0 (every vertex of ∂K has f {'>' if s > 0 else '<'} c)",
                  file=sys.stderr, flush=True)
        shape3 = [len(a) for a in grid.axes]
        return f.reshape(shape3), cpu, out.reshape(shape3)
    t = time.process_time()
    x, y, z = np.meshgrid(*grid.axes, indexing="ij")
    vol = shape.g(x, y, z)
    return vol, time.process_time() - t, None


def exact_boundary_crossings(ism: str, model: str, level: float, grid: Grid, outside: np.ndarray,
                             v: np.ndarray, tmp: Path) -> int:
    """Moves marching cubes' vertices on grid edges that leave |K| to F's exact crossing there.

    Such an edge joins a grid point inside |K| to one outside, whose value is only a sign
    (`sample`), so the linear interpolation places the vertex anywhere up to h off the surface,
    which would dominate MC's error where the surface runs close to ∂|K| (the fitted torus). Here
    the crossing is found by bisection of the sign of F − c along the edge (a point outside |K| has
    the sign proved on ∂|K|, `boundary_sign`) to 2⁻⁴⁵ h: marching cubes with exact crossings on
    those edges, a kinder peer than plain marching cubes. Returns how many vertices moved."""
    idx = (v - grid.lo) / grid.h
    near = np.round(idx)
    off = np.abs(idx - near)
    axis = np.argmax(off, axis=1)
    on_edge = off[np.arange(len(v)), axis] > 1e-9
    a = near.astype(np.int64)
    a[np.arange(len(v)), axis] = np.floor(idx[np.arange(len(v)), axis]).astype(np.int64)
    b = a.copy()
    b[np.arange(len(v)), axis] += 1
    dims = np.array(outside.shape) - 1
    a, b = np.clip(a, 0, dims), np.clip(b, 0, dims)
    oa = outside[a[:, 0], a[:, 1], a[:, 2]]
    ob = outside[b[:, 0], b[:, 1], b[:, 2]]
    sel = np.flatnonzero(on_edge & (oa != ob))
    if len(sel) == 0:
        return 0
    s = boundary_sign(ism, model, tmp)
    inside_end = np.where(oa[sel, None], b[sel], a[sel])
    outside_end = np.where(oa[sel, None], a[sel], b[sel])
    p0 = grid.lo + grid.h * inside_end
    p1 = grid.lo + grid.h * outside_end
    lo_t, hi_t = np.zeros(len(sel)), np.ones(len(sel))
    f0, _, _ = query(ism, model, p0, tmp)
    if not (np.all(np.isfinite(f0)) and np.all(np.sign(f0 - level) == -s)):
        raise SystemExit(f"{model}: a boundary edge's inside end is not on the other side of the level")
    for _ in range(45):
        mid = (lo_t + hi_t) / 2
        f, _, _ = query(ism, model, p0 + mid[:, None] * (p1 - p0), tmp)
        side = np.where(np.isfinite(f), np.sign(f - level), s)
        towards_out = side == s
        hi_t = np.where(towards_out, mid, hi_t)
        lo_t = np.where(towards_out, lo_t, mid)
    v[sel] = p0 + ((lo_t + hi_t) / 2)[:, None] * (p1 - p0)
    return len(sel)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--case", action="append", help="NAME:MODEL:SHAPE (see the docstring)")
    ap.add_argument("--tolerance", action="append", type=float)
    ap.add_argument("--samples", type=int, default=50_000, help="surface points for the O → mesh half")
    ap.add_argument("--max-cells", type=int, default=640,
                    help="largest grid (cells per side); 641³ doubles are 2.1 GB, x4 with the meshgrid")
    ap.add_argument("--plain-fill", action="store_true",
                    help="SHAPE model: keep MC's interpolated vertices on grid edges leaving |K| "
                         "(default: moved to F's exact crossing, `exact_boundary_crossings`)")
    args = ap.parse_args()
    ism = os.environ.get("ISM_BIN", str(ROOT / "target" / "release" / "ism"))
    cases = args.case or DEFAULT_CASES
    tolerances = args.tolerance or [1e-3, 1e-4]
    print(f"ism: {ism}; load average {os.getloadavg()}")
    print(
        "| model | tolerance | ISM triangles | ISM true error | ISM CPU s (whole export) | MC grid | MC triangles | MC true error "
        "| MC CPU s (marching cubes) | grid values CPU s | triangles ISM/MC | CPU ISM/MC |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for case in cases:
            name, model, *shape_spec = case.split(":")
            shape = None if shape_spec in ([], ["model"]) else Shape(shape_spec)
            info = json.loads(subprocess.run([ism, "info", model, "--json"], check=True, capture_output=True, text=True).stdout)
            level = float(info["level"])
            box = info["bounding_box"]
            # Exact points of the model's surface for the O → mesh half of the error.
            subprocess.run([ism, "sample", model, "--surface", str(args.samples), "--seed", "1", "-o", str(tmp / "s.npy"), "-q"], check=True)
            sa = np.load(tmp / "s.npy")
            on_model = np.stack([sa["x"], sa["y"], sa["z"]], axis=1)
            on_shape = shape.samples(args.samples) if shape else on_model
            for tol in tolerances:
                out = tmp / "out.glb"
                cpu, summary = ism_export(ism, model, tol, out)
                mesh = trimesh.load(str(out), force="mesh", process=False)
                pts = probe_points(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces))
                vm, fm = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
                err = max(model_distance(ism, model, level, pts, tmp), float(surface_to_mesh(on_model, vm, fm, 16).max()))
                cells = min(32, args.max_cells)
                tried = {}
                for _ in range(12):
                    grid = Grid(box, cells)
                    vol, grid_cpu, outside = sample(shape, ism, model, level, grid, tmp)
                    v, f, mc_cpu = mc(grid, vol, 0.0 if shape else level)
                    del vol
                    if outside is not None and outside.any() and not args.plain_fill:
                        moved = exact_boundary_crossings(ism, model, level, grid, outside, v, tmp)
                        print(f"  {moved:,} MC vertices on grid edges leaving |K| moved to F's exact crossing",
                              file=sys.stderr, flush=True)
                    probes = probe_points(v, f)
                    mc_err = float(shape.distance(probes).max()) if shape else model_distance(ism, model, level, probes, tmp)
                    mc_err = max(mc_err, float(surface_to_mesh(on_shape, v, f, 16).max()))
                    tried[cells] = (len(f), mc_cpu, mc_err, grid_cpu)
                    print(f"  grid {cells}: {len(f):,} triangles, error {mc_err:.3e} (target {err:.3e}), grid values {grid_cpu:.2f} CPU-s", file=sys.stderr, flush=True)
                    if mc_err <= err and (cells - 1) in tried and tried[cells - 1][2] > err:
                        break
                    # Error ∝ h²: aim at the target, then walk by one cell to the smallest grid meeting it.
                    nxt = max(4, int(np.ceil(cells * np.sqrt(mc_err / err))))
                    if nxt == cells or nxt in tried:
                        nxt = cells + 1 if mc_err > err else cells - 1
                    # The cap keeps the grid (and numpy's meshgrid copies) in memory: uncapped, the
                    # h² law asked for 2,621 cells per side (38 GiB) on the fitted torus at 1e-4.
                    nxt = min(nxt, args.max_cells)
                    if nxt in tried:
                        break
                    cells = nxt
                ok = [c for c, t in tried.items() if t[2] <= err]
                if not ok:
                    # The finest grid tried, with the ISM side: MC's triangles there are a lower bound.
                    cells = max(tried)
                    n_mc, mc_cpu, mc_err, grid_cpu = tried[cells]
                    print(
                        f"| {name} | {tol:g} | {summary['cells']:,} | {err:.3e} | {cpu:.3f} | {cells} (none up to "
                        f"{args.max_cells} met the error) | {n_mc:,} | {mc_err:.3e} | {mc_cpu:.3f} | {grid_cpu:.2f} "
                        f"| < {summary['cells'] / n_mc:.2f} | — |",
                        flush=True,
                    )
                    print(f"  grids tried (triangles, MC CPU s, error, grid values CPU s): {tried}", file=sys.stderr, flush=True)
                    continue
                cells = min(ok)
                n_mc, mc_cpu, mc_err, grid_cpu = tried[cells]
                print(
                    f"| {name} | {tol:g} | {summary['cells']:,} | {err:.3e} | {cpu:.3f} | {cells} | {n_mc:,} | {mc_err:.3e} "
                    f"| {mc_cpu:.3f} | {grid_cpu:.2f} | {summary['cells'] / n_mc:.2f} | {cpu / mc_cpu:.2f} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
