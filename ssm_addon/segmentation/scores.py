"""Judging a segmentation against a reference label map, and images made worse the way real scans are."""

from __future__ import annotations

import numpy as np
from nibabel.affines import apply_affine
from scipy import ndimage
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from .image import GreyImage, segmentation_mask

__all__ = ["degrade_image", "mask_surface_points", "segmentation_scores"]


def mask_surface_points(mask: np.ndarray, affine: np.ndarray, *, step_mm: float = 0.5) -> np.ndarray:
    """(M, 3) world mm: points on the boundary of a voxel mask (marching cubes at 0.5 on the mask
    padded by a voxel, vertices taken through the affine)."""
    box = ndimage.find_objects(mask.astype(np.uint8))[0]
    sub = np.pad(mask[box], 1).astype(np.float32)
    verts, _f, _n, _v = marching_cubes(sub, 0.5)
    ijk = verts - 1 + np.array([s.start for s in box], float)
    return apply_affine(affine, ijk)


def segmentation_scores(points_world: np.ndarray, faces: np.ndarray, reference: np.ndarray, affine: np.ndarray) -> dict:
    """Dice on the reference's grid and symmetric surface distances (mm) of a segmented surface.

    Parameters
    ----------
    points_world, faces
        The segmented closed surface (world mm).
    reference : (I, J, K) bool
        The expert's mask; ``affine`` its voxel -> world (mm).

    Returns
    -------
    dict with ``dice``, ``mean_mm`` and ``p95_mm`` (over both directions: surface to reference
    boundary and back) and ``max_mm``.
    """
    grid = GreyImage(np.zeros(reference.shape, np.float32), np.asarray(affine, float))
    seg = segmentation_mask(points_world, faces, grid)
    inter = np.count_nonzero(seg & reference)
    dice = 2.0 * inter / max(np.count_nonzero(seg) + np.count_nonzero(reference), 1)
    ref_pts = mask_surface_points(reference, affine)
    seg_pts = mask_surface_points(seg, affine) if seg.any() else np.asarray(points_world, float)
    d1 = cKDTree(ref_pts).query(seg_pts)[0]
    d2 = cKDTree(seg_pts).query(ref_pts)[0]
    d = np.concatenate([d1, d2])
    return {"dice": float(dice), "mean_mm": float(d.mean()), "p95_mm": float(np.percentile(d, 95)),
            "max_mm": float(d.max())}


def degrade_image(image: GreyImage, *, slice_mm: float = 3.0, noise_hu: float = 30.0, seed: int = 0) -> GreyImage:
    """The image as a thick-slice scan: along the voxel axis nearest the superior direction,
    slices ``slice_mm`` thick (the mean over each slab, sampled every ``slice_mm``), plus Gaussian
    noise of SD ``noise_hu``; the affine says the new spacing."""
    a = np.asarray(image.affine, float)
    axis = int(np.argmax(np.abs(a[2, :3]) / np.linalg.norm(a[:3, :3], axis=0)))
    step = float(np.linalg.norm(a[:3, axis]))
    factor = max(1, int(round(slice_mm / step)))
    data = np.moveaxis(np.asarray(image.data, np.float32), axis, 0)
    n = data.shape[0] // factor
    thick = data[:n * factor].reshape(n, factor, *data.shape[1:]).mean(axis=1)
    rng = np.random.default_rng(seed)
    thick = thick + rng.normal(0.0, noise_hu, thick.shape).astype(np.float32)
    out = np.moveaxis(thick, 0, axis)
    new = a.copy()
    new[:3, axis] = a[:3, axis] * factor
    new[:3, 3] = a[:3, 3] + a[:3, axis] * (factor - 1) / 2.0  # the slab's centre
    return GreyImage(out.astype(np.float32), new, f"{image.path} (slices {factor * step:g} mm, noise {noise_hu:g})")
