"""Model quality: compactness, generalization, specificity, fit figures, report and plots.

Standard definitions (Davies et al., IEEE TMI 2002; Styner et al. 2003):

* compactness C(k): cumulative share of the total variance in the first k modes (the
  eigenvalue version of eq. 8), with the standard error sqrt(2/n) Σ λ_i / trace(S);
* generalization G(k): a model built without instance i reconstructs i with k modes;
  the error is the mean point-to-point distance in mm, averaged over the held-out shapes
  (mean ± standard deviation). Leave-one-out up to ``max_loo`` instances, k-fold beyond,
  both computed from one Gram matrix (no refit of a 3N x 3N problem);
* specificity S(k): random shapes with b_j ~ N(0, λ_j) on the first k modes (seeded), each
  compared with its nearest training shape (nearest in the sum of squared distances); the
  error is the mean point-to-point distance in mm (mean ± standard deviation).

Plots use matplotlib's object API with the Agg canvas (no pyplot state, safe inside
Blender); without matplotlib they are skipped with a clear message.
"""

from __future__ import annotations

import dataclasses
import json
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.sparse.linalg import eigsh

from ..base.errors import InputError, SSMError, check_cancelled
from ..base.params import ALIGNMENTS
from ..base.progress import report, sub_progress
from ..model.pca import (
    RANDOMIZED_MIN_ELEMENTS,
    ShapeModel,
    generalized_procrustes,
    jsonable,
    own_side_instances,
    procrustes_fit,
)


@dataclass(frozen=True)
class ModelMetrics:
    """How good a model is on its own training shapes (see the module docstring).

    Attributes
    ----------
    compactness : dict
        :func:`compactness`: C(k) with its standard error, per k (eq. 8 of the eigenvalues).
    generalization : dict or None
        :func:`generalization`: leave-one-out (or k-fold) reconstruction error per k, mm.
    specificity : dict or None
        :func:`specificity`: distance of random model shapes to the nearest training
        shape per k, mm.
    """

    compactness: dict
    generalization: dict | None = None
    specificity: dict | None = None

    def to_dict(self) -> dict:
        """The ``metrics`` entry of ``report.json`` (what is measured only)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if getattr(self, f.name) is not None}

    @classmethod
    def from_dict(cls, d) -> ModelMetrics | None:
        """From :meth:`to_dict`'s form (None when there are no metrics)."""
        if not d:
            return None
        return cls(compactness=d.get("compactness") or {}, generalization=d.get("generalization"),
                   specificity=d.get("specificity"))


# ---------------------------------------------------------------------------------------
# Compactness
# ---------------------------------------------------------------------------------------
def compactness(model: ShapeModel) -> dict:
    """Cumulative variance fraction C(k) = Σ_{i<=k} λ_i / trace(S), k = 1..K (eq. 8).

    Returns
    -------
    dict with ``k``, ``variance_mm2`` (λ_k), ``fraction`` (λ_k / trace S), ``cumulative``
    (C(k)), ``cumulative_std`` (Davies' standard error sqrt(2/n) C(k)) and
    ``modes_for`` {"0.9": k, "0.95": k, "0.99": k} (smallest k reaching the share).
    """
    total = model.total_variance
    lam = np.asarray(model.variances, dtype=float)
    frac = lam / total if total > 0 else np.zeros_like(lam)
    cum = np.cumsum(frac)
    n = max(model.n_instances, int(model.params.get("n_instances", 0) or 0), 1)
    modes_for = {}
    for share in (0.9, 0.95, 0.99):
        hit = np.flatnonzero(cum >= share - 1e-12)
        modes_for[str(share)] = int(hit[0] + 1) if hit.size else None
    return {
        "k": list(range(1, len(lam) + 1)),
        "variance_mm2": lam.tolist(),
        "fraction": frac.tolist(),
        "cumulative": cum.tolist(),
        "cumulative_std": (np.sqrt(2.0 / n) * cum).tolist(),
        "modes_for": modes_for,
    }


# ---------------------------------------------------------------------------------------
# Generalization
# ---------------------------------------------------------------------------------------
def _point_errors(residual: np.ndarray) -> np.ndarray:
    """(h, 3N) residual vectors -> (h,) mean point-to-point distance."""
    r = residual.reshape(len(residual), -1, 3)
    return np.sqrt(np.einsum("ijk,ijk->ij", r, r)).mean(axis=1)


def _leading_eigenpairs(mat: np.ndarray, kmax: int) -> tuple[np.ndarray, np.ndarray]:
    """The first ``kmax`` eigenpairs of a symmetric positive semi-definite matrix, largest first,
    without the numerically zero ones: (w (k,), v (m, k))."""
    m = len(mat)
    if kmax < m // 10:
        # a few leading eigenpairs: Lanczos is much cheaper than a dense m x m solve
        v0 = np.random.default_rng(0).standard_normal(m)
        w, v = eigsh(mat, k=kmax, which="LA", v0=v0, tol=0)
    else:
        w, v = np.linalg.eigh(mat)
    order = np.argsort(w)[::-1]
    w, v = w[order], v[:, order]
    tol = max(w[0], 0.0) * m * 64 * np.finfo(float).eps
    k = int(min(kmax, np.count_nonzero(w > tol)))
    return w[:k], v[:, :k]


