#!/usr/bin/env python3
"""Validator throughput against Gmsh on the same curved triangles and tetrahedra (BENCHMARKS.md,
section validate).

For each dimension (2, 3) and degree (2, 3, 4) it draws general Bezier control nets on the unit
simplex: vertices fixed, every other control point b_I = I/d + a * r_I with r_I a random vector of
the plane sum(w) = 0 and an amplitude a uniform in [0, A] per element, so the set mixes valid and
folded elements (no theorem covers such nets). With --near, every element is then moved toward its
own fold threshold: the amplitude is bisected (--near-steps times, our certifier deciding each
step) between 0 and the largest amplitude that folds, and the element is emitted at the last
valid or the last folded amplitude (alternately) — nets whose det DX nearly touches 0, where a
certificate must subdivide deep or fall back to exact arithmetic. The Rust side
(`cargo run --release -p ism-validate --example certify_nets`) certifies the nets; Gmsh builds the
same elements as Lagrange tetrahedra of the same order (the map evaluated at Gmsh's own reference
nodes, taken from getElementProperties, so the node ordering is Gmsh's by construction) and runs
gmsh.model.mesh.getElementQualities(tags, "minDetJac"). Both are timed on the check alone, as CPU
time (ours: the process's CPU time around each certification pass, read by certify_nets from
/proc/self/task/*/schedstat; Gmsh: process CPU time around the call), best of --repeat, with 1 and 2 threads (wall
time for 2); verdicts are compared element by element (ours: certified valid / invalid /
undetermined; Gmsh: minDetJac > 0). --whole-process also times both tools end to end on a
3,000-element file (ours: `ism validate` on an ISM JSON file of 3,000 elements; Gmsh: a Python
process that reads the same elements from a .msh file and computes minDetJac). Rational stages (adjusted nets, random
weights) are timed on our side only: a Lagrange element cannot represent a rational map.

Install: `pip install gmsh` (a self-contained wheel, a few seconds; listed in tools/requirements.txt).
Run:     .venv/bin/python tools/bench_gmsh.py --count 100000
"""

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def multi_indices(m, d):
    """All multi-indices of degree d in m variables, canonical order (lexicographically decreasing)."""
    if m == 1:
        return [(d,)]
    out = []
    for first in range(d, -1, -1):
        for rest in multi_indices(m - 1, d - first):
            out.append((first,) + rest)
    return out


def bernstein_matrix(bary, d):
    """B[k, I] = B_I(bary[k]) for barycentric points (K x m)."""
    m = bary.shape[1]
    idx = multi_indices(m, d)
    cols = []
    for i in idx:
        mult = math.factorial(d) / math.prod(math.factorial(e) for e in i)
        cols.append(mult * np.prod([bary[:, c] ** i[c] for c in range(m)], axis=0))
    return np.stack(cols, axis=1)


def pad4(nets):
    """Pads barycentric coordinates to the 4 the Rust reader expects."""
    out = np.zeros(nets.shape[:-1] + (4,))
    out[..., : nets.shape[-1]] = nets
    return out


def general_directions(rng, count, n, d):
    """Base nets I/d and random moves r (zero on vertices, coordinates summing to 0)."""
    idx = np.array(multi_indices(n + 1, d), dtype=float)
    base = np.repeat((idx / d)[None, :, :], count, axis=0)
    r = rng.normal(size=base.shape)
    r -= r.mean(axis=2, keepdims=True)
    moving = (idx.max(axis=1) < d)[None, :, None]
    return base, r * moving


def general_nets(rng, count, n, d, amplitude):
    """count x N x (n+1) barycentric control points of general (non-adjusted) nets."""
    base, r = general_directions(rng, count, n, d)
    a = rng.uniform(0.0, amplitude, size=(count, 1, 1))
    return base + a * r


