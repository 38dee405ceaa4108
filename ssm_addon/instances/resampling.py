"""Isotropic resampling of an object along its object axes (paper section 2)."""

from __future__ import annotations

import numpy as np
from nibabel.affines import apply_affine, voxel_sizes
from scipy import ndimage

from ..base.errors import InputError, check_cancelled
from ..base.progress import report
from ..base.resources import BYTES_PER_OBJECT_VOXEL, check_allocation
from ..formats.label_maps import Volume
from ..instances.volume import ObjectFrame, ObjectVolume, bounding_box

__all__ = ["resample"]


def resample(
    volume: Volume, frame: ObjectFrame, spacing_mm: float = 1.0, *, progress=None, cancelled=None
) -> ObjectVolume:
    """Isotropic resampling of the object along its object axes (paper section 2).

    The float mask is interpolated trilinearly (on a padded crop around the object,
    so objects touching the input border work) at the centres of an isotropic grid
    aligned with the object axes, and thresholded at 0.5. The grid is aligned to
    multiples of ``spacing_mm`` in object mm (the centre of mass is a grid point) and
    cropped to the result's bounding box plus 2 background voxels on every side.

    Parameters
    ----------
    volume : Volume
        The object in its input grid (world mm).
    frame : ObjectFrame
        Object frame, e.g. from :func:`object_frame`.
    spacing_mm : float
        Output voxel edge (mm).

    Returns
    -------
    ObjectVolume
    """
    h = float(spacing_mm)
    name = volume.source or "volume"
    if not np.isfinite(h) or h <= 0:
        raise InputError(f"{name}: spacing must be a positive number of mm, got {spacing_mm!r}")
    try:
        box = bounding_box(volume.mask)
    except InputError as err:
        raise InputError(f"{name}: empty mask: no object voxels") from err
    pad = 2
    # before any large allocation: the object's box at the new spacing, and its float crop
    box_vox = np.array([s.stop - s.start for s in box], dtype=float)
    extent_mm = box_vox * voxel_sizes(volume.affine)
    along_axes = np.abs(frame.axes_world.T @ volume.affine[:3, :3]) @ box_vox  # the box seen along the object axes
    estimate = float(np.prod(np.ceil(along_axes / h) + 2 * pad + 2)) * BYTES_PER_OBJECT_VOXEL
    check_allocation(estimate + 4.0 * np.prod([s.stop - s.start + 2 * pad for s in box], dtype=float),
                     f"{name}: resampling the object's box ({' x '.join(f'{e:.0f}' for e in extent_mm)} mm) at {h:g} mm",
                     "use a coarser [template] spacing, or check the mask for stray voxels far from the object")
    sub = np.pad(volume.mask[box], pad).astype(np.float32)
    offset = np.array([s.start for s in box], dtype=float) - pad  # input index of sub[0, 0, 0]
    A = volume.affine[:3, :3]
    # object-frame bounding box of the object's voxel centres (corners of the crop box
    # are too loose for oblique grids): project the surface layer of the object only.
    inner = ndimage.binary_erosion(sub > 0.5)
    surf = np.nonzero((sub > 0.5) & ~inner)
    ijk = np.stack(surf, axis=1).astype(np.float64) + offset
    world = apply_affine(volume.affine, ijk)
    obj = frame.to_object(world)
    reach = np.abs(frame.axes_world.T @ A).sum(axis=1)  # one input voxel, in object mm per axis
    lo = np.floor((obj.min(axis=0) - reach) / h).astype(np.int64) - pad
    hi = np.ceil((obj.max(axis=0) + reach) / h).astype(np.int64) + pad
    shape = tuple(int(s) for s in hi - lo + 1)
    check_allocation(float(np.prod(shape, dtype=float)) * BYTES_PER_OBJECT_VOXEL,
                     f"{name}: resampling at {h:g} mm ({' x '.join(str(s) for s in shape)} voxels)",
                     "use a coarser [template] spacing, or check the mask for stray voxels far from the object")
    origin_object = lo * h
    # output voxel index -> sub index: inv(A) (to_world(origin + h*ijk) - t) - offset
    Ainv = np.linalg.inv(A)
    M = Ainv @ frame.axes_world * h
    b = Ainv @ (frame.to_world(origin_object[None])[0] - volume.affine[:3, 3]) - offset
    out = np.empty(shape, dtype=bool)
    slab = max(1, int((1 << 22) // max(shape[1] * shape[2], 1)))
    for i in range(0, shape[0], slab):
        check_cancelled(cancelled)
        n = min(slab, shape[0] - i)
        vals = ndimage.affine_transform(
            sub, M, offset=b + M[:, 0] * i, output_shape=(n, shape[1], shape[2]),
            order=1, mode="constant", cval=0.0, prefilter=False, output=np.float32,
        )  # fmt: skip
        out[i : i + n] = vals >= 0.5
        report(progress, (i + n) / shape[0], "resampling")
    if not out.any():
        raise InputError(f"{name}: the object vanished when resampled at {h} mm; use a finer spacing")
    tight = bounding_box(out)
    starts = np.array([max(s.start - pad, 0) for s in tight])
    stops = np.array([min(s.stop + pad, n) for s, n in zip(tight, shape)])
    mask = out[tuple(slice(a, z) for a, z in zip(starts, stops))]
    return ObjectVolume(
        mask=np.ascontiguousarray(mask), spacing_mm=h, origin_object=origin_object + starts * h,
        frame=frame, source=volume.source,
    )  # fmt: skip
