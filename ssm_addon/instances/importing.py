"""Instances: where each object of a study comes from, and its import (paper section 2).

An instance is one segmented object of the training set: a label of a label map, or a
closed surface mesh. Its import is always the same three steps, here and only here:
read (:mod:`ssm_addon.formats.label_maps` or :mod:`ssm_addon.instances.voxelize`), object frame
(:func:`ssm_addon.instances.frame.object_frame`) and isotropic resampling along the object axes
(:func:`ssm_addon.instances.resampling.resample`). The command line and Blender both call
:func:`import_instance` (or :func:`load_object` for a bare file), so the same source
gives the same :class:`~ssm_addon.instances.volume.ObjectVolume` in both, bit for bit.
"""

from __future__ import annotations

import contextlib
import unicodedata
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..base.errors import InputError, check_cancelled
from ..base.progress import CancelledFn, ProgressFn, report, sub_progress
from ..formats.label_maps import LabelMap, Volume, is_mesh_file, load_volume, select_label
from ..formats.landmarks import LandmarkSet
from ..formats.meshes import mesh_space, read_mesh
from ..instances.frame import mesh_solid_frame, object_frame
from ..instances.resampling import resample
from ..instances.volume import ObjectFrame, ObjectVolume, bounding_box, mirrored
from ..instances.voxelize import keep_thin_parts, load_mesh_volume, mesh_edge_defects, voxelize_mesh

__all__ = ["InstanceSpec", "file_names", "import_instance", "instance_frame", "load_object", "mesh_frame", "object_from_mesh", "object_from_volume",
           "landmark_space", "mesh_coordinates", "mesh_instance", "read_instance", "safe_file_name"]


@dataclass(frozen=True)
class InstanceSpec:
    """Where one instance comes from (a project's ``[[instances]]`` entry; paths absolute).

    Attributes
    ----------
    name : str
    landmarks_path : Path or None
        Landmark file (world mm); None when the instance has no landmarks.
    volume_path : Path or None
        Label map file (NIfTI/NRRD/MetaImage/NumPy), or None for a mesh instance.
    label : int or None
        Label picked from the label map (None: all non-zero voxels).
    mesh_path : Path or None
        Closed surface mesh (STL/PLY/OBJ) in world mm.
    mesh_spacing_mm : float or None
        Voxel size (mm) of a mesh's input volume (:func:`read_instance`: what Blender shows and
        measures beside it; None: the study's spacing). Its object frame is its solid's
        (:func:`mesh_frame`) and its object grid the study's spacing.
    landmarks : LandmarkSet or None
        The landmarks as read (world mm of the instance's file), in the study's common
        name order.
    space : {"RAS", "LPS"} or None
        The coordinate convention of the instance's files that state none (a project's
        per-instance ``space``); None: the study's ``[template] space``.
    image_path : Path or None
        The instance's grey-value image (CT) in the same world space as its label map or mesh:
        the build learns the boundary's appearance from it (:mod:`ssm_addon.segmentation`).
    side : str or None
        The side given for the instance (a project's ``side``, e.g. ``"left"``), or None.
    mirror : bool or None
        Whether the instance is a mirror image of the template's side and is imported
        mirrored (:func:`~ssm_addon.instances.volume.mirrored`: the same world points, object
        coordinates of its mirror image); None: not decided yet (the coating stage decides,
        :mod:`ssm_addon.correspondence.sides`), imported as it is.
    """

    name: str
    landmarks_path: Path | None = None
    volume_path: Path | None = None
    label: int | None = None
    mesh_path: Path | None = None
    mesh_spacing_mm: float | None = None
    landmarks: LandmarkSet | None = None
    space: str | None = None
    image_path: Path | None = None
    side: str | None = None
    mirror: bool | None = None

    @property
    def source(self) -> Path:
        """The label map or mesh file."""
        return self.volume_path if self.volume_path is not None else self.mesh_path

    def given_space(self, study_space: str = "auto") -> str | None:
        """The convention given for files that state none: this instance's, else the study's
        (``[template] space``), or None ("auto")."""
        if self.space is not None:
            return self.space
        return None if study_space in (None, "", "auto") else study_space


