#!/usr/bin/env bash
# Regenerates the 2D figures in spec/examples/figures/ (complex, control points, linear contour
# dashed, curved shape solid) with `ism fit --svg`. Usage: bash tools/figures.sh [path/to/ism]
set -euo pipefail
cd "$(dirname "$0")/.."
ISM=${1:-target/release/ism}
[ -x "$ISM" ] || cargo build --release -q -p ism-cli
out=spec/examples/figures
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
# Exit 1 (tolerance not met) still writes the picture; anything else is an error.
fig() {
  name=$1; shift
  "$ISM" fit "$@" -q -o "$tmp/$name.ism.json" --svg "$out/$name.svg" >/dev/null || [ $? -eq 1 ]
  echo "$out/$name.svg"
}
fig circle-coarse --preset circle --resolution 4 --tolerance 1 --no-topology
fig circle-fit --preset circle --resolution 6 --tolerance 1e-4
fig taubin-fit --preset taubin --resolution 8 --tolerance 1e-3
fig taubin-fit-no-pv --preset taubin --resolution 8 --tolerance 1e-3 --no-topology
# The same fixed complex without and with the rational weights (BENCHMARKS.md, section fit).
fig taubin-coarse --preset taubin --resolution 10 --tolerance 10
fig taubin-coarse-rational --preset taubin --resolution 10 --tolerance 10 --rational
