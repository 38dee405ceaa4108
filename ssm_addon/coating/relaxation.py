"""The mass-spring relaxation of paper 4.2, eq. (3), fold detection and fold removal.

F_i = Σ_j k1 (d_ij − d0_ij) e_ij + k2 d_DM(p_i), integrated with m a + g v = F
(:func:`relax`); triangles whose normal turns away from the surface normal are folded
(:func:`folded_triangles`) and lose the surface force while folded; folds left after
the relaxation are removed locally (:func:`untangle`, not in the paper). Coordinates in
mm, the target's object frame.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..base.errors import InputError, check_cancelled
from ..base.params import CoatingParams
from ..base.progress import CancelledFn, ProgressFn, report
from ..coating.distance_map import DistanceMap
from ..meshutil import edges as mesh_edges
from ..meshutil import face_centroids, face_normals

__all__ = ["folded_triangles", "relax", "untangle"]


def folded_triangles(
    points: np.ndarray, faces: np.ndarray, distance_map: DistanceMap, fold_angle_deg: float = 90.0,
    normal_sigma_mm: float = 3.0,
):
    """(F,) bool: triangles whose normal deviates from the surface normal by > fold_angle_deg.

    The surface normal is taken at the triangle's centroid (paper 4.2), both from the
    distance map's raw gradient and from the distance map smoothed at ``normal_sigma_mm``
    (:meth:`DistanceMap.smooth_normals`), and a triangle is folded when it turns from
    both. Each alone flags correct triangles: the raw gradient those that span a thin
    process or lamina (their centroid lies inside, near the medial surface, where the raw
    gradient flips), the smoothed one those on the walls of a notch narrower than its
    width (where the smoothed field sees the notch filled); a triangle turned over turns
    from both (figures in ``docs/history.md``, Coating, and "The template keeps the
    instance's shape"). ``normal_sigma_mm`` 0: the raw gradient alone (the paper's test).
    Degenerate (zero-area) triangles count as folded.
    """
    fn = face_normals(points, faces)
    cen = face_centroids(points, faces)
    sn = distance_map.smooth_normals(cen, normal_sigma_mm)
    limit = math.cos(math.radians(fold_angle_deg))
    turned = np.einsum("ij,ij->i", fn, sn) < limit
    if normal_sigma_mm > 0:  # the raw normal only where the smoothed one says turned (few)
        at = np.flatnonzero(turned)
        turned[at] = np.einsum("ij,ij->i", fn[at], distance_map.normals(cen[at])) < limit
    zero = ~np.any(fn, axis=1)
    return turned | zero


UNTANGLE_PATIENCE = 10  # rounds without fewer folds before the untangling widens by one ring


def _neighbour_sum(p: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(N, 3) sum of each vertex's edge neighbours (mm): the umbrella operator's numerator."""
    n = len(p)
    out = np.empty_like(p)
    for k in range(3):
        out[:, k] = (np.bincount(edges[:, 0], p[edges[:, 1], k], minlength=n)
                     + np.bincount(edges[:, 1], p[edges[:, 0], k], minlength=n))
    return out


def _grow(vertices: np.ndarray, edges: np.ndarray, rings: int) -> np.ndarray:
    """Boolean vertex set grown by ``rings`` edge rings."""
    sel = vertices.copy()
    for _ in range(rings):
        hit = sel[edges[:, 0]] | sel[edges[:, 1]]
        sel[edges[hit].ravel()] = True
    return sel