def landmark_space(spec: InstanceSpec, study_space: str = "auto") -> tuple[str | None, str]:
    """The convention of the instance's landmark file where the file states none (CSV,
    Scalismo JSON): the one given (the instance's or the study's ``space``), else the one its
    mesh file states (landmarks are in the frame of the mesh they were clicked on), else
    None (RAS). Returns it and why."""
    given = spec.given_space(study_space)
    if given is not None:
        return given, "given as space"
    if spec.mesh_path is not None:
        stated = mesh_space(spec.mesh_path)
        if stated is not None:
            return stated, f"its mesh {Path(spec.mesh_path).name} states {stated}"
    return None, "taken as RAS"


def mesh_coordinates(path, given: str | None) -> tuple[str | None, str]:
    """The convention a mesh file is read in, and how it was decided.

    Returns (``"LPS"``, ``"RAS"`` or None for a file taken as RAS with nothing said, the note).
    """
    stated = mesh_space(path)
    if stated is not None:
        return stated, f"{stated}, stated in the file"
    if given is not None:
        return given, f"{given}, none stated (given)"
    return None, "RAS, none stated (taken as RAS; set space = \"LPS\" for a 3D Slicer file without a header)"


def safe_file_name(name: str) -> str:
    """An instance name as a file name: letters and digits of any script and ``._-`` kept
    (Unicode NFC), the rest ``_``.

    Output files of an instance (``coated/<file name>.ply``, ``landmarks/<file name>.fcsv``)
    use this, so a name like ``../../x`` or ``L1/L2`` cannot leave the output folder, and
    names in Cyrillic or Chinese keep their letters (file systems take them).

    >>> safe_file_name("../../escaped"), safe_file_name("L1 (left)"), safe_file_name("позвонок 2")
    ('escaped', 'L1_left', 'позвонок_2')
    """
    cleaned = "".join(c if c.isalnum() or c in "._-" else "_" for c in unicodedata.normalize("NFC", name))
    return "_".join(part for part in cleaned.split("_") if part).strip("._") or "instance"


def file_names(names) -> dict[str, str]:
    """``{instance name: safe file name}``; an error when two names give the same file name."""
    out = {n: safe_file_name(n) for n in names}
    seen: dict[str, str] = {}
    for n, f in out.items():
        key = f.lower()  # case-insensitive file systems
        if key in seen:
            raise InputError(f"instances {seen[key]!r} and {n!r} would write the same files ({f}.*); rename one")
        seen[key] = n
    return out


def instance_frame(volume: Volume, frame_method: str = "auto") -> ObjectFrame:
    """The object frame (paper section 2) of an object as read (world mm).

    The one place a frame is computed: the import below, and a fitting target's start
    pose (:mod:`ssm_addon.fitting.batch`), so a new shape starts in the frame its training had.
    """
    return object_frame(volume, frame_method)


def mesh_frame(vertices_world: np.ndarray, faces: np.ndarray, *, frame_method: str = "moments",
               patient_oriented: bool = False, spacing_mm: float = 1.0, source: str = "",
               cancelled: CancelledFn = None) -> ObjectFrame:
    """The object frame (paper section 2) of a mesh's solid (world mm). With the ``"moments"``
    method (a mesh in arbitrary coordinates, as Scalismo and ShapeWorks write them) and a closed,
    consistently oriented mesh: its exact moments
    (:func:`~ssm_addon.instances.frame.mesh_solid_frame`, the same for the mesh in any pose);
    else (``"patient"``: axes paired with R, A, S of a file that states its convention) from its
    voxelization at ``spacing_mm`` on the world grid. ``frame_method`` as
    :func:`~ssm_addon.instances.frame.object_frame` (``"auto"``: ``"patient"`` where
    ``patient_oriented``). The one place a mesh's frame is computed: the build's import,
    Blender's *Add Mesh Instances* and a fit's target."""
    method = (frame_method or "auto").lower()
    if method == "auto":
        method = "patient" if patient_oriented else "moments"
    # a patient frame keeps the voxelization's (docs/history.md, "The same coatings in any scanner pose")
    if method == "moments" and len(faces) and not any(mesh_edge_defects(faces)):
        with contextlib.suppress(InputError):  # bounds no volume: the voxelization says what is wrong
            return mesh_solid_frame(vertices_world, faces, method)
    vol = voxelize_mesh(vertices_world, faces, spacing_mm, source=source, patient_oriented=patient_oriented,
                        cancelled=cancelled)
    return instance_frame(vol, method)


