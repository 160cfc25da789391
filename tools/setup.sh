#!/usr/bin/env bash
# Installs the test-time tools into the clone: a Python venv (.venv) with the interop readers, and the
# npm tools of tools/package.json (tools/node_modules). Nothing outside the clone is cached.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/python ]; then
  echo "== Creating the Python venv .venv (python3 -m venv)"
  python3 -m venv .venv
fi
echo "== Installing the Python interop readers into .venv (tools/requirements.txt: numpy, vtk, meshio, trimesh, gmsh, ...; about 900 MB the first time)"
# pipefail keeps pip's status; the subshell keeps grep's "nothing left" (status 1) from failing.
.venv/bin/python -m pip install --disable-pip-version-check --progress-bar off -r tools/requirements.txt \
  | (grep -v '^Requirement already satisfied' || true)
if [ -f tools/package.json ]; then
  echo "== Installing the Khronos glTF validator into tools/node_modules (npm)"
  (cd tools && npm install --no-audit --no-fund)
fi
