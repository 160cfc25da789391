#!/usr/bin/env bash
# Installs the test-time tools into the clone: a Python venv (.venv) with the interop readers, and the
# npm tools of tools/package.json (tools/node_modules). Nothing outside the clone is cached.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
.venv/bin/python -m pip install -q --disable-pip-version-check -r tools/requirements.txt
if [ -f tools/package.json ]; then
  (cd tools && npm install --no-audit --no-fund --silent)
fi
