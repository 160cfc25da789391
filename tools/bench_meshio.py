"""Peer for the format benchmark: meshio writing and reading the same tetrahedra and vertex values
as binary .vtu (uncompressed, the fastest meshio setting). Prints one JSON line per operation.

usage: python tools/bench_meshio.py DIR     (DIR from `bench_format make DIR`)
       python tools/bench_meshio.py read FILE [--repeat K]   (best of K reads, wall and CPU
                                                            time; the driver measures peak memory)
"""
import json
import os
import sys
import time

import meshio
import numpy as np


def best_of(k, fn):
    best = float("inf")
    for _ in range(k):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def main():
    if sys.argv[1] == "read":
        # Best of --repeat K reads (default 1), wall and CPU time of this process (the machine is
        # shared and noisy: CPU time is the comparable figure).
        k = int(sys.argv[sys.argv.index("--repeat") + 1]) if "--repeat" in sys.argv else 1
        best, best_cpu, n = float("inf"), float("inf"), 0
        for _ in range(k):
            t, c = time.perf_counter(), time.process_time()
            mesh = meshio.read(sys.argv[2])
            n = len(mesh.cells_dict["tetra"])
            best = min(best, time.perf_counter() - t)
            best_cpu = min(best_cpu, time.process_time() - c)
            del mesh
        print(json.dumps({"op": "read", "tool": "meshio", "seconds": round(best, 4),
                          "cpu_seconds": round(best_cpu, 2),
                          "bytes": os.path.getsize(sys.argv[2]), "simplices": n}))
        return
    d = sys.argv[1]
    points = np.load(os.path.join(d, "points.npy"))
    tets = np.load(os.path.join(d, "tets.npy"))
    values = np.load(os.path.join(d, "values.npy"))
    mesh = meshio.Mesh(points, [("tetra", tets)], point_data={"f": values})
    path = os.path.join(d, "large.vtu")
    secs = best_of(3, lambda: meshio.write(path, mesh, file_format="vtu", binary=True, compression=None))
    print(json.dumps({"op": "write", "tool": "meshio", "seconds": round(secs, 4),
                      "bytes": os.path.getsize(path), "simplices": len(tets)}))
    back = meshio.read(path)
    assert np.array_equal(back.cells_dict["tetra"], tets) and np.array_equal(back.point_data["f"], values)


if __name__ == "__main__":
    main()
