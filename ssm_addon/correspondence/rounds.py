"""Model-guided correspondence: the mean shape as template, coating driven by the model.

The paper's single pass coats one instance's template onto every other by landmarks
(paper 4). Its section 3.3 proposes a second pass with the mean shape as template, and
section 7 a bootstrap in which a preliminary model replaces the landmarks. This module
does both (``[correspondence] method = "model"``):

1. **Start**: instances with landmarks are coated by them (paper 4); instances without
   start from the model of the landmarked ones fitted to their surface, relaxed onto it
   (:func:`start_from_model`, paper 7), or from the object frames alone when only the
   template instance has landmarks (paper 2 aligns them roughly).
2. **Rounds**, each: every instance is **fitted by the model built without it**
   (leave-one-out, so an instance never fits itself) — pose and coefficients under the
   model's prior, against its surface (:func:`round_landmarks`). The fit read off at the
   template's landmark points supplies the landmarks an instance lacks (its posterior,
   the given ones as soft constraints of weight ``landmark_weight``). The given ones are
   moved towards the fit's prediction by the share their **click error** calls for
   (:func:`landmark_noise`): the template instance's transfer error is the model's error
   alone (its landmarks define the correspondence), the other instances' hold the click
   error too; each given landmark moves α = σ_c² / (σ_c² + σ_m²) of the way
   (``[correspondence] landmark_noise_mm``: estimated by default, 0 for exact landmarks,
   which stay where given). The template is then coated onto the instance with them by
   the paper's pipeline (:func:`coat_mean_shape`: landmark warp eq. 2, registration,
   projection, relaxation eq. 3): with ``round_template = "instance"`` (the default) the
   template itself, and instances whose every landmark is given and stays keep their
   coating; with ``"mean"`` the **mean shape** (paper 3.3), re-sampled at the template's
   points.
   A round is **kept only when it helps**, judged without truth by the landmark transfer
   error (:class:`CorrespondenceCheck`): each instance's given landmarks predicted by the
   model of the *other* instances fitted to its surface alone; the next round's fits
   measure it. A round that does not lower it by ``KEEP_MARGIN``, and by more than chance
   (:func:`round_helps`: a paired test of the instances' own figures), is dropped, the rounds
   stop and the coatings before it are kept (when that is the start, the model method's
   result is the single pass). Otherwise the rounds stop when the mean shape moves less
   than ``tolerance_mm`` (RMS) or after ``iterations`` (a finding: they did not settle).
3. **Re-sampling** (:func:`resample_instance`), every ``"mean"`` round: the mean shape's points are
   not the template's; each round's coatings are read off at the template's points
   (located on the template instance's coating of that round), so the template's
   curvature-guided sampling and point numbering stay, and every round is judged at the
   sampling of the start.

The fit supplies the landmarks of the warp, not the start of the coating. The figures
behind these choices are in ``docs/history.md``.

The per-instance steps are pure functions of arrays, so rounds run in processes.
Frames: each instance's object frame (paper 2, mm). Object frames can disagree by a turn
of the principal axes (a near-symmetric bone's moments frame), so coatings are put onto
one another by their correspondence before a model is built of them
(:func:`aligned_to`), and a surface without a coating is fitted from the rotations of the
axes (``AXIS_ROTATIONS``), the pose of the input coordinates preferred.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields, replace

import numpy as np
from scipy.special import stdtrit

from ..base.compute import executor_or_local
from ..base.errors import InputError, check_cancelled
from ..base.params import CoatingParams, CorrespondenceParams, FitParams
from ..base.progress import CancelledFn, ProgressFn, sub_progress
from ..coating.coating import CoatingResult, CoatingStart, coat, coat_from_start, settle_on_surface
from ..coating.distance_map import DistanceMap
from ..coating.relaxation import folded_triangles
from ..fitting.fit import AXIS_ROTATIONS, Pose, Target, coarse_ranked, fit_model, rigid_screen
from ..formats.landmarks import LandmarkSet
from ..instances.volume import ObjectVolume
from ..meshutil import LandmarkLocations, Mesh, MeshLocation, MeshLocator, edge_lengths, vertex_normals
from ..meshutil import edges as mesh_edges
from ..model.pca import build_model, procrustes_fit
from ..template.template import Template

# the fit only supplies the landmarks' posterior places and the coating does the rest:
# a coarser surface sample and a looser stop than ``ssm fit`` (20,000 samples, 0.001 mm)
REFINE_FIT_SAMPLES = 2000
REFINE_FIT_TOLERANCE_MM = 0.01
# points of the shape and of the surface the start poses are screened with (rigid ICP, for ranking
# the turns of the axes; the fit that follows uses REFINE_FIT_SAMPLES)
SCREEN_SAMPLES = 500

__all__ = ["AXIS_TURNS", "Population", "WORLD_POSE_TOLERANCE", "CorrespondenceCheck", "LandmarkNoise", "RoundFigures",
           "RoundLandmarks", "aligned_to", "landmark_noise", "round_helps", "round_landmarks", "coat_mean_shape",
           "correspondence_fit_params", "check_correspondence", "landmark_transfer", "refine_instance",
           "refine_rounds", "resample_instance", "round_fits", "start_from_model", "starts_from_model",
           "SELF_CHECK_INSTANCES", "SELF_CHECK_OTHERS", "evenly_spaced"]


@dataclass
class Population:
    """The coated instances the rounds refine: what :func:`refine_rounds` and :func:`round_fits` read,
    and the coatings and template the rounds leave (:func:`refine_rounds` replaces them).

    Attributes
    ----------
    names : tuple of str
        The instances, in study order.
    template_instance : str
        The instance whose landmarks define the correspondence (paper 3).
    template : Template
        The template (object mm of its instance), or the mean shape (model frame) after rounds.
    coatings : dict name -> CoatingResult
        Every instance's coating, object mm of that instance.
    volumes : dict name -> ObjectVolume
        Every instance, resampled in its object frame (paper 2).
    landmarks : dict name -> dict landmark -> (3,) mm
        The given landmarks of each instance in its object frame (empty without landmarks).
    coating_params : CoatingParams
        The coating's parameters (paper 4).
    """

    names: tuple[str, ...]
    template_instance: str
    template: Template
    coatings: dict[str, CoatingResult]
    volumes: dict[str, ObjectVolume]
    landmarks: dict[str, dict[str, np.ndarray]]
    coating_params: CoatingParams

    def volume(self, name: str) -> ObjectVolume:
        if name not in self.volumes:
            raise InputError(f"model-guided correspondence: instance {name!r} is not imported")
        return self.volumes[name]

    def landmarks_object(self, name: str) -> dict[str, np.ndarray]:
        return self.landmarks.get(name, {})


def correspondence_fit_params(params: CorrespondenceParams) -> FitParams:
    """The fits of the model method and of the self-check: the ``[correspondence]`` noise
    and landmark weight, the looser stop, and no model error in the posterior (these fits
    use the fitted shape, never its posterior SD). The pose is stepped alternately with the
    shape (``pose_step = "alternating"``), which stays nearer the pose the fit starts from
    (the input coordinates' or the coating's); why: docs/history.md, "The fit's pose
    step"."""
    return FitParams(noise_mm=params.fit_noise_mm, landmark_weight=params.landmark_weight,
                     tolerance_mm=REFINE_FIT_TOLERANCE_MM, model_error=False, pose_step="alternating")


