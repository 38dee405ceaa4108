"""Benchmark of a joint build against the separate builds of its structures (knee30 femur + tibia).

Usage::

    .venv/bin/python tools/bench_joint.py [--n 30] [--landmarks 12] [--jobs 2] [--runs 3]

Writes three projects over the same meshes and landmark files (``tools/eval_joint.py``'s
``knee_project``): the joint one (``meshes = { femur = …, tibia = … }``) and one per bone
(``mesh = …``), then runs ``python -m ssm_addon build … --no-blend --cache off`` on each, the
three alternating ``--runs`` times, each in a fresh process. Prints the wall time of every run,
the medians and the ratio of the joint build to the sum of the two separate builds (the joint
build does both structures' work, then one PCA, its metrics, shape and pose and collisions).
"""

from __future__ import annotations

import argparse
import re
import shutil
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

from bench_build import run_build  # noqa: E402
from eval_joint import DATA, knee_project  # noqa: E402


def single_projects(joint: Path) -> dict:
    """One project per bone over the joint project's meshes and landmark files."""
    text = joint.read_text()
    out = {}
    for bone in ("femur", "tibia"):
        lines = []
        for line in text.splitlines():
            m = re.match(r"(meshes|landmarks) = \{ (.*) \}", line)
            if m:
                parts = dict(re.findall(r'(\w+) = "([^"]*)"', m.group(2)))
                key = "mesh" if m.group(1) == "meshes" else "landmarks"
                line = f'{key} = "{parts[bone]}"'
            lines.append(line)
        path = joint.with_name(f"{bone}.toml")
        path.write_text("\n".join(lines))
        out[bone] = path
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=30, help="subjects (default 30)")
    ap.add_argument("--landmarks", type=int, default=12)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args(argv)
    if not DATA.is_dir():
        print(f"{DATA}: not present (the knee30 data); nothing to measure")
        return 1
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        joint = knee_project(tmp, args.n, args.landmarks)
        cases = {"joint": joint, **single_projects(joint)}
        times = {k: [] for k in cases}
        for r in range(args.runs):
            for name, project in cases.items():
                out = tmp / f"out_{name}"
                if out.exists():
                    shutil.rmtree(out)
                times[name].append(run_build(project, out, args.jobs, False, ("--cache", "off"))["wall_s"])
                print(f"run {r + 1} {name:6s} {times[name][-1]:7.2f} s", flush=True)
    med = {k: float(sorted(v)[len(v) // 2]) for k, v in times.items()}
    separate = med["femur"] + med["tibia"]
    ratios = [j / (f + t) for j, f, t in zip(times["joint"], times["femur"], times["tibia"])]
    print(f"\nknee30, {args.n} subjects, --jobs {args.jobs}, {args.runs} alternating runs (median wall, s):")
    print(f"  femur alone {med['femur']:.2f}, tibia alone {med['tibia']:.2f}, sum {separate:.2f}")
    print(f"  joint       {med['joint']:.2f}  ratio {med['joint'] / separate:.3f} "
          f"(per run {', '.join(f'{x:.3f}' for x in ratios)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
