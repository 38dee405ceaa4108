"""The relative pose a joint model reads against the truth's: knee30 femur + tibia without landmarks.

Usage::

    python tools/eval_relative_pose.py [--n 20] [--pose-seed 1] [--template-choice medoid|given] [--jobs 2]

The first ``n`` knee30 subjects, each knee (both bones) in its own random scanner pose as 3D Slicer
writes it (LPS PLY), built as a joint project without landmarks (``run_joint``). Each subject's
tibia-in-femur pose is read twice: from its coatings (what the joint model reads) and from the
truth's own correspondence (the meshes share their vertices); the femurs are put onto their mean
by a rigid fit of the points and the tibia's rotation onto the mean tibia then read as a rotation
vector. Prints the turn SD (degrees, RMS of each subject's rotation vector about their mean) and
the shift SD (mm) of both, and the coatings' mean distance from their true places per structure.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from foreign_data import random_rigid, slicer_ply  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from ssm_addon.formats.meshes import read_mesh  # noqa: E402
from ssm_addon.meshutil import MeshLocation, MeshLocator  # noqa: E402
from ssm_addon.model.pca import procrustes_fit  # noqa: E402
from ssm_addon.pipeline.joint import JointStudy, run_joint  # noqa: E402
from ssm_addon.pipeline.project import read_project  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "knee30"


def relative_poses(femurs: np.ndarray, tibias: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each subject's tibia pose in its femur's frame: (S, 3) rotation vectors (degrees) and (S, 3)
    shifts (mm) of the tibia onto the mean tibia, after the femur is put rigidly onto the mean femur."""
    mean_f = femurs.mean(axis=0)
    moved = []
    for f, t in zip(femurs, tibias):
        _s, rot, shift = procrustes_fit(f[None], mean_f, scale=False)
        moved.append(t @ rot[0].T + shift[0])
    moved = np.stack(moved)
    mean_t = moved.mean(axis=0)
    turns, shifts = [], []
    for t in moved:
        _s, rot, shift = procrustes_fit(t[None], mean_t, scale=False)
        turns.append(np.degrees(Rotation.from_matrix(rot[0]).as_rotvec()))
        shifts.append(t.mean(axis=0) - mean_t.mean(axis=0))
    return np.array(turns), np.array(shifts)


def spread(values: np.ndarray) -> float:
    return float(np.sqrt(((values - values.mean(axis=0)) ** 2).sum(axis=1).mean()))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20)
    ap.add_argument("--pose-seed", type=int, default=1)
    ap.add_argument("--template-choice", default=None, choices=["medoid", "given", "landmark-medoid"])
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args(argv)
    if not DATA.exists():
        raise SystemExit(f"knee30 not found at {DATA}")
    rng = np.random.default_rng(args.pose_seed)
    subjects = [f"S{i:03d}" for i in range(1, args.n + 1)]
    meshes = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        lines = []
        for s in subjects:
            rot, shift = random_rigid(rng, shift_mm=200.0)
            entries = []
            for bone in ("femur", "tibia"):
                v, f = read_mesh(DATA / f"{s}_{bone.title()}.ply")
                meshes[s, bone] = (v @ rot.T + shift, f)
                slicer_ply(folder / f"{s}_{bone}.ply", *meshes[s, bone])
                entries.append(f'{bone} = "{s}_{bone}.ply"')
            lines += ["[[instances]]", f'name = "{s}"', "meshes = { " + ", ".join(entries) + " }", ""]
        (folder / "project.toml").write_text("\n".join(lines))
        joint = JointStudy.from_project(read_project(folder / "project.toml"))
        if args.template_choice:
            for st in joint.structures.values():
                st.params = st.params.replace(correspondence=dataclasses.replace(
                    st.params.correspondence, template_choice=args.template_choice))
        joint = run_joint(joint, jobs=args.jobs, log=lambda line: print("  " + line, flush=True))
    coated, truth = {}, {}
    for bone, st in joint.structures.items():
        vt, ft = meshes[st.template_instance, bone]
        _c, _d, tri, bary = MeshLocator(vt, ft).query(st.frame(st.template_instance).to_world(st.template.points_object), k=12)
        where = MeshLocation(tri, bary)
        coated[bone] = np.stack([st.frame(s).to_world(st.coatings[s].points_object) for s in subjects])
        truth[bone] = np.stack([where.evaluate(*meshes[s, bone]) for s in subjects])
        err = np.linalg.norm(coated[bone] - truth[bone], axis=2).mean()
        print(f"{bone}: template {st.template_instance}, coatings {err:.3f} mm from their true places")
    for label, pts in (("coatings", coated), ("truth", truth)):
        turns, shifts = relative_poses(pts["femur"], pts["tibia"])
        print(f"{label}: relative turn SD {spread(turns):.2f} deg, shift SD {spread(shifts):.2f} mm")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
