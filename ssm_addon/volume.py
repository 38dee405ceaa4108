"""Label maps and meshes in, the world affine, the object frame and resampling (paper section 2).

Frames and units
----------------
* *voxel* coordinates are array indices (i, j, k) of a mask;
* *world* coordinates are the input file's scanner/patient coordinates in mm (RAS for
  NIfTI; NRRD/MetaImage LPS spaces are converted to RAS on load);
* *object* coordinates are mm in the object frame of paper section 2: origin at the
  centre of mass, axes along the principal axes of the second-moment matrix.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class LabelMap:
    """A label map as read from disk.

    Attributes
    ----------
    labels : (I, J, K) integer ndarray
        Label per voxel (0 = background).
    affine : (4, 4) float ndarray
        Voxel index (i, j, k, 1) -> world (x, y, z, 1) in mm (RAS).
    path : str
        The file it came from (for messages).
    """

    labels: np.ndarray
    affine: np.ndarray
    path: str = ""


@dataclass(frozen=True)
class Volume:
    """A binary object in its input grid.

    Attributes
    ----------
    mask : (I, J, K) bool ndarray
        True inside the object.
    affine : (4, 4) float ndarray
        Voxel index -> world mm.
    source : str
        File or object the mask came from.
    label : int or None
        The label picked from a label map (None: all non-zero, or a mesh).
    patient_oriented : bool
        True when world axes are patient axes (R, A, S), i.e. the input was an image
        with an orientation; False for meshes in arbitrary coordinates.
    """

    mask: np.ndarray
    affine: np.ndarray
    source: str = ""
    label: int | None = None
    patient_oriented: bool = True

    @property
    def spacing_mm(self) -> np.ndarray:
        """(3,) voxel edge lengths in mm (column norms of the affine)."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    @property
    def voxel_volume_mm3(self) -> float:
        """Volume of one voxel in mm³ (|det| of the affine's linear part)."""
        return float(abs(np.linalg.det(self.affine[:3, :3])))

    @property
    def volume_mm3(self) -> float:
        """Object volume in mm³: voxel count × voxel volume."""
        return float(np.count_nonzero(self.mask)) * self.voxel_volume_mm3

    def voxel_to_world(self, ijk: np.ndarray) -> np.ndarray:
        """(M, 3) voxel coordinates -> (M, 3) world mm."""
        ijk = np.asarray(ijk, dtype=float)
        return ijk @ self.affine[:3, :3].T + self.affine[:3, 3]


@dataclass(frozen=True)
class ObjectFrame:
    """The object-related coordinate system of paper section 2.

    Attributes
    ----------
    origin_world : (3,) float ndarray
        Centre of mass in world mm.
    axes_world : (3, 3) float ndarray
        Columns are the object x, y, z axes as unit vectors in world coordinates;
        orthonormal and right-handed (det = +1).
    second_moments_mm2 : (3,) float ndarray
        Second moments (variances, mm²) of the object along the three axes.
    method : str
        How axis order and signs were fixed: ``"patient"`` (paired with the nearest
        patient axes R, A, S) or ``"moments"`` (eigenvalue order + third-moment signs).
    """

    origin_world: np.ndarray
    axes_world: np.ndarray
    second_moments_mm2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    method: str = "moments"

    def to_world(self, points_object: np.ndarray) -> np.ndarray:
        """(M, 3) object mm -> (M, 3) world mm."""
        return np.asarray(points_object, float) @ self.axes_world.T + self.origin_world

    def to_object(self, points_world: np.ndarray) -> np.ndarray:
        """(M, 3) world mm -> (M, 3) object mm."""
        return (np.asarray(points_world, float) - self.origin_world) @ self.axes_world

    @property
    def matrix_world(self) -> np.ndarray:
        """(4, 4) object mm -> world mm."""
        m = np.eye(4)
        m[:3, :3] = self.axes_world
        m[:3, 3] = self.origin_world
        return m


@dataclass(frozen=True)
class ObjectVolume:
    """An isotropic binary image resampled along the object axes (paper section 2).

    The basis of all further processing: template generation and coating work on it.

    Attributes
    ----------
    mask : (I, J, K) bool ndarray
        Object voxels on an isotropic grid aligned with the object axes, with at least
        one background voxel on every side.
    spacing_mm : float
        Isotropic voxel edge in mm.
    origin_object : (3,) float ndarray
        Object coordinates (mm) of voxel (0, 0, 0)'s centre.
    frame : ObjectFrame
        The frame that maps object coordinates to world.
    source : str
        Where the object came from (for messages).
    """

    mask: np.ndarray
    spacing_mm: float
    origin_object: np.ndarray
    frame: ObjectFrame
    source: str = ""

    def voxel_to_object(self, ijk: np.ndarray) -> np.ndarray:
        """(M, 3) voxel coordinates -> (M, 3) object mm."""
        return np.asarray(ijk, float) * self.spacing_mm + self.origin_object

    def object_to_voxel(self, points_object: np.ndarray) -> np.ndarray:
        """(M, 3) object mm -> (M, 3) continuous voxel coordinates."""
        return (np.asarray(points_object, float) - self.origin_object) / self.spacing_mm

    @property
    def affine_object(self) -> np.ndarray:
        """(4, 4) voxel index -> object mm."""
        m = np.eye(4) * self.spacing_mm
        m[3, 3] = 1.0
        m[:3, 3] = self.origin_object
        return m

    @property
    def volume_mm3(self) -> float:
        """Object volume in mm³ of the resampled mask."""
        return float(np.count_nonzero(self.mask)) * self.spacing_mm**3
