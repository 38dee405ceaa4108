#!/usr/bin/env bash
# Create .venv with Python 3.11 (bpy==5.0.1 needs exactly CPython 3.11) and install the
# requirements. pip keeps its download cache in ~/.cache/pip, so reruns are fast.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=""
for cand in python3.11 python3 python; do
    if command -v "$cand" >/dev/null 2>&1 && "$cand" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
        PY="$cand"; break
    fi
done
if [ -z "$PY" ]; then
    echo "error: Python 3.11 not found (bpy==5.0.1 needs CPython 3.11)" >&2
    exit 1
fi
if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -r "${1:-requirements-dev.txt}"
