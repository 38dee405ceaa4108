"""The statistical shape model of paper section 5: mean, eigenmodes, new shapes, files.

Shapes are point sets in correspondence: instance i is an (N, 3) array of points in its
object frame (mm), the parameter vector p_i of the paper is that array flattened to
length 3N in the order (x1, y1, z1, x2, ...). The model frame is the object frame
(paper 5: "no other normalization ... has been applied"); generalized Procrustes
alignment (rigid, or similarity with scale) is available as an option.

Eigen-decomposition. With P the 3N x n matrix of centred shape vectors, the covariance
of eq. (5) is S = P P^T / n. Its non-zero eigenpairs are obtained from the n x n Gram
problem of eq. (6): S~ = P^T P / n has the same non-zero eigenvalues, and the
eigenvectors are q_i = P q~_i / |P q~_i|. This costs O(n^2 3N) instead of O((3N)^3)
and is the natural choice for n << 3N (31 vertebrae of ~600 points in the paper, up to
1,000 instances of 5,000 points here); with more instances than coordinates (a biobank
of 10,000 shapes of 600 points) the 3N x 3N covariance itself is the smaller problem and is
used instead (``solver="auto"``); the raw Gram matrix is also what makes
leave-one-out generalization cheap (see :mod:`ssm_addon.model.metrics`). At most n - 1
eigenvalues are non-zero (the data are centred); modes whose eigenvalue is zero to
rounding are dropped. Each mode's sign is fixed so that its largest-magnitude component
is positive, which makes the model deterministic.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import cholesky, solve_triangular

from ..base.errors import InputError, check_cancelled
from ..base.params import ALIGNMENTS
from ..base.progress import report
from ..base.records import jsonable, versions
from ..meshutil import LandmarkLocations, faces_within

# ---------------------------------------------------------------------------------------
# The model
# ---------------------------------------------------------------------------------------
#: A mode whose variance is at most this share of the largest is empty (numerically zero): float32
#: files and rank-deficient covariances leave such modes, which move nothing.
EMPTY_MODE_SHARE = 1e-7


def own_side_instances(model) -> np.ndarray:
    """Row indices of the training instances whose world points (``instance_points_world``) are in
    the model's side: all but those mirrored into it (``params["mirrored"]``, a left-right set)."""
    mirrored = set((getattr(model, "params", None) or {}).get("mirrored") or ())
    names = [str(n) for n in getattr(model, "instance_names", ())]
    return np.array([i for i, n in enumerate(names) if n not in mirrored], dtype=np.int64)


def drop_empty_modes(model: ShapeModel) -> tuple[ShapeModel, int]:
    """The model without its modes of (numerically) zero variance, and how many there were.

    A mode is empty when its variance λ_k is at most :data:`EMPTY_MODE_SHARE` of the largest:
    its shape key would do nothing, and in a fit its weight would divide by zero (a
    Mahalanobis distance counting it would say nothing). ``params`` records the count
    (``dropped_empty_modes``).
    """
    lam = np.asarray(model.variances, float)
    keep = lam > EMPTY_MODE_SHARE * max(float(lam.max(initial=0.0)), 0.0)
    dropped = int((~keep).sum())
    if not dropped:
        return model, 0
    params = {**model.params, "dropped_empty_modes": dropped}
    return dataclasses.replace(model, modes=model.modes[keep], variances=lam[keep], params=params), dropped


# shapes aligned and projected together by ShapeModel.project_all (bounded temporaries)
PROJECT_BLOCK = 1000


