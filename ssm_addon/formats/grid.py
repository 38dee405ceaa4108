"""The geometry every image and label map shares: a voxel grid and its (4, 4) affine.

:class:`AffineGrid` maps voxel indices (i, j, k) to world millimetres (RAS) and back with
nibabel's affine helpers (:func:`nibabel.affines.apply_affine`, :func:`~nibabel.affines.voxel_sizes`),
and says which world points the grid holds and what it spans. :class:`~.label_maps.LabelMap`,
:class:`~.label_maps.Volume` and :class:`~ssm_addon.segmentation.image.GreyImage` are grids of it;
an instance's :class:`~ssm_addon.instances.volume.ObjectVolume` is not (its grid lies in its
object frame, paper section 2).

>>> import numpy as np
>>> from ssm_addon.formats.label_maps import Volume
>>> v = Volume(np.zeros((4, 5, 6), bool), np.diag([2.0, 2.0, 3.0, 1.0]))
>>> v.shape, v.spacing_mm.tolist(), v.to_world([[1, 1, 1]]).tolist()
((4, 5, 6), [2.0, 2.0, 3.0], [[2.0, 2.0, 3.0]])
>>> v.contains([[7.0, 0.0, 0.0], [8.0, 0.0, 0.0]]).tolist()
[True, False]
"""

from __future__ import annotations

import numpy as np
from nibabel.affines import apply_affine, voxel_sizes

__all__ = ["AffineGrid"]


class AffineGrid:
    """A voxel grid with its voxel -> world (RAS mm) affine; a base of the image and label-map types.

    A subclass holds ``affine`` ((4, 4) float) and names its voxel array in ``GRID_ARRAY``.
    """

    GRID_ARRAY = ""

    @property
    def shape(self) -> tuple:
        """The voxel array's shape (I, J, K)."""
        return tuple(np.shape(getattr(self, self.GRID_ARRAY)))

    @property
    def spacing_mm(self) -> np.ndarray:
        """(3,) voxel edge lengths in mm (column norms of the affine)."""
        return voxel_sizes(self.affine)

    @property
    def voxel_volume_mm3(self) -> float:
        """Volume of one voxel in mm³ (|det| of the affine's linear part)."""
        return float(abs(np.linalg.det(self.affine[:3, :3])))

    def to_world(self, ijk) -> np.ndarray:
        """(…, 3) voxel indices -> world mm."""
        return apply_affine(self.affine, np.asarray(ijk, float))

    def voxel_to_world(self, ijk) -> np.ndarray:
        """(M, 3) voxel coordinates -> (M, 3) world mm (:meth:`to_world`)."""
        return self.to_world(ijk)

    def to_index(self, points_world) -> np.ndarray:
        """(…, 3) world mm -> continuous voxel indices."""
        return apply_affine(np.linalg.inv(self.affine), np.asarray(points_world, float))

    def contains(self, points_world) -> np.ndarray:
        """(M,) bool: the world points lie inside the grid (the voxel centres' hull, ±½ voxel)."""
        ijk = self.to_index(np.atleast_2d(points_world))
        return np.all((ijk >= -0.5) & (ijk <= np.asarray(self.shape) - 0.5), axis=1)

    def extent_world(self) -> np.ndarray:
        """(2, 3) the lowest and highest world coordinates of the grid's corner voxels' centres (mm)."""
        s = np.asarray(self.shape, float) - 1.0
        corners = np.array([[i, j, k] for i in (0, s[0]) for j in (0, s[1]) for k in (0, s[2])])
        w = self.to_world(corners)
        return np.stack([w.min(axis=0), w.max(axis=0)])