def untangle(
    points: np.ndarray,
    faces: np.ndarray,
    distance_map: DistanceMap,
    *,
    params: CoatingParams | None = None,
    edges: np.ndarray | None = None,
    cancelled: CancelledFn = None,
):
    """Remove folds left on the surface: local umbrella smoothing + reprojection.

    Not in the paper. Repeats up to ``params.untangle_iterations`` times: the vertices
    of folded triangles (:func:`folded_triangles`) and their ``params.untangle_rings``
    neighbour rings (one more ring after 10 rounds without fewer folds) move halfway to
    the average of their neighbours and back onto the surface (two projection steps);
    stops as soon as no triangle is folded. Then, per connected region of moved
    vertices, the new positions are kept only where the region's triangles are all
    unfolded; a region whose folds were not removed goes back to its start. Vertices
    away from removed folds do not move, so correspondence elsewhere is untouched.

    Why the regions that fail go back: smoothing a fold it cannot remove (a thin
    lamina narrower than the triangles) widens round after round and drags points
    along the surface; going back keeps correspondence where the folds stay (figures
    against known correspondence in ``docs/history.md``, Coating).

    Returns
    -------
    points : (N, 3) mm; rounds used : int
    """
    params = CoatingParams() if params is None else params
    p = np.array(points, dtype=float)
    e = mesh_edges(faces) if edges is None else edges
    n = len(p)
    deg = np.maximum(np.bincount(e.ravel(), minlength=n), 1).astype(float)[:, None]
    rings = params.untangle_rings
    start = p.copy()
    best, stall = None, 0
    for rounds in range(params.untangle_iterations):
        folded = folded_triangles(p, faces, distance_map, params.fold_angle_deg, params.fold_normal_sigma_mm)
        count = int(folded.sum())
        if count == 0:
            return _keep_improved(start, p, faces, e, distance_map, params), rounds
        if best is None or count < best:
            best, stall = count, 0
        else:
            stall += 1
            if stall >= UNTANGLE_PATIENCE:  # this width does not help: one ring wider
                rings, stall = rings + 1, 0
        check_cancelled(cancelled)
        seed = np.zeros(n, dtype=bool)
        seed[faces[folded].ravel()] = True
        sel = _grow(seed, e, rings)
        nsum = _neighbour_sum(p, e)
        p[sel] += 0.5 * (nsum[sel] / deg[sel] - p[sel])
        p[sel] = distance_map.project(p[sel], 2)
    return _keep_improved(start, p, faces, e, distance_map, params), params.untangle_iterations


def _keep_improved(start, p, faces, e, distance_map, params):
    """Per connected region of moved vertices (edges between moved vertices): the untangled
    positions where no triangle touching the region is folded, else the start positions.
    Two regions share no triangle, so each region's folds depend on it alone."""
    moved = np.any(p != start, axis=1)
    if not moved.any():
        return p
    n = len(p)
    both = moved[e[:, 0]] & moved[e[:, 1]]
    g = coo_matrix((np.ones(int(both.sum())), (e[both, 0], e[both, 1])), shape=(n, n))
    _k, comp = connected_components(g, directed=False)
    comp = np.where(moved, comp, -1)
    face_comp = comp[faces].max(axis=1)  # the one region a triangle touches, or -1
    folded = folded_triangles(p, faces, distance_map, params.fold_angle_deg, params.fold_normal_sigma_mm)
    failed = np.unique(face_comp[folded & (face_comp >= 0)])
    keep = moved & ~np.isin(comp, failed)
    return np.where(keep[:, None], p, start)