def _top_modes(data: np.ndarray, rows, mu: np.ndarray, gram_centred: np.ndarray, kmax: int) -> np.ndarray:
    """First ``kmax`` orthonormal modes (rows, (kmax, 3N)) via the Gram matrix (eq. 6).

    The centred training vectors are ``data[rows] - mu``; the modes are formed as
    Cᵀ data[rows] - (Σ C) mu without copying the training block.
    """
    w, v = _leading_eigenpairs(gram_centred, kmax)
    coeff = v / np.sqrt(w)
    full = np.zeros((len(data), len(w)))
    full[rows] = coeff
    return full.T @ data - np.outer(coeff.sum(axis=0), mu)


def _top_modes_from_covariance(covariance: np.ndarray, kmax: int) -> np.ndarray:
    """First ``kmax`` orthonormal modes (rows, (kmax, 3N)) from the 3N × 3N matrix of the
    centred training vectors' products (eq. 5): the smaller problem when a fold has more
    training shapes than coordinates."""
    return np.ascontiguousarray(_leading_eigenpairs(covariance, kmax)[1].T)


def generalization(
    instance_points,
    *, faces=None,
    ks=None,
    alignment: str = "none",
    folds: int | None = None,
    max_loo: int = 100,
    seed: int = 0,
    solver: str = "auto",
    progress=None,
    cancelled=None,
) -> dict:
    """Generalization ability G(k): error of reconstructing unseen shapes with k modes.

    Parameters
    ----------
    instance_points : (n, N, 3) array_like
        Training shapes (object frame, mm) in correspondence.
    faces : ignored (kept for a uniform signature; the error is point-to-point).
    ks : sequence of int, optional
        Numbers of modes (default 1..min(30, n_train - 1)).
    alignment : {"none", "rigid", "similarity"}
        As in :func:`ssm_addon.model.pca.build_model`; with Procrustes each fold aligns its
        training set (GPA) and the held-out shapes to that mean; errors are reported in
        the input's mm (rotation removed, scale undone).
    folds : int, optional
        Number of folds. Default: leave-one-out (n folds) when n <= ``max_loo``, else
        10-fold cross-validation with a seeded random partition.
    solver : {"auto", "gram", "randomized"}
        How each fold's modes are found. ``"gram"``: exactly, from one n × n Gram matrix of
        all shapes. ``"randomized"``: a randomized SVD of each fold's training rows, without
        the Gram matrix (bounded memory; k-fold without alignment only; the errors agree
        with ``"gram"`` to float32 precision). ``"auto"``: exactly from the 3N × 3N products
        (eq. 5) when every fold trains on more shapes than coordinates; else randomized for
        k-fold studies of at least ``RANDOMIZED_MIN_ELEMENTS`` shape-vector entries, else the
        Gram route.

    Returns
    -------
    dict with ``k``, ``mean_mm``, ``std_mm`` (over held-out shapes), ``per_instance_mm``
    (n x len(k)), ``method``, ``folds``, ``seconds``.
    """
    t0 = time.perf_counter()
    x = np.asarray(instance_points, dtype=float)
    if x.ndim != 3 or x.shape[2] != 3:
        raise InputError(f"generalization: instance_points has shape {x.shape}; expected (n, N, 3)")
    n = x.shape[0]
    if n < 3:
        raise InputError(f"generalization: need at least 3 instances, got {n}")
    if alignment not in ALIGNMENTS:
        raise InputError(f"generalization: unknown alignment {alignment!r}")
    if folds is None:
        folds = n if n <= max_loo else 10
    folds = int(folds)
    if not 2 <= folds <= n:
        raise InputError(f"generalization: folds must be in 2..{n}, got {folds}")
    rng = np.random.default_rng(seed)
    perm = np.arange(n) if folds == n else rng.permutation(n)
    fold_of = np.empty(n, dtype=int)
    fold_of[perm] = np.arange(n) % folds
    n_train_min = n - int(np.bincount(fold_of).max())
    kcap = n_train_min - 1
    if ks is None:
        ks = list(range(1, min(30, kcap) + 1))
    ks = sorted({int(k) for k in ks if 1 <= int(k) <= kcap})
    if not ks:
        raise InputError(f"generalization: no valid k (1..{kcap}) for {n} instances in {folds} folds")
    method = "leave-one-out" if folds == n else f"{folds}-fold cross-validation (n = {n} > {max_loo})"

    if solver not in ("auto", "gram", "randomized"):
        raise InputError(f"generalization: unknown solver {solver!r} (auto, gram, randomized)")
    if solver == "randomized" and (alignment != "none" or folds == n):
        raise InputError("generalization: the randomized solver is for k-fold studies without alignment")
    flat = x.reshape(n, -1)
    raw_gram = raw_cov = None
    large = folds < n and flat.size >= RANDOMIZED_MIN_ELEMENTS
    # a fold with more training shapes than coordinates: its modes from the 3N × 3N products
    # (eq. 5), not from an n × n Gram matrix (docs/history.md, "Scale")
    by_covariance = solver == "auto" and n_train_min > flat.shape[1]
    if alignment == "none" and (solver == "randomized" or (solver == "auto" and large and not by_covariance)):
        errors = _generalization_randomized(flat, fold_of, folds, ks, progress=progress, cancelled=cancelled)
        method += ", leading modes of each fold by randomized SVD"
    elif alignment == "none":
        flat = flat - flat.mean(axis=0)  # shifts cancel in centred products; better rounding
        report(progress, 0.0, "covariance matrix" if by_covariance else "Gram matrix")
        if by_covariance:
            raw_cov = flat.T @ flat
            method += ", each fold's modes from its 3N × 3N products (more shapes than coordinates)"
        else:
            raw_gram = flat @ flat.T
        total = flat.sum(axis=0)
    elif by_covariance:
        method += ", each fold's modes from its 3N × 3N products (more shapes than coordinates)"
    if raw_gram is not None or raw_cov is not None or alignment != "none":
        errors = _generalization_folds(x, flat, raw_gram, total if alignment == "none" else None, fold_of, ks,
                                       alignment, progress, cancelled, raw_cov=raw_cov, by_covariance=by_covariance)
    report(progress, 1.0, "generalization done")
    return {
        "k": ks,
        "mean_mm": errors.mean(axis=0).tolist(),
        "std_mm": errors.std(axis=0).tolist(),
        "per_instance_mm": errors.tolist(),
        "method": method,
        "folds": folds,
        "alignment": alignment,
        "error": "mean point-to-point distance (mm) of the held-out shape to its reconstruction",
        "seconds": time.perf_counter() - t0,
    }


