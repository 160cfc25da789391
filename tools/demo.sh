#!/usr/bin/env bash
# The README's first command: build `ism`, then read, validate, export and sample a bundled example.
# Outputs go to ./ism-demo/.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release -q -p ism-cli
ism=target/release/ism
model=${1:-spec/examples/sphere.ism.json}
out=ism-demo
mkdir -p "$out"
run() { echo "\$ ism $*"; "$ism" "$@"; echo; }
run info "$model"
run validate "$model"
run convert "$model" "$out/model.ismb"
run export "$model" "$out/shape.glb" --tolerance 1e-3
run export "$model" "$out/shape.obj" --tolerance 1e-3
run export "$model" "$out/shape.vtu" --tolerance 1e-3
run sample "$model" --surface 20000 --seed 1 -o "$out/surface.ply"
echo "wrote: $(ls "$out" | tr '\n' ' ')"
