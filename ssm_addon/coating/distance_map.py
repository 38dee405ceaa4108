"""The distance map of paper 4.2: sub-voxel signed distance to an instance's surface.

The surface of an instance is the 0.5 iso-surface of its binary
:class:`~ssm_addon.instances.volume.ObjectVolume` mask (its marching-cubes surface), with the
mask's cavities filled (:func:`~ssm_addon.instances.volume.fill_cavities`): the outer surface,
which the template (its cleaning fills cavities too) coats; a cavity's wall a few mm under the
surface would otherwise be a part the coating falls short of. The map gives
signed distance (mm, negative inside) and its gradient anywhere in the object frame by
trilinear interpolation, projects points onto the surface, and gives exact
point-to-triangle distances for fit figures.
"""

from __future__ import annotations

import contextlib
import hashlib
import mmap
import os
import shutil
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from scipy import ndimage

from ..base.compute import inner_threads
from ..base.errors import InputError
from ..instances.volume import ObjectVolume, fill_cavities
from ..meshutil import MeshLocator, marching_cubes

__all__ = ["DistanceMap", "gradient_into"]

# a store (ObjectVolume.distance_map_store) keeps at most this many bytes of maps, and leaves
# this much of its disk free: beyond either, maps are computed each time as without a store
STORE_BUDGET_BYTES = 4 << 30
STORE_KEEP_FREE_BYTES = 2 << 30
STORE_FORMAT = 2  # 2: the map of the mask with its cavities filled


def gradient_into(f: np.ndarray, spacing: float, out: np.ndarray) -> np.ndarray:
    """The gradient of a 3-D float64 grid, written into ``out`` (3, *f.shape): central
    differences inside, one-sided at the faces, divided by the grid ``spacing`` (mm), in
    the same operations and order as ``np.gradient(f, spacing)``, so the same values,
    without its three arrays and their copy into a stack.

    >>> f = np.arange(24.0).reshape(2, 3, 4) ** 2
    >>> out = np.empty((3, *f.shape))
    >>> all(np.array_equal(a, b) for a, b in zip(gradient_into(f, 0.5, out), np.gradient(f, 0.5)))
    True
    """
    if f.ndim != 3 or out.shape != (3, *f.shape) or min(f.shape) < 2:
        return np.stack(np.gradient(f, spacing), out=out)  # np.gradient's own errors for a grid too small
    h = float(spacing)
    for axis in range(3):
        o = np.moveaxis(out[axis], axis, 0)
        g = np.moveaxis(f, axis, 0)
        np.subtract(g[2:], g[:-2], out=o[1:-1])
        o[1:-1] /= 2.0 * h
        np.subtract(g[1], g[0], out=o[0])
        o[0] /= h
        np.subtract(g[-1], g[-2], out=o[-1])
        o[-1] /= h
    return out