def _generalization_randomized(flat: np.ndarray, fold_of: np.ndarray, folds: int, ks, *, progress=None,
                               cancelled=None, oversample: int = 10, power_iterations: int = 1) -> np.ndarray:
    """k-fold generalization errors for large studies, with bounded memory.

    Each fold's leading modes come from a randomized SVD of its centred training rows,
    applied implicitly ((X − 1μᵀ)M = XM − 1(μᵀM), test rows weighted 0), so no n × n
    Gram matrix and no copy of the n × 3N data is made. The held-out residuals are
    evaluated in float32 (errors of tenths of a mm, 7 significant digits). One power
    iteration is enough (``docs/history.md``, Model).
    """
    n, d = flat.shape
    kmax = ks[-1]
    ell = int(min(kmax + oversample, n, d))
    errors = np.zeros((n, len(ks)))
    rng = np.random.default_rng(0)
    for f in range(folds):
        check_cancelled(cancelled)
        report(progress, 0.05 + 0.95 * f / folds, f"generalization: fold {f + 1}/{folds}")
        test = np.flatnonzero(fold_of == f)
        train_w = (fold_of != f).astype(float)
        mu = (train_w @ flat) / train_w.sum()

        def a_times(m, mu=mu, w=train_w):
            return (flat @ m - (mu @ m)[None]) * w[:, None]

        def at_times(y, mu=mu):
            return flat.T @ y - np.outer(mu, y.sum(axis=0))

        y = a_times(rng.standard_normal((d, ell)))
        for _ in range(power_iterations):
            qy, _ = np.linalg.qr(y)
            z, _ = np.linalg.qr(at_times(qy))
            y = a_times(z)
        qy, _ = np.linalg.qr(y)
        _, _, vt = np.linalg.svd(at_times(qy).T, full_matrices=False)
        modes = vt[:kmax].astype(np.float32)
        yt = (flat[test] - mu).astype(np.float32)
        errors[test] = _reconstruction_errors(yt, modes, ks)
    return errors


def _reconstruction_errors(y: np.ndarray, modes: np.ndarray, ks) -> np.ndarray:
    """(h, len(ks)) mean point distances (mm) of held-out vectors ``y`` (h, 3N, centred)
    to their reconstruction with the first k of ``modes`` (rows, orthonormal), for each k.
    ``y`` is updated in place (pass a copy)."""
    b = y @ modes.T
    out = np.empty((len(y), len(ks)))
    prev = 0
    for j, k in enumerate(ks):
        kk = min(k, modes.shape[0])
        if kk > prev:
            y -= b[:, prev:kk] @ modes[prev:kk]
            prev = kk
        out[:, j] = _point_errors(y)
    return out


