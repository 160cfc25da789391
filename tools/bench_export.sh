#!/usr/bin/env bash
# Export benchmark (BENCHMARKS.md, section export): curved extraction of the ≥ 1,000,000-tet
# stratified sphere at two tolerances on 1 and 2 threads, and marching tetrahedra on the same
# complex in the same run (the PL lower bound). One process per case so peak memory is per case.
set -euo pipefail
cd "$(dirname "$0")/.."
TETS=${TETS:-1000000}
cargo build --release -q -p ism-export --example export_bench
BIN=target/release/examples/export_bench
for threads in 1 2; do
  "$BIN" "$TETS" marching 0 "$threads"
  for tol in 1e-3 2.5e-4; do
    "$BIN" "$TETS" curved "$tol" "$threads"
  done
done
