"""Two builds of `ism` side by side on `ism export --volume`: CPU, size, and the *true* field error.

For each MODEL, runs `BIN export MODEL out.vtu --volume -j 1 -q --json` with the old and the new
binary alternately, REPEAT times each, and keeps the least CPU time of each (user + system of the
child, from `os.wait4`; the machine is shared, so the best of alternated runs
is the fairest figure), the wall time of that run, and the largest peak resident set of any run
(`ru_maxrss` of the child; Linux counts the forked interpreter's pages before `exec`, so small
models read ~27 MiB whatever `ism` used). From `--json`: cells, control points, degree,
refinement levels, the reported bound, whether it is certified, exact, and meets the tolerance.

Then the error each output really has, measured by the consumer: with the Python `vtk` package, at
`--points` random parameters of random cells, VTK's own evaluation of the written cell
(`vtkCell.EvaluateLocation`: the physical point and the weights of the cell's (rational) basis,
curved geometry included) gives a point and an interpolated F; `ism query` (the model's evaluator,
which inverts parametric stages by Newton) gives the model's F at that point. The largest
difference is the measured `max |F_vtk − F|` — independent of how either build computed its cells.
Also the CPU VTK's reader takes for each file, and whether VTK reads the same arrays (points,
cells, every point and cell array, bit for bit) from the new file as from the old one: the check
that a change of encoding changed no value.

Usage: .venv/bin/python tools/bench_volume_builds.py --old OLD_ISM --new NEW_ISM [--repeat 3]
           [--points 1500] MODEL [...]
  e.g. an old build from a worktree:
    git worktree add /tmp/old <rev> && CARGO_TARGET_DIR=/tmp/oldtarget cargo build --release -p ism-cli
    ism fit --preset sphere -o fs.ismb -q
    .venv/bin/python tools/bench_volume_builds.py --old /tmp/oldtarget/release/ism \\
        --new target/release/ism spec/examples/torus.ismb fs.ismb
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import tempfile
import time

import numpy as np


def child_cpu(cmd: list[str]) -> tuple[float, float, int, str]:
    """User + system CPU seconds, wall seconds and peak resident set (KiB) of one run of `cmd`
    (which must succeed), and its stdout. The child is reaped by `os.wait4`, whose usage is that
    child's alone (`RUSAGE_CHILDREN`'s peak would be the largest of every child so far)."""
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    text = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise subprocess.CalledProcessError(proc.returncode, cmd)
    return usage.ru_utime + usage.ru_stime, wall, usage.ru_maxrss, text


def vtk_arrays(grid) -> str:
    """A digest of every array VTK read from a grid (points, cells, point and cell data), so two
    files can be compared as VTK sees them, whatever their encoding."""
    import hashlib

    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    h = hashlib.sha256()
    # VTK ≥ 9.6 returns the types array from GetCellTypes() and deprecates GetCellTypesArray().
    types = grid.GetCellTypes() if vtk.vtkVersion.GetVTKMajorVersion() * 100 + \
        vtk.vtkVersion.GetVTKMinorVersion() >= 906 else grid.GetCellTypesArray()
    arrays = [grid.GetPoints().GetData(), grid.GetCells().GetConnectivityArray(),
              grid.GetCells().GetOffsetsArray(), types]
    for data in (grid.GetPointData(), grid.GetCellData()):
        arrays += [data.GetArray(i) for i in range(data.GetNumberOfArrays())]
    for a in arrays:
        h.update(str(a.GetName()).encode())
        h.update(np.ascontiguousarray(vtk_to_numpy(a)).astype(np.float64 if a.GetDataType() in
                 (vtk.VTK_FLOAT, vtk.VTK_DOUBLE) else np.int64).tobytes())
    return h.hexdigest()


def true_error(ism: str, model: str, vtu: str, points: int, seed: int = 1) -> tuple[float, float, str]:
    """Largest |F_vtk − F| at `points` random parameters of random cells of `vtu` (module doc),
    the CPU seconds VTK's reader took for the file (`vtkXMLUnstructuredGridReader.Update`, this
    process), and the digest of what it read ([`vtk_arrays`])."""
    import vtk

    reader = vtk.vtkXMLUnstructuredGridReader()
    reader.SetFileName(vtu)
    start = time.process_time()
    reader.Update()
    read_cpu = time.process_time() - start
    grid = reader.GetOutput()
    values = grid.GetPointData().GetArray("F")
    three = grid.GetCellType(0) == vtk.VTK_BEZIER_TETRAHEDRON
    rng = np.random.default_rng(seed)
    xs, fs = [], []
    for c in rng.integers(0, grid.GetNumberOfCells(), size=points):
        cell = grid.GetCell(int(c))
        count = cell.GetNumberOfPoints()
        b = rng.dirichlet(np.ones(4 if three else 3))
        x, w = [0.0, 0.0, 0.0], [0.0] * count
        cell.EvaluateLocation(vtk.reference(0), list(b[1:]) + ([] if three else [0.0]), x, w)
        xs.append(x if three else x[:2])
        fs.append(sum(w[i] * values.GetValue(cell.GetPointId(i)) for i in range(count)))
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "points.csv")
        np.savetxt(path, np.array(xs), delimiter=",")
        out = subprocess.run([ism, "query", model, path, "-q", "--format", "csv"], check=True,
                             capture_output=True, text=True).stdout
    column = 4 if three else 3  # x y [z] simplex f …
    f = np.array([float(line.split(",")[column]) for line in out.splitlines()[1:]])
    return float(np.max(np.abs(f - np.array(fs)))), read_cpu, vtk_arrays(grid)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--old", required=True)
    ap.add_argument("--new", required=True)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--points", type=int, default=1500)
    ap.add_argument("models", nargs="+")
    args = ap.parse_args()
    print(f"load before: {os.getloadavg()[0]:.2f}")
    print("| model | build | CPU s | wall s | peak RSS KiB | cells | control points | bytes | degree, levels |"
          " reported bound | certified | exact | met | measured max \\|F_vtk − F\\| | VTK read CPU s |"
          " VTK reads the old build's arrays |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as d:
        for model in args.models:
            best: dict[str, tuple[float, float, dict]] = {}
            peak = {"old": 0, "new": 0}
            for _ in range(args.repeat):
                for name, ism in (("old", args.old), ("new", args.new)):
                    out = os.path.join(d, name + ".vtu")
                    cpu, wall, rss, text = child_cpu(
                        [ism, "export", model, out, "--volume", "-j", "1", "-q", "--json"])
                    peak[name] = max(peak[name], rss)
                    if name not in best or cpu < best[name][0]:
                        best[name] = (cpu, wall, json.loads(text))
            digest = {}
            for name, ism in (("old", args.old), ("new", args.new)):
                out = os.path.join(d, name + ".vtu")
                cpu, wall, s = best[name]
                err, read_cpu, digest[name] = true_error(args.new, model, out, args.points)
                print(f"| {os.path.basename(model)} | {name} | {cpu:.3f} | {wall:.3f} | {peak[name]:,} | {s['cells']:,} |"
                      f" {s['control_points']:,} | {os.path.getsize(out):,} | {s['degree']}, {s['refinement_levels']} |"
                      f" {s['field_error_bound']:.2e} | {s['field_error_certified']} | {s.get('field_exact', False)} |"
                      f" {s['field_tolerance_met']} | {err:.1e} | {read_cpu:.2f} |"
                      f" {'(reference)' if name == 'old' else 'yes' if digest[name] == digest['old'] else 'no'} |")
    print(f"load after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