def _generalization_folds(x, flat, raw_gram, total, fold_of, ks, alignment, progress, cancelled, *, raw_cov=None,
                          by_covariance=False):
    """The exact folds (Gram route, the covariance route, or Procrustes per fold): errors (n, len(ks))."""
    n = x.shape[0]
    folds = int(fold_of.max()) + 1
    kmax = ks[-1]
    errors = np.zeros((n, len(ks)))
    for f in range(folds):
        check_cancelled(cancelled)
        report(progress, 0.05 + 0.95 * f / folds, f"generalization: fold {f + 1}/{folds}")
        test = np.flatnonzero(fold_of == f)
        train = np.flatnonzero(fold_of != f)
        scale = np.ones(len(test))
        if raw_cov is not None:
            # the training products: all shapes' less the test shapes', centred on the training mean
            mu = (total - flat[test].sum(axis=0)) / len(train)
            cov = raw_cov - flat[test].T @ flat[test] - len(train) * np.outer(mu, mu)
            errors[test] = _reconstruction_errors(flat[test] - mu, _top_modes_from_covariance(cov, kmax), ks)
            continue
        if raw_gram is not None:
            mu = (total - flat[test].sum(axis=0)) / len(train)  # no copy of the training block
            data, rows = flat, train
            kt = raw_gram[np.ix_(train, train)]
            rm = kt.mean(axis=0)
            g = kt - rm[None] - rm[:, None] + rm.mean()
            y = flat[test] - mu
        else:
            aligned, _ = generalized_procrustes(x[train], scale=alignment == "similarity")
            mean_shape = aligned.mean(axis=0)
            s, rot, t = procrustes_fit(x[test], mean_shape, scale=alignment == "similarity")
            ya = s[:, None, None] * np.einsum("inj,ikj->ink", x[test], rot) + t[:, None]
            xt = aligned.reshape(len(train), -1)
            mu = xt.mean(axis=0)
            y = ya.reshape(len(test), -1) - mu
            data, rows = xt - mu, slice(None)
            mu = np.zeros_like(mu)
            scale = s
            if by_covariance:
                errors[test] = _reconstruction_errors(y.copy(), _top_modes_from_covariance(data.T @ data, kmax),
                                                      ks) / scale[:, None]
                continue
            g = data @ data.T
        modes = _top_modes(data, rows, mu, g, kmax)
        errors[test] = _reconstruction_errors(y.copy(), modes, ks) / scale[:, None]
    return errors


