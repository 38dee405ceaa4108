"""Permutation tests of shape on a linear model: the engine behind group and covariate analysis.

Shapes are ``(n, N, 3)`` corresponding points (mm, one frame). A *term* (a group factor, a
covariate) is tested against a *reduced model* (intercept and the other terms) by the
Freedman–Lane permutation of the reduced model's residuals [1]_, globally and at every
point:

- **global**: Pillai's trace of the term on the reduced model's leading residual modes
  (those that hold :data:`GLOBAL_VARIANCE` of the residual variance, at most
  n − p − 1 of them), so a difference confined to a small mode counts as much as one along
  the largest (``p_value``); and the pseudo-F of the term on all 3N coordinates (Goodall's
  F / Procrustes ANOVA as in geometric morphometrics [2]_), which large modes dominate
  (``p_value_f``);
- **per point**: the term's share of the point's residual scatter, ``V = tr(H E⁻¹)`` with
  ``H`` the term's 3×3 sum of squares and ``E`` the reduced model's residual scatter at that
  point (Pillai's trace; for two groups without covariates the two-sample Hotelling
  ``T² = (n − 2) V / (1 − V)``); p-values by permutation, Benjamini–Hochberg FDR across
  points [3]_ and the family-wise maximum-statistic p-value [4]_.

All permutations are evaluated as matrix products (no Python loop over permutations or
points), and they come from one seed, so a result never depends on a library's
iteration order.

References
----------
.. [1] Freedman D, Lane D (1983). A nonstochastic interpretation of reported significance
   levels. J Bus Econ Stat 1(4):292–298. Anderson MJ, Robinson J (2001). Permutation
   tests for linear models. Aust N Z J Stat 43(1):75–88.
.. [2] Goodall C (1991). Procrustes methods in the statistical analysis of shape. J R
   Stat Soc B 53(2):285–339. Collyer ML, Sekora DJ, Adams DC (2015). A method for
   analysis of phenotypic change for phenotypes described by high-dimensional data.
   Heredity 115:357–365.
.. [3] Benjamini Y, Hochberg Y (1995). Controlling the false discovery rate. J R Stat Soc
   B 57(1):289–300.
.. [4] Westfall PH, Young SS (1993). Resampling-Based Multiple Testing. Wiley.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..base.errors import Cancelled, InputError
from ..model.pca import gram_factor

__all__ = ["TermTest", "benjamini_hochberg", "centroid_size", "orthonormal_basis", "permutation_orders",
           "term_test"]

#: Share of the residual variance the global test's modes hold.
GLOBAL_VARIANCE = 0.95

#: Memory (bytes) one block of permuted products may take.
BLOCK_BYTES = 64 * 2**20


def centroid_size(points) -> np.ndarray:
    """Centroid size of each shape: sqrt of the summed squared distances of its points from
    their centroid (mm).

    Parameters
    ----------
    points : (n, N, 3) or (N, 3) array_like, mm

    Returns
    -------
    (n,) ndarray or float, mm

    >>> float(centroid_size([[1, 0, 0], [-1, 0, 0]]))
    1.4142135623730951
    """
    p = np.asarray(points, dtype=float)
    c = p - p.mean(axis=-2, keepdims=True)
    return np.sqrt(np.einsum("...ij,...ij->...", c, c))


def benjamini_hochberg(p) -> np.ndarray:
    """Benjamini–Hochberg adjusted p-values (q-values) of a family of tests [3]_.

    >>> benjamini_hochberg([0.01, 0.04, 0.03]).round(3).tolist()
    [0.03, 0.04, 0.04]
    """
    p = np.asarray(p, dtype=float)
    m = p.size
    if m == 0:
        return p.copy()
    order = np.argsort(p, kind="stable")
    ranked = p[order] * m / np.arange(1, m + 1)
    q = np.minimum.accumulate(ranked[::-1])[::-1]
    out = np.empty(m)
    out[order] = np.minimum(q, 1.0)
    return out


def permutation_orders(n: int, permutations: int, seed: int = 0) -> np.ndarray:
    """``(permutations, n)`` row orders drawn from ``seed``: the argsort of uniform draws
    (PCG64 doubles, stable sort), so the same seed gives the same orders on every numpy."""
    rng = np.random.Generator(np.random.PCG64(int(seed)))
    return np.argsort(rng.random((int(permutations), int(n))), axis=1, kind="stable")


def orthonormal_basis(matrix, *, tol: float = 1e-10) -> np.ndarray:
    """Orthonormal basis ``(n, r)`` of the column space of ``matrix`` (SVD, rank by ``tol``
    relative to the largest singular value)."""
    a = np.asarray(matrix, dtype=float)
    if a.shape[1] == 0:
        return np.zeros((a.shape[0], 0))
    u, s, _ = np.linalg.svd(a, full_matrices=False)
    keep = s > tol * max(float(s[0]), 1e-300) if s.size else np.zeros(0, bool)
    u = u[:, keep]
    # sign convention: the largest entry of each column positive (SVD signs vary by LAPACK)
    idx = np.argmax(np.abs(u), axis=0)
    return u * np.sign(u[idx, np.arange(u.shape[1])])


@dataclass(frozen=True)
class TermTest:
    """The permutation test of one term.

    Attributes
    ----------
    df : int
        Degrees of freedom of the term (levels − 1 for a category, 1 for a covariate).
    residual_df : int
        n − (columns of the full model).
    f : float
        Pseudo-F on all coordinates (Goodall's F); ``p_value_f`` its permutation p-value.
    global_pillai : float
        Pillai's trace of the term on ``global_modes`` leading residual modes.
    r_squared : float
        The term's sum of squares over the total sum of squares about the mean (partial R²).
    p_value : float
        The global test's permutation p-value (Pillai's trace on the leading modes),
        ``(1 + #{V* >= V}) / (1 + permutations)``.
    pillai : (N,) ndarray
        Per-point statistic V in [0, min(df, 3)].
    p_point : (N,) ndarray
        Per-point permutation p-values.
    p_fdr : (N,) ndarray
        Benjamini–Hochberg adjusted ``p_point``.
    p_fwer : (N,) ndarray
        Maximum-statistic (family-wise) adjusted p-values.
    permutations : int
    """

    df: int
    residual_df: int
    f: float
    r_squared: float
    p_value: float
    p_value_f: float
    global_pillai: float
    global_modes: int
    pillai: np.ndarray
    p_point: np.ndarray
    p_fdr: np.ndarray
    p_fwer: np.ndarray
    permutations: int

    @property
    def hotelling_t2(self) -> np.ndarray:
        """(N,) Hotelling's T² = residual_df · V / (1 − V) (the two-sample T² for a two-level term
        without covariates)."""
        v = np.clip(self.pillai, 0.0, 1.0 - 1e-15)
        return self.residual_df * v / (1.0 - v)


def _whitening(residuals: np.ndarray) -> np.ndarray:
    """Per-point (N, 3, 3) E^{-1/2} of the residual scatter E = Rᵀ R (pseudo-inverse where E is
    rank deficient, e.g. a point that never moves)."""
    scatter = np.einsum("inj,ink->njk", residuals, residuals)
    w, v = np.linalg.eigh(scatter)
    top = np.maximum(w[:, -1:], 1e-300)
    inv = np.where(w > 1e-12 * top, 1.0 / np.sqrt(np.maximum(w, 1e-300)), 0.0)
    return np.einsum("nij,nj,nkj->nik", v, inv, v)


def term_test(points, reduced, term, *, permutations: int = 1000, seed: int = 0, per_point: bool = True,
              cancelled=None) -> TermTest:
    """Test a term of a linear model of shape by Freedman–Lane permutation.

    Parameters
    ----------
    points : (n, N, 3) array_like, mm
        Corresponding points of the n shapes (one frame).
    reduced : (n, p0) array_like
        Design of the reduced model; must contain the intercept column.
    term : (n, q) array_like
        The term's design columns (dummy-coded levels, or a covariate).
    permutations : int
        Number of random permutations (>= 1); p-values have resolution 1 / (permutations + 1).
    seed : int
        Seed of the permutation orders (:func:`permutation_orders`).
    per_point : bool
        Also compute the per-point statistic and its p-values (else those arrays are empty).
    cancelled : callable, optional
        Returns True to stop (raises :class:`~ssm_addon.base.errors.Cancelled`).

    Returns
    -------
    TermTest
    """
    x = np.asarray(points, dtype=float)
    n, n_points = x.shape[0], x.shape[1]
    d0 = np.asarray(reduced, dtype=float).reshape(n, -1)
    d1 = np.asarray(term, dtype=float).reshape(n, -1)
    u0 = orthonormal_basis(d0)
    flat_x = x.reshape(n, -1)
    r0 = (flat_x - u0 @ (u0.T @ flat_x)).reshape(x.shape)  # (I − H0) X
    uq = orthonormal_basis(d1 - u0 @ (u0.T @ d1))
    q = uq.shape[1]
    residual_df = n - u0.shape[1] - q
    if q == 0:
        raise InputError("the term adds nothing to the reduced model (its columns are constant or repeat others)")
    if residual_df < 1:
        raise InputError(f"{n} instances cannot fit a model of {u0.shape[1] + q} columns: need more instances "
                         "than columns")
    flat = r0.reshape(n, -1)
    # Global: squared norms need only the residuals' Gram matrix; factor it as Z Zᵀ (n × r).
    w, z, v = gram_factor(flat)
    total_r0 = float(np.sum(w))
    # the leading residual modes, whitened (the Gram matrix's eigenvectors, largest first)
    share = np.cumsum(w[::-1]) / max(total_r0, 1e-300)
    k_modes = int(min(np.searchsorted(share, GLOBAL_VARIANCE) + 1, max(residual_df - 1, 1), share.size))
    modes_w = v[:, ::-1][:, :k_modes]
    g_obs = float(np.sum((uq.T @ modes_w) ** 2))
    centred = flat_x - flat_x.mean(axis=0)
    total = float(np.sum(centred * centred))
    a_obs = float(np.sum((uq.T @ z) ** 2))
    f_obs = (a_obs / q) / max((total_r0 - a_obs) / residual_df, 1e-300)

    orders = permutation_orders(n, permutations, seed)
    # Permuting the residuals' rows equals gathering the bases' rows by the inverse order.
    inverse = np.argsort(orders, axis=1, kind="stable")
    ub = np.concatenate([u0, uq], axis=1)
    zm = np.concatenate([z, modes_w], axis=1)
    count_global = count_f = 0
    tol = 1e-9
    if per_point:
        whiten = _whitening(r0)
        rw = np.empty_like(r0)
        for j in range(3):  # (n, N, 3) @ (N, 3, 3) as three broadcast products
            rw[:, :, j] = np.sum(r0 * whiten[None, :, :, j], axis=2)
        rw = rw.reshape(n, -1)
        v_obs = np.sum(((uq.T @ rw) ** 2).reshape(q, n_points, 3), axis=(0, 2))
        counts = np.zeros(n_points, np.int64)
        max_stats = np.empty(int(permutations))
    block = max(1, int(BLOCK_BYTES // max(8 * q * flat.shape[1], 1)))
    for start in range(0, int(permutations), block):
        if cancelled is not None and cancelled():
            raise Cancelled("analysis cancelled")
        inv = inverse[start:start + block]
        c = inv.shape[0]
        # (c, p0 + q, n): row a of permutation k is column a of ub with its rows gathered by inv[k]
        gathered = np.ascontiguousarray(ub.T[:, inv].transpose(1, 0, 2))
        p0 = u0.shape[1]
        both = (gathered.reshape(-1, n) @ zm).reshape(c, p0 + q, -1)  # one product for both global statistics
        a = np.sum(both[:, p0:, : z.shape[1]] ** 2, axis=(1, 2))
        b = np.sum(both[:, :p0, : z.shape[1]] ** 2, axis=(1, 2))
        f = (a / q) / np.maximum((total_r0 - a - b) / residual_df, 1e-300)
        count_f += int(np.sum(f >= f_obs * (1 - tol)))
        gm = np.sum(both[:, p0:, z.shape[1]:] ** 2, axis=(1, 2))
        count_global += int(np.sum(gm >= g_obs * (1 - tol)))
        if per_point:
            prod = (gathered[:, p0:].reshape(c * q, n) @ rw).reshape(c, q, n_points, 3)
            vp = np.sum(prod**2, axis=(1, 3))  # (c, N)
            counts += np.sum(vp >= v_obs * (1 - tol), axis=0)
            max_stats[start:start + c] = vp.max(axis=1)
    p_value = (1 + count_global) / (1 + permutations)
    p_value_f = (1 + count_f) / (1 + permutations)
    if per_point:
        p_point = (1 + counts) / (1 + permutations)
        sorted_max = np.sort(max_stats)
        exceed = permutations - np.searchsorted(sorted_max, v_obs * (1 - tol), side="left")
        p_fwer = (1 + exceed) / (1 + permutations)
        p_fdr = benjamini_hochberg(p_point)
    else:
        v_obs = p_point = p_fdr = p_fwer = np.zeros(0)
    return TermTest(df=q, residual_df=residual_df, f=float(f_obs), r_squared=a_obs / max(total, 1e-300),
                    p_value=float(p_value), p_value_f=float(p_value_f), global_pillai=g_obs,
                    global_modes=k_modes, pillai=v_obs, p_point=p_point, p_fdr=p_fdr, p_fwer=p_fwer,
                    permutations=int(permutations))
