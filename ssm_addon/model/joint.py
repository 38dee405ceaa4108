"""The geometry of a joint model (several structures in one model): each structure's exact
sub-model, the pose of a structure relative to a reference structure (a rotation vector by the
log map, a translation, a log scale), the split of the training shapes into shape and relative
pose with one PCA over both, and the overlap of the structures in the model's shapes.

All in mm; rotation vectors in radians (axis × angle). The joint model's points are the
structures' concatenation (``ShapeModel.structure_names`` / ``structure_offsets``).

References
----------
Bossa MN, Olmos S. Multi-object statistical pose+shape models. ISBI 2007.
Rasoulian A, Rohling R, Abolmaesumi P. Lumbar spine segmentation using a statistical
multi-vertebrae anatomical shape+pose model. IEEE TMI 32(10), 2013.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

from ..base.errors import check_cancelled
from ..base.progress import CancelledFn
from ..meshutil import MeshLocator, connected_components, face_normals
from .pca import ShapeModel, own_side_instances, procrustes_fit
from .quality import Finding

__all__ = ["INPUT_OVERLAP_MM", "INPUT_OVERLAP_SHARE", "collision_findings", "collisions", "joined_parts", "relative_pose", "relative_poses", "shape_and_pose",
           "structure_model"]

#: A part of a joined reference needs at least this many points to count as a structure.
MIN_PART_POINTS = 4


def joined_parts(model: ShapeModel) -> ShapeModel | None:
    """A model of one structure whose reference is several disconnected parts, each a contiguous
    range of points (a joined model, as users of tools without multi-object models write
    several structures into one statismo file), as a joint model of structures ``"part 1"``,
    ``"part 2"`` … in point order; None when the reference is one part, when a part's points
    are not one contiguous range, or when a part has fewer than :data:`MIN_PART_POINTS` points."""
    if model.structure_names or not len(model.faces):
        return None
    n, labels = connected_components(np.asarray(model.faces), model.n_points)
    if n < 2:
        return None
    starts = np.flatnonzero(np.r_[True, labels[1:] != labels[:-1]])
    if len(starts) != n:  # some part's points are not one contiguous range
        return None
    offsets = np.r_[starts, model.n_points].astype(np.int64)
    if np.diff(offsets).min() < MIN_PART_POINTS:
        return None
    return dataclasses.replace(model, structure_names=tuple(f"part {k + 1}" for k in range(n)),
                               structure_offsets=offsets)


def structure_model(model: ShapeModel, name: str) -> ShapeModel:
    """Structure ``name``'s rows of a joint model, exactly: the mean's rows and the marginal
    covariance of its points (Q_s Λ Q_sᵀ) as its own orthonormal modes and variances; the
    instances' rows; the structure's faces."""
    sl = model.structure_slice(name)
    npts = sl.stop - sl.start
    scaled = (np.asarray(model.modes[:, sl], float).reshape(model.n_modes, -1)
              * np.sqrt(np.asarray(model.variances, float))[:, None])  # (K, 3 n_s): rows of Q_s √Λ, transposed
    u, sv, vt = np.linalg.svd(scaled, full_matrices=False)
    keep = sv > 1e-9 * max(float(sv.max(initial=0.0)), 1e-300)
    return ShapeModel(mean=np.asarray(model.mean[sl], float), faces=model.structure_faces(name),
                      modes=vt[keep].reshape(-1, npts, 3), variances=sv[keep] ** 2,
                      instance_names=np.asarray(model.instance_names),
                      instance_points=np.asarray(model.instance_points[:, sl], float),
                      instance_points_world=np.asarray(model.instance_points_world[:, sl], float),
                      params={**model.params, "structure": name})


# ------------------------------------------------------------------------ shape and pose
def relative_pose(points: np.ndarray, reference: np.ndarray, mean_points: np.ndarray,
                  mean_reference: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """One structure's pose relative to the reference structure, in the reference's frame.

    Each structure is put onto its mean shape by a similarity (Procrustes); the pose of the
    structure relative to the reference is R = R_refᵀ R_s (a rotation vector, the log map,
    radians), t the structure's centroid in the reference's aligned frame minus the mean's
    (mm), and the log of the scale ratio. Returns (rotation vector (3,), translation (3,), log scale).
    """
    return _pose_from_fits(procrustes_fit(points[None], mean_points, True),
                           procrustes_fit(reference[None], mean_reference, True), points, mean_points)


def _pose_from_fits(fit, fit_ref, points: np.ndarray, mean_points: np.ndarray):
    """:func:`relative_pose` from the structure's and the reference's Procrustes fits onto their means."""
    s_s, r_s, _t_s = fit
    s_r, r_r, t_r = fit_ref
    rel = r_r[0] @ r_s[0].T  # the structure's pose (mean -> it) as the reference's alignment sees it
    in_ref = s_r[0] * points.mean(axis=0) @ r_r[0].T + t_r[0]  # the structure's centroid where the reference sits
    return _log_rotation(rel), in_ref - mean_points.mean(axis=0), float(np.log(s_s[0] / s_r[0]))


def _log_rotation(rot: np.ndarray) -> np.ndarray:
    """The rotation vector (axis × angle, radians) of a rotation matrix (the log map)."""
    angle = float(np.arccos(np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0)))
    if angle < 1e-12:
        return np.zeros(3)
    w = np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    if np.pi - angle < 1e-6:  # a half turn: the axis from the symmetric part
        axis = np.sqrt(np.maximum((np.diag(rot) + 1.0) / 2.0, 0.0))
        axis *= np.where(np.sign(w) == 0, 1.0, np.sign(w))
        return axis / max(np.linalg.norm(axis), 1e-300) * angle
    return w / (2.0 * np.sin(angle)) * angle


def _decompose(model: ShapeModel, shapes: np.ndarray, reference: str) -> tuple[np.ndarray, dict]:
    """Per shape: each structure's aligned shape (mm) and its pose relative to the reference."""
    names = list(model.structure_names)
    slices = {n: model.structure_slice(n) for n in names}
    mean = np.asarray(model.mean, float)
    rows, poses = [], {n: [] for n in names if n != reference}
    for shape in shapes:
        fits = {n: procrustes_fit(shape[sl][None], mean[sl], True) for n, sl in slices.items()}  # each once
        rows.append(np.concatenate([(f[0][0] * shape[slices[n]] @ f[1][0].T + f[2][0]).ravel()
                                    for n, f in fits.items()]))
        for n in poses:
            poses[n].append(_pose_from_fits(fits[n], fits[reference], shape[slices[n]], mean[slices[n]]))
    return np.stack(rows), poses


