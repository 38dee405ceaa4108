"""Fitting a shape model to new data: pose and mode coefficients under the model's prior.

The model (paper 5, eq. 7) says a shape is p = p̄ + Q b with b ~ N(0, Λ). Fitting it to a
target (a surface, a point cloud, landmarks, or a part of any of these) alternates

1. correspondences: each model point to its closest target point, and each target point
   to its closest model point (only the latter for a partial target, so the unobserved
   part of the model is not pulled onto the observed part), each observing the distance
   along the shape's normal (point to plane); model landmarks (points of the mean mesh,
   barycentric) to the target's landmarks of the same name (point to point);
2. the pose T (rigid, or with scale) that best maps the current shape onto those points
   (weighted Procrustes);
3. the coefficients b: the posterior mean of the linear Gaussian model
   T⁻¹(y) = p̄ + Q b + ε, ε ~ N(0, σ²), b ~ N(0, Λ/η):
   (QᵀWQ/σ² + η Λ⁻¹) b = QᵀW (T⁻¹y − p̄)/σ²,

until the points stop moving. The posterior covariance of b, (QᵀWQ/σ² + ηΛ⁻¹)⁻¹, gives
each point's posterior standard deviation: where the target says nothing (completion of
a partial shape) it grows to the model's own variability. The same engine serves
``ssm fit`` and the model-driven coating of model-guided correspondence.

Frames: the model in its model frame (object mm, paper 5); the target, its landmarks and
every result in the target's frame (world mm for files); ``pose`` maps model → target.
"""

from __future__ import annotations

import itertools
import math
import weakref
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from scipy.special import chdtrc, chdtri

from ..base.errors import InputError, check_cancelled
from ..base.params import FitParams
from ..base.progress import CancelledFn, ProgressFn, report
from ..formats.landmarks import LandmarkSet
from ..meshutil import MeshLocator, outer_surface, vertex_normals

__all__ = ["FitResult", "ModelErrorField", "Pose", "Target", "correlation_length", "farthest_point_indices",
           "fit_any_pose", "fit_floor", "fit_model", "loo_residuals", "model_error_field", "model_error_variance", "outlier_limit",
           "pose_freedom", "rigid_screen", "start_poses", "weighted_pose", "axis_rotation"]


@dataclass(frozen=True)
class Pose:
    """x_target = scale · rotation @ x_model + translation (mm)."""

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(points, float) @ self.rotation.T + self.translation

    def inverse(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, float) - self.translation) @ self.rotation / self.scale

    @property
    def matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    def to_dict(self) -> dict:
        return {"rotation": self.rotation.tolist(), "translation_mm": self.translation.tolist(),
                "scale": float(self.scale), "matrix": self.matrix.tolist()}