# ---------------------------------------------------------------------------------------
# Specificity
# ---------------------------------------------------------------------------------------
def specificity(
    model: ShapeModel,
    *, instance_points=None,
    ks=None,
    n_samples: int = 500,
    seed: int = 0,
    chunk: int = 128,
    progress=None,
    cancelled=None,
) -> dict:
    """Specificity S(k): distance of random model shapes to the nearest training shape.

    Samples z ~ N(0, I) are drawn once (seeded) and shared by every k (common random
    numbers): b_j = z_j √λ_j for j <= k, shape = p̄ + Q_k b (eq. 7). The nearest training
    shape minimises the sum of squared distances, found from the scores without forming
    the n x 3N differences: |s - x_i|² = |b|² - 2 b·Q_kᵀ(x_i - p̄) + |x_i - p̄|².

    Parameters
    ----------
    model : ShapeModel
    instance_points : (n, N, 3) array_like, optional
        Training shapes in the model frame (default: ``model.instance_points``).
    ks : sequence of int, optional
        Numbers of modes (default 1..min(30, K)).
    n_samples : int
        Random shapes per k.

    Returns
    -------
    dict with ``k``, ``mean_mm``, ``std_mm`` (over samples), ``rms_mean_mm``,
    ``n_samples``, ``seed``, ``seconds``.
    """
    t0 = time.perf_counter()
    x = model.instance_points if instance_points is None else np.asarray(instance_points, dtype=float)
    if x.ndim != 3 or x.shape[1:] != model.mean.shape or x.shape[0] < 1:
        raise InputError(f"specificity: training shapes have shape {x.shape}; expected (n, {model.n_points}, 3)")
    if model.n_modes == 0:
        raise InputError("specificity: the model has no modes")
    if ks is None:
        ks = list(range(1, min(30, model.n_modes) + 1))
    ks = sorted({int(k) for k in ks if 1 <= int(k) <= model.n_modes})
    if not ks:
        raise InputError(f"specificity: no valid k (1..{model.n_modes})")
    n = x.shape[0]
    flat = x.reshape(n, -1)
    mu = model.mean.reshape(-1)
    kmax = ks[-1]
    q = model.modes[:kmax].reshape(kmax, -1)
    scores = np.empty((n, kmax))
    norms = np.empty(n)
    rows = max(1, (1 << 24) // max(flat.shape[1], 1))  # centred rows in blocks of 128 MB: no n x 3N copy
    for start in range(0, n, rows):
        c = flat[start:start + rows] - mu
        scores[start:start + rows] = c @ q.T  # (n, kmax)
        norms[start:start + rows] = (c**2).sum(axis=1)
    rng = np.random.default_rng(seed)
    sd = model.standard_deviations[:kmax]
    total = int(n_samples)
    # samples in blocks (bounded memory for any n_samples); the generator fills row after
    # row, so the blocks are the same numbers as one (n_samples, kmax) draw
    block = max(1, min(total, (1 << 22) // max(n + kmax, 1)))
    sums = np.zeros((len(ks), 3))  # per k: sum of errors, of squared errors, of RMS distances
    lowest = np.full(len(ks), np.inf)  # per k: the smallest error (the plot's bars stop there)
    done = 0
    while done < total:
        z = rng.standard_normal((min(block, total - done), kmax))
        for j, k in enumerate(ks):
            check_cancelled(cancelled)
            report(progress, (done + (j / len(ks)) * len(z)) / total, f"specificity: k = {k}")
            b = z[:, :k] * sd[:k]
            d2 = (b**2).sum(axis=1)[:, None] - 2.0 * b @ scores[:, :k].T + norms[None]
            nearest = np.argmin(d2, axis=1)
            err = np.empty(len(b))
            for start in range(0, len(b), chunk):
                sl = slice(start, start + chunk)
                diff = b[sl] @ q[:k] - (flat[nearest[sl]] - mu)
                err[sl] = _point_errors(diff)
            rms_b = np.sqrt(np.maximum(d2[np.arange(len(b)), nearest], 0.0) / model.n_points)
            sums[j] += (err.sum(), (err * err).sum(), rms_b.sum())
            lowest[j] = min(lowest[j], float(err.min()))
        done += len(z)
    means = [float(s[0] / total) for s in sums]
    stds = [float(np.sqrt(max(s[1] / total - (s[0] / total) ** 2, 0.0))) for s in sums]
    rms = [float(s[2] / total) for s in sums]
    report(progress, 1.0, "specificity done")
    return {
        "k": ks,
        "mean_mm": means,
        "std_mm": stds,
        "min_mm": lowest.tolist(),
        "rms_mean_mm": rms,
        "n_samples": int(n_samples),
        "seed": seed,
        "error": "mean point-to-point distance (mm) of a random model shape to the nearest training shape",
        "seconds": time.perf_counter() - t0,
    }


def evaluate(
    model: ShapeModel,
    *, ks=None,
    n_samples: int = 500,
    seed: int = 0,
    max_loo: int = 100,
    progress=None,
    cancelled=None,
) -> ModelMetrics:
    """Compactness, generalization and specificity of a model on its own training shapes.

    Generalization refits from ``model.instance_points`` (the model frame); for an
    aligned model each fold re-runs the same Procrustes alignment on its training part.
    """
    comp = compactness(model)
    gen = generalization(
        model.instance_points,
        faces=model.faces,
        ks=ks,
        alignment=model.alignment,
        max_loo=max_loo,
        seed=seed,
        progress=sub_progress(progress, 0.0, 0.7),
        cancelled=cancelled,
    )
    spe = specificity(
        model, ks=ks, n_samples=n_samples, seed=seed, progress=sub_progress(progress, 0.7, 1.0), cancelled=cancelled
    )
    return ModelMetrics(compactness=comp, generalization=gen, specificity=spe)


# ---------------------------------------------------------------------------------------
# Fit figures and the report
# ---------------------------------------------------------------------------------------
def _as_dict(fit) -> dict:
    if fit is None:
        return {}
    if dataclasses.is_dataclass(fit) and not isinstance(fit, type):
        return dataclasses.asdict(fit)
    if isinstance(fit, str):
        try:
            fit = json.loads(fit)
        except json.JSONDecodeError:
            return {}
    return dict(fit) if isinstance(fit, dict) else {}


def aggregate_fit(per_instance: dict) -> dict:
    """Summary (mean, std, min, max, n) of every numeric scalar fit figure over instances.

    Parameters
    ----------
    per_instance : dict name -> fit figures (dict, JSON string or dataclass, e.g. the
        coating's ``FitFigures``).
    """
    values: dict[str, list[float]] = {}
    for fit in (per_instance or {}).values():
        for key, val in _as_dict(fit).items():
            if isinstance(val, (bool, np.bool_)):
                val = float(val)
            if isinstance(val, (int, float, np.integer, np.floating)) and math.isfinite(float(val)):
                values.setdefault(key, []).append(float(val))
    out = {}
    for key, vals in values.items():
        a = np.asarray(vals)
        out[key] = {"mean": a.mean(), "std": a.std(), "min": a.min(), "max": a.max(), "n": len(a)}
    return jsonable(out)


def model_summary(model: ShapeModel) -> dict:
    """Numbers that describe a model (sizes, spectrum, eq. 8 both ways)."""
    k = model.n_modes
    coord = model.variability_concentration("coordinate") if model.n_points else np.zeros(0)
    return jsonable(
        {
            "n_instances": model.n_instances,
            "n_points": model.n_points,
            "n_faces": int(len(model.faces)),
            "n_modes": k,
            "instance_names": [str(s) for s in model.instance_names],
            "variances_mm2": model.variances,
            "standard_deviations_mm": model.standard_deviations,
            "total_variance_mm2": model.total_variance,
            "concentration_eigen": model.variability_concentration("eigen"),
            "concentration_coordinate_first_k": coord[: max(k, 1)],
            "point_variance_mm2": {
                "mean": float(model.point_variance.mean()) if model.n_points else 0.0,
                "max": float(model.point_variance.max()) if model.n_points else 0.0,
            },
            "params": model.params,
        }
    )


# ---------------------------------------------------------------------------------------
# Plots (paper fig. 9)
# ---------------------------------------------------------------------------------------
def _import_plotting() -> None:
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: F401
        from matplotlib.figure import Figure  # noqa: F401
        from matplotlib.ticker import FuncFormatter  # noqa: F401
    except ImportError:  # pragma: no cover - depends on the environment; the plots say so
        pass


def import_plotting_in_background() -> threading.Thread:
    """Start importing matplotlib's figure, Agg canvas and tickers (about 0.4 s) on a daemon
    thread and return the thread. A build starts it before its coating, whose work runs in
    worker processes, so the plots drawn after the model do not wait for the import; the
    plots are the same. Without matplotlib the thread ends and the plots are skipped as
    before (:func:`write_plots`)."""
    thread = threading.Thread(target=_import_plotting, name="ssm-import-plotting", daemon=True)
    thread.start()
    return thread


def _figure(width=5.0, height=3.6, ncols=1):
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise SSMError("plots need matplotlib, which is not installed (pip install matplotlib); plots skipped") from err
    fig = Figure(figsize=(width * ncols, height), dpi=100)
    fig.subplots_adjust(left=0.16 / ncols, right=1 - 0.04 / ncols, bottom=0.14, top=0.9, wspace=0.3)
    FigureCanvasAgg(fig)
    axes = [fig.add_subplot(1, ncols, i + 1) for i in range(ncols)]
    return fig, axes


def draw_spectrum(ax, model):
    k = np.arange(1, model.n_modes + 1)
    lam = np.maximum(model.variances, np.finfo(float).tiny)
    ax.bar(k, lam, color="#4477aa")
    ax.set_yscale("log")
    ax.set_xlabel("mode k")
    ax.set_ylabel("eigenvalue λ_k (mm²)")
    ax.set_title("Eigenvalue spectrum")


def draw_cumulative(ax, model, coordinate=None):
    k = np.arange(1, model.n_modes + 1)
    ax.plot(k, 100 * model.variability_concentration("eigen"), "o-", ms=3, color="#aa3377", label="eigenvalues")
    coord = (model.variability_concentration("coordinate") if coordinate is None else np.asarray(coordinate))
    coord = coord[: model.n_modes]
    ax.plot(k[: len(coord)], 100 * coord, "s--", ms=2, color="#999933",
            label="k largest point-coordinate variances\n(no PCA: what the modes gain over raw coordinates)")
    ax.set_xscale("log")
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:g}"))  # 1, 2, 5, 10 … not colliding 3×10⁰
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_ylim(0, 101)
    ax.set_xlabel("number of modes k")
    ax.set_ylabel("variability captured (%)")
    ax.set_title("Concentration of variability (eq. 8)")
    ax.grid(True, which="both", alpha=0.3)
    _legend_below(ax)


def _legend_below(ax) -> None:
    """The legend under the axes (below the x label), never over a curve."""
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), fontsize="small", frameon=False)
    ax.figure.subplots_adjust(bottom=0.34)


