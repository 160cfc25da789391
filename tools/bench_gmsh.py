#!/usr/bin/env python3
"""Validator throughput against Gmsh on the same curved tetrahedra (BENCHMARKS.md, section validate).

For each degree (2, 3, 4) it draws general Bezier control nets on the unit tetrahedron: vertices
fixed, every other control point b_I = I/d + a * r_I with r_I a random vector of the plane
sum(w) = 0 and an amplitude a uniform in [0, A] per element, so the set mixes valid and folded
elements (no theorem covers such nets). The Rust side
(`cargo run --release -p ism-validate --example certify_nets`) certifies the nets; Gmsh builds the
same elements as Lagrange tetrahedra of the same order (the map evaluated at Gmsh's own reference
nodes, taken from getElementProperties, so the node ordering is Gmsh's by construction) and runs
gmsh.model.mesh.getElementQualities(tags, "minDetJac"). Both are timed on the check alone, best of
--repeat runs, with 1 and 2 threads; verdicts are compared element by element (ours: certified
valid / invalid / undetermined; Gmsh: minDetJac > 0). Rational stages (adjusted nets, random
weights) are timed on our side only: a Lagrange element cannot represent a rational map.

Install: `pip install gmsh` (a self-contained wheel, a few seconds; listed in tools/requirements.txt).
Run:     .venv/bin/python tools/bench_gmsh.py --count 100000
"""

import argparse
import json
import math
import os
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


def general_nets(rng, count, d, amplitude):
    """count x N x 4 barycentric control points of general (non-adjusted) nets on a tetrahedron."""
    idx = np.array(multi_indices(4, d), dtype=float)
    base = idx / d
    nets = np.repeat(base[None, :, :], count, axis=0)
    r = rng.normal(size=nets.shape)
    r -= r.mean(axis=2, keepdims=True)
    a = rng.uniform(0.0, amplitude, size=(count, 1, 1))
    moving = (idx.max(axis=1) < d)[None, :, None]
    return nets + a * r * moving


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


def write_nets(path, d, nets, weights=None):
    header = {"n": 3, "degree": d, "rational": weights is not None, "count": int(nets.shape[0])}
    with open(path, "wb") as f:
        f.write((json.dumps(header) + "\n").encode())
        f.write(np.ascontiguousarray(nets, dtype="<f8").tobytes())
        if weights is not None:
            f.write(np.ascontiguousarray(weights, dtype="<f8").tobytes())


def run_ours(binary, nets_path, threads, repeat):
    out = tempfile.NamedTemporaryFile(delete=False, suffix=".verdicts").name
    res = subprocess.run(
        [binary, nets_path, out, "--threads", str(threads), "--repeat", str(repeat)],
        check=True,
        capture_output=True,
        text=True,
    )
    stats = json.loads(res.stdout.strip().splitlines()[-1])
    verdicts = np.fromfile(out, dtype=np.uint8)
    os.unlink(out)
    return stats, verdicts


def _gmsh_worker(nets, d, repeat, barrier, queue, slot):
    """Builds the elements in one Gmsh instance and times getElementQualities (best of repeat)."""
    import gmsh

    count = nets.shape[0]
    gmsh.initialize(["-noenv"], readConfigFiles=False)
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.model.add("bench")
    etype = gmsh.model.mesh.getElementType("Tetrahedron", d)
    _, _, _, num_nodes, local, _ = gmsh.model.mesh.getElementProperties(etype)
    uvw = np.array(local).reshape(num_nodes, 3)
    bary = np.column_stack([1.0 - uvw.sum(axis=1), uvw])
    B = bernstein_matrix(bary, d)  # nodes x N
    # Unit tetrahedron: physical position = (X_1, X_2, X_3).
    phys = np.einsum("kn,enc->ekc", B, nets)[:, :, 1:4]
    tag = gmsh.model.addDiscreteEntity(3)
    node_tags = np.arange(1, count * num_nodes + 1)
    gmsh.model.mesh.addNodes(3, tag, node_tags, phys.reshape(-1))
    elem_tags = np.arange(1, count + 1)
    gmsh.model.mesh.addElementsByType(tag, etype, elem_tags, node_tags)
    times = []
    q = None
    for _ in range(repeat):
        if barrier is not None:
            barrier.wait()
        start = time.perf_counter()
        q = np.asarray(gmsh.model.mesh.getElementQualities(elem_tags, "minDetJac"))
        times.append(time.perf_counter() - start)
    gmsh.finalize()
    queue.put((slot, times, q))


