"""Segmenting a grey-value image with a shape model: an active shape model search.

From a start pose (a point inside the structure, landmarks clicked on the image, or a
rough mask), every level of the search (coarse to fine: the image blurred by 2, 1 and
0.5 mm, the search range along the normals shrinking with it) repeats

1. each model point looks along its normal for the position the boundary evidence
   prefers (learned profiles, or the image gradient: :mod:`.appearance`);
2. the pose (rigid) and the mode weights b that bring the shape closest to those
   positions under the model's prior: the posterior mean of
   n_iᵀ(T⁻¹y_i − p̄_i) = n_iᵀ Q_i b + ε, ε ~ N(0, σ²), b ~ N(0, Λ/η) (paper eq. 7; the
   point-to-plane step of :func:`ssm_addon.fitting.fit_model`),

until the points stop moving (Cootes et al. 1995, section 5; multi-resolution after
Cootes, Taylor & Lanitis 1994). The coarse level starts from several turns of the
model's typical pose and keeps the one whose boundary evidence fits best. Last, each
point may leave the model's span along its normal by as much as the model's own error at
that point (its leave-one-out residual) and the evidence call for; the offsets are
smoothed over the mesh so the surface stays a surface.

Frames: the model in its model frame (mm); the image, the start point, the result in
the image's world frame (RAS mm); ``pose`` maps model -> world.

References
----------
Cootes TF, Taylor CJ, Cooper DH, Graham J. Active shape models — their training and
application. Computer Vision and Image Understanding 61(1):38–59, 1995.
Cootes TF, Taylor CJ, Lanitis A. Active shape models: evaluation of a multi-resolution
method for improving image search. BMVC 1994, 327–336.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.special import chdtrc

from ..base.errors import InputError, check_cancelled
from ..base.params import SegmentParams, to_table
from ..base.progress import CancelledFn, ProgressFn, report
from ..fitting.fit import Pose, model_error_variance, outlier_limit, spd_solve, weighted_gram, weighted_pose
from ..meshutil import edges, vertex_normals
from ..model.pca import own_side_instances
from .appearance import LEVEL_SIGMAS_MM, Appearance, boundary_grey_values, normalised_derivative
from .image import GreyImage

__all__ = ["BONE_HU", "BONE_REACH_MM", "CT_AIR_HU", "MIN_SCANS", "SegmentResult", "bone_near", "landmark_pose", "segment_image", "start_pose", "typical_rotation",
           "volume_centroid"]


@dataclass(frozen=True, eq=False)
class SegmentResult:
    """A model's segmentation of an image.

    Attributes
    ----------
    points : (N, 3) mm
        The segmented surface (world, RAS), the model's triangles ``faces``.
    model_points : (N, 3) mm
        The shape within the model's span (before the deviation step), world.
    pose : Pose
        Model -> world.
    coefficients : (K,) SD
        b_k/√λ_k.
    posterior_sd_mm : (N,) mm
        Per point √(trace of its posterior covariance + the model's own error + the boundary's
        spread there), where the spread is the expected squared offset of the boundary from the
        point under its own profile (:func:`boundary_spread`), smoothed over its neighbours: where
        the true surface lies around the point (predictive).
    deviation_mm : (N,) mm
        How far each point left the model's span along its normal.
    evidence : str
        "learned" or "gradient".
    boundary : dict
        How well the boundary evidence fits at the result.
    findings : list of (str, str)
        (kind, message): ``outlier``, ``not_converged``, ``weak_evidence``, ``intensities``, ``orientation``.
    structures : tuple of (name, first point, end point)
        A joint model's structures and their point ranges (empty for one structure).
    parameters : dict
        The search's parameters as `ssm segment`'s options and Blender's sidebar give them
        (:class:`~ssm_addon.base.params.SegmentParams`, by key; recorded in ``segment.json``).
    """

    points: np.ndarray
    faces: np.ndarray
    model_points: np.ndarray
    pose: Pose
    coefficients: np.ndarray
    posterior_sd_mm: np.ndarray
    deviation_mm: np.ndarray
    mahalanobis: float
    p_value: float
    evidence: str
    boundary: dict
    levels: list
    start: dict
    iterations: int
    converged: bool
    findings: list = field(default_factory=list)
    seconds: float = 0.0
    structures: tuple = ()
    parameters: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"pose": self.pose.to_dict(), "coefficients": [float(x) for x in self.coefficients],
                "mahalanobis": float(self.mahalanobis), "p_value": float(self.p_value),
                "posterior_sd_mm": {"mean": float(self.posterior_sd_mm.mean()),
                                    "max": float(self.posterior_sd_mm.max()),
                                    "per_point": [round(float(x), 4) for x in self.posterior_sd_mm]},
                "deviation_mm": {"mean": float(np.abs(self.deviation_mm).mean()),
                                 "max": float(np.abs(self.deviation_mm).max())},
                "evidence": self.evidence, "boundary": self.boundary, "levels": self.levels, "start": self.start,
                "iterations": int(self.iterations), "converged": bool(self.converged),
                "verdict": {"outlier": any(k == "outlier" for k, _ in self.findings),
                            "not_converged": any(k == "not_converged" for k, _ in self.findings),
                            "boundary_evidence_weak": any(k == "weak_evidence" for k, _ in self.findings),
                            "findings": [{"kind": k, "message": m} for k, m in self.findings]},
                "seconds": float(self.seconds), "parameters": dict(self.parameters),
                **({"structures": [{"name": n, "points": [int(a), int(b)]} for n, a, b in self.structures]}
                   if self.structures else {})}


def volume_centroid(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(3,) mm: the centroid of the solid a closed mesh bounds (signed tetrahedra from the origin);
    the points' mean for a mesh without volume."""
    p = np.asarray(points, float)
    f = np.asarray(faces)
    if len(f) == 0:
        return p.mean(axis=0)
    o = p.mean(axis=0)
    a, b, c = p[f[:, 0]] - o, p[f[:, 1]] - o, p[f[:, 2]] - o
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    if abs(vol.sum()) < 1e-9:
        return o
    return o + ((a + b + c) / 4.0 * vol[:, None]).sum(axis=0) / vol.sum()


