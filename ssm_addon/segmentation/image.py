"""Grey-value images (CT) in world mm: reading, smoothing and sampling along normals.

An image is its voxel values with the affine that maps voxel indices to world RAS mm (the
same convention as the label maps of :mod:`ssm_addon.formats.label_maps`). Sampling
takes world points, so a model's surface, its normals and the search along them stay in
world mm whatever the grid's spacing, orientation or obliqueness.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from ..base.errors import InputError
from ..formats.grid import AffineGrid
from ..formats.label_maps import read_image_array
from ..instances.voxelize import voxelize_mesh

__all__ = ["PLANES", "GreyImage", "read_image", "segmentation_mask", "window_values", "world_slice"]


@dataclass(frozen=True, eq=False)
class GreyImage(AffineGrid):
    """A grey-value image and its voxel -> world (RAS mm) affine (an
    :class:`~ssm_addon.formats.grid.AffineGrid` of its values).

    Attributes
    ----------
    data : (I, J, K) float32 ndarray
        Voxel values (Hounsfield units for CT).
    affine : (4, 4) float ndarray
        Voxel index (i, j, k, 1) -> world (x, y, z, 1), mm, RAS.
    path : str
        The file it came from (for messages).
    """

    data: np.ndarray
    affine: np.ndarray
    path: str = ""
    _smoothed: dict = field(default_factory=dict, repr=False, compare=False)

    GRID_ARRAY = "data"

    def smoothed(self, sigma_mm: float) -> np.ndarray:
        """The image blurred by a Gaussian of ``sigma_mm`` (world mm, per axis by its spacing); cached."""
        key = round(float(sigma_mm), 6)
        if key not in self._smoothed:
            if key <= 0:
                self._smoothed[key] = np.asarray(self.data, np.float32)
            else:
                sig = key / self.spacing_mm
                self._smoothed[key] = ndimage.gaussian_filter(np.asarray(self.data, np.float32), sig, mode="nearest")
        return self._smoothed[key]

    def sample(self, points_world: np.ndarray, *, sigma_mm: float = 0.0) -> np.ndarray:
        """Trilinear values at world points (…, 3) of the image blurred by ``sigma_mm``; outside: the nearest edge."""
        pts = np.asarray(points_world, float)
        ijk = self.to_index(pts.reshape(-1, 3))
        vals = ndimage.map_coordinates(self.smoothed(sigma_mm), ijk.T, order=1, mode="nearest")
        return vals.reshape(pts.shape[:-1])

    def profiles(self, points_world: np.ndarray, normals: np.ndarray, offsets_mm: np.ndarray, *,
                 sigma_mm: float = 0.0) -> np.ndarray:
        """(N, M) values along each point's normal at ``offsets_mm`` (M,), outward positive (mm)."""
        pos = (np.asarray(points_world, float)[:, None, :]
               + np.asarray(offsets_mm, float)[None, :, None] * np.asarray(normals, float)[:, None, :])
        return self.sample(pos, sigma_mm=sigma_mm)


PLANES = ("sagittal", "coronal", "axial")
"""The slice planes, by the world axis they are perpendicular to (x: R, y: A, z: S)."""


