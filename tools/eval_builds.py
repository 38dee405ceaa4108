"""Single pass against the model method on whole builds: model quality, carried landmarks, time.

Usage::

    python tools/eval_builds.py verse [--landmarks-on L1,T11,L4] [--jobs 2]
    python tools/eval_builds.py demo [--n 24] [--jobs 2]

For each method it builds the project (``ssm_addon.pipeline.project_build.build``) and prints the
leave-one-out generalization and the specificity at the first modes, the coating time,
folds left and relaxation convergence; for ``verse`` with landmarks on a few instances
only, the distance of every carried-over landmark (``landmarks/<name>.fcsv`` of the build)
to the one in the data set, per landmark.
"""

from __future__ import annotations

import argparse
import re
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ssm_addon import demo  # noqa: E402
from ssm_addon.formats.landmarks import read_landmarks  # noqa: E402
from ssm_addon.pipeline.project import read_project  # noqa: E402
from ssm_addon.pipeline.project_build import build  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
VERSE = {"T9": 16, "T10": 17, "T11": 18, "T12": 19, "L1": 20, "L2": 21, "L3": 22, "L4": 23, "L5": 24}


def verse_project(folder: Path, landmarks_on, method: str, iterations: int, exact: bool = False) -> Path:
    src = DATA / "verse004"
    lines = ["[template]", 'instance = "L1"', "spacing = 1.0", "", "[correspondence]", f'method = "{method}"',
             f"iterations = {iterations}", ("landmark_noise_mm = 0.0" if exact else ""), "", "[model]",
             'alignment = "none"', ""]
    for name, label in VERSE.items():
        lines += ["[[instances]]", f'name = "{name}"', f'volume = "{src / "sub-verse004_seg-vert_msk.nii.gz"}"',
                  f"label = {label}"]
        if landmarks_on is None or name in landmarks_on:
            lines.append(f'landmarks = "{src / "landmarks" / f"{name}.fcsv"}"')
        lines.append("")
    path = folder / f"verse-{method}.toml"
    path.write_text("\n".join(lines))
    return path


def demo_project(folder: Path, n: int, method: str, iterations: int, exact: bool = False) -> Path:
    path = folder / "population" / "project.toml"
    if not path.exists():
        demo.make_demo_population(folder / "population", n=n, seed=0)
    text = path.read_text()
    text = re.sub(r"\n\[correspondence\][^\[]*", "\n", text)
    text = text.replace("[coating]", f'[correspondence]\nmethod = "{method}"\niterations = {iterations}\n'
                        ('landmark_noise_mm = 0.0' if exact else '') + '\n\n[coating]')
    out = path.with_name(f"project-{method}.toml")
    out.write_text(text)
    return out


def summary(result, label: str, seconds: float, baseline=None) -> np.ndarray:
    """Print a build's figures; returns its per-instance leave-one-out errors (n x k) so a
    later build can be compared instance by instance (paired) against ``baseline``."""
    doc = result.report
    g, s = doc["metrics"]["generalization"], doc["metrics"]["specificity"]
    fits = [c.fit for c in result.study.coatings.values()]
    print(f"{label}: build {seconds:.1f} s, coating {doc['timings_s'].get('coating', 0):.1f} s; "
          f"generalization (LOO) k=1..3 " + ", ".join(f"{x:.3f}" for x in g["mean_mm"][:3]) + " mm, last "
          f"{g['mean_mm'][-1]:.3f} mm; specificity k=1..3 "
          + ", ".join(f"{x:.3f} ± {sd / np.sqrt(s['n_samples']):.3f}" for x, sd in zip(s["mean_mm"][:3], s["std_mm"]))
          + f" mm; folds left {sum(f.folded_after for f in fits)}; converged {sum(f.converged for f in fits)}"
          f"/{len(fits)}", flush=True)
    rounds = doc.get("correspondence", {}).get("rounds", [])
    for r in rounds:
        print(f"  round {r['round']}: mean shape moved {r['mean_change_mm']:.3f} mm, {r['seconds']:.1f} s "
              f"({r['seconds'] / max(len(r['instance_change_mm']), 1):.2f} s per instance)")
    per = np.asarray(g["per_instance_mm"], float)
    if baseline is not None and baseline.shape == per.shape:
        d = per[:, :3] - baseline[:, :3]
        se = d.std(axis=0, ddof=1) / np.sqrt(len(d))
        print("  generalization against the single pass, instance by instance (k=1..3): "
              + ", ".join(f"{m:+.3f} ± {e:.3f}" for m, e in zip(d.mean(axis=0), se)) + " mm (mean difference ± SE)")
    return per


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("population", choices=("verse", "demo"))
    ap.add_argument("--landmarks-on", default="L1,T11,L4")
    ap.add_argument("--n", type=int, default=24)
    ap.add_argument("--iterations", type=int, default=3)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--methods", default="landmarks,model")
    ap.add_argument("--exact-landmarks", action="store_true", help="[correspondence] landmark_noise_mm = 0 (exact landmarks)")
    args = ap.parse_args(argv)
    baseline = None
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for method in args.methods.split(","):
            for on in ([None] if method == "landmarks" or args.population == "demo" else
                       [None, set(args.landmarks_on.split(","))]):
                if args.population == "verse":
                    proj = verse_project(folder, on, method, args.iterations, args.exact_landmarks)
                else:
                    proj = demo_project(folder, args.n, method, args.iterations, args.exact_landmarks)
                t0 = time.perf_counter()
                out = folder / f"out-{method}-{'all' if on is None else 'few'}"
                result = build(read_project(proj), out, jobs=args.jobs, log=None)
                label = f"{args.population} {method}" + ("" if on is None else f" landmarks on {','.join(sorted(on))}")
                per = summary(result, label, time.perf_counter() - t0, baseline)
                if method == "landmarks":
                    baseline = per
                if on is not None:
                    per_landmark: dict = {}
                    for name in VERSE:
                        if name in on:
                            continue
                        given = read_landmarks(DATA / "verse004" / "landmarks" / f"{name}.fcsv").as_dict()
                        carried = read_landmarks(out / "landmarks" / f"{name}.fcsv")
                        for lm, p in zip(carried.names, carried.points_world):
                            if lm in given:
                                per_landmark.setdefault(lm, []).append(float(np.linalg.norm(p - given[lm])))
                    allv = np.concatenate([np.array(v) for v in per_landmark.values()])
                    print(f"  carried landmarks on the {len(VERSE) - len(on)} instances without: mean "
                          f"{allv.mean():.2f} mm, median {np.median(allv):.2f} mm, max {allv.max():.2f} mm")
                    for lm, v in per_landmark.items():
                        print(f"    {lm:28s} mean {np.mean(v):5.2f} mm, max {np.max(v):5.2f} mm")


if __name__ == "__main__":
    main()