def _save(fig, path):
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def modes_figure_labels(model: ShapeModel, n_modes: int, sigmas: float = 2.0) -> list[str]:
    """Row labels of the fig-10 picture: the mean, then each mode with ±σ and its share of the variance."""
    share = model.variances / max(model.total_variance, np.finfo(float).tiny)
    rows = ["mean shape"]
    for k in range(min(int(n_modes), model.n_modes)):
        rows.append(f"mode {k + 1}: {100 * share[k]:.1f} % of variance\n"
                    f"blue −{sigmas:g}σ, red +{sigmas:g}σ")
    return rows


#: Patient directions of the model frame's axes (+, −) when the object frames follow the patient
#: axes (frame method "auto" or "patient"): x right, y anterior, z superior.
AXIS_LETTERS = (("R", "L"), ("A", "P"), ("S", "I"))
#: The axes' names when they need not be patient directions (moments frames, other tools' models).
AXIS_NAMES = (("+x", "−x"), ("+y", "−y"), ("+z", "−z"))


def patient_oriented(model: ShapeModel) -> bool:
    """Whether the model frame's axes are patient directions: every instance's object frame
    paired its axes with R, A, S (``frame_methods``; a model written before they were recorded:
    its frame setting was "auto" or "patient")."""
    methods = model.params.get("frame_methods")
    if methods is not None:
        return list(methods) == ["patient"]
    return model.params.get("frame_method") in ("auto", "patient")


_PERMUTATIONS = ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0))


