"""The landmark warp of paper 4.1, eq. (2): a thin-plate-type spline through the landmarks.

F(p) = p0 + A p + Σ_i w_i U(|p − p_i|) maps the template's landmarks onto an
instance's; U is the 3D biharmonic r (default), r² ln r or Hardy's (r² + s²)^a.
:func:`fold_free_warp` smooths the warp just enough that inconsistent landmarks do not
fold the template (det J > 0 at every template point). Coordinates in mm, object frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..base.errors import InputError
from ..base.params import KERNELS

__all__ = ["KERNELS", "ThinPlateSpline", "fold_free_warp", "landmark_warp", "warp_jacobian_det"]


# ---------------------------------------------------------------------------------------
# 4.1 Landmark warp, eq. (2)
# ---------------------------------------------------------------------------------------
def _kernel(r: np.ndarray, kernel: str, hardy_a: float, hardy_s_mm: float) -> np.ndarray:
    """Radial basis U(r) of eq. (2); r in mm."""
    if kernel == "biharmonic":
        return r
    if kernel == "thin-plate":
        with np.errstate(divide="ignore", invalid="ignore"):
            out = r * r * np.log(r)
        return np.where(r > 0.0, out, 0.0)
    return (r * r + hardy_s_mm * hardy_s_mm) ** hardy_a


@dataclass(frozen=True)
class ThinPlateSpline:
    """The landmark warp of eq. (2): F(p) = p0 + A p + sum_i w_i U(|p - p_i|).

    Coordinates are mm; the source landmarks are stored relative to their centroid
    ``offset_mm`` for a well-conditioned system (the map is the same).

    Attributes
    ----------
    centers_mm : (L, 3) source landmarks minus ``offset_mm``.
    weights : (L, 3) radial weights w_i.
    affine : (4, 3) rows: translation p0 (in centred coordinates), then A^T.
    offset_mm : (3,) centroid of the source landmarks.
    kernel, hardy_a, hardy_s_mm : the radial basis U.
    """

    centers_mm: np.ndarray
    weights: np.ndarray
    affine: np.ndarray
    offset_mm: np.ndarray
    kernel: str = "biharmonic"
    hardy_a: float = 0.5
    hardy_s_mm: float = 10.0

    def __call__(self, points: np.ndarray, chunk: int = 65536) -> np.ndarray:
        """Map (M, 3) points (mm, source frame) to (M, 3) points (mm, target frame)."""
        p = np.asarray(points, dtype=float).reshape(-1, 3) - self.offset_mm
        out = np.empty_like(p)
        for s in range(0, len(p), chunk):
            q = p[s : s + chunk]
            r = np.linalg.norm(q[:, None, :] - self.centers_mm[None, :, :], axis=2)
            u = _kernel(r, self.kernel, self.hardy_a, self.hardy_s_mm)
            out[s : s + chunk] = self.affine[0] + q @ self.affine[1:] + u @ self.weights
        return out


def landmark_warp(
    source_points: np.ndarray,
    target_points: np.ndarray,
    *,
    kernel: str = "biharmonic",
    hardy_a: float = 0.5,
    hardy_s_mm: float | None = None,
    regularization: float = 0.0,
) -> ThinPlateSpline:
    """Fit the landmark warp of eq. (2) (paper 4.1) that maps source onto target landmarks.

    Solves the bordered system [[K + λI, P], [P^T, 0]] [W; c] = [Y; 0] with
    K_ij = U(|p_i - p_j|) and P = [1, x, y, z], so the map is exact on the landmarks
    (for ``regularization`` 0) and reproduces every affine map exactly.

    Parameters
    ----------
    source_points, target_points : (L, 3) mm
        Corresponding landmarks in the source and target object frames.
    kernel : {"biharmonic", "thin-plate", "hardy"}
        U(r) = r (3D biharmonic, default), r² ln r, or Hardy's (r² + s²)^a.
    hardy_a : float
        Exponent a > 0 of the Hardy kernel.
    hardy_s_mm : float or None
        Hardy "stiffness radius" s in mm; None: the median distance between landmarks.
    regularization : float
        λ ≥ 0 added to the diagonal of K (smoothing spline; 0 = interpolation).

    Raises
    ------
    InputError
        Fewer than 4 landmarks, duplicates, coplanar/collinear source landmarks,
        non-finite values, mismatched shapes or an unknown kernel.
    """
    src = np.asarray(source_points, dtype=float)
    dst = np.asarray(target_points, dtype=float)
    if src.ndim != 2 or src.shape[1:] != (3,) or dst.shape != src.shape:
        raise InputError(
            f"landmark warp: source and target landmarks must both be (L, 3) arrays, got {src.shape} and {dst.shape}"
        )
    if kernel not in KERNELS:
        raise InputError(f"landmark warp: unknown kernel {kernel!r} (choose one of {', '.join(KERNELS)})")
    n = len(src)
    if n < 4:
        raise InputError(f"landmark warp: needs at least 4 landmarks (not all in one plane), got {n}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise InputError("landmark warp: landmark coordinates contain NaN or infinity")
    if regularization < 0:
        raise InputError(f"landmark warp: regularization must be >= 0, got {regularization}")
    offset = src.mean(axis=0)
    c = src - offset
    dist = np.linalg.norm(c[:, None, :] - c[None, :, :], axis=2)
    scale = float(dist.max())
    iu = np.triu_indices(n, 1)
    close = dist[iu] <= 1e-9 * max(scale, 1e-12)
    if scale <= 0 or np.any(close):
        i, j = iu[0][close][0], iu[1][close][0]
        raise InputError(f"landmark warp: source landmarks {i} and {j} are at the same position")
    sv = np.linalg.svd(c, compute_uv=False)
    if sv[2] <= 1e-6 * sv[0]:
        what = "collinear" if sv[1] <= 1e-6 * sv[0] else "coplanar"
        raise InputError(
            f"landmark warp: the {n} source landmarks are {what}; the affine part of eq. (2) is undetermined "
            "(place at least one landmark off their plane)"
        )
    if kernel == "hardy":
        if hardy_a <= 0:
            raise InputError(f"landmark warp: Hardy exponent a must be > 0, got {hardy_a}")
        s = float(np.median(dist[iu])) if hardy_s_mm is None else float(hardy_s_mm)
        if s <= 0:
            raise InputError(f"landmark warp: Hardy stiffness radius s must be > 0 mm, got {s}")
    else:
        s = float(hardy_s_mm) if hardy_s_mm is not None else 0.0
    k = _kernel(dist, kernel, hardy_a, s) + regularization * np.eye(n)
    p = np.hstack([np.ones((n, 1)), c])
    a = np.zeros((n + 4, n + 4))
    a[:n, :n] = k
    a[:n, n:] = p
    a[n:, :n] = p.T
    rhs = np.zeros((n + 4, 3))
    rhs[:n] = dst
    try:
        sol = np.linalg.solve(a, rhs)
    except np.linalg.LinAlgError as err:
        raise InputError(f"landmark warp: the {kernel} system is singular for these landmarks ({err})") from None
    tps = ThinPlateSpline(
        centers_mm=c, weights=sol[:n], affine=sol[n:], offset_mm=offset, kernel=kernel, hardy_a=float(hardy_a), hardy_s_mm=s
    )
    # one step of iterative refinement keeps the landmark residual at rounding level
    resid = dst - tps(src)
    if np.any(resid):
        rhs[:n] = resid
        rhs[n:] = 0.0
        sol = sol + np.linalg.solve(a, rhs)
        tps = ThinPlateSpline(c, sol[:n], sol[n:], offset, kernel, float(hardy_a), s)
    return tps


def warp_jacobian_det(tps: ThinPlateSpline, points: np.ndarray, step_mm: float = 1e-3) -> np.ndarray:
    """(M,) determinant of the warp's Jacobian at points (central differences); <= 0: the warp folds space."""
    p = np.asarray(points, float).reshape(-1, 3)
    cols = [(tps(p + step_mm * e) - tps(p - step_mm * e)) / (2 * step_mm) for e in np.eye(3)]
    return np.linalg.det(np.stack(cols, axis=2))