def near_nets(rng, count, n, d, amplitude, binary, steps, tmp):
    """Nets moved to their fold threshold by bisection on the amplitude, our certifier deciding."""
    base, r = general_directions(rng, count, n, d)
    lo = np.zeros(count)
    hi = np.full(count, 4.0 * amplitude)
    path = os.path.join(tmp, "near.bin")
    write_nets(path, n, d, base + hi[:, None, None] * r)
    _, verdicts = run_ours(binary, path, 0, 1)
    folds = verdicts == 0
    base, r, lo, hi = base[folds], r[folds], lo[folds], hi[folds]
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        write_nets(path, n, d, base + mid[:, None, None] * r)
        _, verdicts = run_ours(binary, path, 0, 1)
        valid = verdicts == 1
        lo = np.where(valid, mid, lo)
        hi = np.where(valid, hi, mid)
    pick = np.where(np.arange(lo.size) % 2 == 0, lo, hi)
    return base + pick[:, None, None] * r


def adjusted_rational(rng, count, d, amplitude):
    """Adjusted nets (each point in the open face owning it) and log-uniform weights in [1/4, 4]."""
    idx = np.array(multi_indices(4, d), dtype=float)
    support = idx > 0
    base = idx / d
    r = rng.uniform(1e-3, 1.0, size=(count,) + idx.shape) * support[None]
    r /= r.sum(axis=2, keepdims=True)
    lam = rng.uniform(0.0, amplitude, size=(count, 1, 1))
    nets = (1 - lam) * base[None] + lam * r
    weights = np.exp(rng.uniform(-math.log(4), math.log(4), size=(count, idx.shape[0])))
    return nets, weights


def write_nets(path, n, d, nets, weights=None):
    header = {"n": n, "degree": d, "rational": weights is not None, "count": int(nets.shape[0])}
    with open(path, "wb") as f:
        f.write((json.dumps(header) + "\n").encode())
        f.write(np.ascontiguousarray(pad4(nets), dtype="<f8").tobytes())
        if weights is not None:
            f.write(np.ascontiguousarray(weights, dtype="<f8").tobytes())


def children_cpu():
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run_ours(binary, nets_path, threads, repeat):
    """Runs certify_nets; stats["cpu_per_run"] is the CPU seconds of one certification pass: the
    process's CPU time around the pass as certify_nets measures it (best of repeat), or, from a
    binary that does not report it, the run with --repeat 0 (which only loads) subtracted."""
    out = tempfile.NamedTemporaryFile(delete=False, suffix=".verdicts").name
    cmd = [binary, nets_path, out, "--threads", str(threads)]
    c0 = children_cpu()
    subprocess.run(cmd + ["--repeat", "0"], check=True, capture_output=True)
    c1 = children_cpu()
    res = subprocess.run(cmd + ["--repeat", str(repeat)], check=True, capture_output=True, text=True)
    c2 = children_cpu()
    stats = json.loads(res.stdout.strip().splitlines()[-1])
    # Mean CPU of a pass by subtraction (loading cancels, start-up noise does not: a few ms, as
    # much as a whole pass on the smaller sets) ...
    stats["cpu_subtracted"] = max((c2 - c1) - (c1 - c0), 1e-9) / repeat
    # ... and, when the binary reports it, its own CPU time around each pass, best of repeat: the
    # same measure as Gmsh's (process CPU time around the call, best of repeat).
    stats["cpu_per_run"] = stats.get("cpu_seconds") or stats["cpu_subtracted"]
    verdicts = np.fromfile(out, dtype=np.uint8)
    os.unlink(out)
    return stats, verdicts


def gmsh_elements(gmsh, nets, n, d):
    """Adds the nets as Lagrange elements of order d at Gmsh's own reference nodes."""
    count = nets.shape[0]
    etype = gmsh.model.mesh.getElementType("Tetrahedron" if n == 3 else "Triangle", d)
    _, _, _, num_nodes, local, _ = gmsh.model.mesh.getElementProperties(etype)
    uvw = np.array(local).reshape(num_nodes, -1)[:, :n]
    bary = np.column_stack([1.0 - uvw.sum(axis=1), uvw])
    B = bernstein_matrix(bary, d)  # nodes x N
    # Unit simplex: physical position = (X_1 … X_n), padded to 3D.
    phys = np.zeros((count, num_nodes, 3))
    phys[:, :, :n] = np.einsum("kn,enc->ekc", B, nets)[:, :, 1 : n + 1]
    tag = gmsh.model.addDiscreteEntity(n)
    node_tags = np.arange(1, count * num_nodes + 1)
    gmsh.model.mesh.addNodes(n, tag, node_tags, phys.reshape(-1))
    elem_tags = np.arange(1, count + 1)
    gmsh.model.mesh.addElementsByType(tag, etype, elem_tags, node_tags)
    return elem_tags


