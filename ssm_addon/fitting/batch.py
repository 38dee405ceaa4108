"""Using a built model: ``ssm fit`` — projection, completion with uncertainty, outlier scores.

Loads a model (``model.npz`` or a statismo HDF5 file), turns files into a fitting
:class:`~ssm_addon.fitting.fit.Target` in their world frame (label map, closed mesh, point
cloud, landmarks), fits (:func:`ssm_addon.fitting.fit.fit_model`) and writes

* ``fitted.ply`` — the model-constrained fit (world mm, the template's triangles, the
  posterior standard deviation per vertex as the ``posterior_sd_mm`` property);
* ``fitted_free.ply`` — with ``free``: that fit relaxed freely onto the target (paper 4.2);
* ``fit.json`` — coefficients (standard deviations), pose, Mahalanobis distance and its
  chi-square p-value, outlier flag, distances, landmark residuals, files;
* ``fit.npz`` — ``posterior_mean`` (N, 3) and ``posterior_sd_mm`` (N,);
* ``fit.png`` — the fit over the target, two views.

A batch (a project's instances or a glob of files) writes one folder per target and a
``coefficients.csv`` for group statistics.
"""

from __future__ import annotations

import csv
import glob
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..base.compute import Executor
from ..base.errors import InputError
from ..base.params import FitParams, to_table
from ..base.progress import CancelledFn, ProgressFn, report
from ..coating.coating import CoatingStart, coat_from_start
from ..fitting.fit import FitResult, Pose, Target, fit_any_pose, fit_floor
from ..fitting.verdict import UNIT_RATIO, is_outlier, judge_fit, size_in_unit_range
from ..formats.label_maps import file_stem, is_mesh_file, read_label_map, select_label
from ..formats.landmarks import read_landmarks
from ..formats.meshes import read_mesh, read_ply, write_ply
from ..instances.frame import frame_axes_patient
from ..instances.importing import InstanceSpec, file_names, import_instance, instance_frame, mesh_frame
from ..instances.volume import display_surface
from ..meshutil import Mesh
from ..model.figures import fit_figure, p_value_text
from ..model.files import load_model, write_npz

__all__ = ["FitTarget", "fit_batch", "fit_structures_to_folder", "fit_to_folder", "load_target"]


@dataclass(frozen=True)
class FitTarget:
    """What to fit, as files (serialisable: workers read them themselves)."""

    name: str
    volume: Path | None = None
    label: int | None = None
    mesh: Path | None = None
    points: Path | None = None
    landmarks: Path | None = None


def _read_points(path: Path) -> np.ndarray:

    if path.suffix.lower() == ".ply":
        v, _, _ = read_ply(path)
        return v
    try:
        rows = []
        with open(path, encoding="utf-8") as fh:
            for line in fh:
                parts = [p for p in line.replace(";", ",").replace("\t", ",").split(",") if p.strip()]
                if not parts:
                    continue
                try:
                    rows.append([float(x) for x in parts[-3:]])
                except ValueError:
                    if rows:
                        raise
        pts = np.asarray(rows, float).reshape(-1, 3)
    except (OSError, ValueError) as err:
        raise InputError(f"{path}: cannot read points (CSV x,y,z per line, or PLY): {err}") from None
    if not len(pts):
        raise InputError(f"{path}: no points")
    return pts


def pose_of_points(points: np.ndarray) -> Pose:
    """A start pose from a point set alone: its centroid and principal axes paired with the
    patient axes (R, A, S), as the object frame of an image (paper 2)."""
    pts = np.asarray(points, float)
    centre = pts.mean(axis=0)
    _, vecs = np.linalg.eigh(np.cov((pts - centre).T))
    axes, _ = frame_axes_patient(vecs)
    return Pose(axes, centre)


MIN_TARGET_POINTS = 10
"""A point target needs this many points (with fewer, the pose and shape rest on the prior)."""


