#!/usr/bin/env bash
# Issue 2 benchmark: read/write throughput and peak memory of each encoding on a ≥ 1,000,000-tet
# model with a stratified stage on every face, and meshio (binary .vtu) on the same tets and values
# in the same run. Needs the venv of tools/setup.sh (meshio). Usage: tools/bench_format.sh [DIR] [TETS]
set -euo pipefail
cd "$(dirname "$0")/.."
dir=${1:-/tmp/ism-bench-format}
tets=${2:-1000000}
cargo build --release -q -p ism-conformance --example bench_format
bin=target/release/examples/bench_format
$bin make "$dir" "$tets"
peak() { /usr/bin/time -f '{"peak_kib":%M}' "$@" 2>&1 >/dev/stderr | tail -n 1; }
for f in large.ismb large.ism.msgpack large.ism.json; do
  for mode in "" "--no-check" "--indexed"; do
    $bin read "$dir/$f" $mode --repeat 3
    echo "{\"file\":\"$f\",\"mode\":\"${mode:-checked}\",\"single_read\":$(peak $bin read "$dir/$f" $mode --repeat 1)}"
  done
done
.venv/bin/python tools/bench_meshio.py "$dir"
.venv/bin/python tools/bench_meshio.py read "$dir/large.vtu" --repeat 3
echo "{\"file\":\"large.vtu\",\"single_read\":$(peak .venv/bin/python tools/bench_meshio.py read "$dir/large.vtu")}"