@dataclass(frozen=True, eq=False)
class ShapeModel:
    """A point distribution model (paper section 5).

    Attributes
    ----------
    mean : (N, 3) float ndarray
        Mean shape p̄ of eq. (4), model frame, mm.
    faces : (F, 3) int ndarray
        Triangles of the template (shared by every instance).
    modes : (K, N, 3) float ndarray
        Eigenmodes q_k of the covariance (eq. 5), orthonormal as vectors of length 3N.
    variances : (K,) float ndarray
        Eigenvalues λ_k (mm²), descending, all > 0.
    instance_names : (n,) str ndarray
        Names of the training instances.
    instance_points : (n, N, 3) float ndarray
        Training shapes in the model frame (after alignment if any), mm.
    instance_points_world : (n, N, 3) float ndarray
        The same points in each instance's input (world) coordinates, mm.
    params : dict
        JSON-serialisable parameters, versions, timings and derived numbers
        (``total_variance_mm2``: trace of S, the denominator of eq. 8).
    structure_names : tuple of str
        A joint model's structures (:mod:`ssm_addon.pipeline.joint`), in point order; empty for
        a model of one structure.
    structure_offsets : (S + 1,) int ndarray or None
        Structure s holds points ``structure_offsets[s]:structure_offsets[s + 1]`` of ``mean``,
        ``modes`` and the instance points; ``faces`` index the concatenated points.

    Equality is identity (the arrays make ``==`` ambiguous); compare arrays explicitly.
    """

    mean: np.ndarray
    faces: np.ndarray
    modes: np.ndarray
    variances: np.ndarray
    instance_names: np.ndarray
    instance_points: np.ndarray
    instance_points_world: np.ndarray
    params: dict = field(default_factory=dict)
    structure_names: tuple = ()
    structure_offsets: np.ndarray | None = None

    def structure_slice(self, name: str) -> slice:
        """The points of structure ``name`` (a joint model)."""
        if name not in self.structure_names:
            raise InputError(f"model: no structure {name!r} (structures: {', '.join(self.structure_names) or 'none'})")
        i = list(self.structure_names).index(name)
        return slice(int(self.structure_offsets[i]), int(self.structure_offsets[i + 1]))

    def structure_faces(self, name: str) -> np.ndarray:
        """The triangles of structure ``name`` (a joint model), indexing its own points
        (``structure_slice``): those of ``faces`` wholly inside it, shifted to start at 0."""
        sl = self.structure_slice(name)
        return faces_within(self.faces, sl.start, sl.stop)

    def structure_points(self, names) -> np.ndarray:
        """Indices of the points of the structures ``names`` (a joint model), in model order."""
        return np.concatenate([np.arange(self.n_points)[self.structure_slice(n)] for n in names]) \
            if len(names) else np.zeros(0, dtype=np.int64)

    # -- sizes -------------------------------------------------------------------------
    @property
    def n_modes(self) -> int:
        """Number K of modes kept."""
        return int(self.variances.shape[0])

    @property
    def n_points(self) -> int:
        """Number N of surface points."""
        return int(self.mean.shape[0])

    @property
    def n_instances(self) -> int:
        """Number n of training instances."""
        return int(self.instance_points.shape[0])

    @property
    def standard_deviations(self) -> np.ndarray:
        """(K,) √λ_k in mm: the natural standard deviation along each mode."""
        return np.sqrt(np.maximum(self.variances, 0.0))

    @property
    def alignment(self) -> str:
        return str(self.params.get("alignment", "none"))

    @property
    def landmark_locations(self) -> LandmarkLocations:
        """The landmarks the model knows, as points of the mean mesh (the template instance's,
        located on the template's triangles; ``params["landmark_locations"]`` in files); empty
        when it has none."""
        return LandmarkLocations.from_dict((self.params or {}).get("landmark_locations"))

    @property
    def total_variance(self) -> float:
        """trace(S) in mm²: the total variance of eq. (8)'s denominator."""
        return float(self.params.get("total_variance_mm2", float(np.sum(self.variances))))

    def basis(self, k: int | None = None) -> np.ndarray:
        """(3N, k) matrix Q of the first ``k`` modes as columns (all if None)."""
        k = self.n_modes if k is None else int(k)
        return self.modes[:k].reshape(k, -1).T

    # -- eq. 7 -------------------------------------------------------------------------
    def generate(self, b) -> np.ndarray:
        """New shape p = p̄ + Q b (eq. 7).

        Parameters
        ----------
        b : (m,) array_like, m <= K
            Weights along the first m orthonormal modes, in mm (b_k = z_k √λ_k for
            z_k standard deviations; see :meth:`generate_sd`).

        Returns
        -------
        (N, 3) ndarray
            Points in the model frame, mm.
        """
        b = np.atleast_1d(np.asarray(b, dtype=float))
        if b.ndim != 1 or b.shape[0] > self.n_modes:
            raise InputError(f"model: weight vector b has shape {b.shape}; expected (m,) with m <= {self.n_modes}")
        m = b.shape[0]
        return self.mean + np.tensordot(b, self.modes[:m], axes=1)

    def generate_sd(self, z) -> np.ndarray:
        """New shape with weights given in standard deviations: b_k = z_k √λ_k (eq. 7)."""
        z = np.atleast_1d(np.asarray(z, dtype=float))
        if z.ndim != 1 or z.shape[0] > self.n_modes:
            raise InputError(f"model: z has shape {z.shape}; expected (m,) with m <= {self.n_modes}")
        return self.generate(z * self.standard_deviations[: z.shape[0]])

    def sample(self, n_samples: int = 1, *, k: int | None = None, seed=None, sd_limit: float | None = None) -> np.ndarray:
        """Random shapes with b_k ~ N(0, λ_k) on the first ``k`` modes.

        Parameters
        ----------
        n_samples : int
        k : int, optional
            Number of modes used (all by default).
        seed : int or numpy Generator, optional
        sd_limit : float, optional
            Clip each z_k = b_k / √λ_k to [-sd_limit, sd_limit].

        Returns
        -------
        (n_samples, N, 3) ndarray in the model frame, mm.
        """
        k = self.n_modes if k is None else min(int(k), self.n_modes)
        rng = np.random.default_rng(seed)
        z = rng.standard_normal((int(n_samples), k))
        if sd_limit is not None:
            z = np.clip(z, -sd_limit, sd_limit)
        b = z * self.standard_deviations[:k]
        return self.mean[None] + np.tensordot(b, self.modes[:k], axes=1)

    # -- projection --------------------------------------------------------------------
    def align(self, points) -> tuple[np.ndarray, tuple[float, np.ndarray, np.ndarray]]:
        """Align a shape to the mean the way the training shapes were aligned.

        Returns the aligned (N, 3) points and the transform (s, R, t) with
        aligned = s · points · Rᵀ + t (identity when the model has no alignment).
        """
        points = _check_shape_points(points, self.n_points, "model.project")
        if self.alignment == "none":
            return points, (1.0, np.eye(3), np.zeros(3))
        s, rot, t = procrustes_fit(points[None], self.mean, scale=self.alignment == "similarity")
        s, rot, t = float(s[0]), rot[0], t[0]
        return s * points @ rot.T + t, (s, rot, t)

    def project(self, points, k: int | None = None) -> np.ndarray:
        """Mode weights b of a shape: least squares b = Qᵀ (p - p̄) (Q orthonormal).

        Parameters
        ----------
        points : (N, 3) array_like
            A shape in correspondence with the model, in the model frame (or any frame
            if the model was built with Procrustes alignment: it is aligned first).
        k : int, optional
            Number of modes (all by default).

        Returns
        -------
        (k,) ndarray, mm along the orthonormal modes.
        """
        aligned, _ = self.align(points)
        k = self.n_modes if k is None else min(int(k), self.n_modes)
        return self.modes[:k].reshape(k, -1) @ (aligned - self.mean).ravel()

    def project_all(self, shapes, k: int | None = None) -> np.ndarray:
        """Mode weights of many shapes: :meth:`project` of each, (n, N, 3) -> (n, k) mm, as one
        matrix product per block of ``PROJECT_BLOCK`` shapes (each aligned as :meth:`align`)."""
        x = np.asarray(shapes, dtype=float)
        if x.ndim != 3 or x.shape[1:] != (self.n_points, 3):
            raise InputError(f"model.project_all: shapes have shape {x.shape}; expected (n, {self.n_points}, 3)")
        k = self.n_modes if k is None else min(int(k), self.n_modes)
        q = self.modes[:k].reshape(k, -1)
        out = np.empty((len(x), k))
        for start in range(0, len(x), PROJECT_BLOCK):
            block = x[start:start + PROJECT_BLOCK]
            if self.alignment != "none":
                s, rot, t = procrustes_fit(block, self.mean, scale=self.alignment == "similarity")
                block = s[:, None, None] * np.einsum("inj,ikj->ink", block, rot) + t[:, None, :]
            out[start:start + len(block)] = (block - self.mean).reshape(len(block), -1) @ q.T
        return out

    def reconstruct(self, points, k: int | None = None) -> np.ndarray:
        """Best approximation of a shape with the first ``k`` modes (eq. 7 of its projection).

        Returns the (N, 3) reconstruction in the frame of ``points`` (the alignment, if
        any, is undone), mm.
        """
        aligned, (s, rot, t) = self.align(points)
        k = self.n_modes if k is None else min(int(k), self.n_modes)
        q = self.modes[:k].reshape(k, -1)
        b = q @ (aligned - self.mean).ravel()
        rec = self.mean + (b @ q).reshape(-1, 3)
        return ((rec - t) @ rot) / s

    # -- eq. 8 -------------------------------------------------------------------------
    def variability_concentration(self, kind: str = "eigen") -> np.ndarray:
        """Concentration of variability n(k) of eq. (8), k = 1, 2, ...

        Parameters
        ----------
        kind : {"eigen", "coordinate"}
            ``"eigen"``: cumulative eigenvalues λ_1..λ_k over trace(S), k = 1..K.
            ``"coordinate"``: the same for the variances s_i² of the 3N coordinates
            (diagonal of S, sorted descending), k = 1..3N — the paper's comparison of
            how much the eigenmode analysis concentrates the variability.

        Returns
        -------
        (K,) or (3N,) ndarray of fractions in [0, 1].
        """
        if kind == "eigen":
            total = self.total_variance
            return np.cumsum(self.variances) / total if total > 0 else np.zeros(self.n_modes)
        if kind == "coordinate":
            s2 = np.sort(self.coordinate_variances().ravel())[::-1]
            total = s2.sum()
            return np.cumsum(s2) / total if total > 0 else np.zeros_like(s2)
        raise InputError(f"variability_concentration: unknown kind {kind!r} (eigen|coordinate)")

    def coordinate_variances(self) -> np.ndarray:
        """(N, 3) diagonal of the covariance S (eq. 5), mm², same normalisation as the model.

        From the training shapes when present, else from the kept modes (Σ λ_k q_k²).
        """
        if self.n_instances >= 2:
            ddof = int(self.params.get("ddof", 0))
            return np.var(self.instance_points, axis=0, ddof=ddof)
        return np.tensordot(self.variances, self.modes**2, axes=1)

    @property
    def point_variance(self) -> np.ndarray:
        """(N,) per-point variance in mm²: trace of the point's 3x3 block of S (heat map)."""
        return self.coordinate_variances().sum(axis=1)

    def scores(self) -> np.ndarray:
        """(n, K) weights b of the training shapes: Qᵀ (p_i - p̄)."""
        if self.n_instances == 0:
            return np.zeros((0, self.n_modes))
        centred = (self.instance_points - self.mean).reshape(self.n_instances, -1)
        return centred @ self.modes.reshape(self.n_modes, -1).T


