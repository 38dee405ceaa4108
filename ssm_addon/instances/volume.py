"""The data of paper section 2: object frames and resampled objects.

Reading files is :mod:`ssm_addon.formats.label_maps` (images: the ``LabelMap`` and the binary
``Volume`` of one label) and :mod:`ssm_addon.formats.meshes` (meshes), voxelizing meshes
:mod:`ssm_addon.instances.voxelize`, the object frame :mod:`ssm_addon.instances.frame` and the
isotropic resampling :mod:`ssm_addon.instances.resampling`; the one step that chains them for
an instance is :func:`ssm_addon.instances.importing.load_object`.

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
from scipy import ndimage

from ..base.errors import InputError
from ..formats.label_maps import Volume
from ..meshutil import marching_cubes


@dataclass(frozen=True)
class ObjectFrame:
    """The object-related coordinate system of paper section 2.

    Attributes
    ----------
    origin_world : (3,) float ndarray
        Centre of mass in world mm.
    axes_world : (3, 3) float ndarray
        Columns are the object x, y, z axes as unit vectors in world coordinates;
        orthonormal and right-handed (det = +1), or left-handed (det = -1) for an instance
        mirrored into the template's side (:func:`mirrored`): its object coordinates are then
        those of its mirror image.
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
    def mirrored(self) -> bool:
        """Whether the frame is left-handed: object coordinates of the object's mirror image."""
        return bool(np.linalg.det(self.axes_world) < 0)

    @property
    def matrix_world(self) -> np.ndarray:
        """(4, 4) object mm -> world mm."""
        m = np.eye(4)
        m[:3, :3] = self.axes_world
        m[:3, 3] = self.origin_world
        return m


def frame_to_arrays(prefix: str, frame: ObjectFrame, out: dict) -> None:
    """Store ``frame`` in ``out`` as plain arrays under ``<prefix>/<field>`` (no pickles)."""
    out[f"{prefix}/origin_world"] = np.asarray(frame.origin_world, float)
    out[f"{prefix}/axes_world"] = np.asarray(frame.axes_world, float)
    out[f"{prefix}/second_moments_mm2"] = np.asarray(frame.second_moments_mm2, float)
    out[f"{prefix}/method"] = np.asarray(frame.method)


