"""Benchmark of the headless build: time per stage and peak memory.

Usage: ``.venv/bin/python tools/bench_build.py [--jobs N] [--blend] [--n 31] [--skip-demo] [--skip-verse]``

Cases, each run as ``python -m ssm_addon build`` in a fresh process:

* the synthetic demo population at paper scale (31 instances, default template: about
  600 points; paper section 6) — target: under 30 s on 2 cores;
* the nine real VerSe vertebrae (T9..L5 of sub-verse004, ``../shared/data/verse004``),
  when present.

Prints wall time per stage (import, template, coating, model, metrics, write[, blender])
from ``report.json`` and the peak resident memory of the build process and its workers.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))


def run_build(project: Path, out: Path, jobs: int, blend: bool, extra=()) -> dict:
    """``python -m ssm_addon build`` in a fresh process (``extra``: further arguments): its
    ``report.json`` with the command's wall time under ``wall_s``."""
    cmd = [sys.executable, "-m", "ssm_addon", "build", str(project), "--out", str(out), "--jobs", str(jobs), *extra]
    if not blend:
        cmd.append("--no-blend")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        print(proc.stdout[-3000:], proc.stderr[-3000:], sep="\n")
        raise SystemExit(f"build of {project} failed (exit {proc.returncode})")
    report = json.loads((out / "report.json").read_text())
    report["wall_s"] = wall
    return report


def _print(case: str, report: dict) -> None:
    t = report["timings_s"]
    mem = report["peak_memory"]
    tpl = report.get("template", {})
    n = len(report.get("instances", {}))
    print(f"\n{case}: {n} instances, template {tpl.get('points')} points / {tpl.get('triangles')} triangles "
          f"(genus {tpl.get('genus')})")
    print(f"  {'stage':10s} {'time (s)':>9s}")
    for key in ("import", "template", "coating", "model", "metrics", "blender", "write", "total"):
        if key in t:
            print(f"  {key:10s} {t[key]:9.2f}")
    print(f"  {'process':10s} {report['wall_s']:9.2f}  (wall time of the whole command, incl. interpreter start)")
    print(f"  peak memory: build process {mem['self_mb']:.0f} MB, largest worker {mem['children_mb']:.0f} MB")
    fits = report.get("instances", {}).values()
    if fits:
        worst = max(f["max_distance_mm"] for f in fits)
        mean = sum(f["mean_distance_mm"] for f in fits) / len(fits)
        print(f"  fit: mean surface distance {mean:.3f} mm, largest {worst:.2f} mm")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--n", type=int, default=31, help="demo instances (paper: 31)")
    parser.add_argument("--blend", action="store_true", help="also write model.blend and modes.png (needs bpy)")
    parser.add_argument("--skip-demo", action="store_true")
    parser.add_argument("--skip-verse", action="store_true")
    args = parser.parse_args(argv)
    from conftest import VERSE_DIR, VERSE_FILE

    from ssm_addon.cli.demo import make_demo_population

    with tempfile.TemporaryDirectory(prefix="ssm-bench-build-") as tmp:
        tmp = Path(tmp)
        if not args.skip_demo:
            t0 = time.perf_counter()
            project = make_demo_population(tmp / "demo", n=args.n, seed=0)
            print(f"demo population: {args.n} label maps + landmark files in {time.perf_counter() - t0:.2f} s")
            _print(f"demo (n={args.n}, jobs={args.jobs})", run_build(project, tmp / "demo_out", args.jobs, args.blend))
        if not args.skip_verse:
            if not VERSE_FILE.exists():
                print(f"\nVerSe: skipped ({VERSE_DIR} not found)")
            else:
                from test_build_verse import write_verse_project

                project = write_verse_project(tmp, VERSE_DIR)
                _print(f"VerSe (9 vertebrae, jobs={args.jobs})", run_build(project, tmp / "verse_out", args.jobs, args.blend))
    return 0


if __name__ == "__main__":
    sys.exit(main())