# ---------------------------------------------------------------------------------------
# Procrustes
# ---------------------------------------------------------------------------------------
def procrustes_fit(src: np.ndarray, dst: np.ndarray, scale: bool):
    """Least-squares similarity (or rigid) transforms of many shapes onto one target.

    Finds s_i, R_i, t_i minimising Σ |s_i R_i x + t_i - y|² for every shape src[i]
    (Umeyama/Kabsch, reflections excluded).

    Parameters
    ----------
    src : (n, N, 3) shapes; dst : (N, 3) target.

    Returns
    -------
    s (n,), R (n, 3, 3), t (n, 3) with aligned = s · x · Rᵀ + t.
    """
    mu_s = src.mean(axis=1)
    mu_d = dst.mean(axis=0)
    xs = src - mu_s[:, None]
    yd = dst - mu_d
    h = np.einsum("inj,nk->ijk", xs, yd)  # (n, 3, 3) = Σ x yᵀ
    u, sv, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.einsum("ijk,ikl->ijl", u, vt)))
    d[d == 0] = 1.0
    corr = np.ones((len(src), 3))
    corr[:, 2] = d
    # R = V diag(1,1,d) Uᵀ maps x onto y
    rot = np.einsum("ikj,ik,ilk->ijl", vt, corr, u)
    if scale:
        var_s = np.einsum("inj,inj->i", xs, xs)
        s = np.einsum("ik,ik->i", sv, corr) / np.where(var_s > 0, var_s, 1.0)
    else:
        s = np.ones(len(src))
    t = mu_d[None] - s[:, None] * np.einsum("ijk,ik->ij", rot, mu_s)
    return s, rot, t


