"""Run every stage benchmark (tools/bench_*.py) and print their tables.

Usage: ``.venv/bin/python tools/benchmark.py [stage ...]`` with stages among
volume, surface, template, coating, model, build (default: all). Each stage script
prints wall time and peak memory per step; the real VerSe sample is used where
``../shared/data/verse004`` (or ``$SSM_SHARED_DATA/verse004``) exists.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
STAGES = ("volume", "surface", "template", "coating", "model", "fit", "segment", "build")


def main(argv: list[str]) -> int:
    stages = argv or list(STAGES)
    unknown = [s for s in stages if s not in STAGES]
    if unknown:
        print(f"unknown stage(s) {unknown}; choose from {', '.join(STAGES)}", file=sys.stderr)
        return 2
    failed = []
    for stage in stages:
        script = HERE / f"bench_{stage}.py"
        print(f"\n=== {stage} ({script.name}) ===", flush=True)
        t0 = time.perf_counter()
        rc = subprocess.call([sys.executable, str(script)], cwd=HERE.parent)
        print(f"--- {stage}: exit {rc}, {time.perf_counter() - t0:.1f} s", flush=True)
        if rc:
            failed.append(stage)
    if failed:
        print(f"\nfailed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
