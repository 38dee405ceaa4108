#!/usr/bin/env bash
# One command on a fresh machine with Python 3.11: set up and run the lint and the tests.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh requirements-dev.txt
.venv/bin/ruff check .
# the test files in parallel: one process per core, at most 4 (pytest-xdist; a file's tests
# stay in one process, so a module's fixture is built once); "-n 0" in the arguments runs
# them in this process. One BLAS thread per process: with a process per core, more BLAS
# threads only wait for each other (README, "How long"); a variable already set is kept
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}" OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
.venv/bin/python -m pytest -n auto --maxprocesses 4 --dist loadfile "$@"
