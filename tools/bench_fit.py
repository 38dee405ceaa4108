"""Benchmark of fitting a model (``ssm fit``): time per target at 600 and 5,000 points, and a batch.

Usage: ``.venv/bin/python tools/bench_fit.py [--batch 100]``

* a synthetic model (40 shapes with 3 known modes, 6 modes kept) at N = 600 and 5,000
  points: the fit to a full surface (mesh target), to 60 % of it (completion), and to
  the points alone, one core, median of 5; and the pose search with its fit for the
  mesh target turned and moved away (median of 3);
* a batch of ``--batch`` point-cloud targets through :func:`ssm_addon.fitting.batch.fit_batch`
  (files written) with 1 and 2 processes.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from scipy.spatial import ConvexHull  # noqa: E402
from test_model import synthetic_population  # noqa: E402

from ssm_addon import meshutil  # noqa: E402
from ssm_addon.base.params import FitParams  # noqa: E402
from ssm_addon.fitting.batch import FitTarget, fit_batch  # noqa: E402
from ssm_addon.fitting.fit import Pose, Target, fit_any_pose, fit_model  # noqa: E402
from ssm_addon.model.files import save_npz  # noqa: E402
from ssm_addon.model.pca import build_model  # noqa: E402


def synthetic_model(n_points: int):
    shapes, mean, _, _ = synthetic_population(n=40, n_points=n_points, noise_mm=0.05, seed=2)
    stretch = np.array([30.0, 18.0, 10.0]) / 10.0
    shapes, mean = shapes * stretch, mean * stretch
    faces = ConvexHull(mean).simplices
    if meshutil.signed_volume(mean, faces) < 0:
        faces = faces[:, ::-1]
    return build_model(shapes, faces, [f"s{i}" for i in range(40)], n_modes=6)


def timed(fn, repeat=5):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--batch", type=int, default=100)
    args = ap.parse_args()
    for n in (600, 5000):
        model = synthetic_model(n)
        z = np.array([1.0, -0.5, 0.3])
        shape = model.generate(z * model.standard_deviations[:3]) + [5.0, -3.0, 2.0]
        seen = shape[:, 0] > np.quantile(shape[:, 0], 0.4)
        params = FitParams(noise_mm=0.05)
        cases = {
            "mesh (full surface)": (Target.from_mesh(shape, model.faces), False),
            "points (full)": (Target.from_points(shape), False),
            "partial (60 % of the points)": (Target.from_points(shape[seen]), True),
        }
        print(f"N = {n} points, {model.n_modes} modes")
        for label, (target, partial) in cases.items():
            res, t = timed(lambda target=target, partial=partial, model=model, params=params: fit_model(
                model, target, params=params, pose=Pose(np.eye(3), np.array([4.0, -2.0, 1.0])), partial=partial))
            err = np.linalg.norm(res.points - shape, axis=1).mean()
            print(f"  {label:30s} {t:7.3f} s  ({res.iterations} steps, error {err:.3f} mm)")
        # the pose search (ssm fit, Fit Model): the same mesh target turned and moved anywhere
        c, s_ = np.cos(2.0), np.sin(2.0)
        turned = shape @ np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]]).T + [300.0, -800.0, 120.0]
        (res, search), t = timed(lambda turned=turned, model=model, params=params: fit_any_pose(
            model, Target.from_mesh(turned, model.faces), params=params), repeat=3)
        print(f"  {'pose search + fit (any pose)':30s} {t:7.3f} s  ({len(search['starts'])} starts screened, "
              f"3 fitted; chosen {search['chosen']!r}, mean distance {res.mean_distance_mm:.3f} mm)")
    model = synthetic_model(600)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        save_npz(model, tmp / "model.npz")
        rng = np.random.default_rng(0)
        targets = []
        for i in range(args.batch):
            pts = model.generate(rng.standard_normal(3) * model.standard_deviations[:3])
            np.savetxt(tmp / f"t{i}.csv", pts, delimiter=",")
            targets.append(FitTarget(name=f"t{i}", points=tmp / f"t{i}.csv"))
        for jobs in (1, 2):
            t0 = time.perf_counter()
            fit_batch(tmp / "model.npz", targets, tmp / f"out{jobs}", params=FitParams(noise_mm=0.05), jobs=jobs)
            t = time.perf_counter() - t0
            print(f"batch of {args.batch} point clouds (600 points), jobs {jobs}: {t:.1f} s, "
                  f"{t / args.batch * 1000:.0f} ms per target (files written)")


if __name__ == "__main__":
    main()
