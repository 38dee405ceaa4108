"""Leave-one-out segmentation of verse005's lumbar vertebrae: Dice and surface distances against the expert.

For each held-out vertebra V of sub-verse005 (L1..L5): a lumbar model is built from
verse004's L1..L5 and verse005's other four (label maps; verse004's landmark files, and
the same extremal-point landmarks computed for verse005), appearance is learned from
verse005's CT at those four only, and V is segmented from points ``--offset`` mm off its
centre (``--starts`` directions), with the learned appearance and with the gradient, on
the CT as it is and degraded (``--degrade``: 3 mm slices along the superior axis, noise).

    python tools/eval_segmentation.py --data ../shared/data --work /tmp/segwork [--held L3,L5]

Prints one row per (vertebra, image, evidence, start) and the means; ``--json`` writes them.
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

from ssm_addon.base.params import SegmentParams  # noqa: E402
from ssm_addon.formats.label_maps import read_label_map  # noqa: E402
from ssm_addon.model.files import load_npz  # noqa: E402
from ssm_addon.pipeline.project import read_project  # noqa: E402
from ssm_addon.pipeline.project_build import build  # noqa: E402
from ssm_addon.segmentation import (  # noqa: E402
    degrade_image,
    load_appearance,
    read_image,
    segment_image,
    segmentation_scores,
)

LUMBAR = {"L1": 20, "L2": 21, "L3": 22, "L4": 23, "L5": 24}
DIRECTIONS = {"right": (1, 0, 0), "left": (-1, 0, 0), "anterior": (0, 1, 0), "posterior": (0, -1, 0),
              "superior": (0, 0, 1), "inferior": (0, 0, -1)}
for _a in ("right", "left"):
    for _b in ("anterior", "posterior"):
        for _c in ("superior", "inferior"):
            DIRECTIONS[f"{_a}-{_b}-{_c}"] = tuple(np.add(np.add(DIRECTIONS[_a], DIRECTIONS[_b]), DIRECTIONS[_c]))


def extremal_landmarks(mask: np.ndarray, affine: np.ndarray, path: Path) -> Path:
    """verse004's landmark recipe for any mask: the surface voxel centre farthest along each of
    14 patient directions, written as a 3D Slicer markups file (LPS)."""
    from nibabel.affines import apply_affine
    from scipy import ndimage

    surface = mask & ~ndimage.binary_erosion(mask)
    pts = apply_affine(affine, np.argwhere(surface).astype(float))
    lines = ["# Markups fiducial file version = 4.11", "# CoordinateSystem = LPS",
             "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID"]
    for i, (name, d) in enumerate(DIRECTIONS.items()):
        p = pts[int(np.argmax(pts @ (np.asarray(d, float) / np.linalg.norm(d))))]
        lines.append(f"vtkMRMLMarkupsFiducialNode_{i},{-p[0]:.3f},{-p[1]:.3f},{p[2]:.3f},0,0,0,1,1,1,0,{name},"
                     "extremal surface point,")
    path.write_text("\n".join(lines) + "\n")
    return path


def build_lumbar_model(data: Path, work: Path, *, held: str):
    """The lumbar model without verse005's ``held`` vertebra, and its appearance from verse005's CT."""
    work.mkdir(parents=True, exist_ok=True)
    out = work / "out"
    v4 = data / "verse004"
    v5_labels = data / "verse005" / "sub-verse005_seg-vert_msk.nii.gz"
    v5_ct = data / "verse005" / "sub-verse005_ct.nii.gz"
    if not (out / "model.npz").is_file():
        labels = read_label_map(v5_labels)
        lines = ["[template]", 'instance = "v4_L1"', "spacing = 1.0", ""]
        for name, label in LUMBAR.items():
            lines += ["[[instances]]", f'name = "v4_{name}"', f'volume = "{(v4 / "sub-verse004_seg-vert_msk.nii.gz").as_posix()}"',
                      f"label = {label}", f'landmarks = "{(v4 / "landmarks" / f"{name}.fcsv").as_posix()}"', ""]
        for name, label in LUMBAR.items():
            if name == held:
                continue
            fcsv = extremal_landmarks(labels.labels == label, labels.affine, work / f"v5_{name}.fcsv")
            lines += ["[[instances]]", f'name = "v5_{name}"', f'volume = "{v5_labels.as_posix()}"', f"label = {label}",
                      f'landmarks = "{fcsv.as_posix()}"', f'image = "{v5_ct.as_posix()}"', ""]
        (work / "lumbar.toml").write_text("\n".join(lines))
        build(read_project(work / "lumbar.toml"), out, log=None, jobs=2, blend=False)
    model = load_npz(out / "model.npz")
    appearance = load_appearance(out / "model.npz", model.n_points)  # learned by the build from the images
    return model, appearance


def start_points(mask: np.ndarray, affine: np.ndarray, offset_mm: float, n: int, *, seed: int) -> list:
    """``n`` points ``offset_mm`` from the mask's centroid (world mm), in seeded random directions."""
    from nibabel.affines import apply_affine

    centre = apply_affine(affine, np.argwhere(mask).mean(axis=0))
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return [centre + offset_mm * v for v in d]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--work", required=True)
    ap.add_argument("--held", default=",".join(LUMBAR))
    ap.add_argument("--offset", type=float, default=10.0)
    ap.add_argument("--starts", type=int, default=3)
    ap.add_argument("--evidence", default="learned,gradient")
    ap.add_argument("--degrade", default="none,3mm")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    data, work = Path(args.data), Path(args.work)
    ct = read_image(data / "verse005" / "sub-verse005_ct.nii.gz")
    labels = read_label_map(data / "verse005" / "sub-verse005_seg-vert_msk.nii.gz")
    rows = []
    for held in args.held.split(","):
        t = time.perf_counter()
        model, appearance = build_lumbar_model(data, work / f"loo_{held}", held=held)
        print(f"{held}: model of {len(model.instance_names)} vertebrae, {model.n_points} points, "
              f"{model.n_modes} modes ({time.perf_counter() - t:.0f} s)", flush=True)
        truth = labels.labels == LUMBAR[held]
        for degrade in args.degrade.split(","):
            image = ct if degrade == "none" else degrade_image(ct, slice_mm=3.0, noise_hu=30.0, seed=5)
            for evidence in args.evidence.split(","):
                for s, at in enumerate(start_points(truth, labels.affine, args.offset, args.starts, seed=11)):
                    res = segment_image(model, image, at=at, appearance=appearance if evidence == "learned" else None,
                                        params=SegmentParams(evidence=evidence))
                    sc = segmentation_scores(res.points, res.faces, truth, labels.affine)
                    row = {"vertebra": held, "image": degrade, "evidence": evidence, "start": s,
                           **sc, "seconds": res.seconds, "findings": [k for k, _ in res.findings]}
                    rows.append(row)
                    print(f"  {held} {degrade:5s} {evidence:8s} start {s}: Dice {sc['dice']:.3f}, mean "
                          f"{sc['mean_mm']:.2f} mm, p95 {sc['p95_mm']:.2f} mm, {res.seconds:.1f} s "
                          f"{' '.join(row['findings'])}", flush=True)
    for degrade in args.degrade.split(","):
        for evidence in args.evidence.split(","):
            sel = [r for r in rows if r["image"] == degrade and r["evidence"] == evidence]
            if sel:
                print(f"mean {degrade:5s} {evidence:8s}: Dice {np.mean([r['dice'] for r in sel]):.3f}, mean "
                      f"{np.mean([r['mean_mm'] for r in sel]):.2f} mm, p95 {np.mean([r['p95_mm'] for r in sel]):.2f}"
                      f" mm, {np.median([r['seconds'] for r in sel]):.1f} s (median)")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