def display_axes(model: ShapeModel) -> np.ndarray:
    """(3, 3) the turn that shows a model as its instances lay in their files: ``D @ p`` for a point
    ``p`` of the model frame.

    A model frame that follows the patient axes (:func:`patient_oriented`) is shown as it is (the
    identity). Other frames (second-moment axes of meshes in no stated convention: the longest axis
    is x, so a femur would lie down) are turned by the proper signed axis permutation nearest to the
    instances' mean turn from the model frame to their file coordinates (a rigid fit of each
    instance's aligned points to its world points, ``instance_points_world``): a bone scanned
    standing stands. Only how the model is shown changes (pictures, ``model.blend``'s object
    rotation, ``model.glb``'s node); the model's arrays stay in the model frame. A copy of the
    model without its training shapes carries the turn in ``params["display_axes"]``.
    """
    if model.params.get("display_axes") is not None:
        return np.asarray(model.params["display_axes"], float).reshape(3, 3)
    world = model.instance_points_world
    if (patient_oriented(model) or world is None or not model.n_instances or len(world) != model.n_instances
            or np.shape(world)[1:] != np.shape(model.instance_points)[1:] or not np.shape(world)[1]):
        return np.eye(3)
    turn = np.zeros((3, 3))
    points, world = np.asarray(model.instance_points, float), np.asarray(world, float)
    for x, w in zip(points[own_side_instances(model)], world[own_side_instances(model)]):
        u, _s, vt = np.linalg.svd((w - w.mean(axis=0)).T @ (x - x.mean(axis=0)))  # w ≈ R x: R = U diag(1, 1, d) Vᵀ
        d = np.sign(np.linalg.det(u @ vt)) or 1.0
        turn += u @ np.diag([1.0, 1.0, d]) @ vt
    best = max(_PERMUTATIONS, key=lambda perm: sum(abs(turn[perm[j], j]) for j in range(3)))
    out = np.zeros((3, 3))
    for j, i in enumerate(best):
        out[i, j] = 1.0 if turn[i, j] >= 0 else -1.0
    if np.linalg.det(out) < 0:  # a mirror: the weakest pairing's sign gives way
        j = min(range(3), key=lambda j: abs(turn[best[j], j]))
        out[best[j], j] *= -1.0
    return out


def axis_letters(model: ShapeModel):
    """:data:`AXIS_LETTERS` for a model whose frames follow the patient axes, else :data:`AXIS_NAMES`."""
    return AXIS_LETTERS if patient_oriented(model) else AXIS_NAMES


def view_names(model: ShapeModel, views) -> list[str]:
    """The views' titles: the patient planes (axial, sagittal, coronal) where the model frame
    follows the patient axes, else the axis a view looks along."""
    along = {"axial": "view along z", "sagittal": "view along x", "coronal": "view along y"}
    return [v if patient_oriented(model) else along.get(v, v) for v in views]


def view_orientation(screen_from_model: np.ndarray, letters=AXIS_LETTERS) -> str:
    """Where the model's axes point on screen for a view (rows: screen x, screen y):
    ``"R → · S ↑"`` (screen right is the model's +x, R; screen up its +z, S)."""
    out = []
    for row, arrow in zip(np.asarray(screen_from_model, float)[:2], ("→", "↑")):
        axis = int(np.argmax(np.abs(row)))
        out.append(f"{letters[axis][0 if row[axis] > 0 else 1]} {arrow}")
    return " · ".join(out)


def scale_bar_mm(mm_per_px: float, cell_px: float) -> float:
    """A round scale-bar length (mm) near a fifth of a cell."""
    target = 0.2 * cell_px * mm_per_px
    for v in (1, 2, 5, 10, 20, 50, 100, 200, 500):
        if v >= target:
            return float(v)
    return 1000.0


def label_grid_picture(grid_rgb: np.ndarray, path_png, *, row_labels, column_labels, title: str = "",
                       mm_per_px: float | None = None) -> Path:
    """A rendered picture grid (rows × columns of equal cells) with row and column labels.

    Used for the paper's fig. 10 (``operators/render.py`` renders the shapes; the
    labels are drawn here, so the picture reads on its own in a paper).

    Parameters
    ----------
    grid_rgb : (H, W, 3 or 4) array in [0, 1]
        The cells, ``len(row_labels)`` rows by ``len(column_labels)`` columns.
    mm_per_px : float, optional
        The render's scale: a scale bar (mm) is drawn in the bottom-left cell.
    """
    img = np.asarray(grid_rgb)
    h, w = img.shape[:2]
    n_rows, n_cols = len(row_labels), len(column_labels)
    left_px, top_px = 320, 110 if title else 70
    fig, _ = _figure(width=(w + left_px + 20) / 100, height=(h + top_px + 10) / 100)
    fig.clear()
    ax = fig.add_axes([left_px / (w + left_px + 20), 10 / (h + top_px + 10), w / (w + left_px + 20),
                       h / (h + top_px + 10)])
    ax.imshow(img, interpolation="lanczos")
    ax.set_xticks([(c + 0.5) * w / n_cols for c in range(n_cols)], column_labels, fontsize=15)
    ax.xaxis.tick_top()
    ax.set_yticks([(r + 0.5) * h / n_rows for r in range(n_rows)], row_labels, fontsize=13)
    ax.tick_params(length=0)
    for spine in ax.spines.values():
        spine.set_visible(False)
    for r in range(1, n_rows):
        ax.axhline(r * h / n_rows, color="#bbbbbb", lw=0.8)
    for c in range(1, n_cols):
        ax.axvline(c * w / n_cols, color="#bbbbbb", lw=0.8)
    if mm_per_px:
        cell_w, cell_h = w / n_cols, h / n_rows
        length = scale_bar_mm(mm_per_px, cell_w)
        x0, y0 = 0.08 * cell_w, h - 0.08 * cell_h
        ax.plot([x0, x0 + length / mm_per_px], [y0, y0], color="black", lw=3, solid_capstyle="butt")
        ax.text(x0, y0 - 0.03 * cell_h, f"{length:g} mm", fontsize=12, va="bottom")
    if title:
        fig.suptitle(title, fontsize=16, y=1 - 12 / (h + top_px + 10), va="top")
    return _save(fig, path_png)


