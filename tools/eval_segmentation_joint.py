"""A vertebra segmented with its neighbour (a joint model of adjacent pairs) against alone, across scanners.

The single model: ``eval_segmentation_cross.py``'s (verse004's and the learning subject's lumbar
vertebrae, each an instance). The joint model: every adjacent pair of the same vertebrae (L1-L2 …
L4-L5 of each subject) as one subject with two structures, ``upper`` and ``lower``, built by
``ssm build`` from the label maps without landmarks. The other subject's vertebrae are segmented from
points ``--offset`` mm off their centres (``--starts`` directions, the same points for both): alone
with the single model, and with the vertebra below (a start off its centre too) with the pair model,
both with the image gradient. Each vertebra is scored against the expert's label map on its own label
(Dice, mean and 95th percentile surface distance); the pair's voxels inside both structures' surfaces
go to the one they lie deeper in, so the two never share one.

    python tools/eval_segmentation_joint.py --learn verse005 --segment verse012 --work /tmp/joint_seg
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

from eval_segmentation import LUMBAR, start_points  # noqa: E402
from eval_segmentation_cross import build_model, cross_arguments, subject_files  # noqa: E402

from ssm_addon.base.params import SegmentParams  # noqa: E402
from ssm_addon.formats.label_maps import read_label_map  # noqa: E402
from ssm_addon.meshutil import faces_within  # noqa: E402
from ssm_addon.model.files import load_npz  # noqa: E402
from ssm_addon.pipeline.project import read_project  # noqa: E402
from ssm_addon.pipeline.project_build import build  # noqa: E402
from ssm_addon.segmentation import read_image, segment_image, start_pose, structure_labels  # noqa: E402
from ssm_addon.segmentation.files import structure_label_map  # noqa: E402
from ssm_addon.segmentation.scores import segmentation_scores  # noqa: E402


def build_pair_model(data: Path, work: Path, learn: str):
    """The joint model of adjacent lumbar pairs of verse004 and ``learn`` (structures upper, lower)."""
    out = work / "out"
    if not (out / "model.npz").is_file():
        work.mkdir(parents=True, exist_ok=True)
        lines = ["[template]", "spacing = 1.0", "", "[correspondence]", "optimise = false", ""]
        for subject in ("verse004", learn):
            seg = data / subject / f"sub-{subject}_seg-vert_msk.nii.gz"
            present = set(np.unique(np.asarray(read_label_map(seg).labels)).tolist())
            names = [n for n, lab in LUMBAR.items() if lab in present]
            for up, low in zip(names[:-1], names[1:]):
                lines += ["[[instances]]", f'name = "{subject}_{up}{low}"', f'volume = "{seg.as_posix()}"',
                          f"labels = {{ upper = {LUMBAR[up]}, lower = {LUMBAR[low]} }}", ""]
        (work / "pairs.toml").write_text("\n".join(lines))
        build(read_project(work / "pairs.toml"), out, log=None, jobs=2, blend=False)
    return load_npz(out / "model.npz")


def main(argv=None) -> int:
    args = cross_arguments(__doc__.splitlines()[0]).parse_args(argv)
    data, work = Path(args.data), Path(args.work)
    single, _appearance, _trained = build_model(data, work / f"learn_{args.learn}", args.learn)
    t = time.perf_counter()
    pairs = build_pair_model(data, work / f"pairs_{args.learn}", args.learn)
    print(f"pair model: {len(pairs.instance_names)} pairs, {pairs.n_points} points, {pairs.n_modes} modes "
          f"({time.perf_counter() - t:.0f} s)", flush=True)
    ct_path, seg_path = subject_files(data, args.segment)
    image, expert = read_image(ct_path), read_label_map(seg_path)
    present = [n for n, lab in LUMBAR.items() if np.any(expert.labels == lab)]
    params = SegmentParams(evidence="gradient")
    rows = []
    for up, low in zip(present[:-1], present[1:]):
        at_up = start_points(expert.labels == LUMBAR[up], expert.affine, args.offset, args.starts, seed=11)
        at_low = start_points(expert.labels == LUMBAR[low], expert.affine, args.offset, args.starts, seed=12)
        for s in range(args.starts):
            alone = segment_image(single, image, at=at_up[s], params=params)
            a = segmentation_scores(alone.points, alone.faces, expert.labels == LUMBAR[up], expert.affine)
            joint = segment_image(pairs, image, pose=start_pose(pairs, named={"upper": at_up[s], "lower": at_low[s]}),
                                  params=params)
            numbers = structure_labels(["upper", "lower"], {"upper": LUMBAR[up], "lower": LUMBAR[low]})
            labels, info = structure_label_map(joint.points, joint.faces, joint.structures, numbers, image)
            scores = {}
            for name, first, end in joint.structures:
                scores[name] = segmentation_scores(joint.points[first:end], faces_within(joint.faces, first, end),
                                                   expert.labels == numbers[name], expert.affine)
            own = labels == LUMBAR[up]
            truth = expert.labels == LUMBAR[up]
            dice_voxels = 2 * np.count_nonzero(own & truth) / max(own.sum() + truth.sum(), 1)
            row = {"vertebra": up, "start": s, "alone": a, "joint": scores["upper"], "joint_lower": scores["lower"],
                   "joint_label_dice": dice_voxels, "shared_given_away": sum(v["shared_voxels_given_away"]
                                                                             for v in info.values()),
                   "seconds": (alone.seconds, joint.seconds)}
            rows.append(row)
            print(f"  {up} (with {low}) start {s}: alone Dice {a['dice']:.3f}, {a['mean_mm']:.2f} / {a['p95_mm']:.2f} mm"
                  f" ({alone.seconds:.1f} s); with {low}: Dice {scores['upper']['dice']:.3f}, "
                  f"{scores['upper']['mean_mm']:.2f} / {scores['upper']['p95_mm']:.2f} mm, in the label map "
                  f"{dice_voxels:.3f}; {low} {scores['lower']['dice']:.3f}; {row['shared_given_away']} shared "
                  f"voxels given to one ({joint.seconds:.1f} s)", flush=True)
    if rows:
        print(f"mean: alone Dice {np.mean([r['alone']['dice'] for r in rows]):.3f}, "
              f"{np.mean([r['alone']['mean_mm'] for r in rows]):.2f} mm; with the neighbour Dice "
              f"{np.mean([r['joint']['dice'] for r in rows]):.3f}, {np.mean([r['joint']['mean_mm'] for r in rows]):.2f}"
              f" mm (label map {np.mean([r['joint_label_dice'] for r in rows]):.3f}); the neighbour itself "
              f"{np.mean([r['joint_lower']['dice'] for r in rows]):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