@dataclass
class Target:
    """What a model is fitted to, in one frame (mm): a surface, points, landmarks, or a mix.

    Build with :meth:`from_mesh`, :meth:`from_points` or :meth:`from_landmarks`.
    """

    samples: np.ndarray  # (M, 3) points on the target (target → model correspondences)
    source: str = ""
    locator: MeshLocator | None = None  # exact closest points on triangles
    tree: cKDTree | None = None  # closest sample points
    landmarks: LandmarkSet | None = None
    merged_labels: tuple = ()  # a label map read without a label: the labels fitted together

    @classmethod
    def from_mesh(cls, vertices, faces, *, source: str = "", landmarks=None, max_samples: int = 20000) -> Target:
        """The target's surface: the mesh's outer surface (:func:`~ssm_addon.meshutil.outer_surface`:
        the walls of cavities inside the object, which a segmentation's marching cubes writes and
        the model does not hold, are left out), every k-th vertex a sample (at most about
        ``max_samples``)."""
        v, f, _cavities = outer_surface(vertices, faces)
        step = max(1, len(v) // max_samples)
        return cls(samples=v[::step], source=source, locator=MeshLocator(v, f), landmarks=landmarks)

    @classmethod
    def from_points(cls, points, *, source: str = "", landmarks=None) -> Target:
        p = np.asarray(points, float).reshape(-1, 3)
        if len(p) == 0 and landmarks is None:
            raise InputError(f"{source or 'target'}: no points to fit to")
        return cls(samples=p, source=source, tree=cKDTree(p) if len(p) else None, landmarks=landmarks)

    @classmethod
    def from_landmarks(cls, landmarks: LandmarkSet, *, source: str = "") -> Target:
        return cls(samples=np.zeros((0, 3)), source=source or landmarks.source, landmarks=landmarks)

    @property
    def has_surface(self) -> bool:
        return len(self.samples) > 0

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closest target points (M, 3) and distances (M,) of query points."""
        if self.locator is not None:
            c, d, _, _ = self.locator.query(points, k=8)
            return c, d
        d, j = self.tree.query(points)
        return self.samples[j], d


@dataclass(frozen=True)
class FitResult:
    """A model fitted to a target.

    Attributes
    ----------
    points : (N, 3) mm
        The fitted shape (posterior mean), target frame.
    coefficients : (K,) float
        b_k / √λ_k, in standard deviations.
    b : (K,) mm
        The mode weights of eq. 7.
    pose : Pose
        Model frame → target frame.
    posterior_sd_mm : (N,) mm
        Per point, √(trace of its posterior covariance): small where the target pins the
        shape, up to the model's variability where it says nothing.
    mahalanobis : float
        √(Σ b_k²/λ_k) over the K modes used.
    p_value : float
        Chi-square (K degrees of freedom) tail of the squared Mahalanobis distance.
    mean_distance_mm, max_distance_mm : float
        Distances between the fitted shape and the target (over the target's points for
        a partial target, over the shape's points otherwise).
    landmark_residuals_mm : dict name -> mm
    iterations : int
    converged : bool
    pose_freedom : dict or None
        A partial target's pose freedom (:func:`pose_freedom`): the turns about the given part's
        long axis that fit nearly as well; its spread is then inside ``posterior_sd_mm``.
    similarity : dict or None
        A rigid fit's size check (:func:`fit_any_pose` ``size_check``): the same fit with a
        similarity pose from this one's, ``mean_distance_mm``, ``scale`` and ``mahalanobis``.
    """

    points: np.ndarray
    coefficients: np.ndarray
    b: np.ndarray
    pose: Pose
    posterior_sd_mm: np.ndarray
    mahalanobis: float
    p_value: float
    mean_distance_mm: float
    max_distance_mm: float
    landmark_residuals_mm: dict
    iterations: int
    converged: bool
    n_modes: int
    b_covariance: np.ndarray | None = None
    pose_freedom: dict | None = None
    similarity: dict | None = None

    def to_dict(self) -> dict:
        return {"coefficients": [float(x) for x in self.coefficients], "b_mm": [float(x) for x in self.b],
                "pose": self.pose.to_dict(), "mahalanobis": float(self.mahalanobis), "p_value": float(self.p_value),
                "n_modes": int(self.n_modes), "mean_distance_mm": float(self.mean_distance_mm),
                "max_distance_mm": float(self.max_distance_mm),
                "landmark_residuals_mm": {k: float(v) for k, v in self.landmark_residuals_mm.items()},
                "iterations": int(self.iterations), "converged": bool(self.converged),
                "posterior_sd_mm": {"mean": float(self.posterior_sd_mm.mean()),
                                    "max": float(self.posterior_sd_mm.max())},
                **({"pose_freedom": self.pose_freedom} if self.pose_freedom is not None else {}),
                **({"similarity": self.similarity} if self.similarity is not None else {})}


def _procrustes(src: np.ndarray, dst: np.ndarray, w: np.ndarray, scale: bool) -> Pose:
    """Weighted least-squares similarity (or rigid) transform src → dst (Umeyama)."""
    w = w / w.sum()
    ms, md = w @ src, w @ dst
    a, b = src - ms, dst - md
    cov = (b * w[:, None]).T @ a
    u, sv, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    corr = np.diag([1.0, 1.0, d])
    rot = u @ corr @ vt
    s = float((sv * np.diag(corr)).sum() / max((w * (a * a).sum(axis=1)).sum(), 1e-300)) if scale else 1.0
    return Pose(rot, md - s * rot @ ms, s)


def weighted_pose(src: np.ndarray, dst: np.ndarray, weights: np.ndarray, scale: bool = False) -> Pose:
    """The weighted least-squares rigid (or, with ``scale``, similarity) pose taking the points
    ``src`` (M, 3) onto ``dst`` (M, 3), mm (Umeyama 1991)."""
    return _procrustes(np.asarray(src, float), np.asarray(dst, float), np.asarray(weights, float), scale)


def _skew(v: np.ndarray) -> np.ndarray:
    """(M, 3, 3) cross-product matrices [v]× of (M, 3) vectors."""
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], 1), np.stack([v[:, 2], z, -v[:, 0]], 1),
                     np.stack([-v[:, 1], v[:, 0], z], 1)], 1)


_MODEL_ERROR: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
MODEL_ERROR_MAX_INSTANCES = 100
"""The model error is estimated from at most this many training instances (evenly spread)."""


def model_error_variance(model, n_modes: int | None = None) -> np.ndarray | None:
    """The model's own error per point: variance (mm², total over x, y, z; model frame).

    Each training instance (``instance_points``) reconstructed by the model of the
    *others* on ``n_modes`` modes (default every mode); the squared residual per point,
    averaged over the instances. What the model cannot represent of a new shape, which a
    fit's posterior adds to the target noise's share (a Gaussian-process augmentation
    with the leave-one-out residuals as its per-point amplitude). None for a model
    without at least 3 training instances (e.g. a statismo file from another tool).

    References
    ----------
    Lüthi M, Gerig T, Jud C, Vetter T. Gaussian Process Morphable Models. IEEE TPAMI
    40(8), 2018 (augmenting a PCA model with a kernel for what it does not span).
    """
    key = (n_modes,)
    cached = _MODEL_ERROR.get(model, {})
    if key in cached:
        return cached[key]
    res = loo_residuals(model, n_modes)
    if res is None:
        return None
    out = (res ** 2).sum(axis=2).mean(axis=0)
    cached[key] = out
    _MODEL_ERROR[model] = cached
    return out


def loo_residuals(model, n_modes: int | None = None) -> np.ndarray | None:
    """Leave-one-out residuals (n, N, 3), mm, model frame: each training instance (at most
    ``MODEL_ERROR_MAX_INSTANCES``, evenly spread) minus its reconstruction by the model of
    the others on ``n_modes`` modes (default every mode). None without 3 instances."""
    pts = np.asarray(getattr(model, "instance_points", np.zeros((0,))), float)
    if pts.ndim != 3 or len(pts) < 3 or pts.shape[1] != len(model.mean):
        return None
    idx = np.unique(np.linspace(0, len(pts) - 1, min(len(pts), MODEL_ERROR_MAX_INSTANCES)).round().astype(int))
    flat = pts.reshape(len(pts), -1)
    out = np.empty((len(idx), pts.shape[1], 3))
    for row, i in enumerate(idx):
        others = np.delete(flat, i, axis=0)
        mu = others.mean(axis=0)
        y = others - mu
        w, u = np.linalg.eigh(y @ y.T)
        order = np.argsort(w)[::-1]
        w, u = w[order], u[:, order]
        keep = int((w > 1e-9 * max(w[0], 1e-300)).sum())
        k = keep if n_modes is None else min(keep, int(n_modes))
        basis = (u[:, :k].T @ y) / np.sqrt(w[:k])[:, None]
        r = flat[i] - mu
        out[row] = (r - basis.T @ (basis @ r)).reshape(-1, 3)
    return out


def farthest_point_indices(points: np.ndarray, k: int) -> np.ndarray:
    """``k`` indices of ``points`` (M, 3) spread by farthest-point sampling from index 0
    (ties: the lowest index)."""
    points = np.asarray(points, float)
    k = min(int(k), len(points))
    idx = np.zeros(k, int)
    d = np.linalg.norm(points - points[0], axis=1)
    for j in range(1, k):
        idx[j] = int(np.argmax(d))
        d = np.minimum(d, np.linalg.norm(points - points[idx[j]], axis=1))
    return idx


MODEL_ERROR_PAIRS = 200_000
"""Point pairs sampled (fixed seed) to measure the residuals' correlation length."""
MODEL_ERROR_CENTRES = 500
"""Most kernel centres of the model-error field (farthest-point samples of the mean)."""


@dataclass(frozen=True)
class ModelErrorField:
    """The model's own error as a smooth Gaussian process on its points (model frame, mm).

    Per axis, cov(e(x), e(y)) = a(x) a(y) exp(−|x − y|² / 2ℓ²): ``amplitude_mm`` a (N,)
    from the training instances' leave-one-out residuals (a² is a third of
    :func:`model_error_variance`), ``length_mm`` ℓ the distance at which those residuals'
    correlation falls to e^(−1/2). ``fields_mm`` (N, r) is its low-rank (Nyström) form on
    ``r`` kernel eigenvectors, each field of prior variance 1 and applied to each axis on
    its own: the 3r extra modes a partial fit is given (:attr:`basis`), so that what the
    model cannot represent neither bends the pose nor vanishes from the posterior of the
    part the target does not show.
    """

    amplitude_mm: np.ndarray
    length_mm: float
    fields_mm: np.ndarray

    @property
    def basis(self) -> np.ndarray:
        """(N, 3, 3r) mm: the fields as modes, axis by axis (mode a·r + j moves axis a by field j)."""
        return _ModeBasis(np.zeros((len(self.fields_mm), 3, 0)), self.fields_mm).rows(np.arange(len(self.fields_mm)))


def weighted_gram(rows: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(K, K): ``rowsᵀ diag(weights) rows`` for rows (P, K) and weights (P,) ≥ 0, as the
    product of the √weight-scaled rows with themselves (one symmetric rank-k update, about
    half the arithmetic of the general product)."""
    scaled = rows * np.sqrt(np.maximum(weights, 0.0))[:, None]
    return scaled.T @ scaled


def spd_solve(a: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """The solution of ``a x = rhs`` for a symmetric positive definite ``a`` (a posterior
    precision): by its Cholesky factor, or by the general solve where rounding left ``a`` not
    positive definite."""
    try:
        return cho_solve(cho_factor(a, check_finite=False), rhs, check_finite=False)
    except LinAlgError:
        return np.linalg.solve(a, rhs)


class _ModeBasis:
    """A fit's linear shape basis (model frame, mm per unit coefficient): the model's modes
    ``q`` (N, 3, k) and, for a partial fit, the model-error field's smooth fields ``f`` (N, r),
    each applied to each axis on its own (coefficient k + a·r + j moves axis a by field j).
    The fields stay in that factored form: the dense (N, 3, k + 3r) basis is three times
    their size and mostly zeros."""

    def __init__(self, q: np.ndarray, f: np.ndarray | None = None):
        self.q = q
        self.f = f
        self.k_modes = q.shape[2]
        self.r = 0 if f is None else f.shape[1]
        self.k = self.k_modes + 3 * self.r

    def apply(self, b: np.ndarray) -> np.ndarray:
        """(N, 3) mm: the basis times the coefficients ``b`` (k + 3r,)."""
        out = self.q @ b[:self.k_modes]
        if self.r:
            out += self.f @ b[self.k_modes:].reshape(3, self.r).T
        return out

    def rows(self, idx: np.ndarray) -> np.ndarray:
        """(*idx.shape, 3, k + 3r) mm: the dense basis at the points ``idx``."""
        idx = np.asarray(idx)
        out = np.zeros(idx.shape + (3, self.k))
        out[..., :self.k_modes] = self.q[idx]
        if self.r:
            fi = self.f[idx]
            for axis in range(3):
                start = self.k_modes + axis * self.r
                out[..., axis, start:start + self.r] = fi
        return out

    def normal_rows(self, normals: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """(M, k + 3r): n·Q at the points ``idx`` (M,) along their ``normals`` (M, 3)."""
        qn = np.einsum("ud,udk->uk", normals, self.q[idx])
        if not self.r:
            return qn
        fi = self.f[idx]
        return np.hstack([qn] + [normals[:, axis:axis + 1] * fi for axis in range(3)])

    def axis_rows(self, axis: int) -> np.ndarray:
        """(N, k + 3r): the basis's ``axis`` component at every point."""
        out = np.zeros((len(self.q), self.k))
        out[:, :self.k_modes] = self.q[:, axis, :]
        if self.r:
            start = self.k_modes + axis * self.r
            out[:, start:start + self.r] = self.f
        return out


def correlation_length(points: np.ndarray, residuals: np.ndarray, *, pairs: int = MODEL_ERROR_PAIRS) -> float:
    """Distance (mm) at which residual fields (n, N, 3) on ``points`` (N, 3) correlate by
    e^(−1/2), the length of a Gaussian kernel with that correlation; from ``pairs`` point
    pairs drawn with a fixed seed, binned by distance."""
    rng = np.random.default_rng(0)
    a = rng.integers(0, len(points), pairs)
    b = rng.integers(0, len(points), pairs)
    d = np.linalg.norm(points[a] - points[b], axis=1)
    num = (residuals[:, a] * residuals[:, b]).sum(-1).mean(0)
    den = np.sqrt((residuals[:, a] ** 2).sum(-1).mean(0) * (residuals[:, b] ** 2).sum(-1).mean(0))
    ok = den > 1e-300
    d, c = d[ok], num[ok] / den[ok]
    extent = float(np.linalg.norm(points.max(0) - points.min(0)))
    edges = np.linspace(0.0, extent, 81)
    which = np.digitize(d, edges) - 1
    counts = np.bincount(which, minlength=len(edges))[:80]
    sums = np.bincount(which, weights=c, minlength=len(edges))[:80]
    centres = 0.5 * (edges[:-1] + edges[1:])
    valid = counts >= 20
    centres, corr = centres[valid], sums[valid] / counts[valid]
    target = math.exp(-0.5)
    below = np.nonzero(corr < target)[0]
    if not len(below):
        return extent
    j = int(below[0])
    if j == 0:
        return float(centres[0])
    t = (corr[j - 1] - target) / max(corr[j - 1] - corr[j], 1e-12)
    return float(centres[j - 1] + t * (centres[j] - centres[j - 1]))


_ERROR_FIELD: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
#: A model without training shapes (another tool's file) takes its error field from its finest modes: the
#: last ``TAIL_MODES_SHARE`` of them give the correlation length (femur10: 16.6 mm, the leave-one-out
#: residuals' 15.8 mm) and, times ``TAIL_AMPLITUDE``, the amplitude (docs/history.md, "Data as users
#: bring it": femur10 completions 1.8 % -> 91 % of true errors within 2 SD, missing half 11.3 -> 5.8 mm).
TAIL_MODES_SHARE = 0.5
TAIL_AMPLITUDE = 3.0


def model_error_field(model, *, keep: float = 0.99) -> ModelErrorField | None:
    """The model's :class:`ModelErrorField` (cached per model): from the training instances'
    leave-one-out residuals, or for a model without them (another tool's file) from its finest
    modes (:data:`TAIL_MODES_SHARE`, :data:`TAIL_AMPLITUDE`). None for a model of one mode, or
    when the correlation length is below twice the points' spacing (independent per point:
    :func:`model_error_variance` is all there is).
    ``keep``: the share of the kernel's trace its eigenvectors keep.

    References
    ----------
    Lüthi M, Gerig T, Jud C, Vetter T. Gaussian Process Morphable Models. IEEE TPAMI
    40(8), 2018 (a PCA model augmented by a smooth kernel for what it does not span).
    """
    if model in _ERROR_FIELD:
        return _ERROR_FIELD[model]
    res = loo_residuals(model)
    mean = np.asarray(model.mean, float)
    if res is not None:
        amp = np.sqrt((res ** 2).sum(-1).mean(0) / 3.0)
        length = correlation_length(mean, res)
    elif model.n_modes >= 2:  # a model without its training shapes (another tool's): its finest modes
        tail = max(1, int(round(model.n_modes * TAIL_MODES_SHARE)))
        fields = np.asarray(model.modes[-tail:], float) * np.sqrt(np.asarray(model.variances[-tail:], float))[:, None, None]
        amp = TAIL_AMPLITUDE * np.sqrt((fields ** 2).sum(-1).sum(0) / 3.0)
        length = correlation_length(mean, fields)
    else:
        return None
    spacing = float(np.median(cKDTree(mean).query(mean, k=2)[0][:, 1]))
    if not length >= 2.0 * spacing:  # independent per point: no smooth part to fit
        _ERROR_FIELD[model] = None
        return None
    centres = mean[farthest_point_indices(mean, MODEL_ERROR_CENTRES)]
    kcc = np.exp(-((centres[:, None] - centres[None]) ** 2).sum(-1) / (2 * length ** 2))
    w, u = np.linalg.eigh(kcc)
    order = np.argsort(w)[::-1]
    w, u = np.maximum(w[order], 0.0), u[:, order]
    r = int(min(len(w), np.searchsorted(np.cumsum(w) / w.sum(), keep) + 1))
    kxc = np.exp(-((mean[:, None] - centres[None]) ** 2).sum(-1) / (2 * length ** 2))
    phi = kxc @ (u[:, :r] / np.sqrt(w[:r]))  # (N, r): phi phiᵀ ≈ the kernel
    phi /= np.maximum(np.linalg.norm(phi, axis=1, keepdims=True), 1e-300)  # unit prior variance per point
    field_ = ModelErrorField(amplitude_mm=amp, length_mm=length, fields_mm=amp[:, None] * phi)
    _ERROR_FIELD[model] = field_
    return field_


def _posterior(modes, shape, faces, rows_v, w, pose, lm_pairs, w_lm, sigma2, params, lam, k):
    """Posterior covariance of b and per-point shape variance (mm², model frame), pose included.

    Linearised at the fit: the parameters are b and a small rotation ω and translation τ
    of the model frame (x_i ≈ s_i + Q_i b − [s_i]× ω + τ); the pose has a flat prior. Its
    uncertainty matters most for a partial target, whose pose the data pins least.
    """
    n = len(shape)
    pose_jac = np.concatenate([-_skew(shape), np.broadcast_to(np.eye(3), (n, 3, 3))], axis=2)  # (N, 3, 6)
    s2 = sigma2 / pose.scale ** 2
    m = modes.k + 6
    if len(rows_v):
        used, inv = np.unique(rows_v, return_inverse=True)
        w_used = np.bincount(inv, weights=w, minlength=len(used))
        if len(faces):
            nu = vertex_normals(shape, faces)[used]
            jn = np.hstack([modes.normal_rows(nu, used), np.einsum("pd,pdm->pm", nu, pose_jac[used])])
            info = weighted_gram(jn, w_used)
        else:
            flat = np.concatenate([modes.rows(used), pose_jac[used]], axis=2).reshape(-1, m)
            info = weighted_gram(flat, np.repeat(w_used, 3))
    else:
        info = np.zeros((m, m))
    if lm_pairs is not None:
        jac_lm = np.concatenate([modes.rows(lm_pairs[1]), pose_jac[lm_pairs[1]]], axis=3)
        jl = np.einsum("lk,lkdm->ldm", lm_pairs[2], jac_lm)
        info = info + w_lm * np.einsum("idm,idl->ml", jl, jl)
    prior = np.zeros((m, m))
    prior[:k, :k] = params.prior_weight * np.diag(1.0 / lam)
    prior[k:, k:] = 1e-9 * np.eye(6)  # (almost) flat: the pose is what the data says
    cov = np.linalg.inv(info / s2 + prior)
    per_point = np.zeros(n)
    for axis in range(3):  # only the parameters that move this axis (the error field's are per axis)
        ja = np.hstack([modes.axis_rows(axis), pose_jac[:, axis, :]])
        cols = np.flatnonzero(np.any(ja != 0.0, axis=0))
        ja = ja[:, cols]
        per_point += ((ja @ cov[np.ix_(cols, cols)]) * ja).sum(axis=1)
    return cov[:k, :k], per_point


PLATEAU_STEPS = 3
PLATEAU_SHARE = 1e-3
"""A partial fit without landmarks stops when the target's mean distance from the shape fell by less
than this share over the last ``PLATEAU_STEPS`` steps. Past that point it keeps creeping (0.01–0.02 mm
a step, in one direction) along what the seen part does not pin, the seen part 1 % nearer over 50
steps and the part it completes farther from its truth (docs/history.md, "Partial fits stop
where the seen part stops coming nearer")."""


TANGENTIAL_PULL = 0.1
"""A partial target's pull on the pose along the shape's surface, against 1 along its normal:
small, so the model's misfit on the seen part cannot drag the pose along the surface, not 0,
so a start shifted along a flat part still converges."""


JOINT_DAMPING = 1e-6
"""Marquardt damping of the joint step, relative to each unknown's own curvature (a floor of
1e-12 of the largest): a direction the surface does not pin (a turn about a sphere's centre)
is not moved by rounding noise."""
JOINT_MAX_TURN = 0.2
"""The joint step's largest turn (radians, about 11°); a longer step is shortened whole."""


def _joint_step(pose, b, shape, normals, modes, lam, rows_v, y, w, lm_pairs, w_lm, sigma2, prior_weight):
    """One Gauss-Newton step of the fit's energy (paper eq. 7 with the prior) in the pose's small
    turn ω, its shift δt and the coefficients δb together, every surface correspondence
    point to plane (its distance along the shape's normal) and every landmark point to point.

    The alternating step (a Procrustes pose from point-to-point pairs, then the coefficients)
    holds each model point to its current closest point along the surface too, so a pose that
    must slide along a smooth surface creeps there over many iterations; solved together, the
    slide is taken at once. World mm; ``shape`` and ``normals`` in the model frame."""
    rot = pose.rotation
    x = pose.apply(shape)
    centre = x.mean(axis=0)  # the turn about the shape's centroid: turn and shift decoupled
    x = x - centre
    y = y - centre
    xp = x[rows_v]
    nw = normals[rows_v] @ rot.T  # the shape's normals in the target frame
    r = np.einsum("pd,pd->p", nw, y - xp)
    jb = pose.scale * modes.normal_rows(normals[rows_v], rows_v)  # (R n)·(s R Q) = s n·Q
    jac = np.hstack([np.cross(xp, nw), nw, jb])
    a = (jac * w[:, None]).T @ jac
    g = (jac * w[:, None]).T @ r
    if lm_pairs is not None:
        xl = np.einsum("lk,lkj->lj", lm_pairs[2], x[lm_pairs[1]])
        ql = np.einsum("lk,lkdm->ldm", lm_pairs[2], modes.rows(lm_pairs[1]))  # (L, 3, K) model frame
        jl = np.concatenate([-_skew(xl), np.broadcast_to(np.eye(3), (len(xl), 3, 3)),
                             pose.scale * np.einsum("de,lek->ldk", rot, ql)], axis=2).reshape(-1, a.shape[0])
        rl = (np.asarray(lm_pairs[3], float) - centre - xl).reshape(-1)
        a += w_lm * jl.T @ jl
        g += w_lm * jl.T @ rl
    a /= sigma2
    g /= sigma2
    a[6:, 6:] += prior_weight * np.diag(1.0 / lam)
    g[6:] -= prior_weight * b / lam
    diag = np.diag(a).copy()
    a[np.diag_indices_from(a)] += JOINT_DAMPING * np.maximum(diag, 1e-12 * max(1.0, float(diag.max())))
    d = np.linalg.solve(a, g)
    angle = float(np.linalg.norm(d[:3]))
    if angle > JOINT_MAX_TURN:  # far from the target the linear model of the turn is poor: a shorter step
        d *= JOINT_MAX_TURN / angle
        angle = JOINT_MAX_TURN
    turn = axis_rotation(d[:3], math.degrees(angle)) if angle > 1e-15 else np.eye(3)
    return Pose(turn @ rot, turn @ (pose.translation - centre) + centre + d[3:6], pose.scale), b + d[6:]


def fit_model(model, target: Target, *, params: FitParams | None = None, pose: Pose | None = None,
              partial: bool = False, tangential_pull: float = TANGENTIAL_PULL, points: np.ndarray | None = None,
              progress: ProgressFn = None, cancelled: CancelledFn = None) -> FitResult:
    """Fit ``model`` to ``target``: pose and coefficients under the model's prior.

    Parameters
    ----------
    model : ShapeModel
    target : Target
    params : FitParams
        Noise σ (mm), prior weight η, modes used, iterations, landmark weight, scale, and the pose
        step (``"joint"``: pose and coefficients in one point-to-plane step for a whole surface
        with a rigid pose; otherwise alternately).
    pose : Pose, optional
        Start pose (model → target). Default: from the landmarks when at least 3 match,
        else the identity (the target is in the model's frame, e.g. an instance in its
        object frame).
    partial : bool
        The target covers only part of the shape: only target → model correspondences,
        and the distances are measured over the target's points. With ``model_error``
        the model is augmented by its :class:`ModelErrorField` (the completion's
        posterior then holds what the model cannot represent where the target is
        silent), and the pose follows the target mostly along the shape's normals.
    tangential_pull : float
        A partial target's pull on the pose along the surface, against 1 along the normal
        (1: point to point, fastest from a rough start; default ``TANGENTIAL_PULL``).
    points : (M,) int array, optional
        The model points the target shows (a joint model's structures given, e.g. the femur of
        a knee model): the target is matched to these alone, both ways, and every other point
        is predicted by the model (the posterior mean and SD hold them: a structure predicted
        from the others).

    Returns
    -------
    FitResult
    """
    params = FitParams() if params is None else params
    k = model.n_modes if params.n_modes is None else min(int(params.n_modes), model.n_modes)
    mean = np.asarray(model.mean, float)
    npts = len(mean)
    q = np.asarray(model.modes[:k], float).reshape(k, npts, 3).transpose(1, 2, 0)  # (N, 3, K)
    lam = np.maximum(np.asarray(model.variances[:k], float), 1e-12)
    n_modes = k
    error_field = model_error_field(model) if partial and params.model_error else None
    modes = _ModeBasis(q, None if error_field is None else error_field.fields_mm)
    if error_field is not None:  # the model's error as extra modes of prior variance 1
        lam = np.concatenate([lam, np.ones(3 * modes.r)])
        k = modes.k
    located = model.landmark_locations
    names = list(located.names)
    lm_pairs = None
    if target.landmarks is not None and len(target.landmarks):
        common = [n for n in names if n in target.landmarks.names]
        unknown = [n for n in target.landmarks.names if n not in names]
        if not common:
            known = ", ".join(names) if names else "none"
            raise InputError(f"{target.landmarks.source or 'landmarks'}: none of the landmark names "
                             f"({', '.join(target.landmarks.names[:5])}{'…' if len(target.landmarks) > 5 else ''}) is "
                             f"one the model knows ({known})")
        idx = [names.index(n) for n in common]
        verts = np.asarray(model.faces)[located.triangles[idx]]  # (L, 3) vertex ids
        lm_pairs = (common, verts, located.bary[idx], target.landmarks.subset(common).points_world, unknown)
    if not target.has_surface and lm_pairs is None:
        raise InputError(f"{target.source or 'target'}: nothing to fit to (no surface, points or known landmarks)")
    if pose is None:
        pose = Pose()
        if lm_pairs is not None and len(lm_pairs[0]) >= 3:
            m_lm = np.einsum("lk,lkj->lj", lm_pairs[2], mean[lm_pairs[1]])
            pose = _procrustes(m_lm, lm_pairs[3], np.ones(len(m_lm)), params.scale)
    sigma2 = params.noise_mm ** 2
    b = np.zeros(k)
    shape = mean.copy()
    it, converged, last = 0, False, pose.apply(shape)
    w_lm = params.landmark_weight
    tree_model = None
    shown = np.arange(npts) if points is None else np.unique(np.asarray(points, np.int64))
    # a whole surface with a rigid pose: pose and shape solved together, point to plane
    joint = (params.pose_step == "joint" and target.has_surface and not partial and not params.scale
             and len(model.faces) > 0)
    # a partial target without landmarks: stop when the seen part stops coming nearer (PLATEAU_SHARE)
    plateau, seen_mm = partial and target.has_surface and lm_pairs is None, []
    for it in range(1, params.iterations + 1):
        check_cancelled(cancelled)
        x = pose.apply(shape)
        rows, ys, ws = [], [], []
        if target.has_surface:
            tree_model = cKDTree(x[shown])
            gaps, nearest = tree_model.query(target.samples)  # target → model
            if plateau:
                seen_mm.append(float(gaps.mean()))
            rows.append(shown[nearest])
            ys.append(target.samples)
            ws.append(np.full(len(nearest), 1.0 if partial else 0.5 * len(shown) / max(len(nearest), 1)))
            if not partial:  # model → target
                c, _ = target.closest(x[shown])
                rows.append(shown)
                ys.append(c)
                ws.append(np.full(len(shown), 0.5))
        rows_v = np.concatenate(rows) if rows else np.zeros(0, int)
        y = np.concatenate(ys) if ys else np.zeros((0, 3))
        w = np.concatenate(ws) if ws else np.zeros(0)
        if plateau and len(seen_mm) > PLATEAU_STEPS and (
                seen_mm[-1 - PLATEAU_STEPS] - seen_mm[-1] < PLATEAU_SHARE * seen_mm[-1]):
            it, converged = it - 1, True  # the shape as it stands: its correspondences just found
            break
        normals = vertex_normals(shape, model.faces) if len(model.faces) else None
        if joint:  # pose and coefficients in one point-to-plane step (see _joint_step)
            pose, b = _joint_step(pose, b, shape, normals, modes, lam, rows_v, y, w, lm_pairs, w_lm, sigma2,
                                  params.prior_weight)
        else:
            # pose from the current shape's corresponding points (and landmarks)
            src, dst, wp = shape[rows_v], y, w
            if partial and normals is not None and len(rows_v) and tangential_pull != 1.0:
                # a partial target pins the pose least: its points pull mostly along the shape's
                # normal, as in the coefficients' step (TANGENTIAL_PULL along the surface)
                nrm_p = normals[rows_v]
                gap = pose.inverse(y) - src
                along = np.einsum("pd,pd->p", nrm_p, gap)[:, None] * nrm_p
                dst = pose.apply(src + along + tangential_pull * (gap - along))
            if lm_pairs is not None:
                lm_shape = np.einsum("lk,lkj->lj", lm_pairs[2], shape[lm_pairs[1]])
                src = np.concatenate([src, lm_shape])
                dst = np.concatenate([dst, lm_pairs[3]])
                wp = np.concatenate([wp, np.full(len(lm_shape), w_lm)])
            if len(src) >= 3:
                pose = _procrustes(src, dst, wp, params.scale)
            # coefficients: the posterior of the linear model in the model frame. A surface
            # correspondence observes the distance along the shape's normal only (point to
            # plane): where it lies along the surface is not observed, so sliding is neither
            # penalised nor mistaken for information (calibrated posterior, no tangential bias)
            yl = pose.inverse(y) - mean[rows_v]  # (P, 3)
            if normals is not None:  # summed per model point: n·Q once per point used
                used, inv = np.unique(rows_v, return_inverse=True)
                qn = modes.normal_rows(normals[used], used)  # (U, K): n·Q
                w_used = np.bincount(inv, weights=w, minlength=len(used))
                r_used = np.bincount(inv, weights=w * np.einsum("pd,pd->p", normals[rows_v], yl), minlength=len(used))
                a = weighted_gram(qn, w_used)
                rhs = qn.T @ r_used
            else:
                qa = modes.rows(rows_v)  # (P, 3, K)
                a = np.einsum("p,pdk,pdl->kl", w, qa, qa)
                rhs = np.einsum("p,pdk,pd->k", w, qa, yl)
            if lm_pairs is not None:
                qlm = np.einsum("lk,lkdm->ldm", lm_pairs[2], modes.rows(lm_pairs[1]))
                mlm = np.einsum("lk,lkj->lj", lm_pairs[2], mean[lm_pairs[1]])
                rlm = pose.inverse(lm_pairs[3]) - mlm
                a += w_lm * np.einsum("idk,idm->km", qlm, qlm)
                rhs += w_lm * np.einsum("idk,id->k", qlm, rlm)
            s2 = sigma2 / pose.scale ** 2
            precision = a / s2 + params.prior_weight * np.diag(1.0 / lam)
            b = spd_solve(precision + 1e-12 * np.eye(k) * max(1.0, float(np.abs(precision).max())), rhs / s2)
        shape = mean + modes.apply(b)
        x_new = pose.apply(shape)
        move = float(np.sqrt(((x_new - last) ** 2).sum(axis=1).mean()))
        last = x_new
        report(progress, it / params.iterations, f"fit step {it}: {move:.4f} mm")
        if move < params.tolerance_mm:
            converged = True
            break
    cov_b, per_point = _posterior(modes, shape, model.faces, rows_v, w, pose, lm_pairs, w_lm, sigma2, params, lam, k)
    if params.model_error and error_field is None:  # what the model cannot represent, added
        extra = model_error_variance(model, k)
        if extra is not None:
            per_point = per_point + extra
    sd = pose.scale * np.sqrt(np.maximum(per_point, 0.0))
    x = pose.apply(shape)
    if target.has_surface:
        if partial:
            dist = cKDTree(x[shown]).query(target.samples)[0]
        else:
            dist = target.closest(x[shown])[1]
        mean_d, max_d = float(dist.mean()), float(dist.max())
    else:
        mean_d = max_d = float("nan")
    residuals = {}
    if lm_pairs is not None:
        lm_fit = np.einsum("lk,lkj->lj", lm_pairs[2], x[lm_pairs[1]])
        residuals = {n: float(r) for n, r in zip(lm_pairs[0], np.linalg.norm(lm_fit - lm_pairs[3], axis=1))}
        if not target.has_surface:
            mean_d = float(np.mean(list(residuals.values())))
            max_d = float(np.max(list(residuals.values())))
    b, lam, cov_b, k = b[:n_modes], lam[:n_modes], cov_b[:n_modes, :n_modes], n_modes
    z = b / np.sqrt(lam)
    d2 = float(np.sum(z * z))
    return FitResult(points=x, coefficients=z, b=b, pose=pose, posterior_sd_mm=sd, mahalanobis=math.sqrt(d2),
                     p_value=float(chdtrc(k, d2)) if k else 1.0, mean_distance_mm=mean_d, max_distance_mm=max_d,
                     landmark_residuals_mm=residuals, iterations=it, converged=converged, n_modes=k,
                     b_covariance=cov_b)


FLOOR_TURN_DEG = 4.0
FLOOR_SHIFT_MM = 2.0
FLOOR_ITERATIONS = 80


#: The rotation group's nearest starts (other than the fit's pose, by more than twice
#: ``FLOOR_TURN_DEG``) the floor is also searched from.
FLOOR_ROTATIONS = 3
#: Such a start is first fitted this many steps, and to the end only if it is then within this
#: factor of the floor found around the fit (a start in another basin stays several mm away).
FLOOR_PROBE_ITERATIONS = 12
FLOOR_PROBE_FACTOR = 1.5


def turn_angle_deg(a: np.ndarray, b: np.ndarray | None = None) -> float:
    """The angle (degrees) of the rotation ``a`` (3, 3), or of the rotation between ``a`` and ``b``.

    >>> round(turn_angle_deg(axis_rotation(np.array([0.0, 0.0, 1.0]), 30.0)), 6)
    30.0
    """
    turn = a if b is None else a @ np.asarray(b).T
    return float(np.degrees(np.arccos(np.clip((np.trace(turn) - 1.0) / 2.0, -1.0, 1.0))))


def fit_floor(model, target: Target, pose: Pose, *, partial: bool = False, points: np.ndarray | None = None,
              scale: bool = False, cancelled: CancelledFn = None) -> dict:
    """The best the model can do for ``target``: its distance (mm) from the model's span.

    Iterative closest points within the span without the prior (η → 0, every mode), started from
    ``pose``, from 12 starts around it (turned by ±``FLOOR_TURN_DEG`` about each axis and moved by
    ±``FLOOR_SHIFT_MM`` along each), and from the ``FLOOR_ROTATIONS`` nearest other rotations of the
    pose search (:func:`start_poses`, screened as :func:`fit_any_pose` screens them), so that the
    floor is the model's, not the basin the fit fell into (each followed past
    ``FLOOR_PROBE_ITERATIONS`` steps only while within ``FLOOR_PROBE_FACTOR`` of the floor around
    the fit); up to ``FLOOR_ITERATIONS`` steps each,
    a similarity pose with ``scale``; the closest fit wins. The distance is measured as the fit's
    (:class:`FitResult` ``mean_distance_mm``). Slow and careful: a yardstick for the fit, not a fit
    to use (it has no prior, so it overfits noise).

    Returns
    -------
    dict with ``floor_mm`` (mean), ``floor_max_mm``, ``starts``, ``from`` (``"the fit"``, or the
    rotation of the pose search whose start won), ``method``.
    """
    params = FitParams(prior_weight=1e-9, iterations=FLOOR_ITERATIONS, tolerance_mm=1e-3, model_error=False,
                       noise_mm=1.0, scale=bool(scale))
    starts = [("the fit", pose)]
    centre = pose.apply(np.asarray(model.mean, float)).mean(axis=0)
    for axis in range(3):
        for sign in (1.0, -1.0):
            turn = axis_rotation(np.eye(3)[axis], sign * FLOOR_TURN_DEG)
            starts.append(("the fit", Pose(turn @ pose.rotation, turn @ (pose.translation - centre) + centre,
                                           pose.scale)))
            starts.append(("the fit", Pose(pose.rotation, pose.translation + sign * FLOOR_SHIFT_MM * np.eye(3)[axis],
                                           pose.scale)))
    mean = np.asarray(model.mean, float) if points is None else np.asarray(model.mean, float)[points]
    searched = start_poses(model, target, partial=partial, points=points)
    taken = [pose.rotation]
    for i, refined, _d in coarse_ranked(mean, target, [p for _n, p in searched], partial=partial):
        if len(taken) > FLOOR_ROTATIONS:
            break
        if all(turn_angle_deg(refined.rotation, q) > 2.0 * FLOOR_TURN_DEG for q in taken):
            taken.append(refined.rotation)
            starts.append((searched[i][0], rigid_screen(mean, target, refined, partial=partial)[0]))
    best, won = None, "the fit"
    probe = replace(params, iterations=FLOOR_PROBE_ITERATIONS)
    for name, start in starts:
        check_cancelled(cancelled)
        if name != "the fit":  # another rotation: followed to the end only if it is heading for the floor
            first = fit_model(model, target, params=probe, pose=start, partial=partial, points=points,
                              tangential_pull=1.0)
            if first.mean_distance_mm > FLOOR_PROBE_FACTOR * best.mean_distance_mm:
                continue
        fit = fit_model(model, target, params=params, pose=start, partial=partial, points=points,
                        tangential_pull=1.0)
        if best is None or fit.mean_distance_mm < best.mean_distance_mm - 1e-12:
            best, won = fit, name
    return {"floor_mm": float(best.mean_distance_mm), "floor_max_mm": float(best.max_distance_mm),
            "starts": len(starts), "from": won,
            "method": f"closest points within the model's span without the prior, every mode, "
                      f"{'a similarity pose, ' if scale else ''}{len(starts)} starts: 13 around the fit "
                      f"(±{FLOOR_TURN_DEG:g}°, ±{FLOOR_SHIFT_MM:g} mm) and the pose search's "
                      f"{len(starts) - 13} nearest other rotations, up to {FLOOR_ITERATIONS} steps each"}


def outlier_limit(n_modes: int, probability: float = 0.99) -> float:
    """The Mahalanobis distance above which a fit on ``n_modes`` modes is an outlier: the
    square root of the chi-square quantile ``probability`` (``inf`` without modes)."""
    return math.sqrt(float(chdtri(n_modes, 1.0 - probability))) if n_modes else math.inf


def _principal_axes(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid and principal axes (columns, by descending variance) of (M, 3) points."""
    c = points.mean(axis=0)
    w, v = np.linalg.eigh(np.cov((points - c).T))
    return c, v[:, np.argsort(w)[::-1]]


def axis_rotation(axis: np.ndarray, degrees: float) -> np.ndarray:
    """The turn by ``degrees`` about ``axis`` (any length), as a matrix (Rodrigues)."""
    a = axis / np.linalg.norm(axis)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    t = np.radians(degrees)
    return np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * (k @ k)


def _axis_rotations() -> tuple[np.ndarray, ...]:
    """The 24 proper rotations that map the coordinate axes onto themselves (signed permutation
    matrices of determinant 1), the identity first, in a fixed order."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            r = np.zeros((3, 3))
            r[np.arange(3), perm] = signs
            if np.linalg.det(r) > 0:
                out.append(r)
    return tuple(out)


#: Every way two sets of principal axes can be put onto each other by a rotation: the rotation
#: group of the axes (the octahedral group, 24 elements), the identity first.
AXIS_ROTATIONS = _axis_rotations()


def _rotation_label(r: np.ndarray) -> str:
    """``r`` of :data:`AXIS_ROTATIONS` by where it sends the model's principal axes 1, 2, 3 (the
    target's, signed): ``"axes +1 +2 +3"`` is the principal axes put on each other."""
    return "axes " + " ".join(f"{'+' if r[j, i] > 0 else '-'}{j + 1}" for i in range(3) for j in range(3) if r[j, i])


def start_poses(model, target: Target, *, frame_pose: Pose | None = None, partial: bool = False,
                points: np.ndarray | None = None) -> list[tuple[str, Pose]]:
    """Candidate start poses (model frame -> target frame, mm) for a target in any coordinates.

    First the pose the target's object frame gives (``frame``), when known, and the model's
    axes moved onto the target's centroid (``model axes``: a target in the model's
    coordinates); then the mean shape's principal axes put on the target's in each of the 24
    ways a rotation can (:data:`AXIS_ROTATIONS`: every axis onto every axis, either way round;
    ``axes +1 +2 +3`` … by where the mean's axes 1, 2, 3 go), so that a target whose second
    moments are nearly equal about two axes (a patella, a vertebral body) is started from each
    swap. A ``partial`` target (part of the shape, whose centroid is not the shape's) also gets
    each of those slid along its longest axis so that its ends meet either end of the mean shape
    (``… slid ±d mm``).
    """
    out = [("frame", frame_pose)] if frame_pose is not None else []
    if len(target.samples) < 4:
        return out
    mean = np.asarray(model.mean, float) if points is None else np.asarray(model.mean, float)[points]
    cm, am = _principal_axes(mean)
    ct, at = _principal_axes(np.asarray(target.samples, float))
    out.append(("model axes", Pose(np.eye(3), ct - cm)))  # the target in the model's axes, moved
    seen = [p.rotation for _n, p in out]
    slide = 0.0
    if partial:  # how far the part's middle can sit from the shape's, along the longest axes
        extent_m = np.ptp((mean - cm) @ am[:, 0])
        extent_t = np.ptp((np.asarray(target.samples, float) - ct) @ at[:, 0])
        slide = max(0.0, 0.5 * float(extent_m - extent_t))
    shifts = (0.0, -slide, slide) if slide > 0 else (0.0,)
    if np.linalg.det(at) * np.linalg.det(am) < 0:  # the eigenvector bases differ in handedness
        at = at * np.array([1.0, 1.0, -1.0])
    for q in AXIS_ROTATIONS:
        r = at @ q @ am.T
        if any(np.abs(r - s).max() < 1e-6 for s in seen):
            continue
        seen.append(r)
        name = _rotation_label(q)
        for shift in shifts:
            label = name + (f" slid {shift:+.0f} mm" if shift else "")
            out.append((label, Pose(r, ct - r @ cm + shift * at[:, 0])))
    return out


def rigid_screen(mean: np.ndarray, target: Target, pose: Pose, *, partial: bool, iterations: int = 15,
                  samples: int = 2000) -> tuple[Pose, float]:
    """A few rigid ICP steps of ``mean`` (N, 3 mm, the model frame) onto ``target`` from ``pose``:
    the refined pose and its mean distance (mm), for ranking start poses cheaply."""
    tgt = np.asarray(target.samples, float)
    tgt = tgt[:: max(1, len(tgt) // samples)]
    src = mean[:: max(1, len(mean) // samples)]
    for _ in range(iterations):
        x = pose.apply(src)
        if partial:  # each target point to its nearest model point
            _, j = cKDTree(x).query(tgt)
            a, b = src[j], tgt
        else:  # both ways: model points to the target, target points to the model
            c, _ = target.closest(x)
            _, j = cKDTree(x).query(tgt)
            a, b = np.vstack([src, src[j]]), np.vstack([c, tgt])
        pose = _procrustes(a, b, np.ones(len(a)), False)
    x = pose.apply(src)
    d = cKDTree(x).query(tgt)[0] if partial else target.closest(x)[1]
    return pose, float(np.mean(d))


#: The starts' first screen (:func:`coarse_screen`): rigid ICP on every k-th point of the mean and
#: of the target (about this many each), this many steps, closest points by k-d tree; the
#: ``SCREEN_KEEP`` nearest go on to :func:`rigid_screen`.
COARSE_SAMPLES = 600
COARSE_ITERATIONS = 8
SCREEN_KEEP = 6


def coarse_screen(mean: np.ndarray, target: Target, poses, *, partial: bool) -> list[tuple[Pose, float]]:
    """A first, cheap screen of many start poses: a few rigid ICP steps of every k-th point of
    ``mean`` (N, 3 mm, the model frame) onto every k-th of the target's samples (about
    :data:`COARSE_SAMPLES` of each, closest points between the samples), from each pose of
    ``poses``. Returns each refined pose with its mean distance (mm): both ways for a whole
    target, from the target's points for a ``partial`` one."""
    tgt = np.asarray(target.samples, float)
    tgt = tgt[:: max(1, len(tgt) // COARSE_SAMPLES)]
    src = np.asarray(mean, float)[:: max(1, len(mean) // COARSE_SAMPLES)]
    tree = cKDTree(tgt)
    out = []
    for pose in poses:
        for _ in range(COARSE_ITERATIONS):
            x = pose.apply(src)
            _, j = cKDTree(x).query(tgt)
            if partial:
                a, b = src[j], tgt
            else:
                _, i = tree.query(x)
                a, b = np.vstack([src, src[j]]), np.vstack([tgt[i], tgt])
            pose = _procrustes(a, b, np.ones(len(a)), False)
        x = pose.apply(src)
        d_target = cKDTree(x).query(tgt)[0].mean()
        out.append((pose, float(d_target if partial else 0.5 * (d_target + tree.query(x)[0].mean()))))
    return out


def coarse_ranked(mean: np.ndarray, target: Target, poses, *, partial: bool) -> list[tuple[int, Pose, float]]:
    """:func:`coarse_screen` of ``poses``, nearest first: (index into ``poses``, refined pose,
    mean distance in mm), ties by index."""
    screened = coarse_screen(mean, target, poses, partial=partial)
    return [(i, *screened[i]) for i in sorted(range(len(screened)), key=lambda i: (screened[i][1], i))]


PRIORITY_TOLERANCE = 1.1

#: The candidates are first fitted this many steps; only those then within ``SEARCH_PROBE_FACTOR`` of the
#: nearest probe are fitted to the end, from their start again (so each result is the fit the candidate
#: always gave; a probe that converged is that fit). A start in another basin stays millimetres away.
SEARCH_PROBE_ITERATIONS = 15
SEARCH_PROBE_FACTOR = 1.5


#: Turns (degrees) about the given part's long axis, and slides (mm) along it, at which a partial
#: fit is fitted again.
FREEDOM_TURNS_DEG = (-180.0, -135.0, -90.0, -60.0, -40.0, -20.0, 20.0, 40.0, 60.0, 90.0, 135.0)
FREEDOM_SLIDES_MM = (-40.0, -20.0, -10.0, 10.0, 20.0, 40.0)
#: A turn or start "fits nearly as well" within this share of the chosen fit's distance (at least
#: :data:`FREEDOM_MIN_MM`).
FREEDOM_SHARE = 0.1
FREEDOM_MIN_MM = 0.05


def _free_range(steps, fit_at, near) -> tuple[list[float], dict]:
    """Walk out from step 0 each way through ``steps`` (signed), fitting at each (``fit_at(step)``)
    until a fit is not ``near(step, fit)``. Returns ([lowest, highest] step reached, {step: fit})."""
    fits, bounds = {}, []
    for side in (sorted((t for t in steps if t < 0), reverse=True), sorted(t for t in steps if t > 0)):
        reached = 0.0
        for t in side:
            fits[t] = fit_at(t)
            if not near(t, fits[t]):
                break
            reached = t
        bounds.append(reached)
    return bounds, fits


def pose_freedom(model, target: Target, chosen: FitResult, *, params: FitParams, others=(), points=None,
                 cancelled: CancelledFn = None) -> tuple[dict, np.ndarray]:
    """How far a partial target leaves its pose free, and what that does to the missing part.

    The chosen fit is turned about the given part's long axis (its points' principal axis,
    through their centre) by each of :data:`FREEDOM_TURNS_DEG`, and slid along it by each of
    :data:`FREEDOM_SLIDES_MM`, and fitted again (pose and shape, ``params`` as the search's),
    walking out from the chosen pose each way until a fit lies beyond the tolerance.
    The turns and slides contiguous with the chosen pose whose fit lies within the tolerance
    (``FREEDOM_SHARE`` of the chosen distance, at least ``FREEDOM_MIN_MM``) and stays turned or
    slid at least half way (a fit that goes back is pinned by the part) are the pose's free
    ranges (a shaft leaves both: a round section turns, a straight one slides); those fits, with
    the search's other candidates (``others``: fits of other starts) within the tolerance, are
    the poses that fit nearly as well.

    Returns
    -------
    freedom : dict
        ``axis`` (unit, target frame), ``centre`` (mm), ``range_deg`` and ``range_mm``
        ([lowest, highest] turn and slide within the tolerance), ``width_deg``, ``width_mm``,
        ``distance_mm`` (the chosen fit's, the search's measure), ``tolerance_mm``, ``turns``
        and ``slides`` ({step: distance mm} of the steps fitted), ``candidates`` (how many fits entered the
        spread), ``spread_mm`` ({mean, max} over the points).
    spread : (N,) ndarray
        Per point, the RMS distance (mm) of its places in those fits from its place in the chosen
        fit (the shape reported): the pose's share of the uncertainty (0 where every candidate
        puts it alike).
    """
    pts = np.asarray(target.samples, float)
    centre, vecs = _principal_axes(pts)
    axis = vecs[:, 0] * np.sign(vecs[np.argmax(np.abs(vecs[:, 0])), 0])  # eigh's sign is arbitrary
    base = float(chosen.mean_distance_mm)
    tol = max(FREEDOM_MIN_MM, FREEDOM_SHARE * base)
    rot, shift = chosen.pose.rotation, chosen.pose.translation

    def refit(pose):
        check_cancelled(cancelled)
        return fit_model(model, target, params=params, pose=pose, partial=True, tangential_pull=1.0, points=points,
                         cancelled=cancelled)

    def turn(t):
        r = axis_rotation(axis, t)
        return refit(Pose(r @ rot, r @ (shift - centre) + centre, chosen.pose.scale))

    def turned_by(f) -> float:  # the refit's own turn about the axis from the chosen pose (degrees)
        rel = Rotation.from_matrix(f.pose.rotation @ rot.T).as_rotvec()
        return float(np.degrees(rel @ axis))

    def slid_by(f) -> float:  # the refit's own slide along the axis (mm)
        return float((np.asarray(f.points, float).mean(axis=0) - np.asarray(chosen.points, float).mean(axis=0)) @ axis)

    # a step counts when its refit fits within the tolerance AND stays where it was put (at least half
    # way): a fit that turns or slides back is pinned by the given part, not free
    range_deg, turned = _free_range(FREEDOM_TURNS_DEG, turn, lambda t, f: float(f.mean_distance_mm) <= base + tol
                                    and turned_by(f) * t >= 0.5 * t * t)
    range_mm, slid = _free_range(FREEDOM_SLIDES_MM, lambda mm: refit(Pose(rot, shift + mm * axis, chosen.pose.scale)),
                                 lambda t, f: float(f.mean_distance_mm) <= base + tol and slid_by(f) * t >= 0.5 * t * t)
    turns = {t: float(f.mean_distance_mm) for t, f in turned.items()}
    slides = {t: float(f.mean_distance_mm) for t, f in slid.items()}
    members = [chosen] + [f for t, f in turned.items() if range_deg[0] <= t <= range_deg[1]]
    members += [f for t, f in slid.items() if range_mm[0] <= t <= range_mm[1]]
    members += [f for f in others if float(f.mean_distance_mm) <= base + tol]
    places = np.stack([np.asarray(f.points, float) for f in members])
    # from the chosen fit's places (the shape reported), not from the candidates' mean: a place
    # equally likely anywhere on a circle of radius r is 2r from the reported one at worst, √2 r RMS
    spread = np.sqrt(((places - places[0]) ** 2).sum(axis=2).mean(axis=0))
    freedom = {"axis": [float(x) for x in axis], "centre": [float(x) for x in centre], "range_deg": range_deg,
               "width_deg": range_deg[1] - range_deg[0], "range_mm": range_mm, "width_mm": range_mm[1] - range_mm[0],
               "distance_mm": base, "tolerance_mm": tol, "turns": {f"{t:g}": d for t, d in sorted(turns.items())},
               "slides": {f"{t:g}": d for t, d in sorted(slides.items())}, "candidates": len(members),
               "spread_mm": {"mean": float(spread.mean()), "max": float(spread.max())}}
    return freedom, spread


def fit_any_pose(model, target: Target, *, params: FitParams | None = None, frame_pose: Pose | None = None,
                 partial: bool = False, keep: int = 3, points: np.ndarray | None = None, size_check: bool = False,
                 progress: ProgressFn = None, cancelled: CancelledFn = None) -> tuple[FitResult, dict]:
    """:func:`fit_model` for a target in any pose: the pose search, then the fit.

    Every start of :func:`start_poses` (the rotation group of the principal axes, and the
    landmarks' pose when at least 3 of the model's landmarks are given) is refined by rigid ICP of
    the mean shape, first coarsely (:func:`coarse_screen`), the nearest ``SCREEN_KEEP`` again
    (:func:`rigid_screen`); the ``keep`` closest are fitted (pose and shape: first a probe of
    ``SEARCH_PROBE_ITERATIONS`` steps, to the end those within ``SEARCH_PROBE_FACTOR`` of the nearest
    probe) and the fit closest to the target wins.

    ``size_check``: a rigid fit of a whole target (not ``partial``, all structures) is fitted again
    with a similarity pose from its own; the result's ``similarity`` holds that fit's distance,
    scale and Mahalanobis distance (:func:`~ssm_addon.fitting.verdict.judge_fit` says when it is
    much closer: the target's size lies outside the model's).

    Returns
    -------
    (FitResult, dict with ``starts``: name, screened distance (mm), the probe's distance after
    ``SEARCH_PROBE_ITERATIONS`` steps (mm) where probed, fitted distance (mm) where fitted; and
    ``chosen``: the winning start's name)
    """
    params = FitParams() if params is None else params
    mean = np.asarray(model.mean, float) if points is None else np.asarray(model.mean, float)[points]
    starts = start_poses(model, target, frame_pose=frame_pose, partial=partial, points=points)
    names = model.landmark_locations.names
    if target.landmarks is not None and len([n for n in target.landmarks.names if n in names]) >= 3:
        starts.insert(0, ("landmarks", None))
    if not target.has_surface or not starts:
        result = fit_model(model, target, params=params, pose=frame_pose, partial=partial, points=points,
                           progress=progress, cancelled=cancelled)
        return result, {"starts": [], "chosen": "landmarks" if frame_pose is None else "frame"}
    # the starts the target's own coordinates give are fitted whatever the screening says,
    # and kept unless a searched pose fits PRIORITY_TOLERANCE times closer (a partial or
    # near-symmetric target fits several poses almost equally well)
    priority = {n for n, _p in starts if n in ("landmarks", "frame", "model axes")}
    # every start screened coarsely; the nearest SCREEN_KEEP and the priority ones again, closer
    searched = [(n, p) for n, p in starts if p is not None and n not in priority]
    ranked = coarse_ranked(mean, target, [p for _n, p in searched], partial=partial)
    coarse_mm = {searched[i][0]: d for i, _p, d in ranked}
    again = {searched[i][0] for i, _p, _d in ranked[:SCREEN_KEEP]}
    screened = []
    for name, pose in starts:
        check_cancelled(cancelled)
        if pose is None:  # the landmarks' pose: fit_model finds it
            screened.append((name, None, float("-inf")))
        elif name in priority or name in again:
            refined, dist = rigid_screen(mean, target, pose, partial=partial)
            screened.append((name, refined, dist))
    report(progress, 0.05, f"pose search: {len(searched)} rotations screened, {len(screened)} refined")
    first = [i for i, (n, _p, _d) in enumerate(screened) if n in priority]
    rest = sorted((i for i in range(len(screened)) if i not in first), key=lambda i: (screened[i][2], i))[:keep]
    order = first + rest
    # a partial target's candidates are fitted point to point (the fastest from a rough start)
    # and without the model-error field (the costly part of a completion), the chosen one again
    # as fit_model would from its pose; a whole surface's by params' pose step, once
    search = replace(params, model_error=False) if partial and params.model_error else params
    probes = {}
    if len(order) > 1 and search.iterations > SEARCH_PROBE_ITERATIONS:
        probe = replace(search, iterations=SEARCH_PROBE_ITERATIONS)
        for n, i in enumerate(order):
            name, pose, _d = screened[i]
            probes[name] = fit_model(model, target, params=probe, pose=pose, partial=partial, tangential_pull=1.0,
                                     points=points, cancelled=cancelled)
            report(progress, 0.05 + 0.3 * (n + 1) / len(order), f"start {name}: {probes[name].mean_distance_mm:.3f} mm "
                   f"after {probes[name].iterations} steps")
        nearest = min(float(r.mean_distance_mm) for r in probes.values())
        order = [i for i in order if probes[screened[i][0]].mean_distance_mm <= SEARCH_PROBE_FACTOR * nearest]
    probed = {n: float(r.mean_distance_mm) for n, r in probes.items()}
    results = {}
    for n, i in enumerate(order):
        name, pose, _d = screened[i]
        if name in probes and probes[name].converged:  # the probe is the whole fit
            results[name] = probes[name]
        else:
            results[name] = fit_model(model, target, params=search, pose=pose, partial=partial, tangential_pull=1.0,
                                      points=points, cancelled=cancelled)
        report(progress, 0.35 + 0.6 * (n + 1) / len(order), f"start {name}: {results[name].mean_distance_mm:.3f} mm")
    fitted = {n: float(r.mean_distance_mm) for n, r in results.items()}
    chosen = min(fitted, key=lambda n: (fitted[n], list(fitted).index(n)))
    own = [n for n in fitted if n in priority]
    if own:
        mine = min(own, key=lambda n: (fitted[n], own.index(n)))
        if fitted[mine] <= PRIORITY_TOLERANCE * fitted[chosen] + 1e-9:
            chosen = mine
    best = results[chosen]
    freedom = None
    if partial and params.pose_freedom:
        report(progress, 0.9, "pose freedom: the fit turned about the given part's long axis")
        freedom, spread = pose_freedom(model, target, best, params=search, points=points, cancelled=cancelled,
                                       others=[r for n, r in results.items() if n != chosen])
    if partial:
        best = fit_model(model, target, params=params, pose=best.pose, partial=True, points=points, cancelled=cancelled)
    if freedom is not None:  # the pose's share of the uncertainty joins the shape's
        best = replace(best, posterior_sd_mm=np.sqrt(best.posterior_sd_mm ** 2 + spread ** 2), pose_freedom=freedom)
    if size_check and not params.scale and not partial and points is None:
        report(progress, 0.95, "size: the fit again with a similarity pose")
        similar = fit_model(model, target, params=replace(params, scale=True), pose=best.pose, cancelled=cancelled)
        best = replace(best, similarity={"mean_distance_mm": float(similar.mean_distance_mm),
                                         "scale": float(similar.pose.scale), "mahalanobis": float(similar.mahalanobis)})
    screened_mm = {n: (None if not np.isfinite(d) else d) for n, _p, d in screened}
    doc = {"starts": [{"name": n, "coarse_mm": coarse_mm.get(n), "screened_mm": screened_mm.get(n),
                       "probed_mm": probed.get(n), "fitted_mm": fitted.get(n)} for n, _p in starts], "chosen": chosen}
    return best, doc
