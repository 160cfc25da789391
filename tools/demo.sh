#!/usr/bin/env bash
# The README's first command. Builds `ism` (release), then shows what it does on one shape, writing
# into ./ism-demo/: fits an ISM to the sphere of radius 0.6, certifies it, exports the curved surface
# (glTF, OBJ, VTK), samples points on it and measures how far they lie from the true sphere.
#   bash tools/demo.sh           the fitted sphere
#   bash tools/demo.sh MODEL     steps 2-5 on a model of your own (no accuracy check)
set -euo pipefail
cd "$(dirname "$0")/.."
say() { printf '\n== %s\n' "$*"; }
run() {
  printf '$ ism %s\n' "$*"
  "$ism" "$@"
}

say "Building ism in release mode (cargo shows its progress; a few minutes the first time, seconds afterwards)"
cargo build --release -p ism-cli
ism=target/release/ism
out=ism-demo
mkdir -p "$out"

if [ $# -gt 0 ]; then
  model=$1
else
  model=$out/sphere.ismb
  say "1. Fit an ISM to the sphere x²+y²+z² = 0.36 (radius 0.6) in the cube [-1,1]³ (preset 'sphere'):
   a Kuhn grid refined where needed, with vertex values g(v) and a stratified Bézier map that moves
   the linear isocomplex onto g = 0. The report gives the error |g|/|∇g| (here ≈ the distance to the
   sphere) and the topology, which must be a sphere's: 1 component, Euler characteristic 2."
  run fit --preset sphere -o "$model"
fi

say "2. What the file holds: the complex, the vertex values and the stages of the map"
run info "$model"
run convert "$model" "$out/model.ism.json"

say "3. Validate: each stage certified a diffeomorphism on every simplex (by a theorem or by Bernstein
   coefficients), so the curved shape has exactly the topology of the linear isocomplex"
run validate "$model"

say "4. Export the curved surface as a watertight triangle mesh (chordal tolerance 1e-3)"
run export "$model" "$out/shape.glb"
run export "$model" "$out/shape.obj"
run export "$model" "$out/shape.vtu"

say "5. Sample 20000 points on the curved surface, uniform by true area, with normals"
run sample "$model" --surface 20000 --seed 1 -o "$out/surface.csv"

if [ $# -eq 0 ]; then
  say "6. Accuracy: distance of the sampled points from the centre (the true radius is 0.6)"
  awk -F, 'NR > 1 { r = sqrt($1*$1 + $2*$2 + $3*$3); if (n++ == 0 || r < lo) lo = r; if (r > hi) hi = r }
    END { dev = (0.6 - lo > hi - 0.6) ? 0.6 - lo : hi - 0.6
          printf "radius of %d points: %.5f to %.5f, largest deviation %.2f %% of 0.6\n", n, lo, hi, 100 * dev / 0.6 }' \
    "$out/surface.csv"
fi

say "Done. In ./$out: $(ls "$out" | tr '\n' ' ')
   shape.glb opens in any glTF viewer, shape.obj in Blender or MeshLab, shape.vtu in ParaView;
   surface.csv (x y z nx ny nz f simplex) loads in numpy or pandas."