class DistanceMap:
    """Sub-voxel signed distance to an instance's surface (paper 4.2), object frame, mm.

    The surface is the marching-cubes 0.5 iso-surface of the binary mask, its cavities filled
    (``mask`` is the filled one). The field is
    sampled on the mask's grid as ``edt_out - 0.5`` outside and ``-(edt_in - 0.5)``
    inside (Euclidean distance transforms to the nearest voxel centre of the other kind,
    in voxels, × spacing): across every grid edge that crosses the surface the two nodes
    hold -0.5 and +0.5 voxel, so the zero level set of the trilinear interpolant passes
    exactly through the marching-cubes vertices (edge midpoints). Optionally
    (``band_vox`` > 0) nodes within that band get exact point-to-triangle distances to
    the marching-cubes surface instead; the kinks of the exact distance at staircase
    corners bias the interpolated zero set, so projections land closer to the surface with
    the EDT field, the default (figures in ``docs/history.md``, Coating). Values and gradients
    (central differences) are interpolated trilinearly; negative inside. Points outside
    the grid are clamped onto it and their distance increased by the clamping offset, so
    projection pulls them in. Fit figures use exact distances to the marching-cubes
    triangles (:meth:`surface_distance`).

    Use :meth:`from_object_volume`.
    """

    def __init__(self, sdf_mm, spacing_mm, origin_object, surface_vertices, surface_faces, mask, source="", locator=None):
        sdf = np.asarray(sdf_mm, dtype=np.float64)
        # field-major (4, voxels): value and gradient; sampling gathers (4, 8 corners, M)
        # so the trilinear lerps run over long contiguous rows (M points), not (M, 8, 4).
        # The rows are written in place (``sdf_mm`` is a view of the first): no stacked copy
        fields = np.empty((4, sdf.size))
        fields[0].reshape(sdf.shape)[...] = sdf
        gradient_into(fields[0].reshape(sdf.shape), float(spacing_mm), fields[1:].reshape(3, *sdf.shape))
        self._set_up(fields, sdf.shape, spacing_mm, origin_object, surface_vertices, surface_faces, mask, source,
                     locator)

    def _set_up(self, fields, shape, spacing_mm, origin_object, surface_vertices, surface_faces, mask, source,
                locator) -> None:
        self.spacing_mm = float(spacing_mm)
        self.origin_object = np.asarray(origin_object, float)
        self.surface_vertices = surface_vertices
        self.surface_faces = surface_faces
        self.mask = mask
        self.source = source
        self._fields_flat = fields
        self.sdf_mm = fields[0].reshape(shape)
        self._shape = np.array(self.sdf_mm.shape)
        self._hi_vox = self._shape - 1.0
        self._hi_base = self._shape - 2
        self._strides = np.array([self._shape[1] * self._shape[2], self._shape[2], 1], dtype=np.int64)
        # the 8 cell corners' offsets, z step outermost: (dz, dy, dx) in the order of np.indices
        self._corner_offsets = (np.indices((2, 2, 2))[::-1].reshape(3, -1).T @ self._strides).reshape(8, 1)
        self._locator_cache = locator
        self._samples_cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    @classmethod
    def from_object_volume(cls, ov: ObjectVolume, band_vox: float = 0.0) -> DistanceMap:
        """Build the distance map of an :class:`ObjectVolume` (its grid is already cropped).

        When the volume names a store (``ov.distance_map_store``, a folder of this machine),
        a map kept there for the same mask, grid and ``band_vox`` is read instead (the same
        arrays), and a map built here is kept there for the next coating of the instance,
        within the store's budget (``STORE_BUDGET_BYTES``; ``STORE_KEEP_FREE_BYTES`` of the
        disk left free). A store that is absent, full or unreadable changes nothing but time.
        """
        store = Path(ov.distance_map_store) if ov.distance_map_store else None
        key = _store_key(ov, band_vox) if store is not None else ""
        kept = _read_kept(store, key, ov) if store is not None else None
        if kept is not None:
            return kept
        dm = cls._build(ov, band_vox)
        if store is not None:
            _keep(dm, store, key)
        return dm

    @classmethod
    def _build(cls, ov: ObjectVolume, band_vox: float) -> DistanceMap:
        mask = np.asarray(ov.mask, dtype=bool)
        if mask.ndim != 3 or not mask.any():
            raise InputError(f"distance map: the object volume of {ov.source or 'an instance'} is empty")
        mask = fill_cavities(mask)
        # inside: distance to the nearest outside centre; every outside voxel nearer than
        # one beyond the mask's bounding box + 1 voxel lies in that box (clamping a voxel
        # onto the box brings it closer and keeps it outside), so the EDT runs on the box
        occupied = [np.flatnonzero(mask.any(axis=tuple(k for k in range(3) if k != a))) for a in range(3)]
        lo = np.maximum(np.array([o[0] for o in occupied]) - 1, 0)
        hi = np.minimum(np.array([o[-1] for o in occupied]) + 2, mask.shape)
        box = tuple(slice(a, b) for a, b in zip(lo, hi))
        sub = mask[box]
        # the two EDTs (scipy releases the GIL in them) run side by side on two threads in
        # the main process (Blender, a serial build), the marching cubes (holds the GIL)
        # after the inside one; in a worker process, whose siblings keep the cores busy, one
        # after the other (:func:`~ssm_addon.base.compute.inner_threads`). The same arrays
        if inner_threads(2) > 1:
            with ThreadPoolExecutor(max_workers=2) as pool:
                outside = pool.submit(ndimage.distance_transform_edt, ~mask)  # voxels, to nearest inside centre
                inside = pool.submit(ndimage.distance_transform_edt, sub)
                verts, faces = marching_cubes(mask)
                sdf = outside.result()
                inside = inside.result()
        else:
            sdf = ndimage.distance_transform_edt(~mask)
            inside = ndimage.distance_transform_edt(sub)
            verts, faces = marching_cubes(mask)
        verts = ov.voxel_to_object(verts)
        sdf -= 0.5
        sdf_box = sdf[box]
        sdf_box[sub] = 0.5 - inside[sub]
        sdf *= ov.spacing_mm
        locator = None
        nodes = np.empty((0, 3))
        if band_vox >= 0.5:  # |sdf| >= 0.5 voxel everywhere: a smaller band holds no node
            band = np.abs(sdf) <= band_vox * ov.spacing_mm
            nodes = np.argwhere(band) * ov.spacing_mm + np.asarray(ov.origin_object, float)
        if len(nodes):
            locator = MeshLocator(verts, faces)
            d = locator.query(nodes)[1]
            sdf[band] = np.where(mask[band], -d, d)
        return cls(sdf, ov.spacing_mm, ov.origin_object, verts, faces, mask, ov.source, locator)

    @property
    def locator(self) -> MeshLocator:
        """Exact nearest-point queries on the marching-cubes triangles (built on first use)."""
        if self._locator_cache is None:
            self._locator_cache = MeshLocator(self.surface_vertices, self.surface_faces)
        return self._locator_cache

    def surface_samples(self, stride: int) -> tuple[np.ndarray, np.ndarray]:
        """Every ``stride``-th marching-cubes vertex (object mm) and its unit normal, cached.

        Marching-cubes vertices are ordered slice by slice, so a stride thins them evenly.
        """
        cache = self._samples_cache
        if stride not in cache:
            pts = self.surface_vertices[::stride]
            cache[stride] = (pts, self.normals(pts))
        return cache[stride]

    # -- sampling -------------------------------------------------------------------------
    def sample(self, points: np.ndarray):
        """Trilinear signed distance (M,) mm and gradient (M, 3) at object points (mm)."""
        return self._sample_fields(self._fields_flat, points)

    def _sample_fields(self, fields_flat: np.ndarray, points: np.ndarray):
        p = np.asarray(points, float).reshape(-1, 3)
        vox = (p - self.origin_object) / self.spacing_mm
        # ufuncs instead of np.clip / np.floor (their wrappers were a fifth of the time
        # for the ~600 points of a template); clamped >= 0, so truncation is the floor
        clamped = np.minimum(np.maximum(vox, 0.0), self._hi_vox)
        base = np.minimum(clamped.astype(np.int64), self._hi_base)
        t = (clamped - base).T.copy()  # (3, M)
        lin = base[:, 0] * self._strides[0] + base[:, 1] * self._strides[1] + base[:, 2]
        # corners (4 fields, dz, dy, dx, M): lerp z, then y, then x (the operations per point
        # are those of a lerp per axis, so the values are the same), each on whole halves
        corners = np.take(fields_flat, self._corner_offsets + lin, axis=1).reshape(4, 2, 2, 2, -1)
        c = corners[:, 0] + t[2] * (corners[:, 1] - corners[:, 0])
        c = c[:, 0] + t[1] * (c[:, 1] - c[:, 0])
        vals = c[:, 0] + t[0] * (c[:, 1] - c[:, 0])
        d = vals[0]
        g = vals[1:].T.copy()
        if not np.any(vox != clamped):  # every point inside the grid
            return d, g
        off = (vox - clamped) * self.spacing_mm
        out = np.any(off != 0.0, axis=1)
        if np.any(out):
            r = np.linalg.norm(off[out], axis=1)
            d[out] = d[out] + r
            gn = g[out] / np.maximum(np.linalg.norm(g[out], axis=1, keepdims=True), 1e-12)
            g[out] = gn + off[out] / r[:, None]
        return d, g

    def smooth_normals(self, points: np.ndarray, sigma_mm: float) -> np.ndarray:
        """(M, 3) unit normals of the surface smoothed at scale ``sigma_mm`` (mm).

        The gradient of the signed distance field convolved with a Gaussian of width
        ``sigma_mm``, interpolated trilinearly (object frame). Inside a thin plate
        (a process or lamina thinner than ~2σ) the raw gradient flips across the medial
        surface, while the smoothed one points along the plate towards its rim, which
        is the normal a triangle spanning the plate should have (used by
        :func:`folded_triangles`). ``sigma_mm`` <= 0: the raw gradient.
        """
        if sigma_mm <= 0:
            return self.normals(points)
        key = round(float(sigma_mm), 6)
        cache = self.__dict__.setdefault("_smooth_cache", {})
        if key not in cache:
            fields = np.empty_like(self._fields_flat)
            sm = fields[0].reshape(self.sdf_mm.shape)
            ndimage.gaussian_filter(self.sdf_mm, key / self.spacing_mm, output=sm, mode="nearest")
            gradient_into(sm, self.spacing_mm, fields[1:].reshape(3, *sm.shape))
            cache[key] = fields
        g = self._sample_fields(cache[key], points)[1]
        return g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(M,) interpolated signed distance in mm (negative inside)."""
        return self.sample(points)[0]

    def normals(self, points: np.ndarray) -> np.ndarray:
        """(M, 3) unit outward surface normals (normalised distance gradient)."""
        g = self.sample(points)[1]
        return g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)

    def project(self, points: np.ndarray, iterations: int = 3) -> np.ndarray:
        """Move points onto the surface: p <- p - d(p) ∇d/|∇d|, ``iterations`` times (paper 4.2)."""
        p = np.array(points, dtype=float).reshape(-1, 3)
        for _ in range(iterations):
            d, g = self.sample(p)
            n = g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)
            p -= d[:, None] * n
        return p

    def project_along(self, points: np.ndarray, normals: np.ndarray, *, reach_mm: float = 4.0) -> np.ndarray:
        """Move points onto the surface along their own outward normals (mm, object frame).

        Along each line p + t n (|t| <= ``reach_mm``) the crossing of the surface from
        inside to outside nearest to p, located to sub-voxel precision by linear
        interpolation of the distance samples (every half voxel). Unlike
        :meth:`project`, which follows the distance gradient, a point inside a thin
        process cannot cross to the far side. Points without such a crossing within
        reach go the gradient way.

        Examples
        --------
        >>> import numpy as np
        >>> from ssm_addon.instances.volume import ObjectFrame, ObjectVolume
        >>> g = np.mgrid[-14:15, -14:15, -14:15]
        >>> ball = ObjectVolume((g ** 2).sum(0) <= 100, 1.0, np.full(3, -14.0), ObjectFrame(np.zeros(3), np.eye(3)))
        >>> dm = DistanceMap.from_object_volume(ball)
        >>> q = dm.project_along([[0.0, 0.0, 8.0], [0.0, 7.0, 0.0]], [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
        >>> np.round(np.linalg.norm(q, axis=1), 1)  # the last voxel centre at 10 mm, its face at 10.5
        array([10.5, 10.5])
        """
        p = np.array(points, dtype=float).reshape(-1, 3)
        n = np.asarray(normals, float).reshape(-1, 3)
        n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        step = 0.5 * self.spacing_mm
        ts = np.arange(-reach_mm, reach_mm + 0.5 * step, step)
        d = self.distance((p[:, None, :] + ts[None, :, None] * n[:, None, :]).reshape(-1, 3)).reshape(len(p), len(ts))
        up = (d[:, :-1] <= 0) & (d[:, 1:] > 0)  # inside -> outside going outwards
        frac = d[:, :-1] / np.where(up, d[:, :-1] - d[:, 1:], 1.0)
        t_cross = np.where(up, ts[None, :-1] + frac * step, np.inf)
        k = np.argmin(np.abs(t_cross), axis=1)
        t = t_cross[np.arange(len(p)), k]
        ok = np.isfinite(t)
        out = p + np.where(ok, t, 0.0)[:, None] * n
        if not ok.all():
            out[~ok] = self.project(p[~ok], 3)
        return out

    def surface_distance(self, points: np.ndarray) -> np.ndarray:
        """(M,) exact unsigned distance (mm) to the marching-cubes surface (for fit figures)."""
        return self.locator.query(points, k=12)[1]

    def closest_surface_points(self, points: np.ndarray) -> np.ndarray:
        """(M, 3) exact nearest points on the marching-cubes surface."""
        return self.locator.query(points, k=12)[0]


def _store_key(ov: ObjectVolume, band_vox: float) -> str:
    """The name of a volume's map in a store: a digest of what the map is computed from."""
    mask = np.asarray(ov.mask, dtype=bool)
    h = hashlib.sha256(f"ssm distance map {STORE_FORMAT} {mask.shape} {float(ov.spacing_mm)!r} "
                       f"{float(band_vox)!r}".encode())
    h.update(np.asarray(ov.origin_object, dtype=np.float64).tobytes())
    h.update(np.packbits(mask).tobytes())
    return h.hexdigest()[:40]


def _read_kept(store: Path, key: str, ov: ObjectVolume) -> DistanceMap | None:
    """The map kept in ``store`` under ``key``, or None (not kept, or not readable as one).

    The fields are mapped from the file, not read: a coating samples the grid near the
    surface, so only those pages are brought in (the file's pages stay in the system's
    cache from when they were written)."""
    mask = np.asarray(ov.mask, dtype=bool)
    try:
        with open(store / f"{key}.npy", "rb") as f:
            vertices, faces = (np.load(f, allow_pickle=False) for _ in range(2))
            version = np.lib.format.read_magic(f)
            if version != (1, 0):
                return None
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
            offset = f.tell()
            if shape != (4, mask.size) or fortran or dtype != np.float64:
                return None
            buffer = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        fields = np.frombuffer(buffer, dtype=np.float64, count=4 * mask.size, offset=offset).reshape(shape)
    except (OSError, ValueError, EOFError):
        return None
    if vertices.ndim != 2 or faces.ndim != 2 or vertices.shape[1:] != (3,) or faces.shape[1:] != (3,):
        return None
    dm = DistanceMap.__new__(DistanceMap)
    dm._set_up(fields, mask.shape, ov.spacing_mm, ov.origin_object, vertices, faces, fill_cavities(mask), ov.source,
               None)
    return dm


def _keep(dm: DistanceMap, store: Path, key: str) -> None:
    """Write ``dm`` into ``store`` under ``key`` when the store exists here and has room.

    Written to a file of this process and renamed, so a reader sees a whole map or none."""
    size = dm._fields_flat.nbytes + dm.surface_vertices.nbytes + dm.surface_faces.nbytes
    part = store / f"{key}.{os.getpid()}.part"
    try:
        if not store.is_dir():
            return
        used = sum(e.stat().st_size for e in os.scandir(store) if e.is_file())
        if used + size > STORE_BUDGET_BYTES or shutil.disk_usage(store).free < size + STORE_KEEP_FREE_BYTES:
            return
        with open(part, "wb") as f:
            for a in (dm.surface_vertices, dm.surface_faces, dm._fields_flat):  # the fields last: mapped
                np.save(f, np.ascontiguousarray(a), allow_pickle=False)
        os.replace(part, store / f"{key}.npy")
    except OSError:
        with contextlib.suppress(OSError):
            part.unlink(missing_ok=True)
