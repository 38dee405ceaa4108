"""Coating: landmark warp, projection and mass-spring relaxation of the template (paper section 4).

The template (points and triangles in the source instance's object frame, mm) is put
onto every other instance in five steps:

1. a landmark warp, eq. (2), maps the template's landmarks exactly onto the instance's
   (:mod:`ssm_addon.coating.warp`); if inconsistent landmarks make
   it fold the template (det J <= 0), it is smoothed just enough not to
   (:func:`~ssm_addon.coating.warp.fold_free_warp`; the λ used is reported);
2. (not in the paper) a smooth coarse-to-fine surface registration (Gaussian widths
   16, 8, 4, 2 mm) moves the warped mesh onto the surface without folding it
   (:mod:`ssm_addon.coating.registration`); parts of the surface at least a voxel thick
   it leaves more than ``reach_mm`` away (a process longer than the template's) then pull
   their nearest vertices in full (:func:`~ssm_addon.coating.registration.reach_far_parts`);
3. every vertex is projected onto the instance surface by a sub-voxel signed distance
   map (:mod:`ssm_addon.coating.distance_map`, paper 4.2);
4. a mass-spring relaxation, eq. (3), unfolds the mesh while a zero-length spring keeps
   every vertex on the surface (:mod:`ssm_addon.coating.relaxation`); vertices of folded triangles
   lose the surface force (paper) and get a Laplacian force that untangles them, then the
   mesh settles (by the velocity tolerance) on tension springs whose rest lengths are the
   projected mesh's edges, so it keeps the registration's spacing where nothing was
   folded; a last projection puts every vertex back on the surface;
5. (not in the paper) folds that are left are removed locally: umbrella smoothing of
   the folded triangles' neighbourhood + reprojection, until none is left
   (:func:`~ssm_addon.coating.relaxation.untangle`).

A triangle is folded when its normal is more than 90° from the surface normal at its
centroid (paper 4.2), both the raw gradient's and the distance field's smoothed at 3 mm
(:func:`~ssm_addon.coating.relaxation.folded_triangles`): with the raw gradient alone the
template's triangles that span a thin process (centroid inside, near the medial surface)
count as folded even on the template's own instance, with the smoothed one alone those on
the walls of a narrow notch.

Without landmarks the start is the template's similarity pose on the instance, carried by a
smooth displacement with pulls along the surface too
(:func:`~ssm_addon.correspondence.frames.coat_from_template_pose`), in place of step 1.

Steps 2, 5 and the fold handling exist because the paper's scheme alone left folds on
real vertebrae, and the object-frame start because extremal-point landmarks can mis-map
whole parts of a template; the measurements are in ``docs/history.md``.

Frames and units
----------------
All coordinates are mm in an *object* frame (:class:`~ssm_addon.instances.volume.ObjectFrame`):
the template and its landmarks in the source instance's frame, the target's volume,
landmarks and the coated points in the target's frame. Because both frames are the
paper's normalised object frames, the identity is already a rough alignment (this is
what :mod:`ssm_addon.correspondence.proposal` relies on).

The *surface* of an instance is the 0.5 iso-surface of its binary
:class:`~ssm_addon.instances.volume.ObjectVolume` mask, i.e. its marching-cubes surface; fit
figures are exact point-to-triangle distances to that surface.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from enum import StrEnum

import numpy as np

from ..base.compute import executor_or_local, inner_threads, inside_blender_program, run_one_thread
from ..base.errors import Cancelled, InputError, check_cancelled
from ..base.params import CoatingParams
from ..base.progress import CancelledFn, ProgressFn, report, sub_progress
from ..coating.distance_map import DistanceMap
from ..coating.registration import reach_far_parts, register_to_surface
from ..coating.relaxation import folded_triangles, relax, untangle
from ..coating.warp import fold_free_warp, landmark_warp
from ..instances.volume import ObjectVolume
from ..meshutil import Mesh, MeshLocation, edge_lengths, locate_on_mesh, mesh_area
from ..meshutil import edges as mesh_edges

__all__ = [
    "CoatingCancelled",
    "CoatingStart",
    "CoatingParams",
    "CoatingResult",
    "FitFigures",
    "coat",
    "coat_all",
    "coat_from_start",
    "template_mesh",
]


class CoatingStart(StrEnum):
    """How a coating began (paper 4); the value is the text reports, files and panels show.

    >>> CoatingStart("model fit") is CoatingStart.MODEL_FIT, f"{CoatingStart.OBJECT_FRAMES}"
    (True, 'object frames')
    """

    #: the landmark warp (eq. 2) with the instance's own landmarks
    LANDMARK_WARP = "landmark warp"
    #: a model's shape fitted to the instance's surface, relaxed onto it (the bootstrap of
    #: paper 7)
    MODEL_FIT = "model fit"
    #: the template put into the instance's object frame (paper 2), without landmarks
    OBJECT_FRAMES = "object frames"


@dataclass(frozen=True)
class FitFigures:
    """How well a coated mesh fits its instance (all distances in mm, exact to the MC surface)."""

    mean_distance_mm: float
    max_distance_mm: float
    folded_before: int
    folded_after: int
    iterations: int
    landmark_residuals_mm: tuple = ()
    time_s: float = 0.0
    spacing_mm: float = 1.0
    converged: bool = True
    warp_regularization: float = 0.0
    untangle_rounds: int = 0
    start: CoatingStart = CoatingStart.LANDMARK_WARP
    landmark_names: tuple = ()  # of landmark_residuals_mm, where known

    def __post_init__(self):
        object.__setattr__(self, "start", CoatingStart(self.start))

    @property
    def max_landmark_residual_mm(self) -> float:
        return max(self.landmark_residuals_mm, default=0.0)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["start"] = str(self.start)
        d["landmark_residuals_mm"] = [float(x) for x in self.landmark_residuals_mm]
        d["landmark_names"] = [str(x) for x in self.landmark_names]
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    @classmethod
    def from_json(cls, text: str) -> FitFigures:
        d = json.loads(text)
        d["landmark_residuals_mm"] = tuple(d.get("landmark_residuals_mm", ()))
        d["landmark_names"] = tuple(d.get("landmark_names", ()))
        return cls(**d)


@dataclass(frozen=True)
class CoatingResult:
    """A template coated onto one instance.

    Attributes
    ----------
    points_object : (N, 3) mm, coated vertices in the target's object frame.
    warped_points_object : (N, 3) mm, the landmark-warped template (before projection).
    fit : FitFigures.
    name : the instance's name (for reports).
    """

    points_object: np.ndarray
    warped_points_object: np.ndarray
    fit: FitFigures
    name: str = ""


class CoatingCancelled(Cancelled):
    """Batch coating cancelled; ``results`` holds the finished instances (None where not done)."""

    def __init__(self, message: str, results: list):
        super().__init__(message)
        self.results = results


def template_mesh(template) -> Mesh:
    """The template's triangles as a :class:`~ssm_addon.meshutil.Mesh` (source object frame, mm).

    ``template`` is a :class:`~ssm_addon.template.template.Template` (``points_object``, ``faces``)
    or a :class:`~ssm_addon.meshutil.Mesh`.
    """
    if isinstance(template, Mesh):
        mesh = template
    else:
        pts = getattr(template, "points_object", None)
        faces = getattr(template, "faces", None)
        if pts is None or faces is None:
            raise InputError("coating: the template needs points_object (N, 3) and faces (F, 3)")
        try:
            mesh = Mesh(pts, faces)
        except InputError as err:
            raise InputError(f"coating: template: {err}") from None
    if not len(mesh.faces):
        raise InputError("coating: the template has no triangles")
    return mesh


def _template_arrays(template):
    mesh = template_mesh(template)
    return mesh.vertices, mesh.faces


def coat_from_start(
    template,
    target: ObjectVolume,
    *,
    start: np.ndarray | None = None,
    params: CoatingParams | None = None,
    template_location: MeshLocation | None = None,
    target_landmarks_object: np.ndarray | None = None,
    distance_map: DistanceMap | None = None,
    start_label: CoatingStart | None = None,
    progress: ProgressFn = None,
    cancelled: CancelledFn = None,
    name: str = "",
) -> CoatingResult:
    """Coat the template onto an instance from a given start: registration, projection, relaxation.

    What follows the landmark warp in :func:`coat` (paper 4.2 and the registration).

    Parameters
    ----------
    template : Template or Mesh
        The template (source object frame, mm).
    target : ObjectVolume
        The instance to coat.
    start : (N, 3) mm, optional
        Where the template's points start in the target's object frame (e.g. warped by
        landmarks, or a model fit); None: the template's points unmoved (the object
        frames alone align the two, paper fig. 8 left).
    template_location, target_landmarks_object : optional
        The landmarks as points on the template (barycentric) and on the target (object
        mm), for the landmark residuals of the fit figures.
    distance_map : DistanceMap, optional
        The target's, if already built.
    start_label : CoatingStart, optional
        How the start was made, for ``FitFigures.start`` (default ``LANDMARK_WARP`` when
        ``start`` is given, else ``OBJECT_FRAMES``).

    Returns
    -------
    CoatingResult
    """
    params = CoatingParams() if params is None else params
    points, faces = _template_arrays(template)
    warped = points.copy() if start is None else np.asarray(start, dtype=float)
    if warped.shape != points.shape:
        raise InputError(f"coating {name or target.source}: start has shape {warped.shape}, template {points.shape}")
    target_landmarks = target_landmarks_object
    label = start_label or (CoatingStart.OBJECT_FRAMES if start is None else CoatingStart.LANDMARK_WARP)
    t0 = time.perf_counter()
    report(progress, 0.0, "distance map")
    dm = distance_map if distance_map is not None else DistanceMap.from_object_volume(target)
    check_cancelled(cancelled)
    sigmas = tuple(params.registration_sigmas_mm) if params.registration_iterations > 0 else ()
    # the start (landmark warp or object frames) is chosen after the coarse half of the
    # widths (16, 8 mm of 16..2): on VerSe this picks the same start as after all of
    # them (L5, T12: 261 / 127 folded from the warp vs 23 / 20 from the frames; L2..L4
    # <= 28 of 1,262), and the losing start does not run the fine widths
    n_coarse = (len(sigmas) + 1) // 2

    def registered(initial, widths):
        if widths:
            return register_to_surface(initial, faces, dm, sigmas_mm=widths, iterations=params.registration_iterations,
                                       cancelled=cancelled)
        return initial

    # the smoothed field of the fold test (a Gaussian filter of the whole grid; scipy
    # releases the GIL) and the fit figures' triangle search tree are built on a
    # second thread while the registration runs (in the main process; a worker process
    # builds them when first needed, :func:`~ssm_addon.base.compute.inner_threads`)
    side = []
    if inner_threads(2) > 1:
        pool = ThreadPoolExecutor(max_workers=1)
        side = [pool.submit(dm.smooth_normals, np.zeros((1, 3)), params.fold_normal_sigma_mm),
                pool.submit(lambda: dm.locator)]
        pool.shutdown(wait=False)

    def folds(p):
        for built in side[:1]:
            built.result()
        return int(folded_triangles(p, faces, dm, params.fold_angle_deg, params.fold_normal_sigma_mm).sum())

    report(progress, 0.1, "surface registration")
    moved = registered(warped, sigmas[:n_coarse])
    start_from = label
    if not np.array_equal(warped, points):
        coarse_folds = folds(dm.project(moved, params.projection_iterations))
        if coarse_folds > params.frame_start_fold_fraction * len(faces):
            # inconsistent landmarks can mis-map whole parts (VerSe L1 -> L5): try the
            # object-frame alignment alone and keep whichever start folds less
            report(progress, 0.15, "surface registration from the object frames")
            alt = registered(points, sigmas[:n_coarse])
            if folds(dm.project(alt, params.projection_iterations)) < coarse_folds:
                moved, start_from = alt, CoatingStart.OBJECT_FRAMES
    moved = registered(moved, sigmas[n_coarse:])
    if sigmas and params.reach_mm > 0:
        report(progress, 0.18, "reaching far parts")
        moved = reach_far_parts(moved, faces, dm, far_mm=params.reach_mm, sigma_mm=sigmas[-1],
                                iterations=params.registration_iterations, cancelled=cancelled)
    report(progress, 0.2, "projection")
    projected = dm.project(moved, params.projection_iterations)
    folded_before = folds(projected)
    e = mesh_edges(faces)
    if params.rest_lengths == "projected":
        d0 = edge_lengths(projected, e)
    elif params.rest_lengths == "warped":
        # the warp lands near, not on, the surface: scale to the projected mesh's size
        d0 = edge_lengths(moved, e) * math.sqrt(mesh_area(projected, faces) / max(mesh_area(moved, faces), 1e-12))
    else:
        scale = math.sqrt(mesh_area(projected, faces) / max(mesh_area(points, faces), 1e-12))
        d0 = edge_lengths(points, e) * scale
    check_cancelled(cancelled)
    coated, iterations, converged, rounds = settle_on_surface(
        projected, faces, d0, dm, params=params, edges=e, cancelled=cancelled,
        progress=sub_progress(progress, 0.25, 0.95, "coating: "))
    folded_after = folds(coated)
    for built in side:
        built.result()
    dist = dm.surface_distance(coated)
    residuals = ()
    if template_location is not None and target_landmarks is not None:
        lm = template_location.evaluate(coated, faces)
        residuals = tuple(float(x) for x in np.linalg.norm(lm - target_landmarks, axis=1))
    fit = FitFigures(
        mean_distance_mm=float(dist.mean()),
        max_distance_mm=float(dist.max()),
        folded_before=folded_before,
        folded_after=folded_after,
        iterations=int(iterations),
        landmark_residuals_mm=residuals,
        time_s=time.perf_counter() - t0,
        spacing_mm=float(target.spacing_mm),
        converged=bool(converged),
        untangle_rounds=int(rounds),
        start=start_from,
    )
    report(progress, 1.0, "coated")
    return CoatingResult(coated, warped, fit, name)


def settle_on_surface(points: np.ndarray, faces: np.ndarray, rest_lengths: np.ndarray, dm: DistanceMap, *,
                      params: CoatingParams, edges: np.ndarray | None = None, cancelled: CancelledFn = None,
                      progress: ProgressFn = None):
    """The coating's last steps on a mesh already near the surface (object frame, mm):
    the relaxation, eq. (3), with ``rest_lengths`` (mm, per edge of ``edges``), the final
    projection and the local untangling.

    Returns
    -------
    points : (N, 3) mm; relaxation steps : int; converged : bool; untangling rounds : int
    """
    e = mesh_edges(faces) if edges is None else edges
    p, iterations, converged = relax(points, faces, rest_lengths, dm, params=params, edges=e, cancelled=cancelled,
                                     progress=progress)
    if params.final_projection:
        p = dm.project(p, params.projection_iterations)
    rounds = 0
    if params.untangle_iterations > 0:
        p, rounds = untangle(p, faces, dm, params=params, edges=e, cancelled=cancelled)
    return p, int(iterations), bool(converged), int(rounds)


def _check_landmarks(lm, name):
    a = np.asarray(lm, dtype=float)
    if a.ndim != 2 or a.shape[1:] != (3,):
        raise InputError(f"coating: {name} must be an (L, 3) array in mm, got shape {a.shape}")
    return a


def coat(
    template,
    template_landmarks_object: np.ndarray,
    target: ObjectVolume,
    target_landmarks_object: np.ndarray,
    *,
    params: CoatingParams | None = None,
    distance_map: DistanceMap | None = None,
    progress: ProgressFn = None,
    cancelled: CancelledFn = None,
    name: str = "",
) -> CoatingResult:
    """Coat the template onto one instance: warp (eq. 2), project, relax (eq. 3).

    Parameters
    ----------
    template : Template
        ``points_object`` (N, 3) mm in the source instance's object frame and ``faces``.
    template_landmarks_object : (L, 3) mm
        The source instance's landmarks in its object frame.
    target : ObjectVolume
        The instance to coat.
    target_landmarks_object : (L, 3) mm
        The same landmarks on the target, in the target's object frame.
    distance_map : DistanceMap, optional
        The target's, if already built.

    Returns
    -------
    CoatingResult with ``points_object`` in the target's object frame.
    """
    params = CoatingParams() if params is None else params
    pts_mesh = template_mesh(template)
    pts, faces = pts_mesh.vertices, pts_mesh.faces
    src = _check_landmarks(template_landmarks_object, "template landmarks")
    dst = _check_landmarks(target_landmarks_object, f"landmarks of {name or target.source or 'the target'}")
    if len(src) != len(dst):
        raise InputError(
            f"coating: {len(src)} template landmarks but {len(dst)} landmarks on {name or target.source or 'the target'}"
        )
    t0 = time.perf_counter()
    report(progress, 0.0, "landmark warp")
    try:
        if params.fold_free_warp:
            tps, lam = fold_free_warp(src, dst, pts, kernel=params.kernel, hardy_a=params.hardy_a,
                                      hardy_s_mm=params.hardy_s_mm, regularization=params.regularization)
        else:
            tps = landmark_warp(src, dst, kernel=params.kernel, hardy_a=params.hardy_a, hardy_s_mm=params.hardy_s_mm,
                                regularization=params.regularization)
            lam = params.regularization
    except InputError as err:
        raise InputError(f"{name or target.source or 'target'}: {err}") from None
    warped = tps(pts)
    location = locate_on_mesh(pts, faces, src)
    result = coat_from_start(pts_mesh, target, start=warped, params=params, template_location=location,
                             target_landmarks_object=dst, distance_map=distance_map,
                             progress=sub_progress(progress, 0.05, 1.0),
                             cancelled=cancelled, name=name)
    fit = FitFigures(**{**asdict(result.fit), "time_s": time.perf_counter() - t0, "warp_regularization": float(lam)})
    return CoatingResult(result.points_object, warped, fit, name)


def _coat_job(args):
    template, src, target, dst, params, name = args
    return coat(template, src, target, dst, params=params, name=name)  # the executor limits the BLAS threads


def coat_all(
    template,
    template_landmarks_object: np.ndarray,
    targets: list[ObjectVolume],
    target_landmarks_object_list: list[np.ndarray],
    *,
    params: CoatingParams | None = None,
    jobs: int = 1,
    progress: ProgressFn = None,
    cancelled: CancelledFn = None,
    names: list[str] | None = None,
    start_method: str = "spawn",
    on_coated: Callable[[str], None] | None = None,
    executor=None,
) -> list[CoatingResult]:
    """Coat the template onto every target (paper 4), serially or across processes.

    Results are identical serial vs parallel (no random state; each instance is
    computed by the same code). Processes (``jobs`` > 1, ``start_method`` "spawn" or
    "forkserver"; fork is avoided because the caller may hold threads) are used
    only outside the Blender program (:func:`~ssm_addon.base.compute.inside_blender_program`), and
    only when there are at least two targets.

    Progress is reported per finished instance. Cancellation is checked between
    instances (and inside an instance when serial): :class:`CoatingCancelled` is
    raised with ``.results``, a list with the finished :class:`CoatingResult` and
    None for the instances not coated. ``on_coated(name)`` is called (in this process) as
    each instance's coating arrives. ``executor`` (:class:`~ssm_addon.base.compute.Executor`):
    where the coatings run, the caller's; default ``jobs`` local processes of its own.
    """
    params = CoatingParams() if params is None else params
    pts, faces = _template_arrays(template)
    if len(targets) != len(target_landmarks_object_list):
        raise InputError(f"coating: {len(targets)} targets but {len(target_landmarks_object_list)} landmark sets")
    names = list(names) if names is not None else [t.source or f"instance {i}" for i, t in enumerate(targets)]
    n = len(targets)
    results: list[CoatingResult | None] = [None] * n
    jobs = max(1, min(int(jobs or 1), n, os.cpu_count() or 1))
    if executor is None and (jobs == 1 or inside_blender_program()):
        for i, (tgt, lm) in enumerate(zip(targets, target_landmarks_object_list)):
            if cancelled is not None and cancelled():
                raise CoatingCancelled(f"coating cancelled after {i} of {n} instances", results)
            sub = sub_progress(progress, i / n, (i + 1) / n, f"{names[i]}: ")
            try:
                results[i] = run_one_thread(
                    lambda _, tgt=tgt, lm=lm, sub=sub, i=i: coat(template, template_landmarks_object, tgt, lm,
                                                                 params=params, progress=sub, cancelled=cancelled,
                                                                 name=names[i]), None)
            except Cancelled:
                raise CoatingCancelled(f"coating cancelled after {i} of {n} instances", results) from None
            report(progress, (i + 1) / n, f"coated {names[i]} ({i + 1}/{n})")
            if on_coated is not None:
                on_coated(names[i])
        return results
    arrays = Mesh(pts, faces)
    args = [(arrays, template_landmarks_object, targets[i], target_landmarks_object_list[i], params, names[i])
            for i in range(n)]

    def keep(i, result):
        results[i] = result
        if on_coated is not None:
            on_coated(names[i])

    try:
        with executor_or_local(executor, jobs, start_method=start_method) as pool:
            pool.map(_coat_job, args, on_result=keep, labels=names, verb="coated", progress=progress,
                     cancelled=cancelled)
    except Cancelled:
        raise CoatingCancelled(f"coating cancelled after {sum(r is not None for r in results)} of {n} instances",
                               results) from None
    return results
