"""Benchmark of the headless build: time per stage and peak memory, alone or paired against an
earlier commit.

Usage::

    .venv/bin/python tools/bench_build.py [--jobs N] [--blend] [--n 31] [--cases demo,verse,femur10,femur10-model]
                                          [--against REV --runs 3]
    .venv/bin/python tools/bench_build.py --cases dense-truth --ratio   # model method / single pass
    .venv/bin/python tools/bench_build.py --cases dense-truth --ratio --template-choice landmark-medoid

Cases, each run as ``python -m ssm_addon build`` in a fresh process (``--cache off``):

* ``demo``: the synthetic demo population at paper scale (31 instances, default template: about
  600 points; paper section 6);
* ``verse``: the nine real VerSe vertebrae (T9..L5 of sub-verse004, ``verse004`` of the shared
  data), when present;
* ``femur10``, ``femur10-model``: the ten femurs of ``femur10`` (meshes; 15 landmarks at farthest
  points of femur00, the same vertices on the others: the data's dense correspondence), by the
  single pass and by the model method, when present;
* ``knee30-femur``, ``knee30-tibia``, ``knee30-patella`` (and ``…-model``): each bone of ``knee30``
  (30 meshes) the same way;
* ``femur10-none``, ``knee30-tibia-none``, …: the same meshes without landmarks (the start of
  :func:`ssm_addon.correspondence.frames.template_start`);
* ``dense-truth``: all eight of the above (with landmarks);
* ``lumbar-L1`` … ``lumbar-L5``: one lumbar level of two subjects as 3D Slicer meshes (verse004's
  and three known deformations of it with Scalismo landmarks, verse005's without: the model method;
  ``tests/foreign_data.py``), when verse004 and verse005 are present;
* ``joint``: the joint model of knee30's femur and tibia (30 subjects, 12 landmarks per bone;
  ``tools/eval_joint.py``'s project).

``--ratio``: for each set built both ways, the model method's time over the single pass's
(coating stage and whole command, medians of ``--runs``).

Alone: wall time per stage (import, template, coating, model, metrics, write[, blender]) from
``report.json`` and the peak resident memory of the build process and its workers. With
``--against REV``: REV checked out in a temporary worktree, every case built ``--runs`` times by
both, alternating; the median of each stage for both and their ratio (this / REV).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "tools"))

from eval_correspondence import MESH_SETS, farthest_points  # noqa: E402  (the dense-truth sets, one definition)

from ssm_addon.base.params import TEMPLATE_CHOICES  # noqa: E402


def run_build(project: Path, out: Path, jobs: int, blend: bool, extra=(), root: Path = ROOT) -> dict:
    """``python -m ssm_addon build`` of the checkout ``root`` in a fresh process (``extra``: further
    arguments): its ``report.json`` with the command's wall time under ``wall_s``."""
    cmd = [sys.executable, "-m", "ssm_addon", "build", str(project), "--out", str(out), "--jobs", str(jobs), *extra]
    if not blend:
        cmd.append("--no-blend")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))}
    if out.exists():
        shutil.rmtree(out)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True)
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
    print(f"  {'stage':18s} {'time (s)':>9s}")
    for key in STAGES:
        if key in t:
            print(f"  {key:18s} {t[key]:9.2f}")
    print(f"  {'process':18s} {report['wall_s']:9.2f}  (wall time of the whole command, incl. interpreter start)")
    print(f"  peak memory: build process {mem['self_mb']:.0f} MB, largest worker {mem['children_mb']:.0f} MB")
    fits = report.get("instances", {}).values()
    if fits:
        worst = max(f["max_distance_mm"] for f in fits)
        mean = sum(f["mean_distance_mm"] for f in fits) / len(fits)
        print(f"  fit: mean surface distance {mean:.3f} mm, largest {worst:.2f} mm")


STAGES = ("import", "template", "sides", "coating", "coating_self_check", "optimisation", "model", "appearance", "metrics", "blender", "write", "report_html",
          "total")