def relative_poses(model: ShapeModel, reference: str | None = None, shapes: np.ndarray | None = None) -> dict:
    """Every training shape's (or ``shapes``') pose of each structure relative to ``reference``
    (default: the joint model's reference, else its first structure): ``{structure: (n, 7)
    array}`` of the rotation vector (radians, the reference's frame), the translation (mm) and
    the log scale (:func:`relative_pose`). Empty for a model of one structure."""
    if len(model.structure_names) < 2:
        return {}
    reference = reference or model.params.get("reference") or model.structure_names[0]
    shapes = np.asarray(model.instance_points if shapes is None else shapes, float)
    _aligned, poses = _decompose(model, shapes, reference)
    return {n: np.array([np.concatenate([rv, t, [ls]]) for rv, t, ls in p]).reshape(-1, 7) for n, p in poses.items()}


def shape_and_pose(model: ShapeModel, *, reference: str, samples: int = 300, seed: int = 0) -> dict:
    """Each structure's shape (in its own frame) and its pose relative to the reference structure,
    and one PCA over both.

    Pose is the rotation vector (log map) times the structure's RMS radius, the translation
    and the log scale times the RMS radius, each times √(number of the structure's points):
    a pose that moves every point of a structure by d mm then weighs N d², as the same
    displacement does among the shape coordinates, so shape and pose are measured alike. Returns, per mode of that PCA, the share of its variance that is
    relative pose; per structure pair (reference, other) the spread of the relative pose in
    the training subjects and in ``samples`` shapes the joint model draws (SD of the turn,
    degrees, and of the shift, mm).
    """
    if len(model.structure_names) < 2 or not model.n_instances:
        return {}
    names = [n for n in model.structure_names if n != reference]
    mean = np.asarray(model.mean, float)
    shapes, poses = _decompose(model, np.asarray(model.instance_points, float), reference)
    radius = {n: float(np.sqrt(((mean[model.structure_slice(n)] - mean[model.structure_slice(n)].mean(0)) ** 2)
                               .sum(1).mean())) for n in names}
    count = {n: model.structure_slice(n).stop - model.structure_slice(n).start for n in names}
    pose_rows = np.stack([np.concatenate([np.sqrt(count[n]) * np.concatenate(
        [poses[n][i][0] * radius[n], poses[n][i][1], [poses[n][i][2] * radius[n]]]) for n in names])
        for i in range(len(shapes))])
    data = np.concatenate([shapes, pose_rows], axis=1)
    centred = data - data.mean(axis=0)
    _u, sv, vt = np.linalg.svd(centred, full_matrices=False)
    var = sv ** 2 / max(len(data), 1)
    keep = var > 1e-9 * max(float(var.max(initial=0.0)), 1e-300)
    n_shape = shapes.shape[1]
    pose_share = (vt[keep][:, n_shape:] ** 2).sum(axis=1)
    rng = np.random.default_rng(seed)
    drawn = model.sample(samples, seed=int(rng.integers(2**31)), sd_limit=3.0) if model.n_modes else np.zeros((0,))
    _shapes_m, poses_m = _decompose(model, drawn, reference) if len(drawn) else (None, {n: [] for n in names})

    def spread(items):
        if not items:
            return {"turn_sd_deg": float("nan"), "shift_sd_mm": float("nan")}
        rv = np.array([p[0] for p in items])
        tr = np.array([p[1] for p in items])
        return {"turn_sd_deg": float(np.degrees(np.sqrt(((rv - rv.mean(0)) ** 2).sum(1).mean()))),
                "shift_sd_mm": float(np.sqrt(((tr - tr.mean(0)) ** 2).sum(1).mean()))}

    return {"reference": reference, "weighting": "rotation vector and log scale times the structure's RMS radius, "
                                                 "translation in mm; each times the square root of its point count",
            "modes_pose_share": [float(x) for x in pose_share], "variances_mm2": [float(x) for x in var[keep]],
            "variances_of": "this decomposition's own PCA (each structure's shape similarity-aligned in its own frame, "
                            "beside the weighted relative poses), not the joint model's modes: their λ are of the "
                            "structures' coordinates together in the reference structure's frame",
            "total_variance_mm2": float(var[keep].sum()),
            "pairs": {f"{reference}-{n}": {"data": spread(poses[n]), "model": spread(poses_m[n])} for n in names}}