def typical_rotation(model) -> np.ndarray:
    """(3, 3) the rotation that takes the model frame to its training instances' world frames
    on average (the rotation part of the mean shape's Procrustes fit to the instances' mean
    world shape after each is centred); the identity for a model without world shapes."""
    world = np.asarray(getattr(model, "instance_points_world", np.zeros((0,))), float)
    if world.ndim != 3 or len(world) == 0:
        return np.eye(3)
    mean = np.asarray(model.mean, float)
    own = own_side_instances(model)  # a mirrored instance's world points are the other side's
    if len(getattr(model, "instance_names", ())) == len(world) and len(own):
        world = world[own]
    acc = np.zeros((3, 3))
    for w in world:
        acc += weighted_pose(mean, w, np.ones(len(mean)), False).rotation
    u, _s, vt = np.linalg.svd(acc)
    r = u @ vt
    if np.linalg.det(r) < 0:
        r = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    return r


def _axis_turn(axis: int, degrees: float) -> np.ndarray:
    t = math.radians(degrees)
    c, s = math.cos(t), math.sin(t)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    r = np.eye(3)
    r[i, i] = r[j, j] = c
    r[i, j], r[j, i] = -s, s
    return r


def start_pose(model, *, at=None, named: dict | None = None, rotation: np.ndarray | None = None) -> Pose:
    """Model -> world pose in the model's typical orientation (or ``rotation``) that puts the mean
    shape's solid centroid at ``at`` (world mm), or, for a joint model, each named structure's
    centroid at its point of ``named`` {structure: (3,) mm} (their mean when several; three or
    more also turn the model onto them)."""
    r = typical_rotation(model) if rotation is None else np.asarray(rotation, float)
    mean = np.asarray(model.mean, float)
    if named:
        src, dst = [], []
        for name, point in named.items():
            sl = model.structure_slice(name)
            src.append(volume_centroid(mean[sl], model.structure_faces(name)))
            dst.append(np.asarray(point, float).reshape(3))
        src, dst = np.asarray(src), np.asarray(dst)
        if len(src) >= 3:
            return weighted_pose(src, dst, np.ones(len(src)), False)
        return Pose(r, dst.mean(axis=0) - r @ src.mean(axis=0))
    c = volume_centroid(mean, model.faces)
    return Pose(r, np.asarray(at, float).reshape(3) - r @ c)


def landmark_pose(model, landmarks) -> Pose:
    """Model -> world pose from landmarks clicked on the image (at least 3 the model knows)."""
    located = model.landmark_locations
    common = [n for n in located.names if n in landmarks.names]
    if len(common) < 3:
        raise InputError(f"{landmarks.source or 'landmarks'}: {len(common)} of the model's landmarks "
                         f"({', '.join(located.names) or 'none'}) are given; at least 3 are needed for a start pose")
    idx = [list(located.names).index(n) for n in common]
    m = located.evaluate(model.mean, model.faces)[idx]
    return weighted_pose(m, landmarks.subset(common).points_world, np.ones(len(common)), False)