def object_from_volume(volume: Volume, *, spacing_mm: float, frame_method: str = "auto",
                       frame: ObjectFrame | None = None, progress: ProgressFn = None,
                       cancelled: CancelledFn = None) -> ObjectVolume:
    """Object frame and isotropic resampling of a binary object (paper section 2).

    Parameters
    ----------
    volume : Volume
        The object in its input grid (world mm).
    spacing_mm : float
        Isotropic voxel edge of the result (mm).
    frame_method : {"auto", "patient", "moments"}
    frame : ObjectFrame, optional
        Use this frame instead of computing one.

    Returns
    -------
    ObjectVolume
    """
    check_cancelled(cancelled)
    report(progress, 0.0, "object frame")
    frame = instance_frame(volume, frame_method) if frame is None else frame
    check_cancelled(cancelled)
    return resample(volume, frame, spacing_mm, progress=sub_progress(progress, 0.2, 1.0), cancelled=cancelled)


def load_object(
    path,
    *,
    label: int | None = None,
    spacing_mm: float = 1.0,
    frame_method: str = "auto",
    mesh: bool | None = None,
    mesh_spacing_mm: float | None = None,
    patient_oriented: bool | None = None,
    label_map: LabelMap | None = None,
    progress: ProgressFn = None,
    cancelled: CancelledFn = None,
) -> ObjectVolume:
    """Read a label map (pick ``label``) or a closed mesh, compute its frame and resample.

    Parameters
    ----------
    path : str or Path
        Label map or mesh file.
    label : int, optional
        Label of a label map (None: all non-zero voxels).
    spacing_mm : float
        Isotropic resampling step (mm).
    frame_method : {"auto", "patient", "moments"}
    mesh : bool, optional
        None decides by extension (STL/PLY/OBJ are meshes).
    mesh_spacing_mm : float, optional
        Voxelization step of a mesh (None: ``spacing_mm``).
    patient_oriented : bool, optional
        Overrides the default (True for images, False for meshes), which drives
        ``frame_method="auto"``.
    label_map : LabelMap, optional
        ``path`` already read (several instances share one file).

    Returns
    -------
    ObjectVolume
    """
    report(progress, 0.0, f"reading {Path(path).name}")
    if mesh is None:
        mesh = is_mesh_file(path)
    if mesh:
        stated = mesh_space(path)
        vertices, faces = read_mesh(path)
        oriented = stated is not None if patient_oriented is None else bool(patient_oriented)
        return object_from_mesh(vertices, faces, spacing_mm=spacing_mm, mesh_spacing_mm=mesh_spacing_mm,
                                frame_method=frame_method, source=str(path), patient_oriented=oriented,
                                cancelled=cancelled)
    else:
        vol = select_label(label_map, label) if label_map is not None else load_volume(path, label)
        if patient_oriented is not None:
            vol = replace(vol, patient_oriented=bool(patient_oriented))
    return object_from_volume(vol, spacing_mm=spacing_mm, frame_method=frame_method,
                              progress=sub_progress(progress, 0.4, 1.0), cancelled=cancelled)


def object_from_mesh(vertices_world: np.ndarray, faces: np.ndarray, *, spacing_mm: float,
                     mesh_spacing_mm: float | None = None, frame_method: str = "moments", source: str = "",
                     patient_oriented: bool = False, frame: ObjectFrame | None = None,
                     cancelled: CancelledFn = None) -> ObjectVolume:
    """A closed mesh given as arrays (world mm) as an object of paper section 2.

    The object frame is :func:`mesh_frame`'s (its exact solid moments; a voxelization at
    ``mesh_spacing_mm``, default ``spacing_mm``, where the mesh is not closed) or ``frame``; then the mesh itself, in object mm, is
    voxelized on the object grid at ``spacing_mm`` (voxel centres at multiples of the spacing,
    two background voxels on every side: :func:`~ssm_addon.instances.resampling.resample`'s
    grid). The surface is sampled once, as a label map's is by its resampling, not
    voxelized and then resampled (which moved it by up to half a voxel).
    """
    if frame is None:
        frame = mesh_frame(vertices_world, faces, frame_method=frame_method, patient_oriented=patient_oriented,
                           spacing_mm=mesh_spacing_mm or spacing_mm, source=source, cancelled=cancelled)
    check_cancelled(cancelled)
    vertices_object = frame.to_object(np.asarray(vertices_world, float))
    grid = voxelize_mesh(vertices_object, faces, spacing_mm, source=source, cancelled=cancelled)
    h = float(spacing_mm)
    kept, _added, _opened = keep_thin_parts(grid.mask, (vertices_object - grid.affine[:3, 3]) / h, faces)
    grid = replace(grid, mask=kept)
    tight = bounding_box(grid.mask)
    starts = np.array([max(s.start - 2, 0) for s in tight])
    stops = np.array([min(s.stop + 2, n) for s, n in zip(tight, grid.mask.shape)])
    mask = grid.mask[tuple(slice(a, z) for a, z in zip(starts, stops))]
    return ObjectVolume(mask=np.ascontiguousarray(mask), spacing_mm=h,
                        origin_object=grid.affine[:3, 3] + starts * h, frame=frame, source=source)