@dataclass(frozen=True)
class LandmarkNoise:
    """How far off the given landmarks are (the click error) and how far the population's
    prediction of them is (the model error), per axis, mm; and how far a round moves each
    given landmark towards its prediction.

    Attributes
    ----------
    model_mm : float
        σ_m: the larger of the template instance's landmark transfer error (its given
        landmarks define the correspondence) and the other instances' predictions against
        their own coatings' landmark points (RMS per axis).
    click_mm : float
        σ_c: estimated from the other landmarked instances' transfer errors (their part
        beyond σ_m), or as given (``[correspondence] landmark_noise_mm``).
    shrink : float
        α = σ_c² / (σ_c² + σ_m²): the share of the way from a given landmark to its
        prediction the round moves it (the least-squares combination of two independent
        estimates with these errors); 0 keeps every landmark where given.
    estimated : bool
        ``click_mm`` was estimated (not given).
    """

    model_mm: float = 0.0
    click_mm: float = 0.0
    shrink: float = 0.0
    estimated: bool = True

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> LandmarkNoise:
        return cls(**{k: d[k] for k in ("model_mm", "click_mm", "shrink", "estimated") if k in d})


def landmark_noise(differences: dict, template_instance: str, *, click_mm: float | None = None,
                   coating_differences: dict | None = None) -> LandmarkNoise:
    """The click and model errors of the given landmarks, from the landmark transfer.

    The least-squares combination of a click and the population's prediction moves the
    click α = σ_c² / (σ_c² + σ_m²) of the way to the prediction. σ_m² (per axis) is the
    larger of the template instance's transfer error (its given landmarks define the
    correspondence, so its difference holds no click error) and the other instances'
    prediction against their own coatings' landmark points (no click in it either): a
    prediction's error is at least that. The other instances' transfer errors hold both:
    σ_c² = mean |d|²/3 less σ_m². A click error below the model's is not acted on (α = 0):
    the clicks are then the better estimate, and what the estimate reads as click error is
    within the coatings' own drift at the landmarks (measured in ``docs/history.md``).

    Parameters
    ----------
    differences : dict instance -> (G, 3) mm
        Each landmarked instance's predicted minus given landmarks (:attr:`RoundLandmarks.difference`).
    template_instance : str
        Its landmarks are exact by definition: their transfer error is the model's alone.
    click_mm : float, optional
        The click error per axis when known (0: the landmarks are exact); default estimated.
    coating_differences : dict instance -> (G, 3) mm, optional
        Each instance's predicted landmarks minus its coating's landmark points.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> d = {f"i{k}": rng.normal(scale=0.5, size=(15, 3)) + rng.normal(scale=1.5 * (k > 0), size=(15, 3))
    ...      for k in range(30)}
    >>> noise = landmark_noise(d, "i0")
    >>> round(noise.click_mm, 1), 0.8 < noise.shrink < 1.0
    (1.5, True)
    >>> landmark_noise(d, "i0", click_mm=0.0).shrink
    0.0
    """
    own = differences.get(template_instance)
    if own is None or not len(own):
        return LandmarkNoise(estimated=click_mm is None)
    model2 = float((np.asarray(own, float) ** 2).sum(axis=1).mean() / 3)
    coating = [np.asarray(d, float) for n, d in (coating_differences or {}).items()
               if n != template_instance and len(d)]
    if coating:
        model2 = max(model2, float(np.mean([(d ** 2).sum(axis=1).mean() / 3 for d in coating])))
    others = [np.asarray(d, float) for n, d in differences.items() if n != template_instance and len(d)]
    if click_mm is None:
        if not others:
            return LandmarkNoise(model_mm=math.sqrt(model2))
        total2 = float(np.mean([(d ** 2).sum(axis=1).mean() / 3 for d in others]))
        click2 = max(0.0, total2 - model2)
        act = click2 >= model2
    else:
        click2, act = float(click_mm) ** 2, True
    shrink = click2 / (click2 + model2) if act and click2 + model2 > 0 else 0.0
    return LandmarkNoise(model_mm=math.sqrt(model2), click_mm=math.sqrt(click2), shrink=shrink,
                         estimated=click_mm is None)


@dataclass(frozen=True)
class RoundFigures:
    """What one refinement round did.

    Attributes
    ----------
    round : int
    mean_change_mm : float
        RMS movement of the mean shape's points against the previous round.
    instance_change_mm : dict name -> mm
        RMS movement of each instance's coated points.
    fit_distance_mm : dict name -> mm
        Mean surface distance of each instance's model fit (before its relaxation).
    folds : dict name -> int
        Folded triangles left after the relaxation and the re-sampling.
    landmark_shift_mm : dict name -> mm
        RMS distance between each instance's given landmarks and the places the round
        warped them to; 0 for exact landmarks or none given.
    landmark_noise : LandmarkNoise
        The click and model errors of the given landmarks the round estimated, and the
        share α of the way to their prediction it moved them (:func:`landmark_noise`).
    sampling_slide_mm : float
        RMS distance by which the mean-shape coating moved the template instance's
        points along its surface; the re-sampling puts them back (:func:`resample_instance`).
    transfer_before_mm, transfer_after_mm : float
        The landmark transfer error (:func:`check_correspondence`, mean over the
        landmarked instances, mm) of the coatings the round started from and of those it
        made (NaN when not measured: the round was the last one and the build stopped).
    kept : bool
        The round's coatings were kept (it lowered the landmark transfer error).
    seconds : float
    """

    round: int
    mean_change_mm: float
    instance_change_mm: dict = field(default_factory=dict)
    fit_distance_mm: dict = field(default_factory=dict)
    folds: dict = field(default_factory=dict)
    landmark_shift_mm: dict = field(default_factory=dict)
    sampling_slide_mm: float = 0.0
    landmark_noise: LandmarkNoise = field(default_factory=lambda: LandmarkNoise())
    transfer_before_mm: float = float("nan")
    transfer_after_mm: float = float("nan")
    kept: bool = True
    seconds: float = 0.0

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> RoundFigures:
        """From :meth:`to_dict`'s form (a value JSON wrote as null is NaN again)."""
        known = {f.name for f in fields(cls)}
        values = {k: v for k, v in d.items() if k in known}
        values["landmark_noise"] = LandmarkNoise.from_dict(d.get("landmark_noise") or {})
        for k in ("transfer_before_mm", "transfer_after_mm"):
            values[k] = float("nan") if values.get(k) is None else float(values[k])
        return cls(**values)