def fold_free_warp(
    source_points, target_points, points, *, kernel="biharmonic", hardy_a=0.5, hardy_s_mm=None,
    regularization=0.0, max_steps: int = 12,
):  # fmt: skip
    """The landmark warp, smoothed just enough not to fold space at ``points``.

    Inconsistent landmarks (e.g. extremal points that jump between anatomical parts)
    make the interpolating warp fold the template (Jacobian determinant <= 0), and no
    projection or relaxation untangles that. Starting from ``regularization``, λ is
    raised (1, 4, 16, ... × the median landmark distance) until det J > 0 at every point.

    Returns
    -------
    (tps, regularization used)
    """
    tps = landmark_warp(source_points, target_points, kernel=kernel, hardy_a=hardy_a, hardy_s_mm=hardy_s_mm,
                        regularization=regularization)
    if np.all(warp_jacobian_det(tps, points) > 0):
        return tps, float(regularization)
    src = np.asarray(source_points, float)
    scale = float(np.median(np.linalg.norm(src[:, None] - src[None], axis=2)))
    lam = max(float(regularization), scale)
    for _ in range(max_steps):
        tps = landmark_warp(source_points, target_points, kernel=kernel, hardy_a=hardy_a, hardy_s_mm=hardy_s_mm,
                            regularization=lam)
        if np.all(warp_jacobian_det(tps, points) > 0):
            break
        lam *= 4.0
    return tps, lam