def _enough_points(points: np.ndarray, path, landmarks) -> None:
    if len(points) < MIN_TARGET_POINTS and landmarks is None:
        raise InputError(f"{path}: {len(points)} point(s); a fit needs at least {MIN_TARGET_POINTS} to fix the pose "
                         "and the shape (or give --landmarks)")


def load_target(t: FitTarget, model, *, spacing_mm: float | None = None,
                partial: bool = False) -> tuple[Target, Pose | None]:
    """The fitting target of some files (world mm) and a start pose from its object frame.

    A label map or closed mesh gets the start pose of the training (its object frame,
    paper 2, the model's frame method); a whole point cloud the frame of its points; a
    partial target (``partial``: a scan or part of a shape), a mesh whose size is far from
    the model's (another unit) and landmarks alone none (the pose search finds it).

    Raises
    ------
    InputError
        An open mesh without ``partial`` (the message says to give ``--partial``); a target
        of fewer than ``MIN_TARGET_POINTS`` points (too few to fix a pose and a shape).
    """
    params = model.params or {}
    method = params.get("frame_method", "auto")
    spacing = spacing_mm or float(params.get("spacing_mm", 1.0))
    landmarks = read_landmarks(t.landmarks) if t.landmarks is not None else None
    given = [x for x in (t.volume, t.mesh, t.points) if x is not None]
    if len(given) > 1:
        raise InputError(f"{t.name}: give one of a volume, a mesh or points (and optionally landmarks)")
    if t.volume is not None:
        label_map = read_label_map(t.volume)  # read once: the object, and the labels merged without --label
        vol = select_label(label_map, t.label)
        verts, faces = display_surface(vol)
        frame = instance_frame(vol, method)
        target = Target.from_mesh(verts, faces, source=str(t.volume), landmarks=landmarks)
        if t.label is None:
            labels = np.unique(np.asarray(label_map.labels))
            target.merged_labels = tuple(int(x) for x in labels[labels != 0])
        return target, Pose(frame.axes_world, frame.origin_world)
    if t.mesh is not None:
        given = (params.get("template") or {}).get("space", "auto")  # the study's convention for unstated files
        verts, faces = read_mesh(t.mesh, space=None if given in (None, "auto") else given)
        _enough_points(verts, t.mesh, landmarks)
        target = Target.from_mesh(verts, faces, source=str(t.mesh), landmarks=landmarks)
        if partial:  # a partial scan need not be closed; its pose comes from the search
            return target, None
        if not size_in_unit_range(verts, model):  # metres or cm: the search fits it, the verdict says so
            return target, None
        try:
            frame = mesh_frame(verts, faces, frame_method=method, spacing_mm=spacing, source=str(t.mesh))
        except InputError as err:
            raise InputError(f"{err}; if it is a partial scan, fit it with --partial") from None
        return target, Pose(frame.axes_world, frame.origin_world)
    if t.points is not None:
        pts = _read_points(t.points)
        _enough_points(pts, t.points, landmarks)
        # a partial point set's own axes are not the shape's: its pose comes from the search
        return (Target.from_points(pts, source=str(t.points), landmarks=landmarks),
                None if partial else pose_of_points(pts))
    if landmarks is not None:
        return Target.from_landmarks(landmarks, source=str(t.landmarks)), None
    raise InputError(f"{t.name}: nothing to fit to: give --volume, --mesh, --points and/or --landmarks")