def mesh_instance(spec: InstanceSpec, *, spacing_mm: float, frame_method: str = "auto", space: str = "auto",
                  cancelled: CancelledFn = None) -> ObjectVolume:
    """A mesh instance's object (:func:`object_from_mesh`), its file read in RAS world mm
    (:func:`mesh_coordinates`); in a known convention it is patient-oriented."""
    try:
        convention, _note = mesh_coordinates(spec.mesh_path, spec.given_space(space))
        vertices, faces = read_mesh(spec.mesh_path, space=convention)
        return object_from_mesh(vertices, faces, spacing_mm=spacing_mm, mesh_spacing_mm=spec.mesh_spacing_mm,
                                frame_method=frame_method, source=str(spec.mesh_path),
                                patient_oriented=convention is not None, cancelled=cancelled)
    except InputError as err:
        raise InputError(f"instance {spec.name!r}: {err}") from None


def read_instance(spec: InstanceSpec, *, spacing_mm: float, label_map: LabelMap | None = None,
                  space: str = "auto", cancelled: CancelledFn = None) -> Volume:
    """The read step of :func:`import_instance`: the instance's binary object in its input grid.

    A mesh is voxelized at ``spec.mesh_spacing_mm`` (or ``spacing_mm``), in RAS world mm
    (:func:`mesh_coordinates`: the convention its file states, else the instance's or the
    study's ``space``); in a known convention it is patient-oriented (``frame = "auto"``
    pairs its axes with R, A, S, as for an image).
    """
    try:
        if spec.mesh_path is not None:
            convention, _note = mesh_coordinates(spec.mesh_path, spec.given_space(space))
            return load_mesh_volume(spec.mesh_path, spec.mesh_spacing_mm or spacing_mm, space=convention,
                                    patient_oriented=convention is not None, cancelled=cancelled)
        if spec.volume_path is None:
            raise InputError("no source file (volume or mesh)")
        return select_label(label_map, spec.label) if label_map is not None else load_volume(spec.volume_path, spec.label)
    except InputError as err:
        raise InputError(f"instance {spec.name!r}: {err}") from None


def import_instance(spec: InstanceSpec, *, spacing_mm: float, frame_method: str = "auto",
                    label_map: LabelMap | None = None, space: str = "auto", progress: ProgressFn = None,
                    cancelled: CancelledFn = None) -> ObjectVolume:
    """Import one instance of a study: read, object frame, resample (paper section 2).

    A mesh instance is voxelized on its object grid directly (:func:`object_from_mesh`). An
    instance with ``spec.mirror`` is returned mirrored into the template's side
    (:func:`~ssm_addon.instances.volume.mirrored`).

    Raises
    ------
    InputError
        Naming the instance and the file.
    """
    report(progress, 0.0, f"reading {spec.name}")
    if spec.mesh_path is not None:
        ov = mesh_instance(spec, spacing_mm=spacing_mm, frame_method=frame_method, space=space, cancelled=cancelled)
    else:
        vol = read_instance(spec, spacing_mm=spacing_mm, label_map=label_map, space=space, cancelled=cancelled)
        try:
            ov = object_from_volume(vol, spacing_mm=spacing_mm, frame_method=frame_method,
                                    progress=sub_progress(progress, 0.4, 1.0), cancelled=cancelled)
        except InputError as err:
            raise InputError(f"instance {spec.name!r}: {err}") from None
    return mirrored(ov) if spec.mirror else ov