def mesh_set_project(folder: Path, data: Path, pattern: str, method: str, landmarks: int = 15,
                     template_choice: str | None = None) -> Path:
    """A folder of meshes sharing one connectivity (``pattern``) with ``landmarks`` at farthest
    points of the first (the same vertices on every mesh: the data's dense correspondence), by
    ``method`` (and ``[correspondence] template_choice`` when given, the model method's)."""
    from foreign_data import scalismo_landmarks

    from ssm_addon.formats.meshes import read_mesh

    folder.mkdir(parents=True, exist_ok=True)
    files = sorted(data.glob(pattern))
    chosen = farthest_points(read_mesh(files[0])[0], max(landmarks, 1), 0)
    lines = ["[correspondence]", f'method = "{method}"']
    if template_choice and method == "model":
        lines.append(f'template_choice = "{template_choice}"')
    lines.append("")
    for f in files:
        v, _f = read_mesh(f)
        lines += ["[[instances]]", f'name = "{f.stem}"', f'mesh = "{f.as_posix()}"']
        if landmarks:
            lm = scalismo_landmarks(folder / f"{f.stem}.json", [f"P{k}" for k in range(landmarks)], v[chosen])
            lines.append(f'landmarks = "{lm.name}"')
        lines.append("")
    path = folder / f"{folder.name}_{method}.toml"
    path.write_text("\n".join(lines))
    return path


def make_cases(tmp: Path, names, n: int, template_choice: str | None = None) -> dict:
    """``{case: project file}`` of the cases asked for whose data are present."""
    from conftest import VERSE_DIR, VERSE_FILE, VERSE_LABELS, shared_data_dir

    from ssm_addon.cli.demo import make_demo_population

    cases = {}
    names = [m for n in names for m in ([s + t for s in MESH_SETS for t in ("", "-model")] if n == "dense-truth" else [n])]
    for name in names:
        if name == "demo":
            t0 = time.perf_counter()
            cases[name] = make_demo_population(tmp / "demo", n=n, seed=0)
            print(f"demo population: {n} label maps + landmark files in {time.perf_counter() - t0:.2f} s")
        elif name == "verse":
            if not VERSE_FILE.exists():
                print(f"VerSe: skipped ({VERSE_DIR} not found)")
                continue
            from test_build_verse import write_verse_project

            cases[name] = write_verse_project(tmp, VERSE_DIR)
        elif name.startswith("lumbar-") and name.removeprefix("lumbar-") in VERSE_LABELS:
            level = name.removeprefix("lumbar-")
            if not (shared_data_dir() / "verse005").is_dir() or not VERSE_FILE.exists():
                print(f"{name}: skipped (verse004 or verse005 not found in {shared_data_dir()})")
                continue
            from foreign_data import two_subject_level

            cases[name] = two_subject_level(tmp / name, shared_data_dir(), level, VERSE_LABELS[level])
        elif name == "joint":
            if not (shared_data_dir() / "knee30").is_dir():
                print(f"joint: skipped ({shared_data_dir() / 'knee30'} not found)")
                continue
            from eval_joint import knee_project

            cases[name] = knee_project(tmp / "joint", 30, 12)
        elif name.removesuffix("-model").removesuffix("-none") in MESH_SETS:
            sub, pattern = MESH_SETS[name.removesuffix("-model").removesuffix("-none")]
            data = shared_data_dir() / sub
            if not data.is_dir():
                print(f"{name}: skipped ({data} not found)")
                continue
            cases[name] = mesh_set_project(tmp / name, data, pattern, "model" if name.endswith("-model") else "landmarks",
                                           template_choice=template_choice, landmarks=0 if name.endswith("-none") else 15)
        else:
            raise SystemExit(f"unknown case {name!r} (demo, verse, lumbar-L1 … lumbar-L5, joint, dense-truth, or a set of "
                             f"{', '.join(MESH_SETS)}, alone, with -model or with -none)")
    return cases


