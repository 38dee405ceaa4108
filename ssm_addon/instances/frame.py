"""The object frame of paper section 2: centre of mass and second-moment axes.

Deterministic and right-handed: ``"patient"`` pairs each principal axis with the
nearest patient axis (R, A, S) of an image; ``"moments"`` uses eigenvalue order and
third-moment signs (meshes in arbitrary coordinates). See :func:`object_frame`.
"""

from __future__ import annotations

import numpy as np
from nibabel.affines import apply_affine

from ..base.errors import InputError
from ..formats.label_maps import Volume
from ..instances.volume import ObjectFrame, bounding_box


def _object_voxels(volume: Volume) -> np.ndarray:
    """(M, 3) float voxel indices of the object voxels (cropped search; no full-size arrays)."""
    try:
        box = bounding_box(volume.mask)
    except InputError as err:
        raise InputError(f"{volume.source or 'volume'}: empty mask: no object voxels") from err
    idx = np.nonzero(volume.mask[box])
    return np.stack([ix.astype(np.float64) + s.start for ix, s in zip(idx, box)], axis=1)


_PATIENT_PERMUTATIONS = (
    (0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0),
)  # fmt: skip


def frame_axes_patient(eigvecs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pair each principal axis with the nearest patient axis R, A, S.

    Parameters
    ----------
    eigvecs : (3, 3) ndarray
        Columns are orthonormal principal axes in world (RAS) coordinates.

    Returns
    -------
    axes : (3, 3) ndarray
        Columns: the principal axes paired with R, A, S (distinct, maximizing the summed
        |cos|), each signed to point along its patient axis; right-handed.
    order : (3,) int
        ``axes[:, p] = ± eigvecs[:, order[p]]``.
    """
    cos = np.abs(eigvecs)  # cos[p, e] = |<patient axis p, eigvec e>|
    best = max(_PATIENT_PERMUTATIONS, key=lambda perm: sum(cos[p, perm[p]] for p in range(3)))
    order = np.array(best)
    axes = eigvecs[:, order].copy()
    diag = np.diag(axes).copy()
    axes *= np.where(diag < 0, -1.0, 1.0)
    if np.linalg.det(axes) < 0:
        weakest = int(np.argmin(np.abs(diag)))
        axes[:, weakest] *= -1.0
    return axes, order


SKEW_TIE = 0.02
"""Normalised third moments below this are treated as zero (sign by tie-break)."""


def frame_axes_moments(eigvals: np.ndarray, eigvecs: np.ndarray, centred_world: np.ndarray):
    """Eigenvalue order (descending) and third-moment signs, made right-handed.

    Each axis is signed so that the object's skewness along it is positive; where the
    normalised third moment is below :data:`SKEW_TIE` (nearly symmetric shapes) the
    sign makes the axis' largest world component positive. If the result is
    left-handed, the axis whose sign was least determined (smallest |skewness|) flips.
    """
    order = np.argsort(eigvals)[::-1]
    axes = eigvecs[:, order].copy()
    lam = np.maximum(eigvals[order], 1e-300)
    proj = centred_world @ axes
    skew = (proj**3).mean(axis=0) / lam**1.5
    for k in range(3):
        if abs(skew[k]) >= SKEW_TIE:
            s = np.sign(skew[k])
        else:
            big = int(np.argmax(np.abs(axes[:, k]) + 1e-9 * np.arange(3, 0, -1)))
            s = np.sign(axes[big, k]) or 1.0
        axes[:, k] *= s
        skew[k] *= s
    if np.linalg.det(axes) < 0:
        weakest = int(np.argmin(np.abs(skew)))
        axes[:, weakest] *= -1.0
    return axes, order


def object_frame(volume: Volume, method: str = "auto") -> ObjectFrame:
    """The object coordinate system of paper section 2.

    Origin: centre of mass of the object voxels (voxel centres mapped through the
    affine, world mm). Axes: eigenvectors of the second-moment (covariance) matrix of
    those centres in world mm. Order and signs:

    * ``"patient"``: each principal axis paired with the nearest patient axis (R, A, S;
      an assignment so that no two share one), signed along it; object x, y, z = the
      axes paired with R, A, S. Stable where eigenvalues are close or third moments
      small (near-symmetric shapes, e.g. vertebrae: ``docs/history.md``, Object
      frames), so it is the default for images.
    * ``"moments"``: descending eigenvalues, signs by third moments, see
      :func:`frame_axes_moments`; for meshes in arbitrary coordinates.
    * ``"auto"``: ``"patient"`` if ``volume.patient_oriented`` else ``"moments"``.

    The result is orthonormal and right-handed (det = +1).
    """
    method = (method or "auto").lower()
    if method not in ("auto", "patient", "moments"):
        raise InputError(f"{volume.source or 'volume'}: unknown frame method {method!r} (auto, patient, moments)")
    if method == "auto":
        method = "patient" if volume.patient_oriented else "moments"
    ijk = _object_voxels(volume)
    A = volume.affine[:3, :3]
    mean_ijk = ijk.mean(axis=0)
    centred_ijk = ijk - mean_ijk
    del ijk
    centred = centred_ijk @ A.T  # world mm, relative to the centre of mass
    del centred_ijk
    origin = apply_affine(volume.affine, mean_ijk)
    cov = centred.T @ centred / len(centred)
    eigvals, eigvecs = np.linalg.eigh(cov)
    if method == "patient":
        axes, order = frame_axes_patient(eigvecs)
    else:
        axes, order = frame_axes_moments(eigvals, eigvecs, centred)
    moments = np.einsum("ik,ij,jk->k", axes, cov, axes)
    return ObjectFrame(origin_world=origin, axes_world=axes, second_moments_mm2=moments, method=method)