def _gmsh_worker(nets, n, d, repeat, barrier, queue, slot):
    """Builds the elements in one Gmsh instance and times getElementQualities (best of repeat):
    wall time and process CPU time."""
    import gmsh

    gmsh.initialize(["-noenv"], readConfigFiles=False)
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.option.setNumber("General.NumThreads", 1)
    gmsh.model.add("bench")
    elem_tags = gmsh_elements(gmsh, nets, n, d)
    times = []
    cpus = []
    q = None
    for _ in range(repeat):
        if barrier is not None:
            barrier.wait()
        start = time.perf_counter()
        c0 = time.process_time()
        q = np.asarray(gmsh.model.mesh.getElementQualities(elem_tags, "minDetJac"))
        cpus.append(time.process_time() - c0)
        times.append(time.perf_counter() - start)
    gmsh.finalize()
    queue.put((slot, times, cpus, q))


def run_gmsh(nets, n, d, threads, repeat):
    """Gmsh's Python API is not thread-safe for concurrent quality queries, so `threads` > 1 runs
    that many processes on equal shares, started together; the time of a round is the slowest
    process's."""
    import multiprocessing as mp

    ctx = mp.get_context("fork")
    queue = ctx.Queue()
    chunks = np.array_split(nets, threads)
    barrier = ctx.Barrier(threads) if threads > 1 else None
    procs = [ctx.Process(target=_gmsh_worker, args=(c, n, d, repeat, barrier, queue, i)) for i, c in enumerate(chunks)]
    for p in procs:
        p.start()
    results = sorted((queue.get() for _ in procs), key=lambda r: r[0])
    for p in procs:
        p.join()
    rounds = np.max(np.array([r[1] for r in results]), axis=0)
    cpu = np.sum(np.array([r[2] for r in results]), axis=0)
    q = np.concatenate([r[3] for r in results])
    return float(rounds.min()), float(cpu.min()), q


def grid_model(rng, cells):
    """An ISM (JSON text) of 2·cells² quadratic triangles on the unit square with a random adjusted
    edge point on every edge, and the same elements as a list of dense nets (for Gmsh)."""
    k = cells + 1
    verts = [(i / cells, j / cells) for j in range(k) for i in range(k)]
    tris = []
    for j in range(cells):
        for i in range(cells):
            a, b, c, d = j * k + i, j * k + i + 1, (j + 1) * k + i + 1, (j + 1) * k + i
            tris += [(a, b, c), (a, c, d)]
    edges = sorted({tuple(sorted(e)) for t in tris for e in ((t[0], t[1]), (t[1], t[2]), (t[0], t[2]))})
    t = {e: float(rng.uniform(0.3, 0.7)) for e in edges}
    model = {
        "version": "1.0",
        "dimension": 2,
        "vertices": [x for v in verts for x in v],
        "simplices": [i for tr in tris for i in tr],
        "values": [1.0 if (v[0] - 0.5) ** 2 + (v[1] - 0.5) ** 2 > 0.1 else -1.0 for v in verts],
        "level": 0.0,
        "stages": [
            {
                "kind": "bezier",
                "degree": 2,
                "direction": "implicit",
                "faces": [{"face": list(e), "points": [t[e], 1.0 - t[e]]} for e in edges],
            }
        ],
    }
    # Dense nets in local order (canonical multi-indices of degree 2 in 3 variables).
    idx = multi_indices(3, 2)
    nets = np.zeros((len(tris), len(idx), 3))
    for e, tr in enumerate(tris):
        for r, I in enumerate(idx):
            support = [c for c in range(3) if I[c] > 0]
            if len(support) == 1:
                nets[e, r, support[0]] = 1.0
                continue
            a, b = support
            lo, hi = sorted((tr[a], tr[b]))
            # The record stores the point for the sorted ids (lo, hi).
            pa = t[(lo, hi)] if tr[a] == lo else 1.0 - t[(lo, hi)]
            nets[e, r, a] = pa
            nets[e, r, b] = 1.0 - pa
    # Physical coordinates: the unit square, not the unit simplex, so map each triangle's net
    # through its own affine map for Gmsh.
    corners = np.array([[verts[i] for i in tr] for tr in tris])  # E x 3 x 2
    return json.dumps(model), nets, corners