def fit_picture(result: FitResult, faces: np.ndarray, target: Target, path, *, title: str = "",
                outlier: bool | None = None) -> Path:
    """``fit.png``: the fit over the target in two views along the fitted shape's principal axes
    (model frame), coloured by the posterior SD with its colour bar, with scale bars, the
    Mahalanobis distance, its p-value (two significant figures, or "< 0.001"), the distances
    and an outlier flag. ``outlier``: the caller's decision (default: the 99 % limit of
    :func:`~ssm_addon.fitting.fit.outlier_limit`)."""
    pts = result.pose.inverse(result.points)  # model frame: a stable view
    tgt = result.pose.inverse(target.samples[:: max(1, len(target.samples) // 4000)]) if target.has_surface else None
    if outlier is None:
        outlier = is_outlier(result.mahalanobis, result.n_modes)
    summary = (f"Mahalanobis distance {result.mahalanobis:.2f} on {result.n_modes} modes "
               f"({p_value_text(result.p_value)}){':  OUTLIER' if outlier else ''};   mean distance "
               f"{result.mean_distance_mm:.2f} mm, largest {result.max_distance_mm:.2f} mm")
    return fit_figure(pts, faces, result.posterior_sd_mm, tgt, path,
                      title=f"{title or target.source or 'target'}: fit of the model", summary=summary, flagged=outlier)


def fit_to_folder(model, t: FitTarget, out_dir, *, params: FitParams | None = None, partial: bool = False,
                  free: bool = False, outlier_probability: float = 0.99, model_path: str = "",
                  floor: bool = False, progress: ProgressFn = None, cancelled: CancelledFn = None) -> dict:
    """Fit ``model`` to one target and write its files into ``out_dir``; returns ``fit.json``'s content.
    ``floor``: also the best the model can do (:func:`~ssm_addon.fitting.fit.fit_floor`), as ``floor_mm``
    beside the fit's distance."""
    params = FitParams() if params is None else params
    target, start = load_target(t, model, partial=partial)
    if partial and t.landmarks is not None:
        start = None  # from the landmarks
    result, search = fit_any_pose(model, target, params=params, frame_pose=start, partial=partial, size_check=True,
                                  progress=progress, cancelled=cancelled)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    faces = np.asarray(model.faces)
    write_ply(out_dir / "fitted.ply", result.points, faces, vertex_scalars={"posterior_sd_mm": result.posterior_sd_mm},
              space="RAS")
    write_npz(out_dir / "fit.npz", {"posterior_mean": result.points, "posterior_sd_mm": result.posterior_sd_mm,
                                    "coefficients": result.coefficients})
    verdict = judge_fit(result, target, model, params=params, partial=partial, probability=outlier_probability)
    doc = result.to_dict()
    doc.update({"name": t.name, "model": model_path, "partial": bool(partial),
                "target": {k: (str(v) if v is not None else None) for k, v in
                           (("volume", t.volume), ("label", t.label), ("mesh", t.mesh), ("points", t.points),
                            ("landmarks", t.landmarks))},
                **verdict.to_dict(),
                "files": {"fitted": "fitted.ply", "npz": "fit.npz", "picture": "fit.png"},
                "params": to_table(params), "pose_search": search})
    doc["landmarks_used"] = sorted(result.landmark_residuals_mm)
    if floor and target.has_surface:
        report(progress, 0.95, "the model's floor: closest points within its span, around the fit and from other "
                               "rotations")
        yardstick = fit_floor(model, target, result.pose, partial=partial, scale=params.scale, cancelled=cancelled)
        doc.update({"floor_mm": yardstick["floor_mm"], "floor": yardstick,
                    "above_floor_mm": float(result.mean_distance_mm - yardstick["floor_mm"])})
    if free and target.locator is not None:
        doc["files"]["free"] = "fitted_free.ply"
        doc["free"] = _free_fit(result, faces, t, model, out_dir / "fitted_free.ply")
    fit_picture(result, faces, target, out_dir / "fit.png", title=t.name, outlier=doc["outlier"])
    (out_dir / "fit.json").write_text(json.dumps(doc, indent=1), encoding="utf-8")
    report(progress, 1.0, f"fitted {t.name}: Mahalanobis {result.mahalanobis:.2f}, mean distance "
                           f"{result.mean_distance_mm:.2f} mm")
    return doc


def _free_fit(result, faces, t, model, path) -> dict:
    """The model fit relaxed freely onto the target's surface (the coating's projection and
    relaxation, paper 4.2), in the target's own object frame."""
    spacing = float((model.params or {}).get("spacing_mm", 1.0))
    spec = InstanceSpec(name=t.name, volume_path=t.volume, label=t.label, mesh_path=t.mesh)
    ov = import_instance(spec, spacing_mm=spacing, frame_method=(model.params or {}).get("frame_method", "auto"))
    start = ov.frame.to_object(result.points)
    coated = coat_from_start(Mesh(start, faces), ov, start=start, start_label=CoatingStart.MODEL_FIT, name=t.name)
    write_ply(path, ov.frame.to_world(coated.points_object), faces, space="RAS")
    return {"mean_distance_mm": coated.fit.mean_distance_mm, "max_distance_mm": coated.fit.max_distance_mm,
            "folded": coated.fit.folded_after}


def _fit_job(args):
    model_path, t, out_dir, params, partial, free, p = args
    model = load_model(model_path)
    return fit_to_folder(model, t, out_dir, params=params, partial=partial, free=free, outlier_probability=p,
                         model_path=str(model_path))


def fit_batch(model_path, targets: list[FitTarget], out_dir, *, params: FitParams | None = None,
              partial: bool = False, free: bool = False, outlier_probability: float = 0.99, jobs: int = 1,
              progress: ProgressFn = None, scheduler: str = "processes") -> list[dict]:
    """Fit a model to many targets (one folder each) and write ``coefficients.csv``.

    Each target is fitted by one call on ``scheduler`` (:class:`~ssm_addon.base.compute.Executor`:
    ``jobs`` local processes, a Dask LocalCluster or a Dask scheduler address); the worker
    reads the model and the target from their paths and writes the target's folder (on a
    remote cluster ``out_dir`` must be on a shared file system).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = [t.name for t in targets]

    folders = file_names(names)
    args = [(str(model_path), t, out_dir / folders[t.name], params, partial, free, outlier_probability)
            for t in targets]
    with Executor(scheduler, jobs, tasks=len(targets)) as executor:
        docs = executor.map(_fit_job, args, progress=progress, labels=names, verb="fitted")
    k = max((len(d["coefficients"]) for d in docs), default=0)
    with open(out_dir / "coefficients.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["name", *[f"z{i + 1}" for i in range(k)], "mahalanobis", "p_value", "outlier",
                    "mean_distance_mm", "max_distance_mm"])
        for d in docs:
            z = d["coefficients"] + [""] * (k - len(d["coefficients"]))
            w.writerow([d["name"], *[f"{v:.6g}" if v != "" else "" for v in z], f"{d['mahalanobis']:.6g}",
                        f"{d['p_value']:.6g}", int(d["outlier"]), f"{d['mean_distance_mm']:.6g}",
                        f"{d['max_distance_mm']:.6g}"])
    return docs


def targets_from_glob(pattern: str, label: int | None = None) -> list[FitTarget]:
    """One target per file of a glob (label maps or meshes by extension)."""
    files = sorted(glob.glob(pattern))
    if not files:
        raise InputError(f"{pattern}: no file matches")
    out = []
    for f in files:
        p = Path(f)
        out.append(FitTarget(name=file_stem(p), mesh=p) if is_mesh_file(p) else
                   FitTarget(name=file_stem(p), volume=p, label=label))
    return out


def fit_structures_to_folder(model, targets: dict, out_dir, *, params: FitParams | None = None,
                             outlier_probability: float = 0.99, model_path: str = "", progress: ProgressFn = None,
                             cancelled: CancelledFn = None) -> dict:
    """Fit a joint model (several structures) to the structures given and predict the others.

    ``targets``: structure name -> :class:`FitTarget` (a closed mesh, or a label map with its
    label), world mm. The model is matched to the given structures' surfaces alone (its points
    of those structures, both ways; the pose search of :func:`~ssm_addon.fitting.fit.fit_any_pose`),
    so every other structure comes out as the model's conditional prediction, its posterior
    SD large where nothing constrains it. Writes ``fitted_<structure>.ply`` for every structure
    (world mm, the template's connectivity, the posterior SD as a vertex property), ``fit.npz``
    (``posterior_mean``, ``posterior_sd_mm`` of every point, ``coefficients``,
    ``structure_names``, ``structure_offsets``) and ``fit.json``; returns ``fit.json``'s content.
    """
    params = FitParams() if params is None else params
    names = list(model.structure_names)
    if not names:
        raise InputError(f"{model_path or 'model'}: not a joint model (no structures); give --mesh FILE")
    unknown = [n for n in targets if n not in names]
    if unknown:
        raise InputError(f"{model_path or 'model'}: no structure {', '.join(map(repr, unknown))} (structures: "
                         f"{', '.join(names)})")
    verts, faces, count = [], [], 0
    unit_warnings = []
    for name, t in targets.items():
        target, _start = load_target(t, model, partial=True)
        if target.locator is None:
            raise InputError(f"{t.name}: a structure to fit is a closed mesh or a label map (surface), not points")
        v, f = np.asarray(target.locator.vertices, float), np.asarray(target.locator.faces)
        size_m = float(np.ptp(np.asarray(model.mean, float)[model.structure_slice(name)], axis=0).max())
        ratio = float(np.ptp(v, axis=0).max()) / size_m if size_m > 0 else 1.0
        if not UNIT_RATIO[0] < ratio < UNIT_RATIO[1]:  # as a single fit says it
            unit_warnings.append(f"{name}: the target is {ratio:.3g} times the structure's size ({ratio * size_m:.3g} "
                                 f"against {size_m:.3g} mm): another unit (m, cm)?")
        verts.append(v)
        faces.append(f + count)
        count += len(v)
    combined = Target.from_mesh(np.concatenate(verts), np.concatenate(faces), source=" + ".join(targets))
    points = model.structure_points(list(targets))
    result, search = fit_any_pose(model, combined, params=params, points=points, progress=progress,
                                  cancelled=cancelled)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    per = {}
    for name in names:
        sl = model.structure_slice(name)
        write_ply(out_dir / f"fitted_{name}.ply", result.points[sl], model.structure_faces(name),
                  vertex_scalars={"posterior_sd_mm": result.posterior_sd_mm[sl]}, space="RAS")
        sd = result.posterior_sd_mm[sl]
        per[name] = {"given": name in targets, "file": f"fitted_{name}.ply", "posterior_sd_mm": {
            "mean": float(sd.mean()), "max": float(sd.max())}}
    write_npz(out_dir / "fit.npz", {"posterior_mean": result.points, "posterior_sd_mm": result.posterior_sd_mm,
                                    "coefficients": result.coefficients,
                                    "structure_names": np.asarray(names), "structure_offsets":
                                    np.asarray(model.structure_offsets, np.int64)})
    verdict = judge_fit(result, combined, model, params=params, partial=True, probability=outlier_probability)
    doc = result.to_dict()
    doc.update({"model": model_path, "given": {n: {k: (str(v) if v is not None else None) for k, v in
                                                   (("volume", t.volume), ("label", t.label), ("mesh", t.mesh))}
                                               for n, t in targets.items()},
                "structures": per, **{k: v for k, v in verdict.to_dict().items() if k != "coverage"},
                "files": {"npz": "fit.npz", **{n: d["file"] for n, d in per.items()}},
                "params": to_table(params), "pose_search": search})
    doc["warnings"] = [w for k, w in verdict.warnings.items() if k != "coverage"] + unit_warnings
    (out_dir / "fit.json").write_text(json.dumps(doc, indent=1), encoding="utf-8")
    report(progress, 1.0, f"fitted {' + '.join(targets)}; predicted {', '.join(n for n in names if n not in targets)}")
    return doc
