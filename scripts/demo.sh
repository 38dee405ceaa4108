#!/usr/bin/env bash
# One command on a fresh machine with Python 3.11: set up, build the extension zip, then
# generate the built-in synthetic population and build its shape model headless.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh requirements-dev.txt
.venv/bin/python tools/build_extension.py --platforms linux-x64 --out dist
.venv/bin/python -m ssm_addon demo --out "${1:-demo_out}"