def paired(cases: dict, rev: str, tmp: Path, *, jobs: int, blend: bool, runs: int) -> None:
    """Every case built ``runs`` times by this checkout and by ``rev``, alternating; the medians."""
    other = tmp / "against"
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(other), rev], check=True,
                   capture_output=True)
    try:
        label = subprocess.run(["git", "-C", str(other), "log", "-1", "--format=%h %s"], capture_output=True,
                               text=True).stdout.strip()
        print(f"against {label}")
        for case, project in cases.items():
            got = {"this": [], "rev": []}
            for r in range(runs):
                for who, root in (("this", ROOT), ("rev", other)):
                    report = run_build(project, tmp / f"out_{case}_{who}", jobs, blend, ("--cache", "off"), root=root)
                    got[who].append({**report["timings_s"], "process": report["wall_s"]})
                    print(f"  {case} run {r + 1} {who:4s} {report['wall_s']:7.2f} s", flush=True)
            print(f"\n{case}: median of {runs} runs (s), this / {rev}")
            others = sorted({k for t in got["this"] for k in t} - {*STAGES, "process"})  # a joint build's structures
            for stage in (*others, *STAGES, "process"):
                a = [t[stage] for t in got["this"] if stage in t]
                b = [t[stage] for t in got["rev"] if stage in t]
                if a and b:
                    ma, mb = statistics.median(a), statistics.median(b)
                    print(f"  {stage:18s} {ma:8.2f} {mb:8.2f}   {ma / mb if mb else float('nan'):6.3f}")
    finally:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(other)], capture_output=True)


def ratio(cases: dict, tmp: Path, *, jobs: int, runs: int) -> None:
    """Each set built by the single pass and by the model method ``runs`` times, alternating; the
    medians and the model method's ratio (coating stage, whole command)."""
    rows = []
    for case in [c for c in cases if not c.endswith("-model") and f"{c}-model" in cases]:
        got = {"single": [], "model": []}
        for r in range(runs):
            for who, key in (("single", case), ("model", f"{case}-model")):
                report = run_build(cases[key], tmp / f"out_{key}", jobs, False, ("--cache", "off"))
                got[who].append({**report["timings_s"], "process": report["wall_s"]})
                print(f"  {key} run {r + 1} {report['wall_s']:7.2f} s (coating {report['timings_s']['coating']:.2f} s)",
                      flush=True)
        med = {who: {k: statistics.median(t[k] for t in got[who]) for k in ("coating", "process")} for who in got}
        rows.append((case, med))
    print(f"\nmodel method / single pass, median of {runs} runs, --jobs {jobs} (s)")
    print(f"  {'set':16s} {'coating':>22s} {'whole command':>22s}")
    for case, med in rows:
        c = med["model"]["coating"], med["single"]["coating"]
        w = med["model"]["process"], med["single"]["process"]
        print(f"  {case:16s} {c[0]:6.2f} / {c[1]:6.2f} = {c[0] / c[1]:4.2f}   {w[0]:6.2f} / {w[1]:6.2f} = {w[0] / w[1]:4.2f}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--n", type=int, default=31, help="demo instances (paper: 31)")
    parser.add_argument("--blend", action="store_true", help="also write model.blend and modes.png (needs bpy)")
    parser.add_argument("--cases", default="demo,verse",
                        help="comma-separated: demo, verse, lumbar-L1 … lumbar-L5, joint, dense-truth, femur10, knee30-femur, knee30-tibia, "
                             "knee30-patella (each also with -model)")
    parser.add_argument("--against", metavar="REV", help="an earlier commit to pair every case against")
    parser.add_argument("--runs", type=int, default=3, help="runs of each case and side with --against or --ratio "
                                                            "(default 3)")
    parser.add_argument("--ratio", action="store_true",
                        help="the model method's time over the single pass's, for every set given both ways")
    parser.add_argument("--template-choice", choices=TEMPLATE_CHOICES, default=None,
                        help="[correspondence] template_choice of the -model cases (default: the method's default)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="ssm-bench-build-") as tmp:
        tmp = Path(tmp)
        cases = make_cases(tmp, [c.strip() for c in args.cases.split(",") if c.strip()], args.n,
                           template_choice=args.template_choice)
        if args.against:
            paired(cases, args.against, tmp, jobs=args.jobs, blend=args.blend, runs=args.runs)
            return 0
        if args.ratio:
            ratio(cases, tmp, jobs=args.jobs, runs=args.runs)
            return 0
        for case, project in cases.items():
            _print(f"{case} (jobs={args.jobs})", run_build(project, tmp / f"out_{case}", args.jobs, args.blend,
                                                           ("--cache", "off")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
