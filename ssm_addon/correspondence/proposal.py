"""Landmark proposal: landmarks for a new instance from a landmarked one (paper 4.1, 7).

Both instances are expressed in their own object frames (paper section 2), which
aligns them roughly (paper fig. 8, left). ``"frame"`` maps each landmark to the nearest
surface point of the target; ``"coating"`` coats a triangulated surface of the source
onto the target from that alignment alone (no landmarks) and reads each landmark off
the coated mesh at its barycentric place. Coordinates: landmarks in world mm in and out,
object mm inside.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..base.errors import InputError, check_cancelled
from ..base.params import CoatingParams, TemplateParams
from ..base.progress import CancelledFn, ProgressFn
from ..coating.coating import coat_from_start, template_mesh
from ..fitting.fit import Pose, Target, fit_any_pose
from ..formats.landmarks import LandmarkSet
from ..instances.resampling import resample
from ..instances.volume import ObjectVolume
from ..instances.voxelize import voxelize_mesh
from ..meshutil import locate_on_mesh, marching_cubes
from ..template.template import build_template

__all__ = [
    "PROPOSAL_METHODS",
    "propose_by_model",
    "propose_from_meshes",
    "propose_landmarks",
    "propose_landmarks_by_coating",
    "surface_points_object",
    "transfer_landmarks",
]


def surface_points_object(object_volume) -> np.ndarray:
    """(M, 3) points on the 0.5 iso-surface of an ObjectVolume's mask, object mm.

    Marching cubes (scikit-image) on the padded mask; the vertices lie on voxel edges
    where the linearly interpolated mask is 0.5, i.e. on the object's surface.
    """
    if not np.any(object_volume.mask):
        raise InputError(f"{object_volume.source or 'object volume'}: empty mask, no surface to propose onto")
    verts, _ = marching_cubes(object_volume.mask)
    return object_volume.voxel_to_object(verts)


def _propose_by_frame(source_points_object, target_points_object):

    _, idx = cKDTree(target_points_object).query(source_points_object)
    return target_points_object[idx]


PROPOSAL_METHODS = {"frame": "nearest target surface point after object-frame alignment",
                    "coating": "coating of a landmarked surface by the object frames (propose_landmarks_by_coating)"}
"""Proposal methods of :func:`propose_landmarks` (the ``method`` hook)."""


def propose_landmarks(source_points_object, target, method: str = "frame", **options) -> np.ndarray:
    """Propose landmarks on a target instance from a landmarked source instance.

    Both instances are expressed in their own object frames (paper section 2: centre
    of mass, second-moment axes), which aligns them as in the paper's fig. 8 (left);
    each source landmark is then mapped to the nearest surface point of the target, so
    the user only corrects the proposal.

    Parameters
    ----------
    source_points_object : (L, 3) array
        Source landmarks in the source's object frame, mm.
    target : (M, 3) array or ObjectVolume
        Target surface points in the target's object frame (mm), e.g. the target mesh's
        vertices, or the target's ObjectVolume (its 0.5 iso-surface is used).
    method : str
        ``"frame"`` (this function: nearest surface point after frame alignment) or
        ``"coating"``: a better proposal by coating (paper section 4): a triangulated
        surface of the source, ``source_template`` (anything with ``points_object``
        (N, 3) and ``faces`` (F, 3) in the source's object frame, e.g. a Template or the
        source's mesh), is projected onto the target and relaxed, and each landmark is
        read off the coated mesh at its barycentric place
        (``ssm_addon.coating.coating.propose_landmarks_by_coating``); ``target`` must then be
        the target's ObjectVolume.
    **options
        Passed on to the chosen method (``"coating"``: ``source_template`` (required),
        ``params``, ``progress``, ``cancelled``).

    Returns
    -------
    (L, 3) float ndarray
        Proposed landmarks on the target's surface, target object frame, mm (row i is
        the proposal for source landmark i).
    """
    src = np.asarray(source_points_object, dtype=float).reshape(-1, 3)
    if len(src) == 0:
        raise InputError("landmark proposal: the source instance has no landmarks")
    if method == "coating":
        func = propose_landmarks_by_coating
        template = options.pop("source_template", None)
        if template is None:
            raise InputError("landmark proposal: method 'coating' needs source_template (the source's surface: points_object, faces)")
        if not (hasattr(target, "mask") and hasattr(target, "voxel_to_object")):
            raise InputError("landmark proposal: method 'coating' needs the target's ObjectVolume")
        return np.asarray(func(template, src, target, **options), dtype=float).reshape(-1, 3)
    if method != "frame":
        raise InputError(f"landmark proposal: unknown method {method!r} (choose from {', '.join(PROPOSAL_METHODS)})")
    if options:
        raise InputError(f"landmark proposal: method 'frame' takes no options, got {', '.join(options)}")
    if hasattr(target, "mask") and hasattr(target, "voxel_to_object"):
        target_points = surface_points_object(target)
    else:
        target_points = np.asarray(target, dtype=float).reshape(-1, 3)
    if len(target_points) == 0:
        raise InputError("landmark proposal: the target has no surface points")
    return _propose_by_frame(src, target_points)


def transfer_landmarks(
    landmarks: LandmarkSet,
    source_frame,
    target_frame,
    target_surface_world,
    method: str = "frame",
    source: str = "",
    **options,
) -> LandmarkSet:
    """Propose a landmark set for a target instance in world mm (see :func:`propose_landmarks`).

    Parameters
    ----------
    landmarks : LandmarkSet
        The source instance's landmarks, world mm.
    source_frame, target_frame : ObjectFrame
        Object frames (paper section 2) of the source and target instances.
    target_surface_world : (M, 3) array or ObjectVolume
        Target surface points in world mm (e.g. mesh vertices), or its ObjectVolume.
    method : str
        Proposal method (``"frame"`` or ``"coating"``).
    source : str
        ``source`` of the returned set (for messages).

    Returns
    -------
    LandmarkSet
        Same names, proposed positions in the target's world mm.
    """
    src_obj = source_frame.to_object(landmarks.points_world)
    if hasattr(target_surface_world, "mask"):
        target = target_surface_world
    else:
        target = target_frame.to_object(np.asarray(target_surface_world, float).reshape(-1, 3))
    proposed = propose_landmarks(src_obj, target, method=method, **options)
    return LandmarkSet(landmarks.names, target_frame.to_world(proposed), source)


def propose_from_meshes(
    landmarks: LandmarkSet,
    source_frame,
    source_mesh_world,
    target_frame,
    target_mesh_world,
    *,
    method: str = "frame",
    spacing_mm: float = 1.0,
    source: str = "",
    progress=None,
    cancelled=None,
    source_volume=None,
    target_volume=None,
    template=None,
) -> LandmarkSet:
    """Propose landmarks for a target instance given both instances' surface meshes.

    What the Blender proposal runs (off the UI thread): ``"frame"`` maps each landmark
    to the nearest target mesh vertex after object-frame alignment; ``"coating"`` coats
    a template of the source onto the target (paper 4) using only the object frames and
    reads the landmarks off the coated mesh. The target's volume is ``target_volume`` or
    its mesh voxelized at ``spacing_mm`` and resampled along its frame (paper 2); the
    template is ``template`` or one built (paper 3, default parameters) from
    ``source_volume`` or the voxelized source mesh.

    Parameters
    ----------
    landmarks : LandmarkSet
        Source landmarks, world mm.
    source_frame, target_frame : ObjectFrame
        The instances' object frames.
    source_mesh_world, target_mesh_world : tuple of ((V, 3) world mm vertices, (F, 3) faces)
        Closed surface meshes of the instances.
    method : {"frame", "coating"}
    spacing_mm : float
        Voxel size (mm) for voxelizing a mesh where no volume is given.
    source_volume, target_volume : ObjectVolume, optional
        The instances' resampled masks (e.g. the Blender instance cache).
    template : Template-like, optional
        ``points_object`` (source object frame, mm) and ``faces``.
    source : str
        ``source`` of the result.
    progress, cancelled : callables, optional

    Returns
    -------
    LandmarkSet
        Same names, on the target's surface, world mm.
    """
    tv, tf = (np.asarray(a) for a in target_mesh_world)
    if method != "coating":
        return transfer_landmarks(landmarks, source_frame, target_frame, tv, method=method, source=source)
    report = progress or (lambda f, m: None)
    sv, sf = (np.asarray(a) for a in source_mesh_world)
    if target_volume is None:
        report(0.0, "voxelizing the target")
        target_volume = resample(
            voxelize_mesh(tv, tf, spacing_mm, source=source, cancelled=cancelled), target_frame, spacing_mm,
            cancelled=cancelled,
        )
    check_cancelled(cancelled)
    if template is None:
        if source_volume is None:
            report(0.05, "voxelizing the source")
            source_volume = resample(
                voxelize_mesh(sv, sf, spacing_mm, cancelled=cancelled), source_frame, spacing_mm, cancelled=cancelled
            )
        report(0.1, "template of the source")
        template = build_template(source_volume, TemplateParams(spacing_mm=source_volume.spacing_mm), cancelled=cancelled)
    target_ov, surface = target_volume, template
    check_cancelled(cancelled)

    def sub(fraction, message):
        report(0.2 + 0.8 * fraction, message)

    proposed = propose_landmarks(
        source_frame.to_object(landmarks.points_world), target_ov, method="coating", source_template=surface, progress=sub, cancelled=cancelled
    )
    report(1.0, "done")
    return LandmarkSet(landmarks.names, target_frame.to_world(proposed), source)


def propose_landmarks_by_coating(
    source_template,
    source_landmarks_object: np.ndarray,
    target: ObjectVolume,
    *,
    params: CoatingParams | None = None,
    progress: ProgressFn = None,
    cancelled: CancelledFn = None,
) -> np.ndarray:
    """Propose a new instance's landmarks by coating a landmarked template onto it.

    Only the object frames align the two (identity warp, no landmarks): the template is
    projected onto the target, relaxed, and each source landmark, expressed as a
    barycentric point of its nearest template triangle, is read off the coated mesh.

    Returns
    -------
    (L, 3) mm landmark positions in the target's object frame.
    """
    params = CoatingParams() if params is None else params
    mesh = template_mesh(source_template)
    src = np.asarray(source_landmarks_object, dtype=float).reshape(-1, 3)
    location = locate_on_mesh(mesh.vertices, mesh.faces, src)
    coated = coat_from_start(mesh, target, params=params, progress=progress, cancelled=cancelled).points_object
    return location.evaluate(coated, mesh.faces)


def propose_by_model(model, target_frame, target_mesh_world, *, known: LandmarkSet | None = None,
                     names=None, params=None, source: str = "", progress=None, cancelled=None) -> LandmarkSet:
    """Landmarks for a target from a built model (paper 7's bootstrap): fit, then read them off.

    The model (pose and mode weights under its Gaussian prior,
    :func:`ssm_addon.fitting.fit.fit_any_pose`) is fitted to the target's surface by the pose
    search of ``ssm fit``, the target's object frame (the frame the model's instances were
    built in, paper 2) and its ``known`` landmarks' pose preferred, the known landmarks as
    soft constraints; the model's landmarks (the template instance's, as points of the mean
    mesh) are read off the fitted shape.

    Parameters
    ----------
    model : ShapeModel
        With landmarks (:attr:`~ssm_addon.model.pca.ShapeModel.landmark_locations`).
    target_frame : ObjectFrame
    target_mesh_world : ((V, 3) world mm, (F, 3))
        The target's closed surface.
    known : LandmarkSet, optional
        The target's landmarks already placed (world mm).
    names : sequence of str, optional
        Landmarks wanted (default: every landmark of the model).
    params : FitParams, optional

    Returns
    -------
    LandmarkSet
        World mm, on the fitted shape (within the fit's surface distance of the target).

    Raises
    ------
    InputError
        The model carries no landmarks, or none of ``names``.
    """
    located = model.landmark_locations
    model_names = located.names
    if not model_names:
        raise InputError("propose landmarks: the model carries no landmarks (build it from a landmarked template)")
    wanted = [n for n in (model_names if names is None else names) if n in model_names]
    if not wanted:
        raise InputError(f"propose landmarks: the model has none of {', '.join(names)} "
                         f"(it has {', '.join(model_names)})")
    verts, faces = (np.asarray(a) for a in target_mesh_world)
    target = Target.from_mesh(target_frame.to_object(verts), faces, source=source,
                              landmarks=None if known is None or not len(known) else
                              LandmarkSet(known.names, target_frame.to_object(known.points_world), source))
    # the pose search of ``ssm fit``, the target's object frame preferred: a near-symmetric shape
    # whose frame's axes were resolved end for end is still found
    result, _search = fit_any_pose(model, target, params=params, frame_pose=Pose(), progress=progress,
                                   cancelled=cancelled)
    pts = located.subset(wanted).evaluate(result.points, model.faces)
    return LandmarkSet(tuple(wanted), target_frame.to_world(pts), source)
