"""Segmentation across scanners: learn the appearance on one CT, segment the other's vertebrae.

The model: verse004's lumbar vertebrae (label maps, its landmark files) and the learning subject's
lumbar vertebrae (label maps, extremal-point landmarks, its CT as ``image``), built by ``ssm build``.
The other subject's lumbar vertebrae are segmented from points ``--offset`` mm off their centres
(``--starts`` directions) with each evidence of ``--evidence``:

* ``gradient``: the image gradient;
* ``learned``: the appearance the build learned (set aside, with a note, on an image coarser than
  1.5x its training's voxels);
* ``matched``: the appearance learned again from the training CT degraded to the target image's
  voxel size along each world axis (the thick slices of the target, per axis);
* ``augmented``: learned from the training CT as it is and degraded to 3 mm slices along each of its
  three voxel axes in turn.

    python tools/eval_segmentation_cross.py --learn verse005 --segment verse012 --work /tmp/cross

Prints a row per (vertebra, evidence, start) with Dice, mean and 95th percentile surface distance, the
posterior SD's Spearman correlation with each point's error and its coverage (within 2 SD), and the
means per evidence.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

from eval_segmentation import LUMBAR, extremal_landmarks, start_points  # noqa: E402

from ssm_addon.base.params import SegmentParams  # noqa: E402
from ssm_addon.formats.label_maps import read_label_map  # noqa: E402
from ssm_addon.model.files import load_npz  # noqa: E402
from ssm_addon.pipeline.project import read_project  # noqa: E402
from ssm_addon.pipeline.project_build import build  # noqa: E402
from ssm_addon.segmentation import (  # noqa: E402
    GreyImage,
    learn_appearance,
    load_appearance,
    read_image,
    segment_image,
    truth_scores,
)


def subject_files(data: Path, subject: str) -> tuple[Path, Path]:
    return data / subject / f"sub-{subject}_ct.nii.gz", data / subject / f"sub-{subject}_seg-vert_msk.nii.gz"


def build_model(data: Path, work: Path, learn: str):
    """The lumbar model of verse004 and ``learn``'s vertebrae, appearance from ``learn``'s CT."""
    out = work / "out"
    ct, seg = subject_files(data, learn)
    labels = read_label_map(seg)
    present = {n: lab for n, lab in LUMBAR.items() if np.any(labels.labels == lab)}
    if not (out / "model.npz").is_file():
        work.mkdir(parents=True, exist_ok=True)
        v4 = data / "verse004"
        lines = ["[template]", 'instance = "v4_L1"', "spacing = 1.0", "", "[correspondence]", "optimise = false", ""]
        for name, label in LUMBAR.items():
            lines += ["[[instances]]", f'name = "v4_{name}"', f'volume = "{(v4 / "sub-verse004_seg-vert_msk.nii.gz").as_posix()}"',
                      f"label = {label}", f'landmarks = "{(v4 / "landmarks" / f"{name}.fcsv").as_posix()}"', ""]
        for name, label in present.items():
            fcsv = extremal_landmarks(labels.labels == label, labels.affine, work / f"{learn}_{name}.fcsv")
            lines += ["[[instances]]", f'name = "{learn}_{name}"', f'volume = "{seg.as_posix()}"', f"label = {label}",
                      f'landmarks = "{fcsv.as_posix()}"', f'image = "{ct.as_posix()}"', ""]
        (work / "lumbar.toml").write_text("\n".join(lines))
        build(read_project(work / "lumbar.toml"), out, log=None, jobs=2, blend=False)
    model = load_npz(out / "model.npz")
    return model, load_appearance(out / "model.npz", model.n_points), [f"{learn}_{n}" for n in present]


def degrade_along(image: GreyImage, axis: int, slice_mm: float) -> GreyImage:
    """The image with voxel axis ``axis`` made ``slice_mm`` thick (the mean over each slab)."""
    a = np.asarray(image.affine, float)
    step = float(np.linalg.norm(a[:3, axis]))
    factor = max(1, int(round(slice_mm / step)))
    if factor == 1:
        return image
    data = np.moveaxis(np.asarray(image.data, np.float32), axis, 0)
    n = data.shape[0] // factor
    thick = np.moveaxis(data[:n * factor].reshape(n, factor, *data.shape[1:]).mean(axis=1), 0, axis)
    new = a.copy()
    new[:3, axis] = a[:3, axis] * factor
    new[:3, 3] = a[:3, 3] + a[:3, axis] * (factor - 1) / 2.0
    return GreyImage(np.ascontiguousarray(thick, np.float32), new, f"{image.path} (axis {axis} {factor * step:g} mm)")


def matched(image: GreyImage, target: GreyImage) -> GreyImage:
    """``image`` degraded to ``target``'s voxel size along each world axis (the voxel axis nearest it)."""
    out = image
    for world_axis in range(3):
        t_axis = int(np.argmax(np.abs(target.affine[world_axis, :3]) / np.linalg.norm(target.affine[:3, :3], axis=0)))
        want = float(np.linalg.norm(target.affine[:3, t_axis]))
        i_axis = int(np.argmax(np.abs(out.affine[world_axis, :3]) / np.linalg.norm(out.affine[:3, :3], axis=0)))
        have = float(np.linalg.norm(out.affine[:3, i_axis]))
        if want > 1.5 * have:
            out = degrade_along(out, i_axis, want)
    return out