def relax(
    points: np.ndarray,
    faces: np.ndarray,
    rest_lengths: np.ndarray,
    distance_map: DistanceMap,
    *,
    params: CoatingParams | None = None,
    progress: ProgressFn = None,
    cancelled: CancelledFn = None,
    edges: np.ndarray | None = None,
):
    """Mass-spring relaxation of a mesh on a surface, eq. (3) (paper 4.2).

    F_i = Σ_j k1 (d_ij − d0_ij) e_ij + k2 d_DM(p_i), with m a + g v = F integrated by
    semi-implicit Euler (v += dt (F − g v)/m; p += dt v). d_DM is the vector to the
    nearest surface point, −d(p) ∇d/|∇d| from the distance map. Two phases:

    1. ``params.fold_iterations`` steps with the paper's fold handling: vertices of
       folded triangles (normal vs surface normal, re-detected every
       ``params.fold_check_interval`` steps) get no surface force and an umbrella force
       ``params.fold_smoothing`` (average of the neighbours − p) instead.
    2. Settling: every vertex is held to the surface, no umbrella force, until the
       largest speed is below ``params.velocity_tol_mm`` (converged) or
       ``params.max_iterations`` steps in all.

    Why two phases: switching vertices between the two force laws every few steps
    kicks the mesh, and the umbrella force (divided by each vertex's own degree, on
    the folded vertices only) is not the gradient of an energy, so the system never
    settles. Phase 2 is conservative and converges. With ``params.springs =
    "tension"`` a spring pulls when stretched and never pushes: the warped template's
    rest lengths do not fit the surface everywhere, and at equilibrium linear springs
    buckle the compressed parts into folds.

    The defaults settle: tension springs whose rest lengths are the edge lengths of
    the registered template projected onto the surface (``rest_lengths = 'projected'``,
    set by the coating), up to 2,000 steps. Where the projection left the mesh unfolded
    that state is already an equilibrium (every spring at rest, every vertex on the
    surface), so the springs act only where the fold handling moved vertices, pulling
    them back to the registration's spacing. Against known correspondence this places
    points as well as a short pass with linear springs and warped rest lengths that never
    converged, and it converges with no fold left (figures in ``docs/history.md``,
    Coating).

    Parameters
    ----------
    points : (N, 3) mm, start positions (object frame of the distance map).
    faces : (F, 3) int triangles (outward oriented).
    rest_lengths : (E,) mm, rest lengths d0 of ``edges`` (default ``mesh_edges(faces)`` order).
    distance_map : DistanceMap of the target.

    Returns
    -------
    points : (N, 3) mm; iterations : int; converged : bool
    """
    params = CoatingParams() if params is None else params
    p = np.array(points, dtype=float)
    faces = np.asarray(faces, np.int64)
    e = mesh_edges(faces) if edges is None else edges
    d0 = np.asarray(rest_lengths, float)
    if len(d0) != len(e):
        raise InputError(f"relaxation: {len(d0)} rest lengths for {len(e)} edges")
    n = len(p)
    v = np.zeros_like(p)
    i0, i1 = e[:, 0], e[:, 1]
    # each edge's force on its ends as one bincount per end over the flat (vertex, axis)
    # index: a bin adds its edges in edge order, as a bincount per axis does
    flat0 = (3 * i0[:, None] + np.arange(3)).ravel()
    flat1 = (3 * i1[:, None] + np.arange(3)).ravel()
    deg = np.maximum(np.bincount(e.ravel(), minlength=n), 1).astype(float)
    it = 0
    converged = params.max_iterations == 0
    tension = params.springs == "tension"
    surface_on = np.ones(n, dtype=bool)
    for it in range(1, params.max_iterations + 1):
        folding = it <= params.fold_iterations
        if it == params.fold_iterations + 1:
            surface_on = np.ones(n, dtype=bool)  # settling: every vertex held to the surface
        vec = np.take(p, i1, axis=0) - np.take(p, i0, axis=0)
        length = np.sqrt(np.add.reduce(vec * vec, axis=1))  # np.linalg.norm's operations
        unit = vec / np.maximum(length, 1e-12)[:, None]
        stretch = length - d0
        if tension:
            stretch = np.maximum(stretch, 0.0)
        fe = ((params.k1 * stretch)[:, None] * unit).ravel()  # force on i0 towards i1 when stretched
        force = (np.bincount(flat0, fe, minlength=3 * n) - np.bincount(flat1, fe, minlength=3 * n)).reshape(n, 3)
        d, g = distance_map.sample(p)
        nrm = g / np.maximum(np.sqrt(np.add.reduce(g * g, axis=1)), 1e-12)[:, None]
        if folding and (it - 1) % params.fold_check_interval == 0:
            # fold detection: triangle normal vs (smoothed) surface normal at the centroid
            folded = folded_triangles(p, faces, distance_map, params.fold_angle_deg, params.fold_normal_sigma_mm)
            surface_on = np.ones(n, dtype=bool)
            if np.any(folded):
                surface_on[faces[folded].ravel()] = False
        # every vertex on the surface (settling, or no fold): the umbrella force's weight is
        # k3 alone and the surface terms need no mask (a product with 1 is the value itself)
        every = not folding or bool(surface_on.all())
        if every:
            if params.k3 > 0:
                force += params.k3 * (_neighbour_sum(p, e) / deg[:, None] - p)
        else:
            k_smooth = params.k3 + params.fold_smoothing * ~surface_on
            if np.any(k_smooth > 0):
                force += k_smooth[:, None] * (_neighbour_sum(p, e) / deg[:, None] - p)
        if params.tangential_springs:
            along = np.einsum("ij,ij->i", force, nrm)[:, None] * nrm
            force -= along if every else along * surface_on[:, None]
        force += (params.k2 * -d if every else params.k2 * -d * surface_on)[:, None] * nrm
        v += params.dt * (force - params.damping * v) / params.mass
        p += params.dt * v
        vmax = float(np.sqrt((v * v).sum(1).max())) if n else 0.0
        if it % 25 == 0:
            report(progress, it / max(params.max_iterations, 1), f"relaxation step {it}")
            check_cancelled(cancelled)
        if vmax < params.velocity_tol_mm:
            converged = True
            break
    return p, it, converged