# ----------------------------------------------------------------------------- collisions
def _penetration(points: np.ndarray, other: np.ndarray, other_faces: np.ndarray) -> float:
    """How deep points reach into the closed surface ``other`` (mm; 0 when none is inside): a point
    is inside when it lies behind the outward normal of its closest triangle. Only the points
    within ``other``'s bounding box can be inside it, so only they are queried."""
    lo, hi = other.min(axis=0), other.max(axis=0)
    points = points[((points >= lo) & (points <= hi)).all(axis=1)]
    if not len(points):
        return 0.0
    closest, dist, tri, _b = MeshLocator(other, other_faces).query(points, k=12)
    normals = face_normals(other, other_faces)[tri]
    inside = np.einsum("ij,ij->i", points - closest, normals) < 0.0
    return float(dist[inside].max()) if inside.any() else 0.0


def collisions(model: ShapeModel, *, samples: int = 200, depth_mm: float = 0.5, seed: int = 0,
               cancelled: CancelledFn = None) -> dict:
    """Per structure pair: how deep one reaches into the other (mm), in the training subjects (as they
    are: ``instance_points_world``) and in shapes the model draws (±3 SD along each mode, and ``samples`` random ones within 3 SD), and the
    share of each with a penetration beyond ``depth_mm``."""
    names = list(model.structure_names)
    if len(names) < 2:
        return {}
    parts = {n: (model.structure_slice(n), model.structure_faces(n)) for n in names}
    sd = model.standard_deviations
    extremes = [model.mean + sign * 3.0 * sd[k] * model.modes[k] for k in range(model.n_modes) for sign in (-1.0, 1.0)]
    drawn = list(model.sample(samples, seed=seed, sd_limit=3.0)) if samples and model.n_modes else []
    # the subjects as they are (their world coordinates: every structure where the scanner saw it); a
    # subject mirrored into the model's side is its own side's there, its triangles facing inwards
    own = set(own_side_instances(model).tolist())
    world = np.asarray(model.instance_points_world, float)
    sets = {"data": [(shape, i not in own) for i, shape in enumerate(world)],
            "model": [(shape, False) for shape in extremes + drawn]}
    out = {}
    for a, b in itertools.combinations(names, 2):
        check_cancelled(cancelled)
        figures = {}
        for label, shapes in sets.items():
            depths = []
            for shape, inward in shapes:
                (sa, fa), (sb, fb) = parts[a], parts[b]
                if inward:
                    fa, fb = fa[:, ::-1], fb[:, ::-1]
                depths.append(max(_penetration(shape[sa], shape[sb], fb), _penetration(shape[sb], shape[sa], fa)))
            d = np.asarray(depths)
            figures[label] = {"shapes": len(d), "max_mm": float(d.max(initial=0.0)),
                              "mean_mm": float(d.mean()) if len(d) else 0.0,
                              "colliding_share": float((d > depth_mm).mean()) if len(d) else 0.0}
        out[f"{a}-{b}"] = figures
    return out