def generalized_procrustes(
    shapes: np.ndarray, *, scale: bool = False, tol: float = 1e-10, max_iter: int = 100
) -> tuple[np.ndarray, dict]:
    """Generalized Procrustes alignment of corresponding point sets.

    Each shape is aligned (rigidly, or with a similarity if ``scale``) to the current
    mean, the mean is recomputed and itself registered rigidly onto the unaligned mean
    of the input (so the result stays in the object frame; with ``scale`` it is also
    rescaled to that mean's centroid size, keeping mm), until the mean moves less than
    ``tol`` times its size.

    Parameters
    ----------
    shapes : (n, N, 3) points, mm.

    Returns
    -------
    aligned : (n, N, 3) ndarray, mm
    info : dict with ``iterations``, ``converged``, ``final_change_mm``.
    """
    shapes = np.asarray(shapes, dtype=float)
    frame_ref = shapes.mean(axis=0)
    # mean centroid size of the inputs (rotation invariant, unlike the raw mean's size)
    size_ref = float(np.sqrt(((shapes - shapes.mean(axis=1, keepdims=True)) ** 2).sum(axis=(1, 2))).mean())
    ref = frame_ref
    change = np.inf
    converged = False
    it = 0
    aligned = shapes
    for it in range(1, max_iter + 1):  # noqa: B007 - reported below
        s, rot, t = procrustes_fit(shapes, ref, scale)
        aligned = s[:, None, None] * np.einsum("inj,ikj->ink", shapes, rot) + t[:, None]
        new = aligned.mean(axis=0)
        # keep the mean in the frame (and, with scale, the size) of the input mean
        s2, rot2, t2 = procrustes_fit(new[None], frame_ref, scale=False)
        new = new @ rot2[0].T + t2[0]
        if scale:
            c = new.mean(0)
            size = np.sqrt(((new - c) ** 2).sum())
            if size > 0:
                new = c + (new - c) * (size_ref / size)
        change = float(np.sqrt(((new - ref) ** 2).sum(axis=1).mean()))
        ref = new
        if change <= tol * max(size_ref, 1e-300):
            converged = True
            break
    s, rot, t = procrustes_fit(shapes, ref, scale)
    aligned = s[:, None, None] * np.einsum("inj,ikj->ink", shapes, rot) + t[:, None]
    return aligned, {"iterations": it, "converged": converged, "final_change_mm": change}


