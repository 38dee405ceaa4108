"""Closed meshes in: voxelization of a surface mesh into a binary object (paper section 2).

Meshes exported from 3D Slicer are in patient coordinates (RAS mm); others are in
arbitrary coordinates, which is why a voxelized mesh's object frame defaults to the
moments method (``patient_oriented=False``).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ..base.errors import InputError, check_cancelled
from ..base.resources import BYTES_PER_OBJECT_VOXEL, check_allocation
from ..formats.label_maps import Volume
from ..formats.meshes import read_mesh
from ..meshutil import surface_samples

# a part of a mesh thinner than a voxel encloses no voxel centre, so voxelizing loses it. A mesh
# point farther than THIN_PART_FAR_VOX voxels from every voxel centre inside is on such a part
# (thick parts' points lie nearer: docs/history.md)
THIN_PART_FAR_VOX = 2.0
# mesh samples at most this far apart (voxels) find the voxels a thin part passes through
THIN_PART_STEP_VOX = 0.5
# steps (voxels) from a thin part's far voxels down to the object, at most
MAX_ROOT_STEPS = 8


def mesh_edge_defects(faces: np.ndarray) -> tuple[int, int, int]:
    """Counts of (boundary, non-manifold, inconsistently oriented) edges of a triangle mesh.

    A closed, consistently oriented 2-manifold has every undirected edge in exactly two
    faces, once in each direction; all three counts are then 0.
    """
    faces = np.asarray(faces, dtype=np.int64)
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    n = int(directed.max()) + 1 if directed.size else 1
    undirected = np.sort(directed, axis=1)
    _, ucount = np.unique(undirected[:, 0] * n + undirected[:, 1], return_counts=True)
    _, dcount = np.unique(directed[:, 0] * n + directed[:, 1], return_counts=True)
    boundary = int(np.count_nonzero(ucount == 1))
    nonmanifold = int(np.count_nonzero(ucount > 2))
    flipped = int(np.count_nonzero(dcount > 1))
    return boundary, nonmanifold, flipped


def _edge_sign(P, u, v, px, py):
    """Sign of the projected edge function of canonical edge u < v at column (px, py).

    Ties (point exactly on the edge line) are broken by simulating a perturbation of the
    point by (eps, eps^2); the same edge always gives the same value for the same point,
    so a ray through a shared edge or vertex is counted by exactly one triangle of a fan.
    """
    ux, uy = P[u, 0], P[u, 1]
    dx, dy = P[v, 0] - ux, P[v, 1] - uy
    e = dx * (py - uy) - dy * (px - ux)
    tie = np.where(dy != 0, -np.sign(dy), np.sign(dx))
    return e, np.where(e != 0, np.sign(e), tie)


def voxelize_mesh(
    vertices_world: np.ndarray,
    faces: np.ndarray,
    spacing_mm: float,
    *, source: str = "",
    patient_oriented: bool = False,
    cancelled=None,
) -> Volume:
    """Voxelize a closed triangle mesh: voxel centres inside the surface become object voxels.

    Inside test by ray parity along the z axis for every (x, y) column of voxel centres,
    all columns at once: each face reports the columns its xy projection covers (with
    exact, consistent tie-breaking for rays through edges and vertices), the crossing z
    is accumulated into a per-column histogram whose cumulative parity is the mask.

    Parameters
    ----------
    vertices_world : (V, 3) float ndarray
        Vertex positions in mm (world frame of the mesh).
    faces : (F, 3) int ndarray
        Triangles.
    spacing_mm : float
        Isotropic voxel edge of the output grid (mm).
    source : str
        File or object name for messages.
    patient_oriented : bool
        True if the mesh is in patient coordinates (e.g. exported from 3D Slicer in RAS).

    Returns
    -------
    Volume
        Mask on a grid aligned with the world axes (multiples of ``spacing_mm``), with at
        least two background voxels on every side.

    Raises
    ------
    InputError
        Open or non-watertight mesh (counts of boundary / non-manifold / inconsistently
        oriented edges in the message), or a bad spacing.
    """
    v = np.asarray(vertices_world, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    name = source or "mesh"
    h = float(spacing_mm)
    if not np.isfinite(h) or h <= 0:
        raise InputError(f"{name}: spacing must be a positive number of mm, got {spacing_mm!r}")
    if len(f) == 0:
        raise InputError(f"{name}: the mesh has no faces")
    boundary, nonmanifold, flipped = mesh_edge_defects(f)
    if boundary or nonmanifold or flipped:
        raise InputError(
            f"{name}: the mesh is not closed and watertight ({boundary} boundary edges, "
            f"{nonmanifold} non-manifold edges, {flipped} inconsistently oriented edges); "
            "close the holes (e.g. Blender's Fill Holes / Make Manifold) before voxelizing"
        )
    lo = np.floor(v.min(axis=0) / h).astype(np.int64) - 2
    hi = np.ceil(v.max(axis=0) / h).astype(np.int64) + 2
    shape = tuple(int(s) for s in hi - lo + 1)
    check_allocation(float(np.prod(shape, dtype=np.float64)) * BYTES_PER_OBJECT_VOXEL,
                     f"{name}: voxelizing at {h:g} mm ({' x '.join(str(s) for s in shape)} voxels)",
                     "use a coarser mesh_spacing (or [template] spacing)")
    origin = lo * h
    P = (v - origin) / h  # vertex coordinates in voxel-index units
    nx, ny, nz = shape
    counts = np.zeros(nx * ny * (nz + 1), dtype=np.uint8)
    tri = P[f]  # (F, 3, 3)
    i0 = np.ceil(tri[:, :, 0].min(axis=1)).astype(np.int64)
    i1 = np.floor(tri[:, :, 0].max(axis=1)).astype(np.int64)
    j0 = np.ceil(tri[:, :, 1].min(axis=1)).astype(np.int64)
    j1 = np.floor(tri[:, :, 1].max(axis=1)).astype(np.int64)
    ni = np.maximum(i1 - i0 + 1, 0)
    nj = np.maximum(j1 - j0 + 1, 0)
    npairs = ni * nj
    csum = np.cumsum(npairs)
    chunk = 1 << 21
    start_face = 0
    while start_face < len(f):
        check_cancelled(cancelled)
        base = csum[start_face - 1] if start_face else 0
        stop_face = int(np.searchsorted(csum, base + chunk, side="right"))
        stop_face = max(stop_face, start_face + 1)
        sel = np.arange(start_face, stop_face)
        cnt = npairs[sel]
        t = np.repeat(sel, cnt)
        if t.size:
            local = np.arange(t.size) - np.repeat(np.cumsum(cnt) - cnt, cnt)
            px = (i0[t] + local % ni[t]).astype(np.float64)
            py = (j0[t] + local // ni[t]).astype(np.float64)
            a, b, c = f[t, 0], f[t, 1], f[t, 2]
            vals, signs = [], []
            for s, e in ((a, b), (b, c), (c, a)):
                u, w = np.minimum(s, e), np.maximum(s, e)
                flip = np.where(s < e, 1.0, -1.0)
                ev, sg = _edge_sign(P, u, w, px, py)
                vals.append(ev * flip)
                signs.append(sg * flip)
            inside = (signs[0] == signs[1]) & (signs[1] == signs[2]) & (signs[0] != 0)
            # barycentric weights: vertex a is opposite edge (b, c), etc.
            wa, wb, wc = vals[1][inside], vals[2][inside], vals[0][inside]
            total = wa + wb + wc
            ok = total != 0
            ti = t[inside][ok]
            z = (wa[ok] * P[f[ti, 0], 2] + wb[ok] * P[f[ti, 1], 2] + wc[ok] * P[f[ti, 2], 2]) / total[ok]
            k = np.clip(np.ceil(z), 0, nz).astype(np.int64)
            col = px[inside][ok].astype(np.int64) * ny + py[inside][ok].astype(np.int64)
            hits = np.bincount(col * (nz + 1) + k, minlength=counts.size)
            counts += (hits & 1).astype(np.uint8)
        start_face = stop_face
    parity = np.cumsum(counts.reshape(nx, ny, nz + 1)[:, :, :nz], axis=2, dtype=np.uint8) & 1
    mask = parity.astype(bool)
    if not mask.any():
        extent = float(np.ptp(np.asarray(vertices_world, float), axis=0).max()) if len(vertices_world) else 0.0
        unit = ""
        if 0.0 < extent < 2.0 * h:  # an anatomical object of a few mm or less: another unit
            unit = (f"; it is {extent:.3g} units across, so it looks like metres (× 1000 for mm)" if extent < 0.5 else
                    f"; it is {extent:.3g} units across, so it looks like centimetres (× 10 for mm)")
        raise InputError(f"{name}: empty mask: the mesh encloses no voxel centre at {h} mm spacing{unit}")
    affine = np.diag([h, h, h, 1.0])
    affine[:3, 3] = origin
    return Volume(mask=mask, affine=affine, source=source, label=None, patient_oriented=patient_oriented)


def keep_thin_parts(mask: np.ndarray, vertices_vox: np.ndarray, faces: np.ndarray, *,
                    far_vox: float = THIN_PART_FAR_VOX) -> tuple[np.ndarray, int, int]:
    """The voxelized ``mask`` of a closed mesh with its parts and gaps thinner than a voxel put back.

    A thin process or plate of the mesh that encloses no voxel centre is missing from the
    mask, which holds only the centres inside (or a few of its centres lie apart from the
    object); a notch or pit narrower than a voxel is filled. Points of the mesh (its surface
    sampled every half voxel, :func:`ssm_addon.meshutil.surface_samples`) farther than
    ``far_vox`` voxels from every centre of the object (the mask's largest face-connected
    part) lie on such a part. The voxels they lie in become object voxels, and so do the
    voxels the mesh passes through from there down to the object (the part's root): a voxel
    joins next to (26-neighbours) a joined one that lies farther from the object, never
    sideways along the object's own surface; what joins the object is kept. The same, with
    inside and outside swapped (the outside: the background around the grid's corner), opens
    the gaps. A part comes back about one voxel thick, a gap one voxel wide (a tip or a pit's
    floor lies in a voxel that changed side, within 1/sqrt(3) voxel of the voxel surface);
    everywhere else the mask is unchanged.

    Parameters
    ----------
    mask : (X, Y, Z) bool ndarray
        Voxel centres inside the mesh (:func:`voxelize_mesh`), background at the corner.
    vertices_vox : (V, 3) float ndarray
        The mesh's vertices in the mask's voxel-index coordinates (centres at integers).
    faces : (F, 3) int ndarray
    far_vox : float
        How far (voxels) from the object's centres a mesh point must lie to be on a lost part
        (from the outside's centres: in a filled gap).

    Returns
    -------
    mask : (X, Y, Z) bool ndarray
        A new array where voxels changed, else ``mask`` itself.
    added, opened : int
        The voxels added (thin parts) and taken away (thin gaps).
    """
    mask = np.asarray(mask, bool)
    vertices_vox = np.asarray(vertices_vox, float)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    if not mask.any() or not len(faces):
        return mask, 0, 0
    # every point of a triangle lies within ``cover`` of one of its vertices: its circumradius
    # (acute) or half its longest edge (else)
    corners = vertices_vox[faces]
    sq = np.sort(((corners - np.roll(corners, 1, axis=1)) ** 2).sum(2), axis=1)
    longest = np.sqrt(sq[:, 2])
    double_area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        circumradius = np.sqrt(sq.prod(1)) / (2.0 * double_area)
    cover = np.where(sq[:, 2] >= sq[:, 0] + sq[:, 1], longest / 2.0, np.fmin(circumradius, longest))
    mesh = (vertices_vox, faces, corners, longest, cover)
    labels, _count = ndimage.label(mask)
    body = labels == 1 + int(np.argmax(np.bincount(labels.ravel())[1:]))
    out = mask.copy()
    added = _thin_voxels(out, body, mesh, far_vox)
    labels, _count = ndimage.label(~out)
    opened = None if mask[0, 0, 0] else _thin_voxels(~out, labels == labels[0, 0, 0], mesh, far_vox)
    if added is None and opened is None:
        return mask, 0, 0
    counts = []
    for found, value in ((added, True), (opened, False)):
        if found is not None:
            box, voxels = found
            out[box][voxels] = value
        counts.append(0 if found is None else int(np.count_nonzero(found[1])))
    return out, counts[0], counts[1]


def _thin_voxels(solid: np.ndarray, body: np.ndarray, mesh: tuple, far_vox: float):
    """The voxels of :func:`keep_thin_parts` for one side: ``solid`` (that side's voxels),
    ``body`` (its main part), ``mesh`` (vertices, faces, corners, longest edge and covering
    radius per triangle, voxels). Returns ``(box, voxels)`` (a box of the grid and the voxels in
    it that join ``solid``), or None."""
    vertices_vox, faces, corners, longest, cover = mesh
    border = np.argwhere(body & ~ndimage.binary_erosion(body, border_value=1))  # next to the other side
    if not len(border):
        return None
    tree = cKDTree(border)
    # only triangles that may hold a far point are sampled: a point lies no farther than the
    # farthest of its triangle's vertices plus ``cover``
    maybe = tree.query(vertices_vox)[0][faces].max(1) + cover > far_vox
    if not maybe.any():
        return None
    samples = surface_samples(vertices_vox, faces[maybe], THIN_PART_STEP_VOX)
    if far_vox >= 1.0 + np.sqrt(3.0) / 2:
        # a point whose voxel is the body's or touches it face to face lies within 1 + sqrt(3)/2
        # of a body centre: only the others are measured
        cells = np.clip(np.rint(samples).astype(np.int64), 0, np.array(solid.shape) - 1)
        samples = samples[~ndimage.binary_dilation(body)[tuple(cells.T)]]
    far = ~(tree.query(samples, distance_upper_bound=float(far_vox) + 1e-9)[0] <= far_vox)
    if not far.any():
        return None
    reach = int(np.ceil(far_vox)) + 2  # the box holds the far voxels' roots and the body there
    far_cells = np.rint(samples[far]).astype(np.int64)
    lo = np.maximum(far_cells.min(axis=0) - reach, 0)
    hi = np.minimum(far_cells.max(axis=0) + reach + 1, solid.shape)
    # the voxels the mesh passes through in the box around the far points (its triangles near the box)
    near = np.all((corners.max(1) + longest[:, None] >= lo) & (corners.min(1) - longest[:, None] < hi), axis=1)
    samples = np.concatenate([samples[far], surface_samples(vertices_vox, faces[near], THIN_PART_STEP_VOX)])
    cells = np.clip(np.rint(samples).astype(np.int64), 0, np.array(solid.shape) - 1)
    inbox = np.all((cells >= lo) & (cells < hi), axis=1)
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    crossed = np.zeros(tuple(hi - lo), bool)  # the voxels the mesh passes through, in the box
    crossed[tuple((cells[inbox] - lo).T)] = True
    crossed &= ~body[box]
    grown = np.zeros_like(crossed)
    grown[tuple((cells[: len(far_cells)] - lo).T)] = True
    grown &= crossed
    # from the far voxels down to the body: a crossed voxel joins next to a joined one that lies
    # farther from the body (the part's root; not sideways along the body's own surface)
    to_body = ndimage.distance_transform_edt(~body[box])
    for _ in range(MAX_ROOT_STEPS):
        above = ndimage.grey_dilation(np.where(grown, to_body, -1.0), size=(3, 3, 3))
        more = crossed & ~grown & (above > to_body)
        if not more.any():
            break
        grown |= more
    # what joins the body (face to face, as its surface will): a part apart from it is not its own
    parts, _n = ndimage.label(grown | solid[box])
    joined = np.unique(parts[body[box]])
    grown &= np.isin(parts, joined[joined > 0]) & ~solid[box]
    return (box, grown) if grown.any() else None


def load_mesh_volume(path, spacing_mm: float, patient_oriented: bool = False, space: str | None = None,
                     cancelled=None) -> Volume:
    """Read a closed mesh (STL/PLY/OBJ) in RAS world mm (``space``: the convention of a file that
    states none, :func:`ssm_addon.formats.meshes.read_mesh`) and voxelize it, see :func:`voxelize_mesh`."""
    vertices, faces = read_mesh(path, space=space)
    return voxelize_mesh(
        vertices, faces, spacing_mm, source=str(path), patient_oriented=patient_oriented, cancelled=cancelled
    )