INPUT_OVERLAP_SHARE = 0.5
INPUT_OVERLAP_MM = 5.0
"""Structures of at least INPUT_OVERLAP_SHARE of the subjects that overlap deeper than INPUT_OVERLAP_MM
(mm): the inputs, not the model, put one inside the other."""


def collision_findings(figures: dict, excess: float) -> list[Finding]:
    """A structure pair whose model shapes collide in ``excess`` more of the draws than the training
    subjects do: the model lets the structures overlap where the data never do (relative pose left
    out of the model, or too few subjects); and a pair whose subjects' own structures overlap deeply in
    most subjects: the inputs put one inside the other."""
    out = []
    for pair, f in figures.items():
        data = f["data"]
        if data["colliding_share"] >= INPUT_OVERLAP_SHARE and data["max_mm"] > INPUT_OVERLAP_MM:
            out.append(Finding("", "collision", f"{pair}: the subjects' own structures overlap in "
                               f"{100 * data['colliding_share']:.0f} % of them, up to {data['max_mm']:.1f} mm deep: the "
                               "inputs put one inside the other (a structure from another coordinate system, or the "
                               "wrong file?)", data["colliding_share"], INPUT_OVERLAP_SHARE))
        more = f["model"]["colliding_share"] - f["data"]["colliding_share"]
        if more > excess:
            out.append(Finding("", "collision", f"{pair}: {100 * f['model']['colliding_share']:.0f} % of the model's "
                               f"shapes overlap by more than the limit (up to {f['model']['max_mm']:.1f} mm), against "
                               f"{100 * f['data']['colliding_share']:.0f} % of the subjects: the structures' relative "
                               "pose is not held by the model", more, excess))
    return out
