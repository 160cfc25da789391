"""Throughput of the exporter in triangles per CPU-second (issue 19's "≥ 500k triangles per CPU-s"),
two ways in one run, on each MODEL:TOLERANCE:

  1. the whole process: `ism export MODEL out.obj --tolerance T -j 1 -q --json`, best of REPS
     (user + system CPU of the child, `resource.getrusage(RUSAGE_CHILDREN)` before and after);
     beside it the floor of any `ism` process on this machine, `ism --version` (best of REPS);
  2. in process: `crates/ism-export/examples/export_throughput.rs` (the same library calls —
     read, lazy index, extraction, OBJ to memory — repeated on one thread, CPU from
     /proc/self/stat over all repetitions), what a caller of the library pays per export.

The two must agree on the triangle count (checked). Prints a Markdown table and the load average
before and after (the machine is shared: quote the load with the figures).

`--floors` also prints what starting any process costs here, below which no `ism export` can go:
`/bin/true` and an empty C program (`int main(void){return 0;}`) built by `cc` dynamically and
statically and, when `musl-gcc` is installed (Debian `musl-tools`), statically against musl. On the
2-core VM of BENCHMARKS.md most of an empty glibc program's CPU is glibc's start-up reading the CPU's
cache sizes with `cpuid` (`init_cacheinfo`: `intel_check_word`, `handle_intel`, … in `perf record`),
an instruction the hypervisor traps; musl does not ask.

    cargo build --release -p ism-cli          # the `ism` binary (an `--example` flag would skip it)
    cargo build --release -p ism-export --example export_throughput
    python3 tools/bench_export_throughput.py [--reps 21] [--inner 200] [MODEL:T ...]

Default cases: the three implicit examples (sphere, torus, stratified-3d) at 1e-3 and 1e-4.
"""

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EXAMPLES = os.path.join(ROOT, "spec", "examples")
DEFAULT_CASES = [
    f"{os.path.join(EXAMPLES, m + '.ism.json')}:{t}"
    for t in ("1e-3", "1e-4")
    for m in ("sphere", "torus", "stratified-3d")
]


def child_cpu(cmd):
    """User + system CPU seconds of one run of `cmd` (which must succeed)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def start_up_floors(reps, tmp):
    """`(name, best CPU seconds)` of processes that do nothing: `/bin/true` and an empty C program
    built each way the installed compilers allow (a missing compiler is said, not skipped silently)."""
    src = os.path.join(tmp, "empty.c")
    with open(src, "w", encoding="utf-8") as f:
        f.write("int main(void) { return 0; }\n")
    builds = [("cc, glibc, dynamic", ["cc", "-O2"]), ("cc, glibc, static-pie", ["cc", "-O2", "-static-pie"]),
              ("musl-gcc, musl, static", ["musl-gcc", "-O2", "-static"])]
    rows = [("/bin/true", min(child_cpu(["/bin/true"]) for _ in range(reps)))]
    for i, (name, cc) in enumerate(builds):
        exe = os.path.join(tmp, f"empty{i}")
        try:
            subprocess.run(cc + [src, "-o", exe], check=True, capture_output=True)
        except (OSError, subprocess.CalledProcessError) as e:
            rows.append((f"{name}: not built ({cc[0]}: {e})", None))
            continue
        rows.append((f"empty C program ({name})", min(child_cpu([exe]) for _ in range(reps))))
    return rows


def obj_faces(path):
    with open(path, encoding="utf-8") as f:
        return sum(1 for line in f if line.startswith("f "))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cases", nargs="*", help="MODEL:TOLERANCE (default: the implicit examples at 1e-3, 1e-4)")
    ap.add_argument("--reps", type=int, default=21, help="whole-process runs per case (best kept)")
    ap.add_argument("--inner", type=int, default=200,
                    help="in-process exports at 1e-3 (a tenth of them at smaller tolerances)")
    ap.add_argument("--ism", default=os.environ.get("ISM_BIN", os.path.join(ROOT, "target", "release", "ism")))
    ap.add_argument("--floors", action="store_true",
                    help="also print the CPU of processes that do nothing (/bin/true, empty C programs)")
    ap.add_argument("--example", default=os.path.join(ROOT, "target", "release", "examples", "export_throughput"))
    args = ap.parse_args()
    for exe in (args.ism, args.example):
        if not os.access(exe, os.X_OK):
            sys.exit(f"missing {exe}: cargo build --release -p ism-cli; "
                     "cargo build --release -p ism-export --example export_throughput")
    cases = args.cases or DEFAULT_CASES
    # The two binaries are built by two commands: say how old each is, so a stale one shows.
    ages = ", ".join(f"{os.path.basename(e)} built {time.strftime('%Y-%m-%d %H:%M', time.gmtime(os.path.getmtime(e)))} UTC"
                     for e in (args.ism, args.example))
    print(f"load {os.getloadavg()} at {time.strftime('%H:%M:%S', time.gmtime())} UTC; ism {args.ism} ({ages})")
    floor = min(child_cpu([args.ism, "--version"]) for _ in range(args.reps))
    print(f"`ism --version` (the process floor): {floor * 1e3:.2f} ms CPU, best of {args.reps}\n")
    if args.floors:
        with tempfile.TemporaryDirectory() as tmp:
            for name, cpu in start_up_floors(args.reps, tmp):
                print(f"- {name}" + ("" if cpu is None else f": {cpu * 1e3:.3f} ms CPU, best of {args.reps}"))
        print()
    print("| model | T | triangles | whole process: CPU ms (triangles/CPU-s) | in process: CPU ms per export (triangles/CPU-s) | best wall ms in process: read + index / extract / write |")
    print("| --- | --- | --- | --- | --- | --- |")
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "out.obj")
        for case in cases:
            model, tol = case.rsplit(":", 1)
            cmd = [args.ism, "export", model, out, "--tolerance", tol, "-j", "1", "-q", "--json"]
            whole = min(child_cpu(cmd) for _ in range(args.reps))
            triangles = obj_faces(out)
            inner = args.inner if float(tol) >= 1e-3 else max(args.inner // 10, 3)
            line = subprocess.run([args.example, model, tol, str(inner)], check=True,
                                  capture_output=True, text=True).stdout
            r = json.loads(line)
            if r["triangles"] != triangles:
                sys.exit(f"{case}: the CLI wrote {triangles} triangles, the library made {r['triangles']}")
            w = r["best_wall_seconds"]
            print(f"| {os.path.basename(model)} | {tol} | {triangles:,} | {whole * 1e3:.2f} ({triangles / whole / 1e3:.0f}k) "
                  f"| {r['cpu_seconds_per_export'] * 1e3:.2f} ({r['triangles_per_cpu_second'] / 1e3:.0f}k) "
                  f"| {w['read_and_index'] * 1e3:.2f} / {w['extract'] * 1e3:.2f} / {w['write'] * 1e3:.2f} |", flush=True)
    print(f"\nload {os.getloadavg()} at {time.strftime('%H:%M:%S', time.gmtime())} UTC")


if __name__ == "__main__":
    main()
