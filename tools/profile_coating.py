"""Where a coating's time goes: each step of paper 4 (and the registration) per instance and per
template point, on real data, as a worker process runs it.

Usage::

    .venv/bin/python tools/profile_coating.py [--sets verse,knee30-tibia,femur10,demo] [--instances 4]

For each set: the import and template stages as a build runs them, then ``--instances`` coatings
(the template onto instances other than its own, by the build's landmarks) in this process with
one thread for the k-d tree searches and for BLAS (a worker process's conditions), under
:mod:`cProfile`. Printed per set: the template's points, the relaxation steps, and for each step
its milliseconds per instance, per 1,000 template points and its share of the coating. Steps
nest (the registration holds its Gaussian smoothing and its nearest-vertex search); the distance
map's sampling is counted in every step that samples it (registration, relaxation, fold test).
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # a worker's BLAS (set before numpy loads)
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from bench_build import mesh_set_project  # noqa: E402
from conftest import VERSE_DIR, VERSE_FILE, shared_data_dir, write_verse_project  # noqa: E402
from eval_correspondence import MESH_SETS  # noqa: E402

from ssm_addon.cli.demo import make_demo_population  # noqa: E402
from ssm_addon.coating import coating as C  # noqa: E402
from ssm_addon.coating import registration as RG  # noqa: E402
from ssm_addon.pipeline.project import read_project  # noqa: E402
from ssm_addon.pipeline.runner import run  # noqa: E402
from ssm_addon.pipeline.study import Study  # noqa: E402

#: (label, function name as pstats shows it, depth): the steps of one coating.
STEPS = (
    ("coating (coat)", "coat", 0),
    ("distance map", "from_object_volume", 1),
    ("landmark warp (eq. 2)", "landmark_warp", 1),
    ("registration", "register_to_surface", 1),
    ("Gaussian smoothing", "_gaussian_smooth", 2),
    ("nearest vertex (k-d tree)", "_nearest_vertex", 2),
    ("distance map sampling (every step)", "_sample_fields", 1),
    ("fold test (smoothed field)", "folded_triangles", 1),
    ("relaxation (eq. 3)", "relax", 1),
    ("untangling", "untangle", 1),
    ("fit figures (exact distances)", "surface_distance", 1),
)


def study_of(name: str, tmp: Path):
    if name == "demo":
        project = make_demo_population(tmp / "demo", n=8, seed=0)
    elif name == "verse":
        if not VERSE_FILE.exists():
            return None
        project = write_verse_project(tmp, VERSE_DIR)
    else:
        sub, pattern = MESH_SETS[name]
        data = shared_data_dir() / sub
        if not data.is_dir():
            return None
        project = mesh_set_project(tmp / name, data, pattern, "landmarks")
    study = Study.from_project(read_project(project))
    run(study, stages=("import", "template"), jobs=1)
    return study


def profile_set(name: str, instances: int, tmp: Path) -> None:
    study = study_of(name, tmp)
    if study is None:
        print(f"{name}: skipped (its data are not here)")
        return
    RG.inner_threads = lambda wanted=2: 1  # noqa: ARG005 - a worker process's k-d tree searches
    tpl = study.template
    given = study.landmarks_object(study.template_instance)
    others = [n for n in study.names if n != study.template_instance][:instances]
    prof = cProfile.Profile()
    iterations = []
    for n in others:
        lm = study.landmarks_object(n)
        common = [k for k in given if k in lm]
        src, dst = np.array([given[k] for k in common]), np.array([lm[k] for k in common])
        prof.enable()
        result = C.coat(tpl, src, study.volume(n), dst, params=study.params.coating, name=n)
        prof.disable()
        iterations.append(result.fit.iterations)
    stats = pstats.Stats(prof)
    cum = {}
    for (_file, _line, func), (_cc, _nc, _tt, ct, _callers) in stats.stats.items():
        cum[func] = cum.get(func, 0.0) + ct
    k = len(others)
    points = len(tpl.points_object)
    total = cum.get("coat", 0.0) / k
    print(f"\n{name}: template {points} points / {len(tpl.faces)} triangles; {k} coatings; relaxation steps "
          f"{', '.join(str(i) for i in iterations)}")
    print(f"  {'step':34s} {'ms/instance':>12s} {'ms/1000 pts':>12s} {'share':>7s}")
    for label, func, depth in STEPS:
        t = cum.get(func, 0.0) / k
        print(f"  {'  ' * depth + label:34s} {1000 * t:12.1f} {1000 * t * 1000 / points:12.1f} {t / total:7.1%}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", default="verse,knee30-tibia,femur10,demo")
    ap.add_argument("--instances", type=int, default=4)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="ssm-profile-coating-") as tmp:
        for name in [s.strip() for s in args.sets.split(",") if s.strip()]:
            profile_set(name, args.instances, Path(tmp))
    return 0


if __name__ == "__main__":
    sys.exit(main())