# ---------------------------------------------------------------------------------------
# PCA
# ---------------------------------------------------------------------------------------
def _orthonormalise_rows(modes: np.ndarray, tol: float = 1e-12) -> tuple[np.ndarray, float]:
    """Restore exact orthonormality of the Gram route's modes (rows) if rounding broke it.

    For eigenvalues far below the largest, q_i = P q~_i / |P q~_i| loses orthogonality
    (error ~ eps λ_1 / λ_i). If max |Q Qᵀ - I| > ``tol``, rows are re-orthonormalised in
    order (Cholesky Gram-Schmidt: Q <- L⁻¹ Q with Q Qᵀ = L Lᵀ), which leaves the leading
    modes essentially untouched and keeps every mode in the span of the data.
    Returns the modes and the orthogonality error before the correction.
    """
    if modes.shape[0] == 0:
        return modes, 0.0

    gram = modes @ modes.T
    err = float(np.abs(gram - np.eye(len(gram))).max())
    if err > tol:
        low = cholesky(gram, lower=True)
        modes = solve_triangular(low, modes, lower=True)
    return modes, err


def gram_factor(flat: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The non-zero spectrum of the Gram matrix G = X Xᵀ of ``flat`` (n, d): its eigenvalues w
    (ascending, those above 1e-12 of the largest), Z (n, r) with Z Zᵀ = G and the eigenvectors
    V = Z / √w, columns in the order of w.

    Through G itself when n <= d; with more rows than columns through the d × d scatter
    XᵀX (the same non-zero eigenvalues; Z = X U for its eigenvectors U), so a study of 10⁴
    shapes needs no 10⁴ × 10⁴ matrix. Z and V are determined up to the signs of their
    columns (and turns within equal eigenvalues), which no sum of squares depends on.
    """
    n, d = flat.shape
    if n <= d:
        w, v = np.linalg.eigh(flat @ flat.T)
        keep = w > 1e-12 * max(float(w[-1]), 1e-300)
        return w[keep], v[:, keep] * np.sqrt(w[keep]), v[:, keep]
    w, u = np.linalg.eigh(flat.T @ flat)
    keep = w > 1e-12 * max(float(w[-1]), 1e-300)
    z = flat @ u[:, keep]
    return w[keep], z, z / np.sqrt(w[keep])


def _nonzero_eigenpairs(mat: np.ndarray, n: int, n_modes: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Eigenpairs of the symmetric product matrix of ``n`` centred shapes (their n × n Gram
    matrix or their 3N × 3N covariance), largest first: at most n - 1 (centring), none zero to
    rounding, at most ``n_modes``."""
    w, v = np.linalg.eigh(mat)
    order = np.argsort(w)[::-1]
    w, v = w[order], v[:, order]
    d = mat.shape[0]
    tol = max(w[0], 0.0) * max(d, 1) * 64 * np.finfo(float).eps if d else 0.0
    keep = np.flatnonzero(w > tol)[: max(n - 1, 0)]
    if n_modes is not None:
        keep = keep[: int(n_modes)]
    return w[keep], v[:, keep]


def _modes_from_gram(centred: np.ndarray, gram: np.ndarray, n_norm: float, n_modes: int | None):
    """Eigenpairs of S = P Pᵀ / n_norm via the Gram matrix Pᵀ P (eq. 6).

    Parameters
    ----------
    centred : (n, 3N) centred shape vectors (rows = Pᵀ).
    gram : (n, n) Pᵀ P.

    Returns
    -------
    variances (K,), modes (K, 3N), orthogonality error before re-orthonormalisation.
    """
    w, v = _nonzero_eigenpairs(gram, gram.shape[0], n_modes)
    # q_i = P q~_i / |P q~_i|, and |P q~_i|² = q~_iᵀ Pᵀ P q~_i = w_i
    modes = (v / np.sqrt(w)[None]).T @ centred
    modes, ortho_err = _orthonormalise_rows(modes)
    return w / n_norm, modes, ortho_err


def _modes_from_covariance(covariance: np.ndarray, n_norm: float, n_modes: int | None, n: int):
    """Eigenpairs of S = P Pᵀ / n_norm from the 3N × 3N matrix P Pᵀ itself (eq. 5): the
    smaller problem when there are more instances than coordinates (n > 3N; eq. 6's Gram
    matrix would be n × n).

    Returns
    -------
    variances (K,), modes (K, 3N), orthogonality error of the modes.
    """
    w, v = _nonzero_eigenpairs(covariance, n, n_modes)
    modes = np.ascontiguousarray(v.T)
    ortho_err = float(np.abs(modes @ modes.T - np.eye(len(modes))).max()) if len(modes) else 0.0
    return w / n_norm, modes, ortho_err


RANDOMIZED_MIN_ELEMENTS = 20_000_000
"""n·3N (shape-vector entries) from which ``solver="auto"`` uses the randomized SVD (160 MB in float64)."""


def _modes_randomized(centred: np.ndarray, n_norm: float, k: int, *, seed: int = 0, oversample: int = 10,
                      power_iterations: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """The first ``k`` eigenpairs of S = P Pᵀ / n_norm by a randomized SVD of the centred data.

    Range finder with ``power_iterations`` subspace iterations (re-orthonormalised each
    time), then the exact SVD of the small projected matrix (Halko, Martinsson & Tropp
    2011, algorithms 4.4 and 5.1). Deterministic for a given ``seed``. Costs
    O(n·3N·(k + oversample)·(2q + 2)) flops and O(n + 3N)·(k + oversample) extra memory.

    Returns variances (k,) and orthonormal modes (k, 3N).
    """
    n, d = centred.shape
    ell = int(min(k + oversample, n, d))
    rng = np.random.default_rng(seed)
    y = centred @ rng.standard_normal((d, ell)).astype(centred.dtype, copy=False)
    for _ in range(power_iterations):
        q, _ = np.linalg.qr(y)
        z, _ = np.linalg.qr(centred.T @ q)
        y = centred @ z
    q, _ = np.linalg.qr(y)
    _, sv, vt = np.linalg.svd(q.T @ centred, full_matrices=False)
    k = min(k, len(sv))
    return (sv[:k].astype(float) ** 2) / n_norm, vt[:k].astype(float)


def leading_modes(centred: np.ndarray, n_norm: float, k: int, *, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The first ``k`` eigenpairs of S = P Pᵀ / n_norm of centred (n, 3N) shape vectors by the
    randomized SVD (:func:`build_model`'s solver for large studies): variances (k,), modes (k, 3N).
    Its cost grows linearly with n."""
    return _modes_randomized(centred, n_norm, k, seed=seed)


def _modes_for_fraction(variances: np.ndarray, total: float, fraction: float | None) -> int:
    """Number of leading modes whose variance reaches ``fraction`` of ``total`` (all when None)."""
    if fraction is None or total <= 0 or not len(variances):
        return len(variances)
    cum = np.cumsum(variances) / total
    return int(min(len(variances), np.searchsorted(cum, fraction - 1e-12) + 1))


def _fix_signs(modes: np.ndarray) -> np.ndarray:
    """Make each mode's largest-magnitude component positive (deterministic sign)."""
    if modes.size == 0:
        return modes
    idx = np.argmax(np.abs(modes), axis=1)
    sgn = np.sign(modes[np.arange(len(modes)), idx])
    sgn[sgn == 0] = 1.0
    return modes * sgn[:, None]


def build_model(
    instance_points,
    faces,
    instance_names,
    *, instance_points_world=None,
    alignment: str = "none",
    n_modes: int | None = None,
    variance_fraction: float | None = None,
    solver: str = "auto",
    precision: str = "float64",
    params: dict | None = None,
    progress=None,
    cancelled=None,
    ddof: int = 0,
) -> ShapeModel:
    """Build the point distribution model of paper section 5.

    Parameters
    ----------
    instance_points : (n, N, 3) array_like
        The coated instances, each in its object frame (mm), in correspondence.
    faces : (F, 3) int array_like
        The template's triangles.
    instance_names : sequence of n str
    instance_points_world : (n, N, 3) array_like, optional
        The same points in each instance's input coordinates (mm); defaults to
        ``instance_points``.
    alignment : {"none", "rigid", "similarity"}
        ``"none"`` (paper: object frame only, size stays part of the variability) or
        generalized Procrustes alignment without / with scaling.
    n_modes : int, optional
        Keep at most this many modes (default: all with a non-zero eigenvalue, <= n-1).
    variance_fraction : float in (0, 1], optional
        Keep the fewest leading modes that explain this fraction of the total variance.
    solver : {"auto", "exact", "randomized"}
        ``"exact"``: the Gram eigenproblem (eq. 6). ``"randomized"``: a randomized SVD
        of the centred data for the leading modes only (needs ``n_modes`` or
        ``variance_fraction``). ``"auto"``: randomized when n·3N ≥
        :data:`RANDOMIZED_MIN_ELEMENTS` and a mode limit below n/4 is given; else the
        3N × 3N covariance of eq. 5 itself when there are more instances than coordinates
        (n > 3N), else exact.
    precision : {"float64", "float32"}
        ``"float32"`` halves the memory of the instance points and of the solver for very
        large studies (mean, modes and variances stay float64; about 7 significant digits).
    params : dict, optional
        Extra JSON-serialisable parameters to record (e.g. template and coating settings).
    ddof : int
        Covariance normalisation 1/(n - ddof); 0 is the paper's eq. (5), 1 the unbiased one.

    Returns
    -------
    ShapeModel
        Mean (eq. 4), eigenmodes and eigenvalues of S (eq. 5) via the Gram problem (eq. 6).
    """
    if precision not in ("float64", "float32"):
        raise InputError(f"build_model: precision must be 'float64' or 'float32', got {precision!r}")
    if solver not in ("auto", "exact", "randomized"):
        raise InputError(f"build_model: solver must be 'auto', 'exact' or 'randomized', got {solver!r}")
    if variance_fraction is not None and not 0 < variance_fraction <= 1:
        raise InputError(f"build_model: variance_fraction must be in (0, 1], got {variance_fraction}")
    x = np.asarray(instance_points, dtype=np.float64 if precision == "float64" else np.float32)
    if x.ndim != 3 or x.shape[2] != 3:
        raise InputError(f"build_model: instance_points has shape {x.shape}; expected (n, N, 3)")
    n, npts, _ = x.shape
    if n < 2:
        raise InputError(f"build_model: need at least 2 instances, got {n}")
    if not np.all(np.isfinite(x)):
        bad = sorted({int(i) for i in np.argwhere(~np.isfinite(x))[:, 0]})
        raise InputError(f"build_model: instances {bad} contain non-finite coordinates")
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if faces.size and (faces.min() < 0 or faces.max() >= npts):
        raise InputError(f"build_model: faces index points outside 0..{npts - 1}")
    names = np.asarray([str(s) for s in instance_names], dtype=str)
    if names.shape != (n,):
        raise InputError(f"build_model: {names.size} instance names for {n} instances")
    if alignment not in ALIGNMENTS:
        raise InputError(f"build_model: unknown alignment {alignment!r} (none|rigid|similarity)")
    if ddof not in (0, 1):
        raise InputError(f"build_model: ddof must be 0 (paper, 1/n) or 1 (1/(n-1)), got {ddof}")
    if instance_points_world is None:
        world = x  # the same numbers; x itself is replaced, never changed in place
    else:
        world = np.asarray(instance_points_world, dtype=x.dtype)
        if world.shape != x.shape:
            raise InputError(f"build_model: instance_points_world has shape {world.shape}, expected {x.shape}")

    report(progress, 0.0, "aligning instances" if alignment != "none" else "centring instances")
    align_info: dict = {}
    if alignment != "none":
        x, align_info = generalized_procrustes(x, scale=alignment == "similarity")
    check_cancelled(cancelled)

    mean = x.mean(axis=0, dtype=np.float64)  # eq. 4
    centred = x.reshape(n, -1) - mean.reshape(-1).astype(x.dtype)  # rows: (p_i - p̄)ᵀ
    n_norm = float(n - ddof)
    total_var = float(np.einsum("ij,ij->", centred, centred, dtype=np.float64)) / n_norm
    use_randomized = solver == "randomized" or (
        solver == "auto" and centred.size >= RANDOMIZED_MIN_ELEMENTS
        and (n_modes is not None and n_modes < n // 4 or variance_fraction is not None and variance_fraction < 1))
    if use_randomized:
        if n_modes is None and variance_fraction is None:
            raise InputError("build_model: the randomized solver needs n_modes or variance_fraction")
        report(progress, 0.2, "randomized SVD of the centred shapes")
        k = int(min(n_modes if n_modes is not None else 64, n - 1))
        while True:
            variances, modes = _modes_randomized(centred, n_norm, k)
            check_cancelled(cancelled)
            enough = _modes_for_fraction(variances, total_var, variance_fraction) < len(variances)
            if n_modes is not None or enough or variance_fraction is None or k >= n - 1:
                break
            k = int(min(2 * k, n - 1))  # the fraction needs more modes than computed: double
        ortho_err = float(np.abs(modes @ modes.T - np.eye(len(modes))).max()) if len(modes) else 0.0
        eigensolver = "randomized SVD of the centred shape vectors (Halko et al. 2011), 4 power iterations"
    elif solver == "auto" and n > centred.shape[1]:
        # more instances than coordinates (a biobank of small templates): the 3N × 3N
        # covariance is the smaller eigenproblem (docs/history.md, "Scale")
        report(progress, 0.2, "covariance matrix (eq. 5)")
        c64 = centred.astype(np.float64, copy=False)
        covariance = c64.T @ c64
        total_var = float(np.trace(covariance)) / n_norm
        check_cancelled(cancelled)
        report(progress, 0.6, "eigen-decomposition")
        variances, modes, ortho_err = _modes_from_covariance(covariance, n_norm, n_modes, n)
        eigensolver = "covariance matrix P P^T (3N x 3N, eq. 5): more instances than coordinates"
        del covariance, c64
    else:
        report(progress, 0.2, "Gram matrix (eq. 6)")
        gram = (centred @ centred.T).astype(np.float64)
        total_var = float(np.trace(gram)) / n_norm
        check_cancelled(cancelled)
        report(progress, 0.6, "eigen-decomposition")
        variances, modes, ortho_err = _modes_from_gram(centred.astype(np.float64, copy=False), gram, n_norm, n_modes)
        eigensolver = "Gram matrix P^T P (n x n, eq. 6), q_i = P q~_i / |P q~_i|"
        del gram
    keep = min(_modes_for_fraction(variances, total_var, variance_fraction),
               len(variances) if n_modes is None else n_modes)
    variances, modes = variances[:keep], modes[:keep]
    modes = _fix_signs(np.asarray(modes, dtype=np.float64))
    del centred
    report(progress, 1.0, f"{len(variances)} modes")

    all_params = {
        "alignment": alignment,
        "alignment_info": align_info,
        "ddof": ddof,
        "normalisation": f"S = 1/{'n' if ddof == 0 else '(n-1)'} sum (p_i - mean)(p_i - mean)^T (eq. 5)",
        "eigensolver": eigensolver,
        "variance_fraction_requested": variance_fraction,
        "precision": precision,
        "orthogonality_error_gram": ortho_err,
        "reorthonormalised": ortho_err > 1e-12,
        "sign_convention": "largest-magnitude component of each mode positive",
        "n_instances": n,
        "n_points": npts,
        "n_faces": int(len(faces)),
        "n_modes_requested": n_modes,
        "n_modes": int(len(variances)),
        "total_variance_mm2": total_var,
        "units": "mm",
        "frame": "object frame (paper 2, 5)" + ("" if alignment == "none" else f" after {alignment} Procrustes"),
        "versions": versions(),
    }
    if params:
        all_params.update(params)
    return ShapeModel(
        mean=mean,
        faces=faces,
        modes=modes.reshape(-1, npts, 3),
        variances=variances,
        instance_names=names,
        instance_points=x,
        instance_points_world=world,
        params=jsonable(all_params),
    )


def _check_shape_points(points, npts: int, what: str) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.shape != (npts, 3):
        raise InputError(f"{what}: points have shape {p.shape}; expected ({npts}, 3)")
    return p