@dataclass(frozen=True)
class CorrespondenceCheck:
    """The correspondence self-check: the landmark transfer error, which needs no truth.

    For every instance with given landmarks, the model of the *other* instances'
    coatings is fitted to the instance's coated surface alone (its own landmarks unused)
    and read off at the template's landmark points: the distance of each prediction from
    the given landmark, in mm. Where the coatings put the same anatomy at the same point
    numbers, the others' model carries their landmarks onto this instance; tangential
    drift of the coatings moves the predictions off. The figure includes what a model of
    the others cannot represent, so it is compared between builds of one population (a
    round against the coatings it started from), not read as the correspondence error.

    Attributes
    ----------
    landmark_mm : dict instance -> {landmark: mm}
    instance_mm : dict instance -> mm
        Mean over the instance's given landmarks.
    study_mm : float
        Mean of ``instance_mm`` (NaN without landmarked instances).
    stop : str
        How the model method's rounds ended: ``"converged"`` (the mean shape moved less than
        ``tolerance_mm``), ``"criterion"`` (a round did not lower ``study_mm``: it was
        dropped), ``"limit"`` (``iterations`` rounds without settling) or ``""`` (the
        single pass: no rounds).
    kept_round : int
        The last round whose coatings were kept (0: the start coatings).
    """

    landmark_mm: dict = field(default_factory=dict)
    instance_mm: dict = field(default_factory=dict)
    study_mm: float = float("nan")
    stop: str = ""
    kept_round: int = 0

    @classmethod
    def from_landmarks(cls, landmark_mm: dict, **kw) -> CorrespondenceCheck:
        per = {n: float(np.mean(list(d.values()))) for n, d in landmark_mm.items() if d}
        return cls({n: dict(d) for n, d in landmark_mm.items() if d}, per,
                   float(np.mean(list(per.values()))) if per else float("nan"), **kw)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["study_mm"] = None if not math.isfinite(self.study_mm) else self.study_mm
        return d

    @classmethod
    def from_dict(cls, d: dict) -> CorrespondenceCheck:
        """From :meth:`to_dict`'s form."""
        study_mm = d.get("study_mm")
        return cls(landmark_mm=dict(d.get("landmark_mm") or {}), instance_mm=dict(d.get("instance_mm") or {}),
                   study_mm=float("nan") if study_mm is None else float(study_mm), stop=str(d.get("stop", "")),
                   kept_round=int(d.get("kept_round", 0)))


