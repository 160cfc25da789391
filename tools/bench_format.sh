#!/usr/bin/env bash
# Issues 2 and 13 benchmark: read/write CPU time and peak memory of each encoding on a ≥ 1,000,000-tet
# model with a stratified stage on every face, and meshio (binary .vtu) on the same tets and values
# in the same run. Needs meshio (the venv of tools/setup.sh, or PYTHON=...).
# Usage: tools/bench_format.sh [DIR] [TETS]   (CARGO_TARGET_DIR and PYTHON are honoured;
#        SKIP_MAKE=1 reuses DIR's files when they exist; ONLY=cli runs only the last part)
# Last part (issue 13): `ism info` and `ism validate` of the binary model against a checked read,
# whole-process CPU (user + system) and peak RSS by /usr/bin/time, alternating, two rounds.
set -euo pipefail
cd "$(dirname "$0")/.."
dir=${1:-/tmp/ism-bench-format}
tets=${2:-1000000}
py=${PYTHON:-.venv/bin/python}
cargo build --release -q -p ism-conformance --example bench_format
cargo build --release -q -p ism-cli
bin=${CARGO_TARGET_DIR:-target}/release/examples/bench_format
ism=${CARGO_TARGET_DIR:-target}/release/ism
if [[ -z "${SKIP_MAKE:-}" || ! -f "$dir/large.ismb" ]]; then
  $bin make "$dir" "$tets"
  $py tools/bench_meshio.py "$dir"
fi
peak() { /usr/bin/time -f '{"peak_kib":%M}' "$@" 2>&1 >/dev/stderr | tail -n 1; }
ls -l "$dir"
cli() {
  local f="$dir/large.ismb"
  for round in 1 2; do
    for what in read info validate; do
      case $what in
        read) cmd=("$bin" read "$f" --repeat 1) ;;
        info) cmd=("$ism" info -q "$f") ;;
        validate) cmd=("$ism" validate -q "$f") ;;
      esac
      # `ism validate` exits 0 on a valid model; anything else is a failed benchmark.
      /usr/bin/time -f "{\"cli\":\"$what\",\"round\":$round,\"user_s\":%U,\"sys_s\":%S,\"peak_kib\":%M,\"exit\":%x}" \
        "${cmd[@]}" >/dev/null
    done
  done
}
if [[ "${ONLY:-}" == cli ]]; then cli; exit; fi
for f in large.ismb large.ism.msgpack large.ism.json; do
  for mode in "" "--no-check" "--indexed"; do
    $bin read "$dir/$f" $mode --repeat 3
    echo "{\"file\":\"$f\",\"mode\":\"${mode:-checked}\",\"single_read\":$(peak $bin read "$dir/$f" $mode --repeat 1)}"
  done
  $py tools/bench_meshio.py read "$dir/large.vtu" --repeat 3
done
out=$(mktemp -d)
for f in large.ismb large.ism.msgpack; do
  $bin write "$dir/$f" "$out/$f" --repeat 3
done
rm -rf "$out"
echo "{\"file\":\"large.vtu\",\"single_read\":$(peak $py tools/bench_meshio.py read "$dir/large.vtu")}"
cli
