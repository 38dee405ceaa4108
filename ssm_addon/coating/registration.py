"""Smooth coarse-to-fine surface registration (not in the paper; between warp and projection).

The warp of eq. (2) with few or inconsistent landmarks leaves vertices many mm off the
surface; projecting those onto the nearest surface point folds the mesh. The
registration moves the warped mesh onto the surface by a Gaussian-smoothed displacement
field at decreasing widths (16, 8, 4, 2 mm by default), see :func:`register_to_surface`;
:func:`reach_far_parts` then extends it into parts it falls short of.
Coordinates in mm, the target's object frame.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..base.compute import inner_threads
from ..base.errors import check_cancelled
from ..base.progress import CancelledFn
from ..coating.distance_map import DistanceMap
from ..meshutil import MeshLocator, vertex_normals

__all__ = ["reach_far_parts", "register_to_surface"]

QUERY_WORKERS = 2  # threads of the registration's k-d tree search in the main process (identical results)


def _gaussian_smooth(
    points: np.ndarray, values: np.ndarray, weights: np.ndarray, sigma_mm: float, chunk=None, dense_max=4_000_000
):
    """Σ_j K_ij w_j u_j / Σ_j K_ij w_j with K = exp(-|p_i - p_j|² / 2σ²).

    Exact (row chunks, O(N²), float32 kernel) while N² <= ``dense_max`` (templates up to
    2,000 vertices); above, the sources are pooled in cells of σ/4 (weighted sums at the
    cell centroids) and the kernel is truncated at 3σ (sparse k-d tree pairs), which is
    O(N · cells within 3σ) (timings in ``docs/history.md``, Coating).
    """
    if len(points) ** 2 > dense_max:
        return _gaussian_smooth_pooled(points, values, weights, sigma_mm, dense_max)
    wv = np.hstack([values * weights[:, None], weights[:, None]])
    return _gaussian_dense(points, points, wv, sigma_mm, chunk)


#: Float32 kernel entries per row chunk of the dense Gaussian sum (4 MB: the chunk's five passes
#: stay in the processor's cache; docs/speed.md)
KERNEL_CHUNK_ENTRIES = 1 << 20


def _gaussian_dense(points, sources, sums, sigma_mm, chunk=None):
    """Σ_j K_ij s_j[:3] / Σ_j K_ij s_j[3] over (M, 4) source sums (float32 kernel, row chunks).

    ``chunk``: rows per chunk; by default about ``KERNEL_CHUNK_ENTRIES`` kernel entries, a
    choice that depends on the number of sources alone (the same inputs, the same chunks).
    """
    if chunk is None:
        chunk = int(min(2048, max(64, KERNEL_CHUNK_ENTRIES // max(len(sources), 1))))
    out = np.empty((len(points), 3))
    wv = np.asarray(sums, np.float32)
    p32 = points.astype(np.float32)
    s32 = sources.astype(np.float32)
    scale = -0.5 / sigma_mm**2
    # exponent -|p - s|²/2σ² = scale (|p|² + |s|² - 2 p·s), built in place; clipped at
    # -80 (e^-80 ~ 1e-35, nothing at float32 precision) because exp of large negative
    # float32 arguments (underflow to denormals) was half the time at σ <= 4 mm
    sq = (p32 * p32).sum(1) * np.float32(scale)
    sqs = (s32 * s32).sum(1) * np.float32(scale)
    s2 = np.ascontiguousarray(s32.T * np.float32(-2.0 * scale))
    for s in range(0, len(points), chunk):
        d2 = p32[s : s + chunk] @ s2
        d2 += sq[s : s + chunk, None]
        d2 += sqs[None, :]
        np.maximum(d2, np.float32(-80.0), out=d2)  # = np.clip(d2, -80, 0) without its wrapper
        np.minimum(d2, np.float32(0.0), out=d2)
        np.exp(d2, out=d2)
        acc = (d2 @ wv).astype(np.float64)
        out[s : s + chunk] = acc[:, :3] / np.maximum(acc[:, 3:], 1e-12)
    return out


def _gaussian_smooth_pooled(points, values, weights, sigma_mm, dense_max):
    n = len(points)
    _, inv = np.unique(np.floor(points / (0.25 * sigma_mm)).astype(np.int64), axis=0, return_inverse=True)
    inv = inv.ravel()
    m = int(inv.max()) + 1
    count = np.bincount(inv, minlength=m).astype(float)
    centres = np.stack([np.bincount(inv, points[:, k], minlength=m) for k in range(3)], axis=1) / count[:, None]
    pooled = np.stack(
        [np.bincount(inv, values[:, k] * weights, minlength=m) for k in range(3)] + [np.bincount(inv, weights, minlength=m)],
        axis=1,
    )
    if n * m <= 4 * dense_max:
        return _gaussian_dense(points, centres, pooled, sigma_mm)
    pairs = cKDTree(points).sparse_distance_matrix(cKDTree(centres), 3.0 * sigma_mm, output_type="ndarray")
    k = np.exp(-0.5 * (pairs["v"] / sigma_mm) ** 2)
    rows = np.ascontiguousarray(pairs["i"])
    terms = pooled.T[:, pairs["j"]]  # (4, pairs): one gather for the four sums
    terms *= k
    acc = np.stack([np.bincount(rows, terms[c], minlength=n) for c in range(4)], axis=1)
    return acc[:, :3] / np.maximum(acc[:, 3:], 1e-12)


#: Candidates searched for exact ties in the first step (:func:`_nearest_vertex`).
TIE_CANDIDATES = 4


def _nearest_vertex(tree: cKDTree, targets: np.ndarray, workers: int, *, ties: bool) -> np.ndarray:
    """Index of the nearest mesh vertex of every target point.

    With ``ties``, of the vertices at exactly the nearest distance (among the
    ``TIE_CANDIDATES`` nearest) the lowest index, so that the k-d tree's traversal order
    does not choose. A registration's first step needs it: a mesh that starts on the
    surface's own voxel lattice (the template on its own instance, or placed by the object
    frames alone) has targets equidistant from two or more vertices; once the smooth
    displacement has moved it, exact ties do not occur (docs/speed.md).
    """
    if not ties:
        return tree.query(targets, workers=workers)[1]
    k = min(TIE_CANDIDATES, tree.n)
    d, idx = tree.query(targets, k=k, workers=workers)
    d, idx = d.reshape(len(targets), k), idx.reshape(len(targets), k)
    return np.where(d == d[:, :1], idx, tree.n).min(axis=1)


def register_to_surface(
    points: np.ndarray,
    faces: np.ndarray,
    distance_map: DistanceMap,
    *,
    sigmas_mm=(8.0, 4.0, 2.0),
    iterations: int = 10,
    cancelled: CancelledFn = None,
    normal_only: bool = True,
    target_density: int = 8,
) -> np.ndarray:
    """Move a mesh onto a surface by a smooth, coarse-to-fine displacement field.

    Not in the paper: a symmetric nearest-point registration added because the warp of
    eq. (2) with few or inconsistent landmarks leaves vertices many mm off the surface,
    and projecting those onto the nearest surface point folds the mesh, which the
    relaxation of eq. (3) does not unfold (figures in ``docs/history.md``, Coating). Each iteration pulls every vertex towards its nearest surface point
    (forward) and towards the surface points that have it as nearest vertex (backward,
    so processes the warp fell short of are reached), both only where the normals agree,
    and applies the Gaussian-smoothed (width σ, mm) average of these displacements.

    Parameters
    ----------
    points : (N, 3) mm, object frame of the distance map.
    faces : (F, 3) outward triangles.
    sigmas_mm : decreasing Gaussian widths in mm; ``iterations`` steps each.
    target_density : surface points used for the backward term per mesh vertex
        (every k-th marching-cubes vertex; 0: all).

    Returns
    -------
    (N, 3) registered points (mm).
    """
    p = np.array(points, dtype=float)
    n = len(p)
    if not len(sigmas_mm) or iterations <= 0 or n == 0:
        return p
    targets, target_normals = _surface_targets(distance_map, n, target_density)
    workers = inner_threads(QUERY_WORKERS)
    first = True
    for sigma in sigmas_mm:
        for _ in range(iterations):
            check_cancelled(cancelled)
            p += _registration_step(p, faces, distance_map, targets, target_normals, sigma, workers,
                                    ties=first, normal_only=normal_only)
            first = False
    return p


def _surface_targets(distance_map: DistanceMap, n: int, target_density: int):
    """The surface samples (M, 3) mm and their normals that pull a mesh of ``n`` vertices.

    The backward term needs the target surface sampled a few times denser than the mesh,
    not all marching-cubes vertices (20,000 on a vertebra: the k-d tree query was 80 % of
    the registration's time); MC vertices are ordered slice by slice, so a stride thins
    them evenly (``target_density`` per vertex; 0: all).
    """
    stride = max(1, len(distance_map.surface_vertices) // (target_density * n)) if target_density > 0 else 1
    return distance_map.surface_samples(stride)


#: Cosine between a vertex's normal and the surface normal below which a pull is ignored
#: (the nearest point is on the far side of a thin part, or the other wall of a notch).
COS_MIN = 0.3


def _registration_step(p, faces, distance_map, targets, target_normals, sigma, workers, *, ties, normal_only,
                       full=None):
    """One step of :func:`register_to_surface`: the smoothed displacement (N, 3) mm.

    ``full`` (M,) bool, optional: surface samples whose backward pull counts in full even
    with ``normal_only`` (:func:`reach_far_parts`); such samples pull whatever the normals.
    """
    n = len(p)
    vn = vertex_normals(p, faces)
    near = distance_map.project(p, 2)
    w_fwd = (np.einsum("ij,ij->i", vn, distance_map.normals(near)) > COS_MIN).astype(float)
    # the search over ~5,000 surface points was 40 % of an iteration: both cores
    # (the same result as one; workers only splits the query points)
    j = _nearest_vertex(cKDTree(p, leafsize=16), targets, workers, ties=ties)
    ok = np.einsum("ij,ij->i", vn[j], target_normals) > COS_MIN
    if full is not None:
        ok |= full
    jj = j[ok]
    count = np.bincount(jj, minlength=n).astype(float)
    back = np.empty_like(p)
    for k in range(3):
        back[:, k] = np.bincount(jj, targets[ok, k] - p[jj, k], minlength=n)
    has_back = count > 0
    back[has_back] /= count[has_back, None]
    if normal_only:
        along = np.einsum("ij,ij->i", back, vn)[:, None] * vn
        if full is None:
            back = along
        else:
            back = np.where((np.bincount(j[full], minlength=n) > 0)[:, None], back, along)
    u = w_fwd[:, None] * (near - p) + back
    w = w_fwd + has_back
    return _gaussian_smooth(p, u / np.maximum(w, 1.0)[:, None], w, sigma)


def reach_far_parts(
    points: np.ndarray,
    faces: np.ndarray,
    distance_map: DistanceMap,
    *,
    far_mm: float = 2.5,
    thickness_mm: float | None = None,
    sigma_mm: float = 2.0,
    iterations: int = 5,
    rounds: int = 6,
    target_density: int = 8,
    cancelled: CancelledFn = None,
) -> np.ndarray:
    """Extend a registered mesh into parts of the surface it falls short of (mm).

    Not in the paper. After :func:`register_to_surface`, whose backward pull acts along
    the vertex normals only (a full pull slides the template's points and costs
    correspondence), a process of the instance that is longer than the template's can
    be left a few mm beyond the mesh's tip. Here the surface samples farther than
    ``far_mm`` from the mesh's triangles, where the object lies behind them (a part of
    the object, a process or the tip of a lamina, not a sample whose inside is thinner
    than ``thickness_mm``), pull their nearest vertex in full; only vertices within 2σ of
    such samples move, by the steps of :func:`register_to_surface` at width ``sigma_mm``.
    Rounds of ``iterations`` steps repeat while the number of far samples falls, at most
    ``rounds`` times.

    Parameters
    ----------
    points : (N, 3) mm, the registered mesh (object frame of the distance map).
    faces : (F, 3) outward triangles.
    far_mm : distance from the mesh (mm) beyond which a surface sample pulls in full.
    thickness_mm : a sample pulls only where the distance map is below -thickness_mm/2
        at thickness_mm inwards along its normal (a part thicker than 1.5 thickness_mm);
        None: half the distance map's voxel, so every part at least a voxel thick pulls.
    sigma_mm : Gaussian width of the steps (mm; the registration's finest).
    iterations : steps per round; rounds : most rounds.
    target_density : surface samples per mesh vertex, as in :func:`register_to_surface`.

    Returns
    -------
    (N, 3) mm; ``points`` unchanged where no part lies farther than ``far_mm``.
    """
    p = np.array(points, dtype=float)
    n = len(p)
    if n == 0 or rounds <= 0 or iterations <= 0:
        return p
    targets, target_normals = _surface_targets(distance_map, n, target_density)
    depth = 0.5 * distance_map.spacing_mm if thickness_mm is None else float(thickness_mm)
    thick = distance_map.distance(targets - depth * target_normals) < -0.5 * depth
    workers = inner_threads(QUERY_WORKERS)
    last = None
    for _ in range(rounds):
        check_cancelled(cancelled)
        # a sample within far_mm of a vertex is within far_mm of the mesh: the exact
        # triangle distance only for the others (most coatings have none)
        tree = cKDTree(p)
        far = thick.copy()
        far[thick] = np.isinf(tree.query(targets[thick], distance_upper_bound=far_mm)[0])
        if far.any():
            far[far] = MeshLocator(p, faces).query(targets[far], k=6)[1] > far_mm
        count = int(far.sum())
        if count == 0 or (last is not None and count >= last):
            break
        last = count
        region = np.zeros(n, bool)
        for near_far in tree.query_ball_point(targets[far], 2.0 * sigma_mm):
            region[near_far] = True
        for _ in range(iterations):
            check_cancelled(cancelled)
            step = _registration_step(p, faces, distance_map, targets, target_normals, sigma_mm, workers,
                                      ties=False, normal_only=True, full=far)
            p[region] += step[region]
    return p