def world_slice(image: GreyImage, axis: int, position_mm: float, *, pixel_mm: float | None = None,
                max_pixels: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """The image on the world plane perpendicular to ``axis`` (0: x, sagittal; 1: y, coronal; 2: z,
    axial) at ``position_mm``, over the image's world extent in the other two axes.

    Returns
    -------
    values : (H, W) float32
        Trilinear grey values (NaN outside the image); rows run along the plane's second
        axis, columns along its first (the two remaining world axes in x, y, z order).
    corners : (4, 3) mm
        World corners of the pixel grid's outer edges: (first-low, second-low), (first-high,
        second-low), (first-high, second-high), (first-low, second-high).
    """
    lo, hi = image.extent_world()
    u, v = [a for a in range(3) if a != axis]
    step = float(pixel_mm or image.spacing_mm.min())
    step = max(step, float(max(hi[u] - lo[u], hi[v] - lo[v])) / max_pixels)
    nu = max(1, int(np.ceil((hi[u] - lo[u]) / step)) + 1)
    nv = max(1, int(np.ceil((hi[v] - lo[v]) / step)) + 1)
    gu = lo[u] + step * np.arange(nu)
    gv = lo[v] + step * np.arange(nv)
    pts = np.zeros((nv, nu, 3))
    pts[..., u] = gu[None, :]
    pts[..., v] = gv[:, None]
    pts[..., axis] = position_mm
    values = image.sample(pts).astype(np.float32)
    values[~image.contains(pts.reshape(-1, 3)).reshape(nv, nu)] = np.nan
    corners = np.zeros((4, 3))
    corners[:, axis] = position_mm
    for i, (a, b) in enumerate(((0, 0), (1, 0), (1, 1), (0, 1))):
        corners[i, u] = gu[0] - step / 2 if a == 0 else gu[-1] + step / 2
        corners[i, v] = gv[0] - step / 2 if b == 0 else gv[-1] + step / 2
    return values, corners


def window_values(values: np.ndarray, *, level: float, width: float) -> np.ndarray:
    """Grey values mapped to [0, 1] by a display window (``level`` its centre, ``width`` its span);
    NaN (outside the image) becomes 0."""
    out = (np.asarray(values, np.float32) - (level - width / 2.0)) / max(float(width), 1e-6)
    return np.nan_to_num(np.clip(out, 0.0, 1.0), nan=0.0)


def read_image(path) -> GreyImage:
    """Read a grey-value image (NIfTI, NRRD, MetaImage) with its voxel -> world RAS mm affine.

    The affine is read as for label maps (NIfTI: the scanner's form, as 3D Slicer reads it;
    NRRD and MetaImage in LPS turned into RAS).

    Raises
    ------
    InputError
        A missing, unreadable, 4-D or non-numeric file, or a degenerate affine (the message
        names the file).
    """
    data, affine, path = read_image_array(path)
    data = np.squeeze(data) if data.ndim > 3 else data
    if data.ndim != 3:
        raise InputError(f"{path}: the image has {data.ndim} dimensions (shape {data.shape}); a 3-D image is needed")
    if not np.issubdtype(data.dtype, np.number) or np.issubdtype(data.dtype, np.complexfloating):
        raise InputError(f"{path}: voxel type {data.dtype} is not a grey value")
    values = data.astype(np.float32)
    if not np.all(np.isfinite(values)):
        raise InputError(f"{path}: {int(np.sum(~np.isfinite(values)))} voxel(s) are NaN or infinite")
    return GreyImage(values, affine, str(path))


def segmentation_mask(points_world: np.ndarray, faces: np.ndarray, image: GreyImage) -> np.ndarray:
    """(I, J, K) bool on ``image``'s grid: the voxels whose centres lie inside the closed surface.

    The surface is taken into the image's voxel-index coordinates (its affine's inverse, so
    an oblique or LPS-stored grid is handled exactly) and voxelized there by ray parity
    (:func:`ssm_addon.instances.voxelize.voxelize_mesh` at unit spacing).
    """
    ijk = image.to_index(np.asarray(points_world, float))
    vol = voxelize_mesh(ijk, faces, 1.0, source="segmented surface")
    origin = np.rint(vol.affine[:3, 3]).astype(np.int64)
    out = np.zeros(image.shape, bool)
    lo = np.maximum(origin, 0)
    hi = np.minimum(origin + np.asarray(vol.mask.shape), np.asarray(image.shape))
    if np.any(hi <= lo):
        return out
    src = tuple(slice(int(a - o), int(b - o)) for a, b, o in zip(lo, hi, origin))
    dst = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))
    out[dst] = vol.mask[src]
    return out
