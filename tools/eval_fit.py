"""Evaluation of ``ssm fit`` on real and demo data: leave-one-out fits and completion.

Usage: ``.venv/bin/python tools/eval_fit.py [--femur10-only | --no-femur10] [--no-demo] [--step K]``
or ``.venv/bin/python tools/eval_fit.py --any-pose knee30-patella knee30-tibia femur10``

For VerSe (the nine vertebrae of sub-verse004, when ``../shared/data`` is present) and
the 24-instance demo: every instance fitted by a model of the others (built from the
study's coatings), its surface distance for the model-constrained fit and for the free
fit (the coating's relaxation from it); and completion: the instance with one side
(x > median, 40–50 %) removed, the predicted missing part's distance to the real surface
and the share of its points within 2 posterior standard deviations of it (target noise
``--noise``, default the fit's own default).

femur10 (dense truth, ``../shared/data/femur10``): each femur completed from its
proximal half (the vertices above its median height, every ``--step``-th as points) by
the model of the other nine (their meshes' own correspondence, rigidly aligned), from the
model frame; the missing half's error is the distance of each vertex from its true place
(not a surface distance), with the share within 2 posterior SD.

``--any-pose SET ...``: held-out instances of dense-truth sets in random poses, fitted from
any pose by the model of the others with each pose step (``FitParams.pose_step``), against
their true points.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from ssm_addon.base.params import FitParams  # noqa: E402
from ssm_addon.cli import demo  # noqa: E402
from ssm_addon.coating.coating import coat_from_start  # noqa: E402
from ssm_addon.coating.distance_map import DistanceMap  # noqa: E402
from ssm_addon.fitting.fit import Pose, Target, fit_model  # noqa: E402
from ssm_addon.meshutil import Mesh, marching_cubes  # noqa: E402
from ssm_addon.model.pca import build_model  # noqa: E402
from ssm_addon.pipeline.project import read_project  # noqa: E402
from ssm_addon.pipeline.project_build import build  # noqa: E402
from ssm_addon.pipeline.stages import import_instances  # noqa: E402

NOISE_MM = [FitParams().noise_mm]  # the completion's target noise (--noise)


def evaluate(label: str, project_path: Path, out: Path) -> None:
    result = build(read_project(project_path), out, jobs=2, log=None)
    s = result.study
    print(f"\n{label}: {len(s.names)} instances, template {len(s.template.points_object)} points")
    print(f"  {'instance':10s} {'fit mean/max (mm)':>18s} {'free mean/max (mm)':>19s} {'Mahal.':>7s} "
          f"{'completion: missing mean/max (mm), within 2 SD':>48s}")
    rows = []
    for left in s.names:
        names = [n for n in s.names if n != left]
        m = build_model(np.stack([s.coatings[n].points_object for n in names]), s.template.faces, names)
        ov = s.volumes[left] if left in s.volumes else import_instances(s, names=[left])[left]
        verts, faces = marching_cubes(ov.mask)
        surf = ov.voxel_to_object(verts)
        dm = DistanceMap.from_object_volume(ov)
        res = fit_model(m, Target.from_mesh(surf, faces), pose=Pose())  # object frame = model frame
        fit_d = dm.surface_distance(res.points)
        free = coat_from_start(Mesh(res.points, s.template.faces), ov, start=res.points, distance_map=dm)
        free_d = dm.surface_distance(free.points_object)
        seen = surf[:, 0] <= np.median(surf[:, 0])
        part = fit_model(m, Target.from_points(surf[seen]), pose=Pose(), partial=True,
                         params=FitParams(noise_mm=NOISE_MM[0]))
        missing = part.points[:, 0] > np.median(surf[:, 0])
        miss_d = dm.surface_distance(part.points[missing])
        within = float((miss_d <= 2 * part.posterior_sd_mm[missing]).mean())
        rows.append((fit_d.mean(), free_d.mean(), miss_d.mean(), within))
        print(f"  {left:10s} {fit_d.mean():8.2f} / {fit_d.max():6.2f} {free_d.mean():9.3f} / {free_d.max():6.3f} "
              f"{res.mahalanobis:7.2f} {miss_d.mean():12.2f} / {miss_d.max():6.2f}, {100 * within:5.1f} %")
    a = np.array(rows)
    print(f"  mean: fit {a[:, 0].mean():.2f} mm, free {a[:, 1].mean():.3f} mm, completion missing part "
          f"{a[:, 2].mean():.2f} mm, {100 * a[:, 3].mean():.1f} % within 2 SD")


def any_pose(population: str, *, count: int = 8) -> None:
    """A held-out instance of a dense-truth set (``tools/eval_correspondence.py``'s folders of
    meshes sharing one connectivity) in a random pose, fitted from any pose
    (:func:`ssm_addon.fitting.fit.fit_any_pose`) by the model of the others (their true
    correspondence, rigidly aligned), with each pose step: mean distance of the fitted points
    from their true places (not a surface distance), the surface distance, and the time."""

    from eval_correspondence import mesh_population
    from scipy.spatial.transform import Rotation

    from ssm_addon.fitting.fit import fit_any_pose

    files, meshes = mesh_population(population)
    points, faces = np.stack([v for v, _f in meshes]), meshes[0][1]
    held_out = list(range(0, len(points), max(1, len(points) // count)))[:count]
    steps = ("joint", "alternating")
    true_mm, surface_mm, seconds = ({s: [] for s in steps} for _ in range(3))
    for k in held_out:
        model = build_model(np.delete(points, k, axis=0), faces, [f.stem for i, f in enumerate(files) if i != k],
                            alignment="rigid")
        truth = points[k] @ Rotation.random(random_state=k).as_matrix().T + [10.0, -20.0, 5.0]
        target = Target.from_mesh(truth, faces)
        for step in steps:
            t0 = time.perf_counter()
            fitted, _doc = fit_any_pose(model, target, params=FitParams(pose_step=step))
            seconds[step].append(time.perf_counter() - t0)
            true_mm[step].append(float(np.linalg.norm(fitted.points - truth, axis=1).mean()))
            surface_mm[step].append(fitted.mean_distance_mm)
    for step in steps:
        print(f"{population}, {len(held_out)} held out in any pose, pose step {step}: fitted points "
              f"{np.mean(true_mm[step]):.3f} mm from their true places (largest {np.max(true_mm[step]):.2f}), "
              f"surface distance {np.mean(surface_mm[step]):.3f} mm, {sum(seconds[step]):.1f} s", flush=True)


def main() -> None:
    import argparse

    from conftest import FEMUR10_DIR, VERSE_DIR

    parser = argparse.ArgumentParser()
    parser.add_argument("--femur10-only", action="store_true")
    parser.add_argument("--no-femur10", action="store_true", help="VerSe and the demo only")
    parser.add_argument("--no-demo", action="store_true")
    parser.add_argument("--noise", type=float, default=FitParams().noise_mm,
                        help="target noise of the VerSe/demo completions, mm (default: the fit's default)")
    parser.add_argument("--step", type=int, default=1)
    parser.add_argument("--any-pose", nargs="+", metavar="SET",
                        help="only the fit from any pose of held-out instances of these dense-truth sets "
                             "(femur10, knee30-femur, knee30-tibia, knee30-patella, folder:PATH[:GLOB])")
    args = parser.parse_args()
    if args.any_pose:
        for population in args.any_pose:
            any_pose(population)
        return
    NOISE_MM[0] = args.noise
    if FEMUR10_DIR.exists() and not args.no_femur10:
        from test_fitting import femur10_completion

        t0 = time.perf_counter()
        rows = femur10_completion(FEMUR10_DIR, step=args.step)
        print(f"femur10: completion of the distal half from the proximal half (model of the other nine), "
              f"{time.perf_counter() - t0:.1f} s for the ten")
        for r in rows:
            print(f"  {r['name']}: missing {r['missing_mm']:.2f} mm (SD {r['sd_missing_mm']:.2f}), "
                  f"seen {r['seen_mm']:.2f} mm, {100 * r['within_2sd']:.1f} % within 2 SD")
        print(f"  mean: missing {np.mean([r['missing_mm'] for r in rows]):.2f} mm, "
              f"{100 * np.mean([r['within_2sd'] for r in rows]):.1f} % within 2 SD")
    if args.femur10_only:
        return

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if VERSE_DIR.exists():
            from test_build_verse import write_verse_project

            evaluate("VerSe sub-verse004 (T9-L5)", write_verse_project(tmp, VERSE_DIR), tmp / "verse")
        if not args.no_demo:
            evaluate("demo (24)", demo.make_demo_population(tmp / "demo", n=24, seed=0), tmp / "demo_out")


if __name__ == "__main__":
    main()