def plot_spectrum(model: ShapeModel, path_png):
    """Eigenvalues λ_k on a log scale (paper fig. 9, left). Returns the PNG path."""
    fig, (ax,) = _figure()
    draw_spectrum(ax, model)
    return _save(fig, path_png)


def plot_cumulative_variance(model: ShapeModel, path_png, coordinate=None):
    """Concentration of variability (eq. 8) over k (paper fig. 9, right); ``coordinate``: the
    coordinates' concentration when ``model`` no longer holds its training shapes (a drawing copy).
    Returns the PNG path."""
    fig, (ax,) = _figure()
    draw_cumulative(ax, model, coordinate)
    return _save(fig, path_png)


def plot_model_figure(model: ShapeModel, path_png, coordinate=None):
    """Both panels of paper fig. 9 side by side (``coordinate`` as :func:`plot_cumulative_variance`).
    Returns the PNG path."""
    fig, (a, b) = _figure(ncols=2, height=4.6)
    draw_spectrum(a, model)
    draw_cumulative(b, model, coordinate)
    return _save(fig, path_png)


def metric_bars(m: dict) -> tuple[np.ndarray, np.ndarray]:
    """A generalization or specificity record's means and error bars (mm, per k): ``(mean, bars)``,
    ``bars`` (2, K) below and above the mean, one SD each, the lower one stopping at the smallest
    distance the metric measured (its ``min_mm``, else its left-out instances' smallest, else 0):
    a distance bar never reaches below what was measured, nor below 0."""
    mean, sd = np.asarray(m["mean_mm"], float), np.asarray(m["std_mm"], float)
    if m.get("min_mm") is not None:
        smallest = np.asarray(m["min_mm"], float)
    elif m.get("per_instance_mm"):
        smallest = np.asarray(m["per_instance_mm"], float).min(axis=0)
    else:
        smallest = np.zeros_like(mean)
    return mean, np.stack([np.clip(mean - np.maximum(smallest, 0.0), 0.0, sd), sd])


def plot_metrics(metrics: ModelMetrics, path_png):
    """Compactness (cumulative share of the variance, %) and generalization and specificity (mean
    ± std, mm) over the number of modes k, side by side. Returns the PNG path."""
    fig, (left, right) = _figure(ncols=2, height=4.6)
    comp = (metrics.compactness or {}).get("cumulative")
    if comp:
        k = np.arange(1, len(comp) + 1)
        left.plot(k, 100 * np.asarray(comp, float), "o-", ms=3, color="#4477aa")
    left.set_ylim(0, 101)
    left.set_xlabel("number of modes k")
    left.set_ylabel("variance captured (%)")
    left.set_title("Compactness")
    left.grid(True, alpha=0.3)
    for key, colour, label in (("generalization", "#228833", "generalization: mean ± SD over the left-out instances"),
                               ("specificity", "#ee6677", "specificity: mean ± SD over the random model shapes")):
        m = getattr(metrics, key)
        if m:
            mean, bars = metric_bars(m)
            right.errorbar(m["k"], mean, yerr=bars, fmt="o-", ms=3, capsize=2, color=colour, label=label)
    if right.get_legend_handles_labels()[0]:
        right.set_ylim(bottom=0.0)
        right.text(0.01, 0.01, "a bar below the mean stops at the smallest distance measured", fontsize=7,
                   transform=right.transAxes, color="#555555")
    right.set_xlabel("number of modes k")
    right.set_ylabel("mean point distance (mm)")
    right.set_title("Generalization and specificity")
    if right.get_legend_handles_labels()[0]:
        _legend_below(right)
    right.grid(True, alpha=0.3)
    return _save(fig, path_png)


def write_plots(model: ShapeModel, out_dir, metrics: ModelMetrics | None = None, *, coordinate=None) -> dict:
    """Write spectrum, cumulative variance, fig. 9 and metrics plots into ``out_dir``.

    ``coordinate``: the coordinates' concentration of variability (eq. 8, at least the model's
    modes long), for a drawing copy of the model without its training shapes.

    Returns {"files": [...]} or {"files": [], "skipped": message} without matplotlib.
    """
    out_dir = Path(out_dir)
    try:
        files = [
            plot_spectrum(model, out_dir / "spectrum.png"),
            plot_cumulative_variance(model, out_dir / "cumulative_variance.png", coordinate),
            plot_model_figure(model, out_dir / "variability.png", coordinate),
        ]
        if metrics is not None and (metrics.generalization or metrics.specificity):
            files.append(plot_metrics(metrics, out_dir / "metrics.png"))
    except SSMError as err:
        return {"files": [], "skipped": str(err)}
    return {"files": [str(f) for f in files]}
