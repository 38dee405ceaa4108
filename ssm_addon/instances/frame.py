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


def frame_axes_moments(eigvals: np.ndarray, eigvecs: np.ndarray, centred_world=None, *, third_moments=None):
    """Eigenvalue order (descending) and third-moment signs, made right-handed.

    Each axis is signed so that the object's skewness along it is positive; where the
    normalised third moment is below :data:`SKEW_TIE` (nearly symmetric shapes) the
    sign makes the axis' largest world component positive. If the result is
    left-handed, the axis whose sign was least determined (smallest |skewness|) flips.
    The third moments (mm³) along given axes come from ``centred_world`` (points about
    the centre of mass, world mm: their mean cube) or from ``third_moments``, a function
    of the (3, 3) axes (a solid's exact integrals, :func:`mesh_solid_frame`).
    """
    order = np.argsort(eigvals)[::-1]
    axes = eigvecs[:, order].copy()
    lam = np.maximum(eigvals[order], 1e-300)
    third = third_moments(axes) if third_moments is not None else ((centred_world @ axes) ** 3).mean(axis=0)
    skew = np.asarray(third, float) / lam**1.5
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


def _solid_tetrahedra(vertices: np.ndarray, faces: np.ndarray, centre: np.ndarray):
    """The corners a, b, c (mm, about ``centre``) of the tetrahedra (centre, a, b, c) of a
    closed mesh's triangles and their signed volumes (mm³, positive for outward triangles)."""
    v = np.asarray(vertices, float) - centre
    f = np.asarray(faces, np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return a, b, c, np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0


def mesh_solid_frame(vertices_world: np.ndarray, faces: np.ndarray, method: str = "moments") -> ObjectFrame:
    """The object frame (paper section 2) of the solid a closed mesh bounds, from its exact moments.

    The volume, centre of mass, second moments and third moments of the solid are the sums
    over the tetrahedra that join each triangle to a reference point (the divergence
    theorem; signed, so a concave solid is exact): a tetrahedron of volume V with corners
    0, a, b, c has  integral of (u.x)^k dV = V k! 3! / (k + 3)! h_k(0, u.a, u.b, u.c),  h_k the
    complete homogeneous symmetric polynomial of degree k [1]_ (second moments
    V / 20 (a a^T + b b^T + c c^T + s s^T), s = a + b + c). Unlike a voxelization
    it is the same for the mesh in any pose: the frame of a moved mesh is the moved frame
    (to rounding), so the object grid, and all that is built on it, does not depend on the
    scanner pose. Axes, order and signs as :func:`object_frame` (``"moments"`` or
    ``"patient"``).

    Parameters
    ----------
    vertices_world : (N, 3) ndarray
        Vertices, world mm.
    faces : (F, 3) int ndarray
        Triangles of a closed, consistently oriented mesh (either way round).
    method : {"moments", "patient"}

    Returns
    -------
    ObjectFrame

    Raises
    ------
    InputError
        The mesh bounds no volume (flat, or empty).

    Examples
    --------
    A tetrahedron's centre of mass is the mean of its corners:

    >>> import numpy as np
    >>> corners = np.array([[0.0, 0, 0], [4, 0, 0], [0, 4, 0], [0, 0, 4]])
    >>> faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    >>> mesh_solid_frame(corners, faces).origin_world.round(12).tolist()
    [1.0, 1.0, 1.0]

    References
    ----------
    .. [1] Lasserre, J. B. (2001). A quick proof for integrating a polynomial on a simplex.
       Computational Geometry 21, 165-175 (the formula above).
    """
    v = np.asarray(vertices_world, float)
    ref = v.mean(axis=0)
    a, b, c, vol = _solid_tetrahedra(v, faces, ref)
    volume = float(vol.sum())
    scale = float(np.ptp(v, axis=0).max()) if len(v) else 0.0
    if not np.isfinite(volume) or abs(volume) <= 1e-9 * max(scale, 1e-12) ** 3:
        raise InputError("the mesh bounds no volume (flat or empty)")
    s = a + b + c
    centre = (vol @ s) / 4.0 / volume
    second = (np.einsum("i,ij,ik->jk", vol, a, a) + np.einsum("i,ij,ik->jk", vol, b, b)
              + np.einsum("i,ij,ik->jk", vol, c, c) + np.einsum("i,ij,ik->jk", vol, s, s)) / 20.0 / volume
    cov = second - np.outer(centre, centre)
    # rounded (1e-9 mm, 1e-9 mm²) so that the same mesh with its vertices or triangles in another
    # order (an STL reader's merge, LPS against RAS) gives the same frame bit for bit, not one
    # the sums' rounding turned by 1e-15
    cov = np.round((cov + cov.T) / 2.0, 9)
    origin = np.round(ref + centre, 9)
    eigvals, eigvecs = np.linalg.eigh(cov)
    if method == "patient":
        axes, _order = frame_axes_patient(eigvecs)
    elif method == "moments":
        a0, b0, c0, vol0 = _solid_tetrahedra(v, faces, origin)

        def third(axes):
            sa, sb, sc = a0 @ axes, b0 @ axes, c0 @ axes
            h3 = (sa**3 + sb**3 + sc**3 + sa * sa * (sb + sc) + sb * sb * (sa + sc) + sc * sc * (sa + sb)
                  + sa * sb * sc)
            return (vol0 / 20.0) @ h3 / volume

        axes, _order = frame_axes_moments(eigvals, eigvecs, third_moments=third)
    else:
        raise InputError(f"unknown frame method {method!r} (patient, moments)")
    moments = np.einsum("ik,ij,jk->k", axes, cov, axes)
    return ObjectFrame(origin_world=origin, axes_world=axes, second_moments_mm2=moments, method=method)