class _Evidence:
    """Scores candidate positions along the normals at one level: lower is better.

    Learned: the profile's Mahalanobis distance over the training's median at the true
    boundary. Gradient: minus the outward derivative over ``scale`` (a fixed value per image and
    level, so the costs of different poses compare)."""

    def __init__(self, image: GreyImage, appearance: Appearance | None, level: int, sigma_mm: float,
                 step_mm: float, scale: float = 1.0):
        self.image, self.appearance, self.level, self.sigma = image, appearance, level, sigma_mm
        self.step, self.scale = step_mm, scale

    def edge(self, x: np.ndarray, normals: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        """(N, C) the negated derivative along the outward normal at the offsets (grey value per mm)."""
        h = self.step
        grid = np.concatenate([[offsets[0] - h], offsets, [offsets[-1] + h]])
        prof = self.image.profiles(x, normals, grid, sigma_mm=self.sigma)
        return -(prof[:, 2:] - prof[:, :-2]) / (2 * h)

    def costs(self, x: np.ndarray, normals: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, C) cost of each candidate offset (mm, (C,)) and (N, C) its strength in [0, 1] (for weights)."""
        h = self.step
        if self.appearance is not None:
            app = self.appearance
            lvl = app.level_of(self.level)
            k = app.half_length
            stride = max(1, int(round(app.step_mm / h)))
            pad = k * stride + 1
            grid = np.concatenate([offsets[0] - h * np.arange(pad, 0, -1), offsets,
                                   offsets[-1] + h * np.arange(1, pad + 1)])
            # the derivative along the normal at every grid sample (central difference over ±h), at the
            # blur the appearance was learned at
            prof = self.image.profiles(x, normals, grid, sigma_mm=float(app.sigmas_mm[lvl]))  # (N, G)
            deriv = np.zeros_like(prof)
            deriv[:, 1:-1] = (prof[:, 2:] - prof[:, :-2]) / (2 * h)
            idx = np.arange(len(offsets))[:, None] + pad + stride * np.arange(-k, k + 1)[None, :]  # (C, 2k + 1)
            feats = normalised_derivative(deriv[:, idx])  # (N, C, 2k + 1)
            dist = app.distance(lvl, feats)
            typical = max(float(app.typical_distance[lvl]), 1e-6)
            cost, strength = dist / typical, np.exp(-0.5 * dist / (3.0 * typical))
            if app.profiled is not None:  # points without a profile model: no evidence, they follow the model
                cost[~app.profiled] = 0.0
                strength[~app.profiled] = 0.0
            return cost, strength
        return self._gradient(x, normals, offsets)

    def _gradient(self, x, normals, offsets):
        h = self.step
        e = self.edge(x, normals, offsets) / self.scale
        # the object's own boundary is the first strong edge met going outwards: an edge beyond
        # it of the same polarity is a neighbour's inner edge (the next vertebra's endplate)
        strong = e >= FIRST_EDGE * np.maximum(e.max(axis=1, keepdims=True), 1e-12)
        cols = np.arange(len(offsets))[None, :]
        first = np.argmax(strong, axis=1)[:, None]
        # the first strong edge runs while the samples stay strong; its peak is the boundary's place
        after = (cols > first) & ~strong
        end = np.where(after.any(axis=1), np.argmax(after, axis=1), len(offsets))[:, None]
        peak = np.argmax(np.where((cols >= first) & (cols < end), e, -np.inf), axis=1)[:, None]
        beyond = cols > peak + int(round(FIRST_EDGE_MM / h))
        cost = -e + np.where(beyond, np.maximum(e, 0.0), 0.0)
        return cost, np.clip(e, 0.0, 1.0)


#: The profile likelihood's temperature of :func:`boundary_spread`, as a share of the median point's
#: cost range along its profile (docs/history.md, "The posterior SD's boundary term").
SPREAD_TEMPERATURE = 0.02


def boundary_spread(cost: np.ndarray, offsets: np.ndarray, *, temperature: float = SPREAD_TEMPERATURE) -> np.ndarray:
    """Per point, the expected squared offset (mm²) of the boundary from it under its profile's likelihood.

    Each point's candidates along its normal at ``offsets`` (mm, 0 at the point) are weighed by
    p_j ∝ exp(-(c_j - min c) / T), with T = ``temperature`` × the median over points of the cost's
    range along the profile, and E[offset²] = Σ p_j offset_j²: large where the image puts the
    boundary elsewhere than the point (a residual) and where two edges compete or none stands
    out (an ambiguity). A boundary-likelihood view of the active shape model's profile search
    (Cootes et al. 1995).

    Parameters
    ----------
    cost : (N, C) the evidence's cost of each point's C candidates (lower is a better boundary).
    offsets : (C,) mm along the outward normal.

    Returns
    -------
    (N,) mm².

    >>> float(boundary_spread(np.array([[1.0, 0.0, 1.0]]), np.array([-1.0, 0.0, 1.0]))[0]) < 1e-3
    True
    """
    rel = cost - cost.min(axis=1, keepdims=True)
    t = max(float(temperature) * float(np.median(rel.max(axis=1))), 1e-12)
    p = np.exp(-rel / t)
    p /= p.sum(axis=1, keepdims=True)
    return p @ (np.asarray(offsets, float) ** 2)


def _refined_offsets(cost: np.ndarray, best: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """The chosen offsets moved to the vertex of the parabola through the cost at the best candidate
    and its two neighbours (at most half a step): suggestions between the candidates."""
    n, c = cost.shape
    rows = np.arange(n)
    inner = (best > 0) & (best < c - 1)
    lo, hi = np.clip(best - 1, 0, c - 1), np.clip(best + 1, 0, c - 1)
    c0, cm, cp = cost[rows, best], cost[rows, lo], cost[rows, hi]
    curv = cm - 2 * c0 + cp
    shift = np.where(inner & (curv > 1e-12), 0.5 * (cm - cp) / np.where(curv > 1e-12, curv, 1.0), 0.0)
    step = offsets[1] - offsets[0] if len(offsets) > 1 else 0.0
    return offsets[best] + np.clip(shift, -0.5, 0.5) * step


#: ``evidence = "auto"`` uses learned profiles only when they were learned from at least this many
#: scans: profiles of one scan segmented another scanner's CT worse than the gradient, both ways
#: (docs/history.md, "Segmentation across scanners").
MIN_SCANS = 2
#: An image whose lowest value is at most this is taken as CT in Hounsfield units (air is -1000 HU),
#: where bone is known by its value.
CT_AIR_HU = -500.0
#: Bone: at least this many HU (cortical and dense trabecular bone; soft tissue is 0-100 HU, fat -100).
BONE_HU = 200.0
#: A start point on a CT must have bone within this distance (mm): a vertebra's centre of mass lies in
#: its canal or its body, within a few mm of bone; air and soft tissue away from bone have none.
BONE_REACH_MM = 10.0


def bone_near(image: GreyImage, at) -> tuple[float, float] | None:
    """For a CT in Hounsfield units (:data:`CT_AIR_HU`): the highest value (HU) within
    :data:`BONE_REACH_MM` of the world point ``at`` (mm) and the value at it; None for an image not
    in HU (MR, a synthetic or normalised image), where values say nothing of bone.

    >>> ct = GreyImage(np.full((30, 30, 30), -1000.0, np.float32), np.eye(4))
    >>> ct.data[20:25, 20:25, 20:25] = 700.0
    >>> bone_near(ct, [5.0, 5.0, 5.0]), bone_near(ct, [15.0, 22.0, 22.0])
    ((-1000.0, -1000.0), (700.0, -1000.0))
    """
    data = image.data
    if float(np.min(data)) > CT_AIR_HU:
        return None
    centre = image.to_index(np.asarray(at, float).reshape(1, 3))[0]
    reach = np.ceil(BONE_REACH_MM / np.maximum(image.spacing_mm, 1e-6)).astype(int)
    lo = np.clip(np.floor(centre).astype(int) - reach, 0, np.asarray(data.shape) - 1)
    hi = np.clip(np.ceil(centre).astype(int) + reach + 1, 1, np.asarray(data.shape))
    box = data[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    ijk = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi)], indexing="ij"), axis=-1).reshape(-1, 3)
    near = np.linalg.norm(image.to_world(ijk) - np.asarray(at, float).reshape(3), axis=1) <= BONE_REACH_MM
    values = box.reshape(-1)[near] if near.any() else box.reshape(-1)
    here = data[tuple(np.clip(np.round(centre).astype(int), 0, np.asarray(data.shape) - 1))]
    return float(values.max()), float(here)


FIRST_EDGE = 0.5
"""Gradient evidence: an edge at least this share of the strongest along a normal counts as strong."""
FIRST_EDGE_MM = 1.0
"""Gradient evidence: edges more than this beyond the peak of the first strong one (outwards) lose their evidence."""
UPSIDE = "turned 180° about z"
COARSE_STEPS = 4
"""Steps of the coarse level from each start pose before they are ranked."""
FINISHED_STARTS = 2
COARSER_THAN_TRAINING = 1.5
"""Learned profiles are used when the image's coarsest voxel edge is at most this many times the
training images' (profiles of thicker slices look otherwise); coarser images use the gradient."""
FULL_STEPS = 3
"""Steps of a level that go the whole way to the suggested positions; later ones go half-way."""
CENTRAL_SHARE = 0.9
CENTRAL_BAND = 0.15
"""A level has converged when CENTRAL_SHARE of the points chose a position within CENTRAL_BAND of the
search range from where they are (Cootes, Taylor & Lanitis 1994 use the central half; a narrower band
keeps a level going while the shape still moves)."""
"""The best-ranked starts taken through every level."""


PLACEMENTS_KEPT = 3
"""The best-placed positions of the mean shape around the start that the pose search starts from."""


def _placements(base: Pose, mean, faces, evidence, grid, reach_mm: float, keep: int) -> list:
    """Shifts (world mm) of the mean shape from ``base`` on a grid within ``reach_mm`` (4 mm steps),
    ranked by how well the shape, unfitted, sits on the coarse level's boundary evidence (mean best
    cost within ±3 mm); the ``keep`` best, the unshifted start always among them."""
    if reach_mm <= 0:
        return [np.zeros(3)]
    ticks = np.arange(-reach_mm, reach_mm + 1e-9, 4.0)
    shifts = np.array([[a, b, c] for a in ticks for b in ticks for c in ticks])
    x = base.apply(mean)
    nrm = vertex_normals(mean, faces) @ base.rotation.T
    scores = []
    for sh in shifts:
        cost, _ = evidence.costs(x + sh, nrm, grid(3.0))
        scores.append(float(np.mean(cost.min(axis=1))))
    order = sorted(range(len(shifts)), key=lambda i: (scores[i], float(np.abs(shifts[i]).sum()), i))
    out = [np.zeros(3)]
    for i in order:
        if len(out) >= keep:
            break
        if all(np.abs(shifts[i] - o).max() > 4.0 + 1e-9 for o in out):
            out.append(shifts[i])
    return out


def _normals_rows(q: np.ndarray, normals: np.ndarray) -> np.ndarray:
    return np.einsum("nd,ndk->nk", normals, q)


def _applicable_appearance(params: SegmentParams, appearance: Appearance | None, image: GreyImage,
                           name: str) -> tuple[Appearance | None, str]:
    """The learned appearance where it applies to ``image`` under ``params.evidence``, else None (the
    gradient), and a note saying why it was set aside: learned from fewer than :data:`MIN_SCANS`
    scans (``"auto"``), or trained on voxels :data:`COARSER_THAN_TRAINING` times finer than the
    image's. ``"learned"`` without an appearance, or on too coarse an image, is refused."""
    if params.evidence == "learned" and appearance is None:
        raise InputError(f"{name}: the model has no learned appearance (it was built without images); segment with "
                         "the image gradient (evidence 'gradient' or 'auto') or rebuild with images")
    if params.evidence == "gradient":
        return None, ""
    if params.evidence == "auto" and appearance is not None and 0 < appearance.scans < MIN_SCANS:
        return None, (f" (the appearance was learned from {appearance.scans} scan: learned profiles are used from "
                      f"{MIN_SCANS} or more scans; evidence 'learned' uses these)")
    if appearance is not None and float(image.spacing_mm.max()) > COARSER_THAN_TRAINING * appearance.voxel_mm:
        if params.evidence == "learned":
            raise InputError(f"{name}: its voxels ({', '.join(f'{v:.3g}' for v in image.spacing_mm)} mm) are coarser "
                             f"than the appearance's training images' ({appearance.voxel_mm:.3g} mm): learned "
                             "profiles do not apply; segment with the gradient (evidence 'auto' or 'gradient')")
        return None, (f" (the image's {float(image.spacing_mm.max()):.3g} mm voxels are coarser than the "
                      f"appearance's {appearance.voxel_mm:.3g} mm training images: learned profiles do not apply)")
    return appearance, ""


def _click_pose(model, image: GreyImage, at, name: str) -> Pose:
    """:func:`start_pose` at a clicked point (world mm), refused where the point lies outside the
    image or, on a CT, with no bone within :data:`BONE_REACH_MM` (saying what the CT reads there)."""
    at = np.asarray(at, float).reshape(3)
    if not image.contains(at)[0]:
        lo, hi = image.extent_world()
        raise InputError(f"{name}: the start point ({', '.join(f'{v:.1f}' for v in at)}) mm lies outside the "
                         f"image, which spans x {lo[0]:.1f}..{hi[0]:.1f}, y {lo[1]:.1f}..{hi[1]:.1f}, "
                         f"z {lo[2]:.1f}..{hi[2]:.1f} mm (RAS); give the point in the image's world "
                         "coordinates (RAS, as 3D Slicer shows them)")
    found = bone_near(image, at)
    if found is not None and found[0] < BONE_HU:
        raise InputError(f"{name}: the start point ({', '.join(f'{v:.1f}' for v in at)}) mm is not on or near "
                         f"bone: the CT reads {found[1]:.0f} HU there and at most {found[0]:.0f} HU within "
                         f"{BONE_REACH_MM:g} mm (bone is {BONE_HU:g} HU or more; air -1000, soft tissue 0 to 100); "
                         "give a point in or on the structure (RAS, as 3D Slicer shows it)")
    return start_pose(model, at=at)


class _Search:
    """The profile search of one segmentation (Cootes et al. 1995): the model's first ``k`` modes
    (``q`` (N, 3, K), variances ``lam``), the evidence at each level, and the progress over every
    level's steps. :meth:`run_level` is one level's iterations, :meth:`score` how well a shape sits
    on a level's boundary."""

    def __init__(self, mean, faces, q, lam, evidences, params: SegmentParams, progress: ProgressFn,
                 cancelled: CancelledFn, total_steps: int):
        self.mean, self.faces, self.q, self.lam = mean, faces, q, lam
        self.evidences, self.params = evidences, params
        self.progress, self.cancelled, self.total_steps, self.done = progress, cancelled, total_steps, 0

    def grid(self, reach: float) -> np.ndarray:
        """Candidate offsets (mm) along a normal within ±``reach``, a search step apart."""
        step = self.params.search_step_mm
        return np.arange(-reach, reach + 0.5 * step, step)

    def score(self, pose_: Pose, b: np.ndarray, level: int) -> float:
        """Mean best cost within ±2 mm of the shape's surface at a level: how well it sits on the boundary."""
        shape = self.mean + self.q @ b
        x = pose_.apply(shape)
        nrm = vertex_normals(shape, self.faces) @ pose_.rotation.T
        cost, _ = self.evidences[level].costs(x, nrm, self.grid(2.0))
        return float(np.mean(cost.min(axis=1)))

    def run_level(self, level: int, pose0: Pose, b0: np.ndarray, iterations: int, record: bool = True):
        """One level from (``pose0``, ``b0``): each step moves every point to its best candidate along
        its normal, fits the pose to the suggestions (weighted by their evidence) and the coefficients
        to their distances along the normals (point to plane) under the prior. Returns (pose, b, the
        level's record)."""
        mean, faces, q, lam, params = self.mean, self.faces, self.q, self.lam, self.params
        sigma = LEVEL_SIGMAS_MM[level]
        ev = self.evidences[level]
        reach = params.search_mm[level]
        offsets = self.grid(reach)
        k = len(lam)
        sigma2 = max(params.noise_mm, sigma) ** 2
        pose_, b = pose0, b0.copy()
        shape = mean + q @ b
        last = pose_.apply(shape)
        converged, it, fit_cost, move, central = False, 0, math.inf, math.inf, 0.0
        strength = np.zeros(len(mean))
        rows = np.arange(len(mean))
        for it in range(1, iterations + 1):
            check_cancelled(self.cancelled)
            x = pose_.apply(shape)
            nrm_model = vertex_normals(shape, faces)
            nrm = nrm_model @ pose_.rotation.T
            cost, strong = ev.costs(x, nrm, offsets)
            cost = cost + 0.02 * (offsets[None, :] / reach) ** 2  # ties go to the nearer candidate
            best = np.argmin(cost, axis=1)
            chosen = _refined_offsets(cost, best, offsets)
            strength = strong[rows, best]
            fit_cost = float(np.mean(cost[rows, best]))
            w = np.clip(strength, 0.0, 1.0)
            if w.sum() < 1e-6:
                w = np.ones(len(mean))
            # after the first steps, half-steps towards the suggestions: a point whose best position
            # flips between two candidates no longer keeps the whole shape moving
            y = x + (1.0 if it <= FULL_STEPS else 0.5) * chosen[:, None] * nrm
            pose_ = weighted_pose(shape, y, w, False)
            # coefficients: each suggestion observes the distance along the shape's normal (point to plane)
            yl = pose_.inverse(y) - mean
            qn = _normals_rows(q, nrm_model)  # (N, K)
            r = np.einsum("nd,nd->n", nrm_model, yl)
            a = weighted_gram(qn, w)
            precision = a / sigma2 + params.prior_weight * np.diag(1.0 / lam)
            b = spd_solve(precision + 1e-12 * np.eye(k) * max(1.0, float(np.abs(precision).max())),
                          qn.T @ (w * r) / sigma2)
            shape = mean + q @ b
            x_new = pose_.apply(shape)
            move = float(np.sqrt(((x_new - last) ** 2).sum(axis=1).mean()))
            last = x_new
            if record:
                self.done += 1
                report(self.progress, self.done / self.total_steps, f"segment level {level + 1} ({sigma:g} mm) step "
                                                                    f"{it}: {move:.3f} mm, evidence {fit_cost:.3f}")
            # Cootes et al. (1994): a level has converged when 90 % of the points found their best
            # position within the central half of their search range (or nothing moves any more)
            central = float(np.mean(np.abs(chosen) <= CENTRAL_BAND * reach))
            if move < params.tolerance_mm or (it >= 3 and central >= CENTRAL_SHARE):
                converged = True
                break
        return pose_, b, {"level": level + 1, "blur_mm": sigma, "search_mm": reach, "iterations": it,
                          "converged": converged, "last_move_mm": move, "evidence_cost": fit_cost,
                          "central_share": central,
                          "weak_share": float(np.mean(strength < 0.25))}


def _search_from_starts(search: _Search, base: Pose, params: SegmentParams) -> tuple:
    """The coarse level from every placement (:func:`_placements`) and turn of the start, ranked by how
    well each then sits on the boundary at the middle level; the best :data:`FINISHED_STARTS` go
    through every level and the better one wins. Returns (pose, b, the levels' records, the start's
    record)."""
    mean, faces, k = search.mean, search.faces, len(search.lam)
    starts = [("start", np.eye(3))]
    if params.turns_deg > 0:
        for axis in range(3):
            for sign in (1, -1):
                starts.append((f"turned {sign * params.turns_deg:+g}° about {'xyz'[axis]}",
                               _axis_turn(axis, sign * params.turns_deg)))
    starts.append((UPSIDE, _axis_turn(2, 180.0)))
    c_model = volume_centroid(mean, faces)
    tried = []
    for shift in _placements(base, mean, faces, search.evidences[0], search.grid, params.placement_mm,
                             PLACEMENTS_KEPT):
        centre = base.apply(c_model) + shift
        moved = "" if not np.any(shift) else f", moved ({', '.join(f'{v:+.0f}' for v in shift)}) mm"
        for label, turn in starts:
            check_cancelled(search.cancelled)
            rot = turn @ base.rotation
            p0 = Pose(rot, centre - base.scale * rot @ c_model, base.scale)
            p1, b1, _info = search.run_level(0, p0, np.zeros(k), COARSE_STEPS, record=False)
            tried.append({"name": label + moved, "pose": p1, "b": b1, "screened": search.score(p1, b1, 1)})
    order = sorted(range(len(tried)), key=lambda i: (tried[i]["screened"], i))[:FINISHED_STARTS]
    finished = []
    n_levels = len(LEVEL_SIGMAS_MM)
    for i in order:
        pose_, b = tried[i]["pose"], tried[i]["b"]
        lv = []
        for level in range(n_levels):
            pose_, b, info = search.run_level(level, pose_, b, params.iterations)
            lv.append(info)
        tried[i]["final"] = search.score(pose_, b, n_levels - 1)
        finished.append((tried[i]["final"], i, pose_, b, lv))
    finished.sort(key=lambda t: (t[0], t[1]))
    _final, win, pose_, b, levels = finished[0]
    start_doc = {"chosen": tried[win]["name"],
                 "candidates": [{"name": t["name"], "screened_cost": t["screened"], "final_cost": t.get("final")}
                                for t in tried]}
    return pose_, b, levels, start_doc


def _shape_posterior(search: _Search, shape, model_points, normals_w, image: GreyImage, error_var):
    """The posterior of the coefficients at the fine level (the weights the evidence gives at the
    result; the suggestions' scatter about the fitted shape is the noise, at least a quarter of the
    finest voxel edge): each point's shape variance (model units², plus the model's own error), the
    fine level's costs, strengths and offsets, the noise (mm²) and its floor."""
    mean, faces, q, lam, params = search.mean, search.faces, search.q, search.lam, search.params
    fine = search.grid(params.search_mm[-1])
    cost, strong = search.evidences[-1].costs(model_points, normals_w, fine)
    best = np.argmin(cost + 0.02 * (fine[None, :] / fine[-1]) ** 2, axis=1)
    w_final = np.clip(strong[np.arange(len(mean)), best], 0.0, 1.0)
    residual = _refined_offsets(cost, best, fine)
    floor2 = (0.25 * float(image.spacing_mm.min())) ** 2
    sigma2 = max(float(np.sum(w_final * residual ** 2) / max(w_final.sum(), 1e-9)), floor2)
    qn = _normals_rows(q, vertex_normals(shape, faces))
    cov_b = np.linalg.inv(weighted_gram(qn, w_final) / sigma2 + params.prior_weight * np.diag(1.0 / lam))
    per_point = np.einsum("ndk,kl,ndl->n", q, cov_b, q)  # the shape's uncertainty
    if error_var is not None:
        per_point = per_point + error_var
    return per_point, cost, strong, fine, sigma2, floor2


def _deviation_step(cost, strong, fine, faces, error_var, n_points: int) -> np.ndarray:
    """Per point, how far (mm, along its normal) the surface leaves the model's span: the best
    candidate under a penalty scaled by the model's own error there (within 2× that error, between
    0.25 and 3 mm), weighted by its evidence and smoothed over the mesh."""
    allowed = np.sqrt(np.maximum(error_var if error_var is not None else np.full(n_points, 1.0), 1e-6) / 3.0)
    allowed = np.clip(allowed, 0.25, 3.0)
    penalty = (fine[None, :] / allowed[:, None]) ** 2
    best = np.argmin(cost + penalty, axis=1)
    raw = fine[best]
    raw = np.clip(raw, -2.0 * allowed, 2.0 * allowed)
    weight = np.clip(strong[np.arange(n_points), best], 0.0, 1.0)
    return _smooth_on_mesh(raw * weight, weight, faces, rounds=3)


def _verdict(model, mahal: float, k: int, levels: list, converged: bool, params: SegmentParams, weak_share: float,
             strong_zero: np.ndarray, sd: np.ndarray, deviation: np.ndarray, evidence: str, boundary: dict,
             appearance: Appearance | None, chosen_start: str) -> list:
    """The segmentation's findings, each (kind, message): an outlier shape, a fine level that did not
    settle, weak boundary evidence (per structure of a joint model too, into ``boundary``), grey values
    unlike the appearance's training images', and a result turned upside down."""
    findings = []
    limit = outlier_limit(k)
    if mahal > limit:
        findings.append(("outlier", f"the segmented shape lies {mahal:.2f} SD from the model's mean (99 % of the "
                                    f"model's shapes lie within {limit:.2f}): an unusual shape or a wrong one"))
    if not converged and levels[-1]["last_move_mm"] > 2 * params.tolerance_mm:
        findings.append(("not_converged", f"the fine level did not settle in {params.iterations} steps: "
                                          f"{100 * levels[-1]['central_share']:.0f} % of the points found the boundary "
                                          f"within ±{CENTRAL_BAND * params.search_mm[-1]:g} mm (90 % needed), last move "
                                          f"{levels[-1]['last_move_mm']:.2f} mm"))
    if weak_share > 0.4:
        findings.append(("weak_evidence", f"{100 * weak_share:.0f} % of the surface has weak boundary evidence "
                                          f"({evidence}); the boundary there follows the model, not the image"))
    if model.structure_names:  # a joint model: each structure's own verdict
        boundary["structures"] = {}
        for name in model.structure_names:
            part = model.structure_slice(name)
            weak = float(np.mean(strong_zero[part] < 0.25))
            boundary["structures"][name] = {"weak_share": weak, "sd_mean_mm": float(sd[part].mean()),
                                            "deviation_mean_mm": float(np.abs(deviation[part]).mean())}
            if weak > 0.4 >= weak_share:
                findings.append(("weak_evidence", f"{name}: {100 * weak:.0f} % of its surface has weak boundary "
                                                  f"evidence ({evidence}); its boundary there follows the model, "
                                                  "not the image"))
    if appearance is not None and np.all(np.isfinite(appearance.boundary_mm)):
        c_train = float(appearance.boundary_mm[0] - appearance.boundary_mm[1])
        c_here = boundary["inside_mean"] - boundary["outside_mean"]
        if c_train != 0 and not (0.25 <= c_here / c_train <= 4.0):
            findings.append(("intensities", f"the grey values across the segmented boundary (inside "
                                            f"{boundary['inside_mean']:.0f}, outside {boundary['outside_mean']:.0f}) "
                                            f"are not those of the appearance's training images (inside "
                                            f"{appearance.boundary_mm[0]:.0f}, outside {appearance.boundary_mm[1]:.0f}):"
                                            " another modality or intensity scale?"))
    if chosen_start.startswith(UPSIDE):
        findings.append(("orientation", "the image fits best with the model turned 180° about the "
                                        "superior axis: is the image's orientation LPS stored as RAS (x and y "
                                        "negated)?"))
    return findings


def segment_image(model, image: GreyImage, *, at=None, pose: Pose | None = None, appearance: Appearance | None = None,
                  params: SegmentParams | None = None, progress: ProgressFn = None,
                  cancelled: CancelledFn = None) -> SegmentResult:
    """Segment ``image`` with ``model``: pose and shape from coarse to fine, then the deviation step.

    The steps: the evidence that applies (:func:`_applicable_appearance`), the start
    (:func:`_click_pose` or ``pose``), the search from the start's placements and turns through
    every level (:func:`_search_from_starts`), the shape's posterior at the result
    (:func:`_shape_posterior`), the deviation step (:func:`_deviation_step`), the boundary's own
    spread in each point's SD (:func:`boundary_spread`) and the verdict (:func:`_verdict`).

    Parameters
    ----------
    model : ShapeModel
    image : GreyImage
        World frame RAS mm.
    at : (3,) mm, optional
        A point inside the structure (world): the mean shape's solid centroid is put there.
    pose : Pose, optional
        A start pose (model -> world) instead of ``at`` (from landmarks or a rough mask).
    appearance : Appearance, optional
        Learned boundary profiles; without them (or with ``params.evidence == "gradient"``)
        the image gradient is the evidence.
    params : SegmentParams

    Returns
    -------
    SegmentResult
    """
    t0 = time.perf_counter()
    params = SegmentParams() if params is None else params
    name = image.path or "image"
    appearance, resolution_note = _applicable_appearance(params, appearance, image, name)
    mean = np.asarray(model.mean, float)
    faces = np.asarray(model.faces, np.int64)
    if len(faces) == 0:
        raise InputError("model: it has no triangles, so it has no surface normals to search along")
    if appearance is not None and appearance.n_points != len(mean):
        raise InputError(f"model: its appearance covers {appearance.n_points} points, the shape {len(mean)}")
    _check_units(model, image)
    if pose is None:
        if at is None:
            raise InputError(f"{name}: a start is needed: a point inside the structure, landmarks or a rough mask")
        base = _click_pose(model, image, at, name)
    else:
        base = pose
    k = model.n_modes if params.n_modes is None else min(int(params.n_modes), model.n_modes)
    q = np.asarray(model.modes[:k], float).reshape(k, len(mean), 3).transpose(1, 2, 0)  # (N, 3, K)
    lam = np.maximum(np.asarray(model.variances[:k], float), 1e-12)
    error_var = model_error_variance(model, k)
    evidence = ("learned" if appearance is not None else "gradient") + resolution_note
    n_levels = len(LEVEL_SIGMAS_MM)
    step = params.search_step_mm

    def grid(reach):
        return np.arange(-reach, reach + 0.5 * step, step)

    # gradient evidence: one scale per level, from the start (so every pose's costs compare)
    scales = []
    shape0 = base.apply(mean)
    nrm0 = vertex_normals(mean, faces) @ base.rotation.T
    for level, sigma in enumerate(LEVEL_SIGMAS_MM):
        e = _Evidence(image, None, level, sigma, step).edge(shape0, nrm0, grid(params.search_mm[level]))
        scales.append(float(np.median(np.maximum(e.max(axis=1), 0.0))) or 1.0)
    evidences = [_Evidence(image, appearance, level, sigma, step, scales[level])
                 for level, sigma in enumerate(LEVEL_SIGMAS_MM)]
    search = _Search(mean, faces, q, lam, evidences, params, progress, cancelled,
                     FINISHED_STARTS * n_levels * params.iterations)
    pose_, b, levels, start_doc = _search_from_starts(search, base, params)
    converged = levels[-1]["converged"]
    iterations = sum(lv["iterations"] for lv in levels)
    shape = mean + q @ b
    model_points = pose_.apply(shape)
    normals_w = vertex_normals(shape, faces) @ pose_.rotation.T
    per_point, cost, strong, fine, sigma2, floor2 = _shape_posterior(search, shape, model_points, normals_w, image,
                                                                     error_var)
    deviation = np.zeros(len(mean))
    points = model_points
    if params.deviation:  # leave the span along the normal by what the model's error allows
        deviation = _deviation_step(cost, strong, fine, faces, error_var, len(mean))
        points = model_points + deviation[:, None] * normals_w
    z = b / np.sqrt(lam)
    d2 = float(np.sum(z * z))
    mahal = math.sqrt(d2)
    # how well the evidence fits at the result
    zero = int(np.argmin(np.abs(fine)))
    normals_at = vertex_normals(points, faces)
    cost_at, strong_at = evidences[-1].costs(points, normals_at, fine)
    weak_share = float(np.mean(strong_at[:, zero] < 0.25))
    boundary = {"evidence_cost": float(np.mean(cost_at[:, zero])), "weak_share": weak_share,
                "residual_sd_mm": math.sqrt(sigma2)}
    # the SD's boundary term per point, at the result: where the image puts or leaves the boundary
    # (at least a quarter of the finest voxel edge), in place of the one scatter for all points
    spread = _smooth_on_mesh(boundary_spread(cost_at, fine), np.ones(len(mean)), faces, rounds=3)
    spread = np.maximum(spread, floor2)
    sd = np.sqrt(np.maximum(pose_.scale ** 2 * per_point + spread, 0.0))  # model units scaled; spread in mm
    inner, outer = boundary_grey_values(image, points, normals_at, sigma_mm=LEVEL_SIGMAS_MM[-1])
    boundary["inside_mean"], boundary["outside_mean"] = float(inner.mean()), float(outer.mean())
    findings = _verdict(model, mahal, k, levels, converged, params, weak_share, strong_at[:, zero], sd, deviation,
                        evidence, boundary, appearance, start_doc["chosen"])
    return SegmentResult(points=points, faces=faces, model_points=model_points, pose=pose_, coefficients=z,
                         posterior_sd_mm=sd, deviation_mm=deviation, mahalanobis=mahal,
                         p_value=float(chdtrc(k, d2)) if k else 1.0, evidence=evidence, boundary=boundary,
                         levels=levels, start=start_doc, iterations=iterations,
                         converged=converged, findings=findings, seconds=time.perf_counter() - t0,
                         structures=tuple((n, model.structure_slice(n).start, model.structure_slice(n).stop)
                                          for n in model.structure_names),
                         parameters=to_table(params))


def _smooth_on_mesh(values: np.ndarray, weights: np.ndarray, faces: np.ndarray, *, rounds: int) -> np.ndarray:
    """Weighted averages of ``values`` over each vertex and its mesh neighbours, ``rounds`` times."""
    e = edges(faces)
    i, j = np.concatenate([e[:, 0], e[:, 1]]), np.concatenate([e[:, 1], e[:, 0]])
    v = np.asarray(values, float)
    w = np.asarray(weights, float) + 1e-3
    n = len(v)
    den = w + np.bincount(i, weights=w[j], minlength=n)
    for _ in range(rounds):
        v = (v * w + np.bincount(i, weights=v[j] * w[j], minlength=n)) / den
    return v


def _check_units(model, image: GreyImage) -> None:
    """The image must span at least the model's size (mm): a smaller one is in metres or cm."""
    size = float(np.linalg.norm(np.ptp(np.asarray(model.mean, float), axis=0)))
    lo, hi = image.extent_world()
    span = float(np.linalg.norm(hi - lo))
    if span < 0.5 * size or float(image.spacing_mm.min()) < 0.01:
        raise InputError(f"{image.path or 'image'}: the image spans {span:.3g} mm (voxels "
                         f"{', '.join(f'{s:.3g}' for s in image.spacing_mm)} mm) but the model is {size:.3g} mm "
                         "across: is the image in metres or centimetres? Rewrite it in mm (its header's units)")
