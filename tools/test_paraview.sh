#!/usr/bin/env bash
# The ParaView plugin in real ParaView: Debian's `python3-paraview` (ParaView 5.11, pvpython) under
# `xvfb-run`. Installs them with apt-get when missing and running as root (CI); puts the `ism` wheel
# built by tools/setup.sh (target/wheels) into target/paraview-site for ParaView's own Python
# (Debian's python3.11 with Debian's numpy 1.24: the abi3 wheel runs on it), then loads the plugin,
# opens an example and saves a screenshot (paraview/test_paraview.py checks it is not empty).
# Then starts the ParaView GUI application (under xvfb) on a script that loads the plugin and opens
# the sphere. Output: target/paraview-torus.png. Measured on the shared 2-core machine: apt-get ~4 min
# the first time (229 MB download in 2 s, the rest unpacking), pvpython test ~10 s, GUI run 30-60 s
# wall (8 s CPU for both).
set -euo pipefail
cd "$(dirname "$0")/.."
if ! command -v pvpython >/dev/null || ! command -v xvfb-run >/dev/null; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "== Installing ParaView (Debian python3-paraview) and xvfb with apt-get"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends \
      python3-paraview python3-numpy xvfb xauth >/dev/null
  else
    echo "tools/test_paraview.sh needs pvpython and xvfb-run (apt-get install python3-paraview xvfb xauth)" >&2
    exit 1
  fi
fi
site=target/paraview-site
rm -rf "$site"
wheel=$(ls target/wheels/ism-*.whl)
.venv/bin/python -m pip install --disable-pip-version-check --quiet --no-deps --target "$site" "$wheel"
# ParaView 5.11 needs inspect.getargspec (gone in Python 3.11) before it loads any Python plugin.
cp paraview/sitecustomize.py "$site/"
# Runs "$@" (an `xvfb-run` command), up to twice more while it fails because the virtual X server
# refused the render window's connection ("bad X server connection"): the environment's fault, not
# the test's. Seen in session 44 on the shared 2-core machine in two of three runs of this step (in
# CI and by hand), each time after every check of the reader had passed, as ParaView opened its
# render window; the next attempt on a fresh server passed. Any other failure stands.
retry_on_x_fault() {
  local log attempt
  log=$(mktemp)
  for attempt in 1 2 3; do
    if "$@" 2>&1 | tee "$log"; then
      rm -f "$log"
      return 0
    fi
    if ! grep -q "bad X server connection" "$log" || [ "$attempt" = 3 ]; then
      rm -f "$log"
      return 1
    fi
    echo "== the virtual X server refused the connection (attempt $attempt): again on a fresh one"
  done
}
echo "== ParaView: load paraview/ism_reader_plugin.py, open spec/examples/torus.ismb, screenshot"
retry_on_x_fault xvfb-run -a env PYTHONPATH="$PWD/$site" pvpython paraview/test_paraview.py \
  paraview/ism_reader_plugin.py spec/examples/torus.ismb target/paraview-torus.png
echo "== ParaView GUI application (paraview --script, under xvfb): load the plugin, open spec/examples/sphere.ismb"
result=target/paraview-gui.json
rm -f "$result"
retry_on_x_fault env PYTHONPATH="$PWD/$site" ISM_PV_PLUGIN="$PWD/paraview/ism_reader_plugin.py" \
  ISM_PV_FILE="$PWD/spec/examples/sphere.ismb" ISM_PV_RESULT="$PWD/$result" \
  timeout 300 xvfb-run -a paraview --script="$PWD/paraview/test_paraview_gui.py" --exit
# The sphere at the reader's default tolerance: the library's surface triangles (counted by the ism
# package in .venv, outside ParaView) + one Bézier cell per tetrahedron.
.venv/bin/python - "$result" "$PWD/spec/examples/sphere.ismb" <<'PY'
import json, sys
import ism
from ism.vtk_reader import DEFAULT_TOLERANCE
r = json.load(open(sys.argv[1]))
m = ism.read(sys.argv[2])
expected = len(m.extract_surface(DEFAULT_TOLERANCE).cells) + m.num_simplices
assert r == {"reader": "ISMReader", "cells": expected, "points": r["points"]} and r["points"] > 0, (r, expected)
print("ok: the ParaView GUI opened the sphere with the ISM reader:", r)
PY
