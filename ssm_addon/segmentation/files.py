"""A segmentation's files: the label map on the image's own grid, the surface, the record, the picture."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..base.errors import InputError
from ..fitting.batch import load_model, model_file
from ..fitting.fit import Target, fit_any_pose
from ..formats.label_maps import load_volume, write_label_map
from ..formats.landmarks import read_landmarks
from ..formats.meshes import write_ply
from .appearance import load_appearance
from .image import GreyImage, read_image, segmentation_mask
from .scores import mask_surface_points
from .segment import SegmentParams, landmark_pose, segment_image, start_pose

__all__ = ["SEGMENT_FILES", "SegmentationRecord", "parse_point", "segment_figure", "segment_files", "write_segmentation"]

SEGMENT_FILES = ("segmentation.nii.gz", "segmented.ply", "segment.json", "segment.png")


def segment_figure(image: GreyImage, mask: np.ndarray, path, *, title: str = "", reference: np.ndarray | None = None,
                   window=(-200.0, 1200.0)) -> Path:
    """Three slices (one per voxel axis) through the segmentation's centre, the image in grey
    (``window`` low/high), the segmentation's outline in orange and, when given, a
    reference mask's in cyan (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    idx = np.argwhere(mask)
    centre = idx.mean(axis=0).round().astype(int) if len(idx) else np.asarray(image.shape) // 2
    fig, axes = plt.subplots(1, 3, figsize=(12, 4.4))
    sp = image.spacing_mm
    for axis, ax in enumerate(axes):
        sl = [slice(None)] * 3
        sl[axis] = int(centre[axis])
        img = np.asarray(image.data[tuple(sl)], float)
        m = mask[tuple(sl)]
        others = [a for a in range(3) if a != axis]
        ax.imshow(img, cmap="gray", vmin=window[0], vmax=window[1], origin="lower", aspect=sp[others[0]] / sp[others[1]],
                  interpolation="nearest")
        if m.any():
            ax.contour(m.astype(float), levels=[0.5], colors=["#ff8c00"], linewidths=1.2)
        if reference is not None and reference[tuple(sl)].any():
            ax.contour(reference[tuple(sl)].astype(float), levels=[0.5], colors=["#00c8ff"], linewidths=0.8,
                       linestyles="dashed")
        ax.set_title(f"voxel axis {'ijk'[axis]} = {int(centre[axis])}", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(title or "segmentation (orange)" + (", reference (cyan, dashed)" if reference is not None else ""),
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return Path(path)


@dataclass(frozen=True, eq=False)
class SegmentationRecord:
    """A segmentation as a scene keeps it (its surface, per-point SD and deviation, and the record of
    :meth:`SegmentResult.to_dict`): what :func:`write_segmentation` needs."""

    points: np.ndarray
    faces: np.ndarray
    posterior_sd_mm: np.ndarray
    deviation_mm: np.ndarray
    record: dict

    def to_dict(self) -> dict:
        return dict(self.record)


def write_segmentation(result, image: GreyImage, out_dir, *, model_source: str = "", extra: dict | None = None,
                       overwrite: bool = False) -> dict:
    """Write ``segmentation.nii.gz`` (label 1 on the image's grid, its affine), ``segmented.ply``
    (world mm, RAS, with the posterior SD per vertex), ``segment.json`` and ``segment.png``.

    ``result``: a :class:`~ssm_addon.segmentation.segment.SegmentResult` or a
    :class:`SegmentationRecord`.

    Existing files of these names are refused unless ``overwrite`` (they may not be ours).
    Returns the paths by kind.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    clash = [n for n in SEGMENT_FILES if (out / n).exists()]
    if clash and not overwrite:
        raise InputError(f"{out}: already holds {', '.join(clash)}; choose another --out (a segmentation never "
                         "overwrites files it did not write)")
    out.mkdir(parents=True, exist_ok=True)
    mask = segmentation_mask(result.points, result.faces, image)
    if not mask.any():
        raise InputError(f"{image.path}: the segmented surface encloses no voxel of the image")
    files = {"segmentation": out / "segmentation.nii.gz", "surface": out / "segmented.ply",
             "record": out / "segment.json", "picture": out / "segment.png"}
    write_label_map(files["segmentation"], mask.astype(np.uint8), image.affine)
    write_ply(files["surface"], result.points, result.faces,
              vertex_scalars={"posterior_sd_mm": result.posterior_sd_mm, "deviation_mm": result.deviation_mm},
              space="RAS")
    vox = float(abs(np.linalg.det(image.affine[:3, :3])))
    doc = {"image": str(image.path), "model": str(model_source), **result.to_dict(),
           "segmentation": {"voxels": int(mask.sum()), "volume_mm3": float(mask.sum() * vox)},
           "files": {k: p.name for k, p in files.items()}, **(extra or {})}
    files["record"].write_text(json.dumps(doc, indent=1))
    segment_figure(image, mask, files["picture"], title=f"{Path(image.path).name}: segmentation (orange)")
    return files


def parse_point(text: str, what: str = "--at") -> np.ndarray:
    """(3,) mm from ``"X,Y,Z"``; a clear error otherwise."""
    try:
        values = [float(v) for v in str(text).replace(" ", "").split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not np.all(np.isfinite(values)):
        raise InputError(f"{what} {text!r}: expected three numbers X,Y,Z in mm (world RAS)")
    return np.asarray(values)


def segment_files(model_path, image_path, out_dir, *, at=(), landmarks_path=None, init_mask_path=None,
                  label: int | None = None, params=None, progress=None, cancelled=None, say=None) -> dict:
    """``ssm segment``: read the model (``model.npz`` with its appearance, or a statismo file), the image
    and the start (``at``: "X,Y,Z" or "STRUCTURE=X,Y,Z" strings; a landmark file; or a rough mask and
    its label), segment and write the files into ``out_dir`` (a folder the caller owns).

    Returns the ``segment.json`` document.
    """
    say = say or (lambda _line: None)
    params = SegmentParams() if params is None else params
    model_path = model_file(model_path)  # a build's output folder: its model.npz
    model = load_model(model_path, say=say)
    appearance = load_appearance(model_path, model.n_points)
    if appearance is None:
        say(f"{Path(model_path).name}: no learned appearance (built without images): the boundary evidence is the "
            "image gradient (a bright structure on a darker background)")
    elif params.evidence == "gradient":
        say("evidence: the image gradient, as asked (the model's learned appearance is not used)")
    else:
        say(f"evidence: the appearance learned from {len(appearance.images)} training image(s)")
    image = read_image(image_path)
    named, pose, start = {}, None, {}
    plain = [a for a in at if "=" not in a]
    for a in at:
        if "=" in a:
            key, value = a.split("=", 1)
            named[key.strip()] = parse_point(value, f"--at {key}")
    if plain and named:
        raise InputError("--at: give one point X,Y,Z, or STRUCTURE=X,Y,Z per structure, not both")
    if len(plain) > 1:
        raise InputError("--at: one point inside the structure (a joint model takes STRUCTURE=X,Y,Z each)")
    starts = sum(bool(x) for x in (plain or named, landmarks_path, init_mask_path))
    if starts != 1:
        raise InputError("give one start: --at X,Y,Z (a point inside the structure), --landmarks FILE or "
                         "--init-mask FILE")
    at_point = parse_point(plain[0]) if plain else None
    if named:
        unknown = [n for n in named if n not in model.structure_names]
        if unknown:
            raise InputError(f"--at {unknown[0]}=…: the model has no structure {unknown[0]!r} (structures: "
                             f"{', '.join(model.structure_names) or 'none: give --at X,Y,Z'})")
        for n, p in named.items():
            if not image.contains(p)[0]:
                raise InputError(f"{image.path}: the point of {n} ({', '.join(f'{v:.1f}' for v in p)}) mm lies "
                                 "outside the image")
        pose = start_pose(model, named=named)
        start = {"points": {n: p.tolist() for n, p in named.items()}}
    elif landmarks_path is not None:
        lms = read_landmarks(landmarks_path)
        pose = landmark_pose(model, lms)
        start = {"landmarks": str(landmarks_path), "names": list(lms.names)}
    elif init_mask_path is not None:
        vol = load_volume(init_mask_path, label)
        if vol.mask.shape != image.shape or not np.allclose(vol.affine, image.affine, atol=1e-3):
            say(f"{Path(init_mask_path).name}: its grid differs from the image's; it is used in world mm")
        pts = mask_surface_points(vol.mask, vol.affine)
        fit, _doc = fit_any_pose(model, Target.from_points(pts, source=str(init_mask_path)))
        pose = fit.pose
        start = {"init_mask": str(init_mask_path), "label": label, "mask_fit_mm": fit.mean_distance_mm}
    else:
        start = {"at": at_point.tolist()}
    result = segment_image(model, image, at=at_point, pose=pose, appearance=appearance, params=params,
                           progress=progress, cancelled=cancelled)
    extra = {"start_given": start}
    files = write_segmentation(result, image, out_dir, model_source=str(model_path), extra=extra, overwrite=True)
    return json.loads(files["record"].read_text())