def relearned(model, names, images) -> object:
    rows = [list(map(str, model.instance_names)).index(n) for n in names]
    shapes = [model.instance_points_world[i] for i in rows]
    sh, im, nm = [], [], []
    for s, n in zip(shapes, names):
        for k, img in enumerate(images):
            sh.append(s)
            im.append(img)
            nm.append(f"{n}#{k}")
    return learn_appearance(model.mean, model.faces, sh, im, names=nm)


def cross_arguments(description: str) -> argparse.ArgumentParser:
    """The options of a learn-on-one-CT, segment-the-other evaluation: data, work, learn, segment, starts."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--work", required=True)
    ap.add_argument("--learn", default="verse005")
    ap.add_argument("--segment", default="verse012")
    ap.add_argument("--offset", type=float, default=10.0)
    ap.add_argument("--starts", type=int, default=2)
    return ap


def main(argv=None) -> int:
    ap = cross_arguments(__doc__.splitlines()[0])
    ap.add_argument("--evidence", default="gradient,learned,matched,augmented")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    data, work = Path(args.data), Path(args.work)
    t = time.perf_counter()
    model, appearance, trained = build_model(data, work / f"learn_{args.learn}", args.learn)
    print(f"model of {len(model.instance_names)} vertebrae, {model.n_points} points, {model.n_modes} modes, appearance "
          f"from {', '.join(trained)} ({time.perf_counter() - t:.0f} s)", flush=True)
    train_ct = read_image(subject_files(data, args.learn)[0])
    ct_path, seg_path = subject_files(data, args.segment)
    image, labels = read_image(ct_path), read_label_map(seg_path)
    print(f"target {args.segment}: voxels {np.round(image.spacing_mm, 2).tolist()} mm; training {args.learn}: "
          f"{np.round(train_ct.spacing_mm, 2).tolist()} mm", flush=True)
    apps = {"gradient": None, "learned": appearance}
    evidences = args.evidence.split(",")
    if "matched" in evidences:
        t = time.perf_counter()
        apps["matched"] = relearned(model, trained, [matched(train_ct, image)])
        print(f"matched appearance: voxel {apps['matched'].voxel_mm:.2f} mm ({time.perf_counter() - t:.0f} s)", flush=True)
    if "augmented" in evidences:
        t = time.perf_counter()
        apps["augmented"] = relearned(model, trained, [train_ct] + [degrade_along(train_ct, k, 3.0) for k in range(3)])
        print(f"augmented appearance: voxel {apps['augmented'].voxel_mm:.2f} mm ({time.perf_counter() - t:.0f} s)",
              flush=True)
    rows = []
    for name, label in LUMBAR.items():
        truth = labels.labels == label
        if not truth.any():
            continue
        for evidence in evidences:
            app = apps[evidence]
            for s, at in enumerate(start_points(truth, labels.affine, args.offset, args.starts, seed=11)):
                res = segment_image(model, image, at=at, appearance=app,
                                    params=SegmentParams(evidence="gradient" if app is None else "learned")
                                    if evidence != "learned" else SegmentParams(evidence="auto"))
                sc = truth_scores(res, truth, labels.affine)
                row = {"vertebra": name, "evidence": evidence, "start": s, "used": res.evidence, "seconds": res.seconds,
                       **{k: sc[k] for k in ("dice", "mean_mm", "p95_mm", "sd_error_spearman", "within_2sd")}}
                rows.append(row)
                print(f"  {name} {evidence:9s} start {s}: Dice {sc['dice']:.3f}, mean {sc['mean_mm']:.2f} mm, p95 "
                      f"{sc['p95_mm']:.2f} mm, SD rho {sc['sd_error_spearman']:.2f}, within 2 SD "
                      f"{100 * sc['within_2sd']:.0f} %, {res.seconds:.1f} s ({res.evidence[:40]})", flush=True)
    for evidence in evidences:
        sel = [r for r in rows if r["evidence"] == evidence]
        if sel:
            print(f"mean {evidence:9s}: Dice {np.mean([r['dice'] for r in sel]):.3f}, mean "
                  f"{np.mean([r['mean_mm'] for r in sel]):.2f} mm, p95 {np.mean([r['p95_mm'] for r in sel]):.2f} mm, "
                  f"SD rho {np.nanmean([r['sd_error_spearman'] for r in sel]):.2f}, within 2 SD "
                  f"{100 * np.mean([r['within_2sd'] for r in sel]):.0f} %, {np.median([r['seconds'] for r in sel]):.1f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
