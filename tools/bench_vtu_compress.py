#!/usr/bin/env python3
"""`.vtu` raw against zlib-compressed (`ism export --compress`): bytes, write CPU and VTK's read CPU.

For each MODEL[:ARG:ARG...] (the extra `ism export` arguments joined by colons, e.g.
`spec/examples/torus.ismb:--tolerance:1e-4` or `fs.ismb:--volume`), writes the `.vtu` both ways
with `ISM_BIN export MODEL out.vtu -j 1 -q [ARGS] [--compress]` (CPU of the child, the least of
three) and reads each file with `vtkXMLUnstructuredGridReader` in this process (CPU, the least of
three), and prints a Markdown table.

Usage: ISM_BIN=target/release/ism .venv/bin/python tools/bench_vtu_compress.py MODEL[:ARGS] [...]
"""
import os
import resource
import subprocess
import sys
import tempfile
import time

import vtk

ISM = os.environ.get("ISM_BIN", "target/release/ism")


def child_cpu(cmd):
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run(cmd, check=True, capture_output=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime


def read_cpu(path):
    start = time.process_time()
    reader = vtk.vtkXMLUnstructuredGridReader()
    reader.SetFileName(path)
    reader.Update()
    assert reader.GetOutput().GetNumberOfCells() > 0, path
    return time.process_time() - start


def main(cases):
    print("| model | output | raw bytes | zlib bytes | raw / zlib | write CPU s raw / zlib | VTK read CPU s raw / zlib |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    with tempfile.TemporaryDirectory() as tmp:
        for case in cases:
            model, *extra = case.split(":")
            row = {}
            for tag, more in (("raw", []), ("zlib", ["--compress"])):
                out = os.path.join(tmp, f"{tag}.vtu")
                write = min(child_cpu([ISM, "export", model, out, "-j", "1", "-q", *extra, *more]) for _ in range(3))
                read = min(read_cpu(out) for _ in range(3))
                row[tag] = (os.path.getsize(out), write, read)
            (sr, wr, rr), (sz, wz, rz) = row["raw"], row["zlib"]
            print(f"| {os.path.basename(model)} | {' '.join(extra)} | {sr:,} | {sz:,} | {sr / sz:.2f} "
                  f"| {wr:.3f} / {wz:.3f} | {rr:.3f} / {rz:.3f} |")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(sys.argv[1:])
