#!/usr/bin/env bash
# One command on a fresh machine with Python 3.11: set up and run the lint and the tests.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh requirements-dev.txt
.venv/bin/ruff check .
.venv/bin/python -m pytest "$@"