def frame_from_arrays(prefix: str, arrays) -> ObjectFrame:
    """The frame stored by :func:`frame_to_arrays` (``arrays``: a mapping or an npz)."""
    return ObjectFrame(origin_world=arrays[f"{prefix}/origin_world"], axes_world=arrays[f"{prefix}/axes_world"],
                       second_moments_mm2=arrays[f"{prefix}/second_moments_mm2"],
                       method=str(arrays[f"{prefix}/method"]))


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
    distance_map_store : str
        A folder where the object's distance map may be kept between the coatings of one
        build (:mod:`ssm_addon.coating.distance_map`); empty: none. Set only for the time of
        a build that coats the instance more than once.
    """

    mask: np.ndarray
    spacing_mm: float
    origin_object: np.ndarray
    frame: ObjectFrame
    source: str = ""
    distance_map_store: str = ""

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


def mirror_axis(frame: ObjectFrame) -> int:
    """The object axis a mirror image is taken along: the one nearest the world's x axis
    (left-right in RAS and LPS), so that a patient-aligned frame mirrors about its sagittal plane."""
    return int(np.argmax(np.abs(np.asarray(frame.axes_world, float)[0])))


def mirrored(volume: ObjectVolume) -> ObjectVolume:
    """The object's mirror image in a left-handed frame: the same voxels in the world.

    The mask is flipped along :func:`mirror_axis` and that axis of the frame negated, so that
    object coordinates are those of the mirror image (a left bone's become a right bone's)
    while ``frame.to_world`` still gives the input's own world points: a coating made on
    the mirrored volume is in the template's side in object mm and in the instance's own side
    in world mm. Mirroring twice gives the volume back.

    >>> m = np.zeros((4, 3, 3), bool); m[0, 1, 1] = True
    >>> fr = ObjectFrame(origin_world=np.zeros(3), axes_world=np.eye(3))
    >>> ov = ObjectVolume(m, 1.0, np.array([-1.0, -1.0, -1.0]), fr)
    >>> mv = mirrored(ov)
    >>> mv.frame.mirrored, mv.voxel_to_object(np.argwhere(mv.mask)).tolist()
    (True, [[1.0, 0.0, 0.0]])
    >>> mv.frame.to_world(mv.voxel_to_object(np.argwhere(mv.mask))).tolist()
    [[-1.0, 0.0, 0.0]]
    """
    k = mirror_axis(volume.frame)
    mask = np.ascontiguousarray(np.flip(volume.mask, axis=k))
    origin = np.array(volume.origin_object, float)
    origin[k] = -(origin[k] + (volume.mask.shape[k] - 1) * volume.spacing_mm)
    return ObjectVolume(mask, volume.spacing_mm, origin, mirrored_frame(volume.frame), source=volume.source,
                        distance_map_store=volume.distance_map_store)


def mirrored_frame(frame: ObjectFrame) -> ObjectFrame:
    """``frame`` with its :func:`mirror_axis` negated: object coordinates of the mirror image (the
    frame of :func:`mirrored`). Mirroring twice gives the frame back."""
    axes = np.array(frame.axes_world, float)
    axes[:, mirror_axis(frame)] *= -1.0
    return ObjectFrame(origin_world=np.asarray(frame.origin_world, float), axes_world=axes,
                       second_moments_mm2=frame.second_moments_mm2, method=frame.method)


def bounding_box(mask: np.ndarray) -> tuple[slice, slice, slice]:
    """Index slices of the smallest box holding every True voxel (InputError if none)."""
    slices = []
    for axis in range(3):
        other = tuple(a for a in range(3) if a != axis)
        hit = np.nonzero(np.any(mask, axis=other))[0]
        if hit.size == 0:
            raise InputError("empty mask: no object voxels")
        slices.append(slice(int(hit[0]), int(hit[-1]) + 1))
    return tuple(slices)


def fill_cavities(mask: np.ndarray) -> np.ndarray:
    """``mask`` with its cavities filled: the background components (6-connected) that do not
    touch the array's border, such as the voxels a segmentation left out inside a vertebral
    body. The same array when there are none.

    >>> m = np.ones((5, 5, 5), bool); m[2, 2, 2] = False; m[0, 0, 0] = False
    >>> filled = fill_cavities(m)
    >>> bool(filled[2, 2, 2]), bool(filled[0, 0, 0]), int(filled.sum())
    (True, False, 124)
    """
    lab, n = ndimage.label(~mask)
    if n <= 1:
        return mask
    border = np.zeros(n + 1, bool)
    for axis in range(3):
        for idx in (0, -1):
            border[np.unique(np.take(lab, idx, axis=axis))] = True
    if border[1:].all():
        return mask
    return mask | ~border[lab]



# ---------------------------------------------------------------------------------------
# Display and summaries
# ---------------------------------------------------------------------------------------


def display_surface(volume, to_world: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Marching-cubes surface of a mask at level 0.5 with outward faces.

    Parameters
    ----------
    volume : Volume or ObjectVolume
        For a :class:`Volume` the vertices are in world mm. For an :class:`ObjectVolume`
        they are in object mm, or in world mm with ``to_world=True``.

    Returns
    -------
    vertices : (V, 3) float ndarray, mm
    faces : (F, 3) int ndarray, outward (positive signed volume)
    """
    if not np.any(volume.mask):
        raise InputError(f"{volume.source or 'volume'}: empty mask: nothing to display")
    ijk, faces = marching_cubes(volume.mask)
    if isinstance(volume, ObjectVolume):
        pts = volume.voxel_to_object(ijk)
        if to_world:
            pts = volume.frame.to_world(pts)
    else:
        pts = volume.voxel_to_world(ijk)
    if np.linalg.det(volume.affine[:3, :3] if isinstance(volume, Volume) else np.eye(3)) < 0:
        faces = faces[:, ::-1].copy()  # a mirroring affine turns outward faces inward
    return pts, faces


def summary(volume) -> dict:
    """Figures for printing: voxel count, volume (mm³), spacing (mm), bounding box.

    ``bbox_min``/``bbox_max`` are the extreme object voxel centres in world mm for a
    :class:`Volume` and in object mm for an :class:`ObjectVolume`.
    """
    if isinstance(volume, ObjectVolume):
        ijk = np.argwhere(volume.mask).astype(float)
        pts = volume.voxel_to_object(ijk) if len(ijk) else np.zeros((1, 3))
        spacing = [volume.spacing_mm] * 3
        vox_vol = volume.spacing_mm**3
        frame = "object"
    else:
        pts = volume.voxel_to_world(np.argwhere(volume.mask)) if volume.mask.any() else np.zeros((1, 3))
        spacing = volume.spacing_mm.tolist()
        vox_vol = volume.voxel_volume_mm3
        frame = "world"
    n = int(np.count_nonzero(volume.mask))
    return {
        "source": volume.source,
        "voxels": n,
        "volume_mm3": n * vox_vol,
        "spacing_mm": [float(s) for s in spacing],
        "shape": list(volume.mask.shape),
        "bbox_frame": frame,
        "bbox_min": pts.min(axis=0).tolist(),
        "bbox_max": pts.max(axis=0).tolist(),
    }
