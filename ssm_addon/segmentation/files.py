"""A segmentation's files: the label map on the image's own grid, the surface, the record, the picture."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.stats import spearmanr

from ..base.errors import InputError
from ..base.params import SegmentParams
from ..fitting.fit import Target, fit_any_pose
from ..formats.label_maps import load_volume, read_label_map, write_label_map
from ..formats.landmarks import read_landmarks
from ..formats.meshes import write_ply
from ..meshutil import MeshLocator, faces_within
from ..model.files import load_model, model_file
from .appearance import load_appearance
from .image import GreyImage, read_image, segmentation_mask
from .scores import mask_surface_points, segmentation_scores
from .segment import MIN_SCANS, landmark_pose, segment_image, start_pose

__all__ = ["FIGURE_MARGIN_MM", "SCALE_BAR_MM", "SEGMENT_FILES", "VIEWS", "SegmentationRecord", "parse_point", "segment_figure", "segment_files",
           "structure_labels", "truth_scores", "view_plane", "write_segmentation"]

SEGMENT_FILES = ("segmentation.nii.gz", "segmented.ply", "segment.json", "segment.png")

#: VerSe's label numbers of the vertebrae (Löffler et al. 2020; Sekuboyina et al. 2021): C1-C7 1-7,
#: T1-T12 8-19, L1-L6 20-25, the sacrum 26, T13 28. A joint model's structure named by a vertebra
#: (``L3``, ``sub_L3``, ``t12``) gets its number in the label map unless ``--labels`` says otherwise.
VERSE_LABELS = {**{f"C{i}": i for i in range(1, 8)}, **{f"T{i}": 7 + i for i in range(1, 13)},
                **{f"L{i}": 19 + i for i in range(1, 7)}, "S1": 26, "SACRUM": 26, "T13": 28}


def structure_labels(names, given: dict | None = None) -> dict:
    """The label number of each structure of a joint model in a segmentation's label map.

    ``given`` {name: number} wins; the others are VerSe's number of the vertebra their name ends
    with (:data:`VERSE_LABELS`, the last ``_``/``-``/space-separated part, any case), and where some
    structure is no vertebra, every structure not given is numbered 1, 2, … in the model's order,
    skipping numbers given. Numbers are 1-65535 and distinct.

    >>> structure_labels(["L1", "sub_L2"]), structure_labels(["femur", "tibia"], {"tibia": 5})
    ({'L1': 20, 'sub_L2': 21}, {'femur': 1, 'tibia': 5})
    """
    names = [str(n) for n in names]
    given = {str(k): int(v) for k, v in (given or {}).items()}
    unknown = [k for k in given if k not in names]
    if unknown:
        raise InputError(f"--labels {unknown[0]}=…: the model has no structure {unknown[0]!r} (structures: "
                         f"{', '.join(names)})")
    verse = {n: VERSE_LABELS.get(re.split(r"[_\-\s]", n.strip())[-1].upper()) for n in names if n not in given}
    if all(v is not None for v in verse.values()):
        out = {n: given.get(n, verse.get(n)) for n in names}
    else:
        free = (k for k in range(1, 65536) if k not in given.values())
        out = {n: given[n] if n in given else next(free) for n in names}
    bad = [(n, v) for n, v in out.items() if not 1 <= v <= 65535]
    if bad:
        raise InputError(f"--labels {bad[0][0]}={bad[0][1]}: a label is a number from 1 to 65535")
    if len(set(out.values())) < len(out):
        raise InputError(f"--labels: two structures share a label ({', '.join(f'{n}={v}' for n, v in out.items())})")
    return out


def parse_labels(items) -> dict:
    """{name: number} from ``NAME=N`` strings (``--labels L1=20 L2=21`` or ``L1=20,L2=21``)."""
    out = {}
    for item in items or ():
        for part in str(item).split(","):
            if not part.strip():
                continue
            name, eq, value = part.partition("=")
            try:
                out[name.strip()] = int(value)
            except ValueError:
                raise InputError(f"--labels {part.strip()!r}: expected STRUCTURE=N (N a whole number)") from None
            if not eq or not name.strip():
                raise InputError(f"--labels {part.strip()!r}: expected STRUCTURE=N")
    return out


def structure_label_map(points: np.ndarray, faces: np.ndarray, structures, labels: dict,
                        image: GreyImage) -> tuple[np.ndarray, dict]:
    """A joint segmentation's label map on ``image``'s grid: each structure's voxels with its label.

    ``structures``: (name, first point, end point) of each (:attr:`SegmentResult.structures`); its
    triangles are those of ``faces`` within its points. A voxel whose centre lies inside two
    structures' surfaces (neighbours whose surfaces cross) goes to the one it lies deeper inside
    (farther from that structure's surface, world mm), so no voxel belongs to two.

    Returns
    -------
    (I, J, K) uint8 or uint16 labels, and per structure {"label", "voxels", "shared_voxels_given_away"}.

    One image-sized mask at a time (a whole spine on a whole CT): each structure takes its free
    voxels, and of those an earlier structure holds, the ones it lies strictly deeper in (so the
    deepest wins, the earlier structure on a tie).
    """
    owner = np.full(image.shape, -1, np.int16)
    locators = []
    given_away = np.zeros(len(structures), np.int64)
    for k, (_name, a, b) in enumerate(structures):
        f = faces_within(faces, a, b)
        locators.append(MeshLocator(points[a:b], f))
        mask = segmentation_mask(points[a:b], f, image)
        held = np.argwhere(mask & (owner >= 0))
        owner[mask & (owner < 0)] = k
        if len(held):
            at = tuple(held.T)
            world = image.to_world(held.astype(float))
            depth_here = locators[k].query(world)[1]
            holder = owner[at].astype(np.int64)
            depth_held = np.empty(len(held))
            for j in np.unique(holder):
                depth_held[holder == j] = locators[j].query(world[holder == j])[1]
            taken = depth_here > depth_held
            np.add.at(given_away, holder[taken], 1)
            given_away[k] += int(np.count_nonzero(~taken))
            owner[tuple(held[taken].T)] = k
    numbers = np.array([labels[name] for name, _a, _b in structures], dtype=np.int64)
    dtype = np.uint8 if numbers.max() <= 255 else np.uint16
    out = np.where(owner >= 0, numbers[np.maximum(owner, 0)], 0).astype(dtype)
    info = {name: {"label": int(numbers[k]), "voxels": int(np.count_nonzero(owner == k)),
                   "shared_voxels_given_away": int(given_away[k])} for k, (name, _a, _b) in enumerate(structures)}
    return out, info


#: The three views as 3D Slicer and ITK-SNAP show them (RAS world): each view's screen-right and
#: screen-up directions and the letters at its left, right, top and bottom edges. Patient right is on
#: the viewer's left (radiological), anterior up in the axial view, superior up in the others.
VIEWS = (
    ("axial", (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0), ("R", "L", "A", "P")),
    ("coronal", (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0), ("R", "L", "S", "I")),
    ("sagittal", (0.0, -1.0, 0.0), (0.0, 0.0, 1.0), ("A", "P", "S", "I")),
)
#: Field of view around the structure (mm beyond its bounding box on every side).
FIGURE_MARGIN_MM = 15.0
#: Length of the scale bar (mm).
SCALE_BAR_MM = 10.0


def view_plane(image: GreyImage, centre, right, up, half_right: float, half_up: float,
               step: float) -> tuple[np.ndarray, np.ndarray]:
    """The world points (mm, RAS) of a view's pixels: rows from the bottom up, columns from the screen's
    left to its right, ``step`` mm apart, and their continuous voxel indices in ``image`` (3, rows, cols)."""
    right, up = np.asarray(right, float), np.asarray(up, float)
    cols = np.arange(-half_right, half_right + 0.5 * step, step)
    rows = np.arange(-half_up, half_up + 0.5 * step, step)
    world = np.asarray(centre, float) + cols[None, :, None] * right + rows[:, None, None] * up
    ijk = image.to_index(world.reshape(-1, 3)).T.reshape(3, len(rows), len(cols))
    return world, ijk


def segment_figure(image: GreyImage, mask: np.ndarray, path, *, title: str = "", reference: np.ndarray | None = None,
                   reference_affine: np.ndarray | None = None, window=(-200.0, 1200.0)) -> Path:
    """Axial, coronal and sagittal views through the segmentation's centre, as 3D Slicer and ITK-SNAP
    show them (:data:`VIEWS`): resampled from the image's grid to square pixels in world mm (any
    voxel size and axis order), centred and zoomed on the structure, with the orientation letters
    and a scale bar; the image in grey (``window`` low/high), the segmentation's outline in orange
    and, when given, a reference mask's (e.g. the expert label map; on the image's grid, or on its own
    with ``reference_affine``, voxel -> world mm) in cyan, dashed (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    idx = np.argwhere(mask)
    pts = image.to_world(idx.astype(float)) if len(idx) else image.to_world((np.asarray(image.shape) - 1) / 2.0)[None]
    centre = pts.mean(axis=0)
    lo, hi = pts.min(axis=0) - FIGURE_MARGIN_MM, pts.max(axis=0) + FIGURE_MARGIN_MM
    half = np.maximum(np.abs(hi - centre), np.abs(centre - lo))
    step = max(0.5, float(np.min(image.spacing_mm)))
    data = np.asarray(image.data, np.float32)

    def ref_ijk(world, ijk):  # the view's pixels in the reference's grid (the image's, unless it has its own)
        if reference is None or reference_affine is None:
            return ijk
        inv = np.linalg.inv(np.asarray(reference_affine, float))
        return (world.reshape(-1, 3) @ inv[:3, :3].T + inv[:3, 3]).T.reshape(3, *world.shape[:2])

    fig, axes = plt.subplots(1, 3, figsize=(13, 4.8))
    for ax, (name, right, up, letters) in zip(axes, VIEWS):
        half_r = float(np.abs(np.asarray(right)) @ half)
        half_u = float(np.abs(np.asarray(up)) @ half)
        world, ijk = view_plane(image, centre, right, up, half_r, half_u, step)
        grey = ndimage.map_coordinates(data, ijk, order=1, mode="constant", cval=float(window[0]))
        extent = (-half_r, half_r, -half_u, half_u)
        ax.imshow(grey, cmap="gray", vmin=window[0], vmax=window[1], origin="lower", extent=extent,
                  interpolation="bilinear")
        for m, grid, colour, style, width in ((mask, ijk, "#ff8c00", "solid", 1.2),
                                              (reference, ref_ijk(world, ijk), "#00c8ff", "dashed", 0.9)):
            if m is None:
                continue
            cut = ndimage.map_coordinates(np.asarray(m, np.float32), grid, order=0, mode="constant", cval=0.0)
            if cut.any() and not cut.all():
                ax.contour(cut, levels=[0.5], colors=[colour], linewidths=width, linestyles=style, origin="lower",
                           extent=extent)
        for (x, y, ha, va), letter in zip(((0.02, 0.5, "left", "center"), (0.98, 0.5, "right", "center"),
                                           (0.5, 0.98, "center", "top"), (0.5, 0.02, "center", "bottom")), letters):
            ax.text(x, y, letter, transform=ax.transAxes, ha=ha, va=va, color="#ffd400", fontsize=11,
                    fontweight="bold")
        x0, y0 = -half_r + 0.06 * 2 * half_r, -half_u + 0.1 * 2 * half_u
        ax.plot([x0, x0 + SCALE_BAR_MM], [y0, y0], color="white", linewidth=2.5)
        ax.text(x0 + SCALE_BAR_MM / 2, y0 + 0.02 * 2 * half_u, f"{SCALE_BAR_MM:g} mm", color="white", ha="center",
                va="bottom", fontsize=8)
        plane_axis = int(np.argmax(np.abs(np.cross(right, up))))
        ax.set_title(f"{name} ({'xyz'[plane_axis]} = {centre[plane_axis]:.1f} mm, RAS)", fontsize=9)
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


def truth_scores(result, truth: np.ndarray, truth_affine: np.ndarray) -> dict:
    """A segmentation against an expert's mask (``truth`` on its grid, ``truth_affine`` voxel -> world
    mm): Dice and the symmetric surface distances (:func:`~ssm_addon.segmentation.scores.segmentation_scores`),
    and how the per-point posterior SD stands to each point's distance from the expert's boundary
    (mm): their Spearman rank correlation and the share of points within 2 SD."""
    if not np.any(truth):
        raise InputError("--truth: the expert's mask is empty (no voxel of the label)")
    scores = segmentation_scores(result.points, result.faces, np.asarray(truth, bool), truth_affine)
    error = cKDTree(mask_surface_points(np.asarray(truth, bool), truth_affine)).query(result.points)[0]
    sd = np.asarray(result.posterior_sd_mm, float)
    rho = float(spearmanr(sd, error)[0]) if np.ptp(sd) > 0 and np.ptp(error) > 0 else float("nan")
    return {**scores, "point_error_mm": {"mean": float(error.mean()), "p95": float(np.percentile(error, 95))},
            "sd_error_spearman": rho, "within_2sd": float(np.mean(error <= 2.0 * sd))}


def write_segmentation(result, image: GreyImage, out_dir, *, model_source: str = "", extra: dict | None = None,
                       overwrite: bool = False, truth: tuple | None = None, labels: dict | None = None) -> dict:
    """Write ``segmentation.nii.gz`` (on the image's grid, its affine: label 1, or a joint model's
    structures each with its own label, :func:`structure_labels` with ``labels``), ``segmented.ply``
    (world mm, RAS, with the posterior SD per vertex), ``segment.json`` and ``segment.png``.

    ``result``: a :class:`~ssm_addon.segmentation.segment.SegmentResult` or a
    :class:`SegmentationRecord`.

    Existing files of these names are refused unless ``overwrite`` (they may not be ours).
    ``truth``: ``(mask, affine, source)`` of an expert's segmentation: scored (:func:`truth_scores`,
    under ``truth`` in ``segment.json``) and outlined in ``segment.png``; for a joint model the mask
    may be the expert's whole label map (integers), then each structure is also scored against the
    expert's voxels of its own label.
    Returns the paths by kind.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    clash = [n for n in SEGMENT_FILES if (out / n).exists()]
    if clash and not overwrite:
        raise InputError(f"{out}: already holds {', '.join(clash)}; choose another --out (a segmentation never "
                         "overwrites files it did not write)")
    record = result.to_dict()
    structures = [(d["name"], *d["points"]) for d in record.get("structures", ())]
    numbers = structure_labels([n for n, _a, _b in structures], labels) if structures else {}
    vox = float(abs(np.linalg.det(image.affine[:3, :3])))
    if structures:
        label_array, per_structure = structure_label_map(np.asarray(result.points, float), result.faces, structures,
                                                         numbers, image)
        mask = label_array > 0
    else:
        mask = segmentation_mask(result.points, result.faces, image)
        label_array, per_structure = mask.astype(np.uint8), {}
    if not mask.any():
        raise InputError(f"{image.path}: the segmented surface encloses no voxel of the image")
    out.mkdir(parents=True, exist_ok=True)
    files = {"segmentation": out / "segmentation.nii.gz", "surface": out / "segmented.ply",
             "record": out / "segment.json", "picture": out / "segment.png"}
    write_label_map(files["segmentation"], label_array, image.affine)
    write_ply(files["surface"], result.points, result.faces,
              vertex_scalars={"posterior_sd_mm": result.posterior_sd_mm, "deviation_mm": result.deviation_mm},
              space="RAS")
    doc = {"image": str(image.path), "model": str(model_source), **record,
           "segmentation": {"voxels": int(mask.sum()), "volume_mm3": float(mask.sum() * vox)},
           "files": {k: p.name for k, p in files.items()}, **(extra or {})}
    for info in per_structure.values():
        info["volume_mm3"] = info["voxels"] * vox
    if per_structure:
        doc["segmentation"]["structures"] = per_structure
    title = f"{Path(image.path).name}: segmentation (orange)"
    reference = None
    if truth is not None:
        expert = np.asarray(truth[0])
        whole = expert.dtype != bool and bool(structures)  # an expert's label map of the structures
        reference = np.isin(expert, list(numbers.values())) if whole else expert.astype(bool)
        doc["truth"] = {"file": str(truth[2]), **truth_scores(result, reference, truth[1])}
        if whole:
            doc["truth"]["structures"] = {name: structure_truth(result, name, a, b, expert == numbers[name],
                                                                numbers[name], truth[1])
                                          for name, a, b in structures}
        title += f", expert (cyan, dashed): Dice {doc['truth']['dice']:.3f}, {doc['truth']['mean_mm']:.2f} mm"
    files["record"].write_text(json.dumps(doc, indent=1))
    segment_figure(image, mask, files["picture"], title=title, reference=reference,
                   reference_affine=None if truth is None else truth[1])
    return files


def structure_truth(result, name: str, first: int, end: int, expert: np.ndarray, label: int, affine) -> dict:
    """One structure of a joint segmentation (its points ``first:end``) against the expert's voxels of
    its label: :func:`truth_scores`, or what is missing."""
    if not np.any(expert):
        return {"label": label, "missing": f"the expert's label map has no voxel of label {label} ({name})"}
    part = SegmentationRecord(points=np.asarray(result.points)[first:end],
                              faces=faces_within(result.faces, first, end),
                              posterior_sd_mm=np.asarray(result.posterior_sd_mm)[first:end],
                              deviation_mm=np.zeros(end - first), record={})
    return {"label": label, **truth_scores(part, expert, affine)}


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
                  label: int | None = None, params=None, progress=None, cancelled=None, say=None,
                  truth_path=None, truth_label: int | None = None, labels: dict | None = None) -> dict:
    """``ssm segment``: read the model (``model.npz`` with its appearance, or a statismo file), the image
    and the start (``at``: "X,Y,Z" or "STRUCTURE=X,Y,Z" strings; a landmark file; or a rough mask and
    its label), segment and write the files into ``out_dir`` (a folder the caller owns). ``truth_path``
    (and ``truth_label``): an expert's label map of the structure, read before the search (a bad file
    fails at once), scored against the result and outlined in ``segment.png``; with a joint model and
    no ``truth_label``, the expert's whole label map, each structure scored against its own label.
    ``labels`` {structure: number}: a joint model's label numbers (:func:`structure_labels`).

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
        say(f"evidence: the appearance learned from {len(appearance.images)} training image(s)"
            + (f" of {appearance.scans} scan: the image gradient is used (learned profiles from {MIN_SCANS} or more "
               "scans; --evidence learned uses these)" if params.evidence == "auto" and 0 < appearance.scans < MIN_SCANS
               else ""))
    numbers = structure_labels(model.structure_names, labels) if model.structure_names else None
    if labels and numbers is None:
        raise InputError(f"--labels: {Path(model_path).name} is not a joint model (one structure, label 1)")
    image = read_image(image_path)
    truth = None
    if truth_path is not None and numbers is not None and truth_label is None:
        expert = read_label_map(truth_path)
        truth = (np.asarray(expert.labels), expert.affine, truth_path)
        if not np.isin(truth[0], list(numbers.values())).any():
            found = np.unique(truth[0][truth[0] > 0])
            raise InputError(f"{truth_path}: the expert's label map holds label(s) "
                             f"{', '.join(map(str, found[:12].tolist())) or 'none'}, none of the structures' "
                             f"({', '.join(f'{n}={v}' for n, v in numbers.items())}): give --labels as that map "
                             "numbers them, or --truth-label N for one structure")
    elif truth_path is not None:
        expert = load_volume(truth_path, truth_label)
        truth = (expert.mask, expert.affine, truth_path)
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
    files = write_segmentation(result, image, out_dir, model_source=str(model_path), extra=extra, overwrite=True,
                               truth=truth, labels=numbers)
    return json.loads(files["record"].read_text())
