"""A joint model predicting a missing structure, leave-one-out on knee30 (femur given, tibia predicted).

Usage::

    python tools/eval_joint.py [--n 30] [--landmarks 12] [--jobs 2] [--max-turn 30]

One joint build of the knee30 femurs and tibias (``[model] alignment`` at its default; each
structure's single pass with landmarks from the dense truth), then for every subject: the joint
model of the other subjects' coatings (the same alignment), fitted to the held-out femur's raw
mesh moved by a random rigid transform (``ssm fit --mesh femur=…``'s computation), and the
tibia it predicts against

* the true tibia's surface (mean distance, mm),
* the true correspondence (the held-out subject's own tibia coating, mm per point) and the
  share of those errors within 2 posterior SD,
* the baseline of separate models: the mean tibia placed by the similarity that puts the mean
  femur on the fitted femur.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import numpy as np  # noqa: E402
from foreign_data import random_rigid  # noqa: E402

from ssm_addon.fitting.fit import FitParams, Target, fit_any_pose  # noqa: E402
from ssm_addon.fitting.verdict import calibration  # noqa: E402
from ssm_addon.formats.meshes import read_mesh  # noqa: E402
from ssm_addon.meshutil import MeshLocator  # noqa: E402
from ssm_addon.model.pca import build_model, procrustes_fit  # noqa: E402
from ssm_addon.pipeline.joint import JointStudy, joint_model  # noqa: E402
from ssm_addon.pipeline.project import read_project  # noqa: E402

DATA = Path(os.environ.get("SSM_SHARED_DATA") or ROOT.parent / "shared" / "data") / "knee30"


def knee_project(folder: Path, n: int, landmarks: int) -> Path:
    """femur + tibia of the first ``n`` knee30 subjects, landmarks at farthest points of subject 1."""
    from foreign_data import scalismo_landmarks

    folder.mkdir(parents=True, exist_ok=True)
    idx = {}
    lines = []
    for i in range(1, n + 1):
        s = f"S{i:03d}"
        meshes, lms = [], []
        for bone in ("Femur", "Tibia"):
            v, _f = read_mesh(DATA / f"{s}_{bone}.ply")
            if bone not in idx:
                chosen, d = [0], np.linalg.norm(v - v[0], axis=1)
                for _ in range(landmarks - 1):
                    j = int(np.argmax(d))
                    chosen.append(j)
                    d = np.minimum(d, np.linalg.norm(v - v[j], axis=1))
                idx[bone] = chosen
            lm = scalismo_landmarks(folder / f"{s}_{bone}.json", [f"P{k}" for k in range(landmarks)], v[idx[bone]])
            meshes.append(f'{bone.lower()} = "{(DATA / f"{s}_{bone}.ply").as_posix()}"')
            lms.append(f'{bone.lower()} = "{lm.name}"')
        lines += ["[[instances]]", f'name = "{s}"', "meshes = { " + ", ".join(meshes) + " }",
                  "landmarks = { " + ", ".join(lms) + " }", ""]
    path = folder / "project.toml"
    path.write_text("\n".join(lines))
    return path


def evaluate(n: int = 30, landmarks: int = 12, jobs: int = 2, max_turn: float = 30.0, seed: int = 0,
             subjects: int | None = None, log=print) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        project = read_project(knee_project(Path(tmp), n, landmarks))
        joint = JointStudy.from_project(project)
        t0 = time.perf_counter()
        from ssm_addon.base.compute import Executor

        with Executor("processes", jobs, tasks=n) as ex:
            for study in joint.structures.values():
                from ssm_addon.pipeline.runner import run

                run(study, stages=("import", "template", "coating"), jobs=jobs, executor=ex)
        build_s = time.perf_counter() - t0
        full = joint_model(joint)
    names = list(full.instance_names)
    fem, tib = full.structure_slice("femur"), full.structure_slice("tibia")
    faces = np.asarray(full.faces)
    rng = np.random.default_rng(seed)
    rows = []
    for i, s in enumerate(names[: subjects or len(names)]):
        keep = [j for j in range(len(names)) if j != i]
        loo = build_model(full.instance_points[keep], faces, [names[j] for j in keep],
                          instance_points_world=full.instance_points_world[keep], alignment=full.params["model"]["alignment"])
        loo = dataclasses.replace(loo, structure_names=full.structure_names, structure_offsets=full.structure_offsets)
        fv, ff = read_mesh(DATA / f"{s}_Femur.ply")
        tv, tf = read_mesh(DATA / f"{s}_Tibia.ply")
        rot, shift = random_rigid(rng, max_turn_deg=max_turn, shift_mm=200.0)
        centre = fv.mean(axis=0)

        def move(p, rot=rot, shift=shift, centre=centre):
            return (p - centre) @ rot.T + centre + shift
        t1 = time.perf_counter()
        result, _search = fit_any_pose(loo, Target.from_mesh(move(fv), ff), params=FitParams(),
                                       points=np.arange(fem.start, fem.stop))
        pred = result.points[tib]
        true_surface = MeshLocator(move(tv), tf).query(pred, k=12)[1]
        true_points = move(full.instance_points_world[i][tib])  # the subject's own tibia coating, moved alike
        err = np.linalg.norm(pred - true_points, axis=1)
        cal = calibration(err, result.posterior_sd_mm[tib])
        within = cal["within_2sd"]
        # separate models: the mean tibia where the similarity of the mean femur onto the fitted femur puts it
        sc, r, t = procrustes_fit(np.asarray(loo.mean[fem])[None], result.points[fem], True)
        base = sc[0] * np.asarray(loo.mean[tib]) @ r[0].T + t[0]
        base_surface = MeshLocator(move(tv), tf).query(base, k=12)[1]
        rows.append({"subject": s, "joint_surface_mm": float(true_surface.mean()),
                     "joint_points_mm": float(err.mean()), "within_2sd": within, "sd_mean_mm": cal["sd_mean_mm"],
                     "sd_error_correlation": cal["correlation"],
                     "baseline_surface_mm": float(base_surface.mean()),
                     "baseline_points_mm": float(np.linalg.norm(base - true_points, axis=1).mean()),
                     "femur_fit_mm": float(result.mean_distance_mm), "seconds": time.perf_counter() - t1})
        r_ = rows[-1]
        log(f"{s}: tibia from the femur {r_['joint_surface_mm']:.3f} mm from the true surface "
            f"({r_['joint_points_mm']:.3f} mm from its true points, {100 * within:.0f} % within 2 SD of mean "
            f"{cal['sd_mean_mm']:.2f} mm, SD-error r {cal['correlation']:.2f}); baseline "
            f"{r_['baseline_surface_mm']:.3f} mm; femur fitted {r_['femur_fit_mm']:.3f} mm ({r_['seconds']:.1f} s)")
    summary = {k: float(np.mean([r[k] for r in rows])) for k in rows[0] if k != "subject"}
    summary["ratio"] = summary["joint_surface_mm"] / summary["baseline_surface_mm"]
    summary["build_s"] = build_s
    log(f"mean: joint {summary['joint_surface_mm']:.3f} mm, baseline {summary['baseline_surface_mm']:.3f} mm "
        f"({summary['ratio']:.2f}×); true points {summary['joint_points_mm']:.3f} mm against "
        f"{summary['baseline_points_mm']:.3f}; {100 * summary['within_2sd']:.1f} % within 2 SD (mean SD "
        f"{summary['sd_mean_mm']:.2f} mm, SD-error r {summary['sd_error_correlation']:.2f}); build {build_s:.0f} s")
    return {"rows": rows, "summary": summary}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=30)
    ap.add_argument("--landmarks", type=int, default=12)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--max-turn", type=float, default=30.0)
    ap.add_argument("--subjects", type=int, default=None, help="held out: the first this many (default all)")
    args = ap.parse_args(argv)
    evaluate(args.n, args.landmarks, args.jobs, args.max_turn, subjects=args.subjects)


if __name__ == "__main__":
    main()