def aligned_to(shapes: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``shapes`` (n, N, 3) moved rigidly onto ``reference`` (N, 3) by their point
    correspondence (Kabsch, no reflection): coatings in object frames that disagree (a
    near-symmetric bone whose moments frame flips) brought into one frame, mm."""
    shapes = np.asarray(shapes, float)
    if not len(shapes):
        return shapes
    _s, rot, t = procrustes_fit(shapes, np.asarray(reference, float), scale=False)
    return np.einsum("inj,ikj->ink", shapes, rot) + t[:, None, :]


# the proper rotations that turn principal axes end for end: the start poses of a fit
# whose target frame may disagree with the model's by such a turn (moments frames)
AXIS_TURNS = tuple(np.diag(d).astype(float) for d in ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)))


#: A surface alone (:func:`landmark_transfer`) is screened coarsely from all 24 rotations of the
#: principal axes (:data:`~ssm_addon.fitting.fit.AXIS_ROTATIONS`: two moments nearly equal swap
#: axes, a patella's or a vertebral body's), and this many nearest by rigid ICP.
SURFACE_TURNS_KEPT = 4
#: … of which this many nearest are fitted, and the fit nearest the surface wins (the input
#: coordinates' pose kept unless a turn fits ``WORLD_POSE_TOLERANCE`` times closer).
SURFACE_TURNS_FITTED = 2


# a start pose from the instances' own coordinates wins over a better-fitting turn of the
# axes unless that turn fits this much closer (a near-symmetric bone fits its own surface
# almost as well turned end for end)
WORLD_POSE_TOLERANCE = 1.25


def landmark_transfer(others: np.ndarray, faces: np.ndarray, surface_points: np.ndarray, landmark_locations: LandmarkLocations,
                      landmarks_object: dict, *, fit: FitParams, surface_faces: np.ndarray | None = None,
                      world_pose: Pose | None = None):
    """Fit the model of ``others`` to one surface alone; predict the landmarks there.

    Parameters
    ----------
    others : (m, N, 3) mm
        The other instances' coated points (their object frames: the model frame).
    faces : (F, 3) int
        The template's triangles.
    surface_points : (V, 3) mm
        The instance's surface (object frame): its coating's points, or the vertices of
        ``surface_faces``.
    landmark_locations : LandmarkLocations
        The template's landmarks as points of the mesh.
    landmarks_object : dict name -> (3,) mm
        The instance's given landmarks (object frame).
    fit : FitParams
        Noise and prior of the fit (its landmark weight is not used: no landmarks).
    surface_faces : (F', 3) int, optional
        The surface's triangles (default ``faces``: ``surface_points`` is a coating). A
        surface alone is fitted from the rotations of the principal axes (``AXIS_ROTATIONS``).
    world_pose : Pose, optional
        The pose the instances' input coordinates give (model frame -> the surface's);
        kept unless a turn screens ``WORLD_POSE_TOLERANCE`` times closer (rigid ICP of the
        mean shape from each; only the pose chosen is fitted).

    Returns
    -------
    (FitResult, (L, 3) predicted landmarks in mm, dict given landmark -> distance in mm)
    """
    if surface_faces is None:  # a coating: the others are put onto it by their correspondence
        others = aligned_to(others, surface_points)
    model = build_model(others, faces, [str(i) for i in range(len(others))])
    sf = faces if surface_faces is None else surface_faces
    target = Target.from_mesh(surface_points, sf, max_samples=REFINE_FIT_SAMPLES)
    if surface_faces is None:
        result = fit_model(model, target, params=fit, pose=Pose())
    else:  # a surface alone: the frames may disagree by any rotation of the principal axes
        centre = model.mean.mean(axis=0)
        poses = [Pose(rotation=r, translation=np.asarray(surface_points, float).mean(axis=0) - r @ centre)
                 for r in AXIS_ROTATIONS]
        # every rotation screened coarsely, the nearest SURFACE_TURNS_KEPT by rigid ICP of the mean
        # shape, and the input coordinates' pose kept unless a turn screens WORLD_POSE_TOLERANCE times
        # closer; the one chosen fitted
        near = sorted(i for i, _p, _d in coarse_ranked(model.mean, target, poses, partial=False)[:SURFACE_TURNS_KEPT])
        screened = sorted((rigid_screen(model.mean, target, poses[i], partial=False, samples=SCREEN_SAMPLES)
                           for i in near), key=lambda x: x[1])
        fits = [fit_model(model, target, params=fit, pose=p) for p, _d in screened[:SURFACE_TURNS_FITTED]]
        result = min(fits, key=lambda r: r.mean_distance_mm)
        if world_pose is not None:
            own = fit_model(model, target, params=fit,
                            pose=rigid_screen(model.mean, target, world_pose, partial=False, samples=SCREEN_SAMPLES)[0])
            if own.mean_distance_mm <= WORLD_POSE_TOLERANCE * result.mean_distance_mm:
                result = own
    predicted = landmark_locations.evaluate(result.points, faces)
    names = list(landmark_locations.names)
    distances = {n: float(np.linalg.norm(predicted[i] - np.asarray(landmarks_object[n], float)))
                 for i, n in enumerate(names) if n in landmarks_object}
    return result, predicted, distances


def _transfer_job(args):
    others, faces, surface, locations, given, fit = args
    return landmark_transfer(others, faces, surface, locations, given, fit=fit)[2]


#: The self-check of a large study: at most this many landmarked instances are checked (evenly
#: spaced in the study's order), each against a model of at most twice as many others (evenly
#: spaced), so its cost stops growing with the study (all of them up to these sizes).
SELF_CHECK_INSTANCES = 100
SELF_CHECK_OTHERS = 2 * SELF_CHECK_INSTANCES


def evenly_spaced(items: Sequence, k: int) -> list:
    """At most ``k`` of ``items`` spread evenly over them, in their order (all when they are
    ``k`` or fewer): the same choice on every library version.

    >>> evenly_spaced(list("abcdefghij"), 4)
    ['a', 'd', 'g', 'j']
    """
    items = list(items)
    if len(items) <= k:
        return items
    return [items[i] for i in np.unique(np.round(np.linspace(0, len(items) - 1, k)).astype(int))]


class _TransferJobs(Sequence):
    """The self-check's jobs, made when the executor takes them (only those in flight are in
    memory: a list of them held n - 1 coatings per instance at once, 15 GB at 1,000 instances)."""

    def __init__(self, stack, names, checked, faces, locations, given, fit, others: int):
        self.stack, self.names, self.checked = stack, names, checked
        self.faces, self.locations, self.given, self.fit, self.others = faces, locations, given, fit, others

    def __len__(self) -> int:
        return len(self.checked)

    def __getitem__(self, i):
        n = self.checked[i]
        me = self.names.index(n)
        rest = evenly_spaced([j for j in range(len(self.names)) if j != me], self.others)
        return (self.stack[rest], self.faces, self.stack[me], self.locations, self.given[n], self.fit)


def check_correspondence(points: dict, faces: np.ndarray, landmark_locations: LandmarkLocations, landmarks_object: dict, *,
                         fit: FitParams, executor=None, jobs: int = 1, cancelled: CancelledFn = None,
                         max_instances: int = SELF_CHECK_INSTANCES, max_others: int = SELF_CHECK_OTHERS,
                         **kw) -> CorrespondenceCheck:
    """The landmark transfer error of a coated study (:class:`CorrespondenceCheck`).

    Parameters
    ----------
    points : dict instance -> (N, 3) mm
        Every instance's coated points (object frame), at least 3 instances.
    faces : (F, 3) int
    landmark_locations : LandmarkLocations
        The template's landmarks as points of the mesh.
    landmarks_object : dict instance -> {landmark: (3,) mm}
        Given landmarks; instances without any are not checked.
    executor : Executor, optional
        Where the fits run (default: ``jobs`` local processes).
    max_instances, max_others : int
        At most ``max_instances`` landmarked instances are checked, each against a model of at
        most ``max_others`` others (both evenly spaced, :func:`evenly_spaced`): the cost is
        bounded for a biobank-sized study, and unchanged below these sizes.
    """
    names = list(points)
    checked = evenly_spaced([n for n in names if landmarks_object.get(n)], max_instances)
    if len(names) < 3 or not checked or not len(landmark_locations):
        return CorrespondenceCheck(**kw)
    stack = np.stack([np.asarray(points[n], float) for n in names])
    args = _TransferJobs(stack, names, checked, np.asarray(faces, np.int64), landmark_locations, landmarks_object, fit,
                         max_others)
    with executor_or_local(executor, jobs, len(args)) as pool:
        found = pool.map(_transfer_job, args, labels=checked, verb="checked", cancelled=cancelled)
    return CorrespondenceCheck.from_landmarks(dict(zip(checked, found)), **kw)


def start_from_model(coated: np.ndarray, faces: np.ndarray, template_points: np.ndarray, landmark_locations: LandmarkLocations,
                     target, *, fit: FitParams, coating: CoatingParams, template_frame=None,
                     name: str = "") -> CoatingResult:
    """The start of an instance without landmarks (the bootstrap of paper 7): the model of
    the landmarked instances' coatings, fitted to its surface, is the rough adaptation of
    the template that the landmark warp (eq. 2) gives a landmarked instance; registration,
    projection and relaxation (eq. 3) take it onto the surface.

    Parameters
    ----------
    coated : (m, N, 3) mm
        The landmarked instances' coatings (object frames; m >= 2).
    faces : (F, 3) int
    template_points : (N, 3) mm
        The template (its instance's object frame).
    landmark_locations : LandmarkLocations
        The template's landmarks as points of the mesh.
    target : ObjectVolume
    template_frame : ObjectFrame, optional
        The template instance's object frame: with the target's, the pose the input
        coordinates give (one scanner, one knee frame), preferred to a turn of the axes
        that fits only a little closer.

    Returns
    -------
    CoatingResult (object frame of ``target``) with ``fit.start = CoatingStart.MODEL_FIT``.
    """
    dm = DistanceMap.from_object_volume(target)
    # the model in the template's frame; its fit tries the turns of the principal axes
    coated = aligned_to(coated, template_points)
    world = None
    if template_frame is not None:
        there = target.frame.to_object(template_frame.to_world(template_points))
        _s, rot, t = procrustes_fit(np.asarray(template_points, float)[None], there, scale=False)
        world = Pose(rotation=rot[0], translation=t[0])
    fitted, predicted, _d = landmark_transfer(coated, faces, dm.surface_vertices, landmark_locations, {}, fit=fit,
                                              surface_faces=dm.surface_faces, world_pose=world)
    # paper 7: the fitted shape replaces the landmark warp as the rough adaptation, and the
    # relaxation (eq. 3) takes it onto the surface; the landmarks it predicts give the
    # coating's landmark residuals
    return coat_from_start(Mesh(template_points, faces), target, start=fitted.points, params=coating,
                           template_location=landmark_locations, target_landmarks_object=predicted,
                           distance_map=dm, start_label=CoatingStart.MODEL_FIT, name=name)


def _start_job(args):
    return start_from_model(*args[:5], fit=args[5], coating=args[6], template_frame=args[7], name=args[8])


def starts_from_model(coated: np.ndarray, faces: np.ndarray, template_points: np.ndarray, landmark_locations: LandmarkLocations,
                      targets: dict, *, fit: FitParams, coating: CoatingParams, template_frame=None, jobs: int = 1,
                      cancelled: CancelledFn = None, executor=None) -> dict[str, CoatingResult]:
    """:func:`start_from_model` for every instance of ``targets`` (name -> ObjectVolume), on
    ``executor`` (default: ``jobs`` local processes)."""
    names = list(targets)
    args = [(coated, faces, template_points, landmark_locations, targets[n], fit, coating, template_frame, n)
            for n in names]
    with executor_or_local(executor, jobs, len(args)) as pool:
        found = pool.map(_start_job, args, labels=names, verb="coated", cancelled=cancelled)
    return dict(zip(names, found))


@dataclass(frozen=True)
class RoundLandmarks:
    """The model half of a round for one instance (:func:`round_landmarks`), object mm.

    Attributes
    ----------
    warp : (L, 3) float ndarray
        The landmarks the round's warp (eq. 2) takes: the given ones where given, the
        fit's estimate of the absent ones (:meth:`shrunk` moves the given ones).
    predicted : (L, 3) float ndarray
        Every landmark as the model of the other instances, fitted to this instance's
        surface alone, puts it (the landmark transfer).
    given : (L,) bool ndarray
        Which landmarks the instance has.
    fit_distance_mm : float
        Mean surface distance of the fit.
    transfer : dict given landmark -> mm
        The landmark transfer error of the coating the round started from.
    """

    warp: np.ndarray
    predicted: np.ndarray
    given: np.ndarray
    fit_distance_mm: float
    transfer: dict

    @property
    def difference(self) -> np.ndarray:
        """(G, 3) mm: the prediction minus the given landmark, for each given landmark."""
        return self.predicted[self.given] - self.warp[self.given]

    def shrunk(self, shrink: float) -> tuple[np.ndarray, float]:
        """The warp with each given landmark moved ``shrink`` (0..1) of the way to its
        prediction, and the RMS move (mm)."""
        warp = np.array(self.warp, float)
        move = float(shrink) * self.difference
        warp[self.given] += move
        return warp, float(np.sqrt((move ** 2).sum(axis=1).mean())) if len(move) else 0.0


def round_landmarks(others: np.ndarray, faces: np.ndarray, target, landmark_locations: LandmarkLocations,
                    landmarks_object: dict, *, fit: FitParams, current: np.ndarray | None = None,
                    name: str = "") -> RoundLandmarks:
    """The model half of a round for one instance: the model of ``others`` fitted to its
    surface alone, its landmark transfer (:func:`landmark_transfer`) and the landmarks the
    round's warp takes (eq. 2): the given ones where given, the absent ones from the fit
    with the given ones as soft constraints (its posterior).

    Parameters
    ----------
    others : (n-1, N, 3) mm
        The other instances' coated points (their object frames = the model frame).
    faces : (F, 3)
    target : ObjectVolume
        The instance.
    landmark_locations : LandmarkLocations
        The template's landmarks as points of the mesh.
    landmarks_object : dict name -> (3,) mm
        The instance's landmarks in its object frame (may be empty).
    current : (N, 3) mm, optional
        The instance's coating the round starts from: the surface of the landmark
        transfer check; default its marching-cubes surface.

    Returns
    -------
    RoundLandmarks
    """
    all_names = list(landmark_locations.names)
    given = np.array([n in landmarks_object for n in all_names], dtype=bool)
    given_points = np.array([landmarks_object[n] for n in all_names if n in landmarks_object], float).reshape(-1, 3)
    posterior = bool(given.any() and not given.all() and fit.landmark_weight > 0)
    # the instance's own surface only where a fit needs it (no coating to fit, or the posterior)
    dm = DistanceMap.from_object_volume(target) if current is None or posterior else None
    if current is None:
        surface, surface_faces = dm.surface_vertices, dm.surface_faces
    else:
        surface, surface_faces = current, None
    result, predicted, transfer = landmark_transfer(others, faces, surface, landmark_locations, landmarks_object,
                                                    fit=fit, surface_faces=surface_faces)
    warp = np.array(predicted, float)
    if posterior:
        # the absent landmarks' posterior places: the fit with the given landmarks as soft
        # constraints, read off at the template's landmark points
        model = build_model(others if current is None else aligned_to(others, current), faces,
                            [str(i) for i in range(len(others))],
                            params={"landmark_locations": landmark_locations.to_dict()})
        lms = LandmarkSet(tuple(n for n in all_names if n in landmarks_object), given_points, name)
        result = fit_model(model, Target.from_mesh(dm.surface_vertices, dm.surface_faces, landmarks=lms,
                                                   max_samples=REFINE_FIT_SAMPLES), params=fit,
                           pose=Pose() if current is None else result.pose)
        warp = landmark_locations.evaluate(result.points, faces)
    warp[given] = given_points
    return RoundLandmarks(warp=warp, predicted=np.asarray(predicted, float), given=given,
                          fit_distance_mm=float(result.mean_distance_mm), transfer=transfer)


def coat_mean_shape(template_points: np.ndarray, faces: np.ndarray, target, landmark_locations: LandmarkLocations,
                    warp_landmarks: np.ndarray, *, coating: CoatingParams, name: str = "") -> CoatingResult:
    """The coating half of a round: the mean shape coated onto one instance by the paper's
    pipeline (landmark warp eq. 2 to ``warp_landmarks`` (L, 3) mm, projection, relaxation
    eq. 3), in the instance's object frame."""
    return coat(Mesh(template_points, faces), landmark_locations.evaluate(template_points, faces), target, warp_landmarks,
                params=coating, name=name)


def refine_instance(others: np.ndarray, faces: np.ndarray, template_points: np.ndarray, target,
                    landmark_locations: LandmarkLocations, landmarks_object: dict, *, fit: FitParams,
                    coating: CoatingParams, shrink: float = 0.0, current: np.ndarray | None = None,
                    name: str = "") -> tuple[CoatingResult, float, float, dict]:
    """One instance in one round: :func:`round_landmarks` (the model of ``others`` fitted to
    it) then :func:`coat_mean_shape` (``template_points`` coated onto it with the landmarks
    the fit gives, the given ones moved ``shrink`` of the way to their prediction).

    Returns
    -------
    (CoatingResult, mean surface distance of the fit in mm, RMS shift of the given
    landmarks in mm, dict given landmark -> transfer distance in mm)
    """
    found = round_landmarks(others, faces, target, landmark_locations, landmarks_object, fit=fit, current=current,
                            name=name)
    warp, shift = found.shrunk(shrink)
    coated = coat_mean_shape(template_points, faces, target, landmark_locations, warp, coating=coating, name=name)
    return coated, found.fit_distance_mm, shift, found.transfer


def resample_instance(coating: CoatingResult, faces: np.ndarray, triangles: np.ndarray, bary: np.ndarray, target,
                      *, params: CoatingParams, name: str = "") -> CoatingResult:
    """A coating re-sampled at the template's points: the same correspondence, read at
    other places of the mesh.

    Coating the mean shape slides the template's points along the surfaces (the mean is
    not the template instance), the same way on every instance: the correspondence is
    kept but point i no longer sits where the template put it. ``triangles`` and ``bary``
    locate the template's points on the template instance's final coating; the same
    places on this instance's coating, moved onto its surface along the mesh normals
    (:meth:`~ssm_addon.coating.distance_map.DistanceMap.project_along`: the gradient projection
    can cross a thin process, and on the deformed population it folded 17 of 20
    instances), carry the rounds' correspondence at the template's sampling (paper 3:
    the curvature-guided points of the template instance). The mesh is then finished
    like a coating: the relaxation (eq. 3) with the re-sampled edge lengths as rest
    lengths, projection and untangling.

    Parameters
    ----------
    coating : CoatingResult of this instance's round (object frame, mm).
    faces : (F, 3) int.
    triangles : (N,) int; bary : (N, 3)
        The template's points as places of the template instance's new coating.
    target : ObjectVolume of this instance.

    Returns
    -------
    CoatingResult with the re-sampled points and their fit figures.
    """
    dm = DistanceMap.from_object_volume(target)
    f = np.asarray(faces, np.int64)
    p = MeshLocation(np.asarray(triangles, np.int64), np.asarray(bary, float)).evaluate(coating.points_object, f)
    p = dm.project_along(p, vertex_normals(p, f))
    # finished like any coating, with the re-sampled spacing as rest lengths
    e = mesh_edges(f)
    p, iterations, converged, rounds = settle_on_surface(p, f, edge_lengths(p, e), dm, params=params, edges=e)
    dist = dm.surface_distance(p)
    folds = int(folded_triangles(p, f, dm, params.fold_angle_deg, params.fold_normal_sigma_mm).sum())
    fit = replace(coating.fit, mean_distance_mm=float(dist.mean()), max_distance_mm=float(dist.max()),
                  folded_after=folds, iterations=coating.fit.iterations + iterations, converged=converged,
                  untangle_rounds=coating.fit.untangle_rounds + rounds)
    return CoatingResult(p, coating.warped_points_object, fit, name or coating.name)


def _resample_job(args):
    return resample_instance(*args[:5], params=args[5], name=args[6])


def _landmarks_job(args):
    return round_landmarks(*args[:5], fit=args[5], current=args[6], name=args[7])


def _coat_mean_job(args):
    return coat_mean_shape(*args[:5], coating=args[5], name=args[6])


# a round is kept only when it lowers the landmark transfer error of the coatings kept so
# far by this share, and by more than chance: the landmarked instances' transfer errors
# fall in a one-sided paired t-test at KEEP_LEVEL (a change within the fits' noise, or
# one a few instances carry, keeps the start: the single pass is the simpler result)
KEEP_MARGIN = 0.01
KEEP_LEVEL = 0.10


def round_helps(after: CorrespondenceCheck, before: CorrespondenceCheck, *, margin: float = KEEP_MARGIN,
                level: float = KEEP_LEVEL) -> bool:
    """Whether a round's coatings (``after``) beat the ones kept so far (``before``).

    The mean landmark transfer error must fall by ``margin`` (a share), and the instances'
    own transfer errors must fall together: a one-sided paired t-test of the per-instance
    differences at ``level`` (with fewer than 3 instances in both, the margin alone). No
    landmarks to judge by (NaN): the round is kept.

    Examples
    --------
    >>> before = CorrespondenceCheck(instance_mm={"a": 1.0, "b": 2.0, "c": 1.5, "d": 1.2}, study_mm=1.425)
    >>> round_helps(CorrespondenceCheck(instance_mm={"a": 0.9, "b": 1.8, "c": 1.4, "d": 1.1}, study_mm=1.3), before)
    True
    >>> round_helps(CorrespondenceCheck(instance_mm={"a": 0.2, "b": 2.1, "c": 1.6, "d": 1.3}, study_mm=1.3), before)
    False
    """
    if not (math.isfinite(after.study_mm) and math.isfinite(before.study_mm)):
        return True
    if not after.study_mm < before.study_mm * (1.0 - margin):
        return False
    common = [n for n in before.instance_mm if n in after.instance_mm]
    if len(common) < 3:
        return True
    diff = np.array([after.instance_mm[n] - before.instance_mm[n] for n in common])
    sd = float(diff.std(ddof=1))
    if sd == 0.0:
        return bool(diff.mean() < 0)
    t = float(diff.mean()) / (sd / math.sqrt(len(diff)))
    return t < float(stdtrit(len(diff) - 1, level))


def round_fits(study: Population, names, *, fit: FitParams, jobs: int = 1, executor=None, cancelled: CancelledFn = None,
               progress: ProgressFn = None, verb: str = "fitted") -> dict[str, RoundLandmarks]:
    """:func:`round_landmarks` for the instances ``names`` of a coated study: each fitted by
    the model of every other instance's coating, against its own coating (object mm), on
    ``executor`` (default: ``jobs`` local processes)."""
    if not names:
        return {}
    every = list(study.names)
    points = np.stack([study.coatings[n].points_object for n in every])
    faces = np.asarray(study.template.faces)
    locations = study.template.landmark_locations
    args = [(np.delete(points, every.index(n), axis=0), faces, study.volume(n), locations, study.landmarks_object(n),
             fit, points[every.index(n)], n) for n in names]
    with executor_or_local(executor, jobs, len(args)) as pool:
        found = pool.map(_landmarks_job, args, labels=list(names), verb=verb, progress=progress, cancelled=cancelled)
    return dict(zip(names, found))


def refine_rounds(study: Population, params: CorrespondenceParams, *, jobs: int = 1, progress: ProgressFn = None,
                  cancelled: CancelledFn = None, log=None, executor=None, on_coated=None,
                  first_fits: dict | None = None) -> tuple[list[RoundFigures], CorrespondenceCheck]:
    """Refinement rounds on a coated population (every instance coated): updates ``study.template``
    (the mean shape, in the model frame) and ``study.coatings`` of the :class:`Population`; returns each round's
    figures and the self-check of the coatings kept. ``on_coated(name)`` is called as each
    round's coating of an instance arrives.

    A round: :func:`round_landmarks` on every instance (the leave-one-out fits, which
    also measure the landmark transfer error of the coatings the round starts from),
    :func:`coat_mean_shape` with the landmarks they give, and :func:`resample_instance`
    (back at the template's points, so every round's coatings are judged at the same
    sampling as the start's). The next round's fits judge it: a round that does not lower
    the transfer error by ``KEEP_MARGIN`` and by more than chance (:func:`round_helps`) is
    dropped and the rounds stop (``stop =
    "criterion"``); after the last round one more pass of fits judges it. When the start
    is kept, ``study`` keeps the single pass's coatings and template.

    Jobs run on ``executor`` (:class:`~ssm_addon.base.compute.Executor`; default ``jobs``
    local processes); their inputs include the instance's resampled volume.

    Raises
    ------
    InputError
        Fewer than 3 coated instances, or a round whose mean shape moves more than the
        instances' size (the refinement diverged; nothing is kept).
    """
    say = log or (lambda _m: None)

    def arrived(labels):  # on_result for one executor.map: the instance's name to on_coated
        return None if on_coated is None else (lambda i, _result: on_coated(labels[i]))

    names = list(study.names)
    if len(names) < 3:
        raise InputError(f"model-guided correspondence needs at least 3 instances, the study has {len(names)}")
    missing = [n for n in names if n not in study.coatings]
    if missing:
        raise InputError(f"model-guided correspondence: instance(s) not coated yet: {', '.join(missing)}")
    faces = np.asarray(study.template.faces)
    # the template's landmarks as mesh points, located when the template was made (pipeline.stages)
    locations = study.template.landmark_locations
    fit = correspondence_fit_params(params)
    lm_object = {n: study.landmarks_object(n) for n in names}
    rounds: list[RoundFigures] = []
    anchor = names.index(study.template_instance)
    # the template's sampling (paper 3: its points on the template instance); a study
    # refined before has the mean shape as template and its template instance re-sampled
    mean_template = study.template.is_mean_shape
    sampling = np.array(study.coatings[names[anchor]].points_object if mean_template else study.template.points_object,
                        dtype=float)
    size = float(np.linalg.norm(np.ptp(study.coatings[names[anchor]].points_object, axis=0)))
    best = (dict(study.coatings), study.template)
    start_template, template_points = study.template, np.asarray(study.template.points_object, float)
    if params.round_template == "instance" and mean_template:
        raise InputError("model-guided correspondence: round_template = \"instance\" needs the template instance's "
                         "template, the study has the mean shape (refined with round_template = \"mean\")")
    complete = {n: bool(len(locations)) and all(k in lm_object[n] for k in locations.names) for n in names}
    best_check, stop, converged, total = None, "limit", False, params.iterations
    with executor_or_local(executor, jobs, len(names)) as executor:
        for r in range(1, total + 2):
            check_cancelled(cancelled)
            t0 = time.perf_counter()
            points = np.stack([study.coatings[n].points_object for n in names])
            # the mean shape (paper 3.3), of the coatings put onto the template instance's
            # (their object frames may disagree by a turn): the new template, in its frame
            mean = aligned_to(points, points[anchor]).mean(axis=0)
            # the fits of this round judge the coatings it starts from (the last round's); the
            # first round's may have come with the study (``first_fits``)
            have = dict(first_fits or {}) if r == 1 else {}
            span = (r - 1) / (total + 1), (r - 0.5) / (total + 1)
            have.update(round_fits(study, [n for n in names if n not in have], fit=fit, executor=executor,
                                   cancelled=cancelled, progress=sub_progress(progress, span[0], span[1]),
                                   verb=f"round {r}: fitted"))
            fitted = [have[n] for n in names]
            check = CorrespondenceCheck.from_landmarks({n: f.transfer for n, f in zip(names, fitted)})
            if best_check is None:
                best_check = check
            else:
                kept = round_helps(check, best_check)
                rounds[-1] = replace(rounds[-1], transfer_after_mm=check.study_mm, kept=kept)
                if not kept:
                    say(f"correspondence round {r - 1} dropped: the landmark transfer error went from "
                        f"{best_check.study_mm:.3f} to {check.study_mm:.3f} mm; keeping "
                        f"{'the start' if not any(f.kept for f in rounds) else 'round ' + str(max(f.round for f in rounds if f.kept))}")
                    stop = "criterion"
                    break
                best, best_check = (dict(study.coatings), study.template), check
                if converged:
                    stop = "converged"
                    break
            if r > total:
                break
            # the given landmarks' click error against the population's prediction of them; each
            # is moved that share of the way to its prediction (the template instance's define
            # the correspondence and stay)
            noise = landmark_noise({n: f.difference for n, f in zip(names, fitted) if f.given.any()},
                                   study.template_instance, click_mm=params.landmark_noise_mm,
                                   coating_differences={n: f.predicted[f.given] - locations.evaluate(points[i], faces)[f.given]
                                                        for i, (n, f) in enumerate(zip(names, fitted)) if f.given.any()})
            moved = {n: f.shrunk(0.0 if n == study.template_instance else noise.shrink) for n, f in zip(names, fitted)}
            warps = {n: w for n, (w, _s) in moved.items()}
            shifts = {n: s for n, (_w, s) in moved.items()}
            if noise.estimated and any(f.given.any() for n, f in zip(names, fitted) if n != study.template_instance):
                say(f"correspondence round {r}: given landmarks {noise.click_mm:.2f} mm off (per axis, estimated), "
                    f"the model's prediction {noise.model_mm:.2f} mm: each moved {noise.shrink:.0%} of the way "
                    "to its prediction")
            if params.round_template == "instance":
                # the template itself, coated with the landmarks the fits give: instances whose
                # every landmark is given and stays where given would be coated as they are, and
                # keep theirs
                redo = [n for n in names if not (complete[n] and shifts[n] == 0.0)]
                if not redo:
                    say("correspondence: every instance has every landmark and none moves: the rounds have nothing "
                        "to refine (the single pass's coatings)")
                    stop = "converged"
                    break
                found = dict(zip(redo, executor.map(
                    _coat_mean_job, [(template_points, faces, study.volume(n), locations,
                                      warps[n], study.coating_params, n) for n in redo],
                    labels=redo, verb=f"round {r}: coated", on_result=arrived(redo),
                    progress=sub_progress(progress, span[1], r / (total + 1)), cancelled=cancelled)))
                resampled = [found.get(n, study.coatings[n]) for n in names]
                change = _finish_round(study, names, points, resampled, fitted, shifts, noise, faces, size, r, t0,
                                       rounds, say, mean, 0.0, check.study_mm, template=start_template)
                converged = change < params.tolerance_mm
                continue
            coated = executor.map(_coat_mean_job, [(mean, faces, study.volume(n), locations, warps[n],
                                                    study.coating_params, n) for n in names],
                                  labels=names, verb=f"round {r}: coated", on_result=arrived(names),
                                  progress=sub_progress(progress, span[1], (r - 0.2) / (total + 1)),
                                  cancelled=cancelled)
            # how far the mean shape's coating slid the template's points on their own instance;
            # the template's sampling back: its points located on the template instance's
            # coating, read off every instance's coating
            slide = float(np.sqrt(((coated[anchor].points_object - sampling) ** 2).sum(axis=1).mean()))
            _c, _d, tri, bary = MeshLocator(coated[anchor].points_object, faces).query(
                sampling, k=12, normals=vertex_normals(sampling, faces))
            resampled = executor.map(_resample_job, [(c, faces, tri, bary, study.volume(n), study.coating_params, n)
                                                     for n, c in zip(names, coated)],
                                     labels=names, verb=f"round {r}: re-sampled at the template's points",
                                     progress=sub_progress(progress, (r - 0.2) / (total + 1), r / (total + 1)),
                                     cancelled=cancelled)
            moved = np.stack([c.points_object for c in coated])
            _check_diverged(aligned_to(moved, moved[anchor]).mean(axis=0), mean, size, r)
            change = _finish_round(study, names, points, resampled, fitted, shifts, noise, faces, size, r, t0, rounds,
                                   say, mean, slide, check.study_mm)
            converged = change < params.tolerance_mm
        study.coatings, study.template = dict(best[0]), best[1]
        for n in names:
            study.coatings[n] = _given_landmark_residuals(study.coatings[n], faces, locations, lm_object[n])
    kept_round = max((f.round for f in rounds if f.kept), default=0)
    return rounds, replace(best_check, stop=stop, kept_round=kept_round)


def _check_diverged(new_mean: np.ndarray, mean: np.ndarray, size: float, r: int) -> float:
    """The RMS movement of the mean shape (mm); more than the shapes' size is an error."""
    change = float(np.sqrt(((new_mean - mean) ** 2).sum(axis=1).mean()))
    if not math.isfinite(change) or change > size:
        raise InputError(f"model-guided correspondence diverged in round {r}: the mean shape moved {change:.1f} mm "
                         f"(the shapes are {size:.0f} mm across); check the instances' frames and landmarks")
    return change


def _finish_round(study: Population, names, points, resampled, fitted, shifts, noise, faces, size, r, t0, rounds, say, mean,
                  slide, before, template=None):
    """Check a round, record its figures, and make its re-sampled coatings and mean shape the
    study's; returns the RMS movement of the mean shape (mm)."""
    new_points = np.stack([c.points_object for c in resampled])
    anchor = names.index(study.template_instance)
    change = _check_diverged(aligned_to(new_points, new_points[anchor]).mean(axis=0), mean, size, r)
    fig = RoundFigures(
        round=r, mean_change_mm=change,
        instance_change_mm={n: float(np.sqrt(((new_points[i] - points[i]) ** 2).sum(axis=1).mean()))
                            for i, n in enumerate(names)},
        fit_distance_mm={n: f.fit_distance_mm for n, f in zip(names, fitted)},
        folds={n: int(c.fit.folded_after) for n, c in zip(names, resampled)},
        landmark_shift_mm=dict(shifts), sampling_slide_mm=slide, landmark_noise=noise, transfer_before_mm=before,
        seconds=time.perf_counter() - t0)
    rounds.append(fig)
    for n, c in zip(names, resampled):
        study.coatings[n] = c
    study.template = _mean_template(study, mean, faces) if template is None else template
    say(f"correspondence round {r}: mean shape moved {change:.3f} mm; instances moved up to "
        f"{max(fig.instance_change_mm.values()):.2f} mm; given landmarks moved up to "
        f"{max(fig.landmark_shift_mm.values(), default=0.0):.2f} mm; the template's points slid {slide:.2f} mm "
        f"(re-sampled); folds left {sum(fig.folds.values())}; landmark transfer error before the round "
        f"{before:.3f} mm ({fig.seconds:.1f} s)")
    return change


def _given_landmark_residuals(coating: CoatingResult, faces: np.ndarray, locations: LandmarkLocations,
                              given: dict) -> CoatingResult:
    """The coating with its landmark residuals measured against the instance's *given*
    landmarks (object frame, mm), not against the round's warp targets (the fit's
    estimate): a given landmark the population moves far is then named by the
    ``landmark_residual`` gate; an instance without landmarks has none."""
    here = locations.subset([n for n in locations.names if n in given])
    residuals = ()
    if len(here):
        at = here.evaluate(coating.points_object, faces)
        want = np.array([given[n] for n in here.names])
        residuals = tuple(float(x) for x in np.linalg.norm(at - want, axis=1))
    return replace(coating, fit=replace(coating.fit, landmark_residuals_mm=residuals, landmark_names=here.names))


def _mean_template(study: Population, mean_points: np.ndarray, faces: np.ndarray):
    """The mean shape as the study's template (model frame; curvature and frame kept)."""
    t = study.template
    return replace(t, points_object=np.asarray(mean_points, float), faces=faces, is_mean_shape=True)