GMSH_WHOLE = """
import sys, gmsh
gmsh.initialize(["-noenv"], readConfigFiles=False)
gmsh.option.setNumber("General.Terminal", 0)
gmsh.option.setNumber("General.NumThreads", 1)
gmsh.open(sys.argv[1])
types, tags, _ = gmsh.model.mesh.getElements(2)
q = gmsh.model.mesh.getElementQualities(tags[0], "minDetJac")
print(sum(1 for x in q if x > 0))
gmsh.finalize()
"""


def whole_process(rng, ism_binary, repeat, tmp):
    """`ism validate` on a 3,042-element JSON file against a Gmsh process on the same elements."""
    text, nets, corners = grid_model(rng, 39)
    ism_path = os.path.join(tmp, "grid.ism.json")
    with open(ism_path, "w") as f:
        f.write(text)
    # The same quadratic triangles as a .msh for Gmsh: Lagrange nodes = the map at Gmsh's nodes,
    # pushed through each triangle's affine map.
    import gmsh

    gmsh.initialize(["-noenv"], readConfigFiles=False)
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.model.add("grid")
    etype = gmsh.model.mesh.getElementType("Triangle", 2)
    _, _, _, num_nodes, local, _ = gmsh.model.mesh.getElementProperties(etype)
    uv = np.array(local).reshape(num_nodes, -1)[:, :2]
    bary = np.column_stack([1.0 - uv.sum(axis=1), uv])
    B = bernstein_matrix(bary, 2)
    mapped = np.einsum("kn,enc->ekc", B, nets)  # E x nodes x 3 (barycentric images)
    phys = np.einsum("ekc,ecx->ekx", mapped, corners)
    pad = np.zeros(phys.shape[:2] + (3,))
    pad[:, :, :2] = phys
    tag = gmsh.model.addDiscreteEntity(2)
    count = nets.shape[0]
    node_tags = np.arange(1, count * num_nodes + 1)
    gmsh.model.mesh.addNodes(2, tag, node_tags, pad.reshape(-1))
    gmsh.model.mesh.addElementsByType(tag, etype, np.arange(1, count + 1), node_tags)
    msh_path = os.path.join(tmp, "grid.msh")
    gmsh.write(msh_path)
    gmsh.finalize()
    script = os.path.join(tmp, "gmsh_whole.py")
    with open(script, "w") as f:
        f.write(GMSH_WHOLE)
    rows = []
    for name, cmd in [
        ("ism validate", [ism_binary, "validate", "--threads", "1", ism_path]),
        ("ism validate --no-theorems", [ism_binary, "validate", "--threads", "1", "--no-theorems", ism_path]),
        ("gmsh (python, minDetJac)", [sys.executable, script, msh_path]),
    ]:
        best_wall, best_cpu = math.inf, math.inf
        for _ in range(repeat):
            c0 = children_cpu()
            t0 = time.perf_counter()
            res = subprocess.run(cmd, capture_output=True, text=True)
            best_wall = min(best_wall, time.perf_counter() - t0)
            best_cpu = min(best_cpu, children_cpu() - c0)
            assert res.returncode == 0, (cmd, res.stdout, res.stderr)
        rows.append({"whole_process": name, "elements": count, "wall_s": round(best_wall, 4), "cpu_s": round(best_cpu, 4)})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--count", type=int, default=100000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--dims", default="2,3")
    ap.add_argument("--degrees", default="2,3,4")
    ap.add_argument("--amplitude", type=float, default=None, help="perturbation bound (default per degree)")
    ap.add_argument("--near", action="store_true", help="also nets moved to their fold threshold")
    ap.add_argument("--near-steps", type=int, default=40, help="bisection steps toward the threshold")
    ap.add_argument("--near-count", type=int, default=None, help="elements of the near sets (default --count)")
    ap.add_argument("--no-rational", action="store_true")
    ap.add_argument("--no-general", action="store_true", help="skip the general sets (with --near)")
    ap.add_argument("--keep", default=None, help="directory to keep every set's nets in ({general,near}ND.bin)")
    ap.add_argument("--whole-process", action="store_true", help="also end-to-end on a 3,042-element file")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--binary", default=os.path.join(ROOT, "target/release/examples/certify_nets"))
    ap.add_argument("--ism", default=os.path.join(ROOT, "target/release/ism"))
    args = ap.parse_args()
    if not os.path.exists(args.binary):
        subprocess.run(
            ["cargo", "build", "--release", "-p", "ism-validate", "--example", "certify_nets"], check=True, cwd=ROOT
        )
    rng = np.random.default_rng(args.seed)
    rows = []
    tmp = tempfile.mkdtemp()
    # Amplitudes giving roughly half folded elements at each degree (control points move less at
    # higher degree because they are closer together).
    default_amp = {2: 0.45, 3: 0.22, 4: 0.14}
    sets = ([] if args.no_general else ["general"]) + (["near"] if args.near else [])
    if args.keep:
        os.makedirs(args.keep, exist_ok=True)
    for n in [int(x) for x in args.dims.split(",")]:
        for d in [int(x) for x in args.degrees.split(",")]:
            amp = args.amplitude or default_amp.get(d, 0.1)
            for which in sets:
                if which == "general":
                    nets = general_nets(rng, args.count, n, d, amp)
                else:
                    nets = near_nets(rng, args.near_count or args.count, n, d, amp, args.binary, args.near_steps, tmp)
                path = os.path.join(args.keep or tmp, f"{which}{n}{d}.bin")
                write_nets(path, n, d, nets)
                count = nets.shape[0]
                for threads in (1, 2):
                    ours, verdicts = run_ours(args.binary, path, threads, args.repeat)
                    gsec, gcpu, q = run_gmsh(nets, n, d, threads, args.repeat)
                    gvalid = q > 0
                    decided = verdicts != 2
                    agree = int(np.sum((verdicts[decided] == 1) == gvalid[decided]))
                    row = {
                        "n": n,
                        "nets": which,
                        "degree": d,
                        "threads": threads,
                        "elements": count,
                        "ours_per_cpu_s": round(count / ours["cpu_per_run"]),
                        "gmsh_per_cpu_s": round(count / gcpu),
                        "ratio_cpu": round(gcpu / ours["cpu_per_run"], 2),
                        "ratio_cpu_subtracted": round(gcpu / ours["cpu_subtracted"], 2),
                        "ours_per_wall_s": round(ours["per_second"]),
                        "gmsh_per_wall_s": round(count / gsec),
                        "ratio_wall": round(ours["per_second"] / (count / gsec), 2),
                        "ours_valid": ours["valid"],
                        "ours_invalid": ours["invalid"],
                        "ours_undetermined": ours["undetermined"],
                        "gmsh_valid": int(gvalid.sum()),
                        "verdicts_agree": agree,
                        "verdicts_differ": int(decided.sum()) - agree,
                    }
                    rows.append(row)
                    print(json.dumps(row), flush=True)
    if not args.no_rational:
        for d in (2, 3):
            nets, weights = adjusted_rational(rng, args.count, d, 1.0)
            path = os.path.join(tmp, f"rational{d}.bin")
            write_nets(path, 3, d, nets, weights)
            for threads in (1, 2):
                ours, verdicts = run_ours(args.binary, path, threads, args.repeat)
                row = {
                    "kind": "rational",
                    "n": 3,
                    "degree": d,
                    "threads": threads,
                    "elements": args.count,
                    "ours_per_cpu_s": round(args.count / ours["cpu_per_run"]),
                    "ours_valid": ours["valid"],
                    "ours_invalid": ours["invalid"],
                    "ours_undetermined": ours["undetermined"],
                }
                rows.append(row)
                print(json.dumps(row), flush=True)
    if args.whole_process:
        if not os.path.exists(args.ism):
            subprocess.run(["cargo", "build", "--release", "-p", "ism-cli"], check=True, cwd=ROOT)
        rows += whole_process(rng, args.ism, args.repeat, tmp)
    return 0


if __name__ == "__main__":
    sys.exit(main())
