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
echo "== Building the ism Python package (python/: PyO3 + maturin, release, abi3 wheel for CPython >= 3.9) and installing it into .venv"
# The wheel goes to target/wheels (cleared first, so exactly one wheel is installed); the release
# build reuses target/release. About 4 min of CPU the first time (measured: 241 s user).
rm -rf target/wheels
.venv/bin/maturin build --release --locked -m python/Cargo.toml -i .venv/bin/python -o target/wheels
.venv/bin/python -m pip install --disable-pip-version-check --force-reinstall --no-deps target/wheels/ism-*.whl
echo "== Installing headless Blender (bpy 5.0.1, CPython 3.11 only; ~375 MB) into .venv-blender (tools/requirements-blender.txt)"
# A venv of its own: bpy pins numpy<2. The add-on tests (blender/tests) install the ism wheel built
# above into Blender through the extension zip (blender/build.py), not with pip.
if [ ! -x .venv-blender/bin/python ]; then
  PY311=$(command -v python3.11 || true)
  if [ -z "$PY311" ] && python3 -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then PY311=python3; fi
  if [ -z "$PY311" ]; then
    echo "tools/setup.sh: bpy 5.0.1 needs CPython 3.11 (python3.11 not found)" >&2
    exit 1
  fi
  "$PY311" -m venv .venv-blender
fi
.venv-blender/bin/python -m pip install --disable-pip-version-check --progress-bar off -r tools/requirements-blender.txt \
  | (grep -v '^Requirement already satisfied' || true)