def run_gmsh(nets, d, threads, repeat):
    """Gmsh's Python API is not thread-safe for concurrent quality queries, so `threads` > 1 runs
    that many processes on equal shares, started together; the time of a round is the slowest
    process's."""
    import multiprocessing as mp

    ctx = mp.get_context("fork")
    queue = ctx.Queue()
    chunks = np.array_split(nets, threads)
    barrier = ctx.Barrier(threads) if threads > 1 else None
    procs = [ctx.Process(target=_gmsh_worker, args=(c, d, repeat, barrier, queue, i)) for i, c in enumerate(chunks)]
    for p in procs:
        p.start()
    results = sorted(queue.get() for _ in procs)
    for p in procs:
        p.join()
    rounds = np.max(np.array([r[1] for r in results]), axis=0)
    q = np.concatenate([r[2] for r in results])
    return float(rounds.min()), q


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--count", type=int, default=100000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--degrees", default="2,3,4")
    ap.add_argument("--amplitude", type=float, default=None, help="perturbation bound (default per degree)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--binary", default=os.path.join(ROOT, "target/release/examples/certify_nets"))
    args = ap.parse_args()
    if not os.path.exists(args.binary):
        subprocess.run(
            ["cargo", "build", "--release", "-q", "-p", "ism-validate", "--example", "certify_nets"], check=True, cwd=ROOT
        )
    rng = np.random.default_rng(args.seed)
    rows = []
    tmp = tempfile.mkdtemp()
    # Amplitudes giving roughly half folded elements at each degree (control points move less at
    # higher degree because they are closer together).
    default_amp = {2: 0.45, 3: 0.22, 4: 0.14}
    for d in [int(x) for x in args.degrees.split(",")]:
        nets = general_nets(rng, args.count, d, args.amplitude or default_amp.get(d, 0.1))
        path = os.path.join(tmp, f"bezier{d}.bin")
        write_nets(path, d, nets)
        for threads in (1, 2):
            ours, verdicts = run_ours(args.binary, path, threads, args.repeat)
            gsec, q = run_gmsh(nets, d, threads, args.repeat)
            gvalid = q > 0
            decided = verdicts != 2
            agree = int(np.sum((verdicts[decided] == 1) == gvalid[decided]))
            row = {
                "kind": "bezier",
                "degree": d,
                "threads": threads,
                "elements": args.count,
                "ours_per_s": round(ours["per_second"]),
                "gmsh_per_s": round(args.count / gsec),
                "ratio": round(ours["per_second"] / (args.count / gsec), 2),
                "ours_valid": ours["valid"],
                "ours_invalid": ours["invalid"],
                "ours_undetermined": ours["undetermined"],
                "gmsh_valid": int(gvalid.sum()),
                "verdicts_agree": agree,
                "verdicts_differ": int(decided.sum()) - agree,
            }
            rows.append(row)
            print(json.dumps(row), flush=True)
    for d in (2, 3):
        nets, weights = adjusted_rational(rng, args.count, d, 1.0)
        path = os.path.join(tmp, f"rational{d}.bin")
        write_nets(path, d, nets, weights)
        for threads in (1, 2):
            ours, verdicts = run_ours(args.binary, path, threads, args.repeat)
            row = {
                "kind": "rational",
                "degree": d,
                "threads": threads,
                "elements": args.count,
                "ours_per_s": round(ours["per_second"]),
                "ours_valid": ours["valid"],
                "ours_invalid": ours["invalid"],
                "ours_undetermined": ours["undetermined"],
            }
            rows.append(row)
            print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
