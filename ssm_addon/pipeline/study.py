"""A shape study: its instances and parameters, and what each stage of the method made.

The study is the state both front ends share. The command line builds one from a
project file (:meth:`Study.from_project`), Blender from the scene; both then call the
same stage functions, which read the study and return a product:

====================  ==========================================  ===================
stage                 function                                    product
====================  ==========================================  ===================
import (paper 2)      :func:`import_instances`                    ``volumes``
template (paper 3)    :func:`make_template`                       ``template``
coating (paper 4)     :func:`coat_instances`                      ``coatings``
model (paper 5)       :func:`make_model`                          ``model``
metrics               :func:`evaluate_model`                      ``metrics``
====================  ==========================================  ===================

:func:`run` is the loop over them. Every number that feeds a later stage is float64
and lives here (Blender meshes are only views of it), so the same inputs give the same
model in Blender and on the command line.

Frames: landmarks are world mm of each instance's input file; volumes, the template
and coatings are object mm (paper 2) of their instance; the model is in the model frame
(the object frame, or Procrustes-aligned).
"""

from __future__ import annotations

import dataclasses
import time
from collections import Counter
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..base.compute import executor_or_local, time_left_text
from ..base.errors import InputError, check_cancelled
from ..base.params import CoatingParams, QualityParams, StudyParams
from ..base.progress import CancelledFn, ProgressFn, report, sub_progress
from ..base.records import versions
from ..coating.coating import CoatingResult, CoatingStart, coat_all
from ..formats.label_maps import read_label_map
from ..formats.landmarks import LandmarkSet
from ..instances.importing import InstanceSpec, import_instance
from ..instances.volume import ObjectFrame, ObjectVolume
from ..meshutil import LandmarkLocations, genus
from ..model.metrics import ModelMetrics
from ..model.pca import ShapeModel, build_model
from ..model.quality import (
    Finding,
    check_coating,
    check_correspondence_rounds,
    check_duplicate_instances,
    check_frames,
    check_landmark_transfer,
    check_landmarks_on_surface,
    check_model,
    check_volume,
    check_volumes_together,
    content_digest,
)
from ..template.template import Template, build_template

__all__ = [
    "STAGES",
    "InstanceJob",
    "StageResult",
    "Study",
    "apply_stage",
    "carried_landmarks",
    "coat_from_source",
    "coat_instances",
    "coating_result",
    "coating_stage",
    "common_landmark_names",
    "evaluate_model",
    "import_instances",
    "import_result",
    "import_stage",
    "landmark_distances",
    "make_model",
    "make_template",
    "medoid_template",
    "merge_findings",
    "metrics_stage",
    "model_stage",
    "population_medoid",
    "refine_correspondence",
    "run",
    "start_coatings",
    "stream_instances",
    "study_parameters",
    "template_landmark_locations",
    "template_stage",
]

Log = Callable[[str], None] | None


@dataclass
class Study:
    """A shape study (paper fig. 1): inputs and the products of each stage.

    Attributes
    ----------
    instances : tuple of InstanceSpec
        The instances in study order (their sources and landmarks, world mm).
    template_instance : str
        Name of the instance the template is built from (paper 3).
    params : StudyParams
        Every stage's parameters, one field per project table
        (:class:`ssm_addon.base.params.StudyParams`); ``params.template.spacing_mm`` and
        ``.frame`` also set every instance's import.
    volumes : dict name -> ObjectVolume
        Each imported instance, resampled in its object frame (paper 2).
    frames : dict name -> ObjectFrame
        Object frames known without the volume (e.g. stored with a Blender scene);
        :meth:`frame` prefers the volume's.
    template : Template or None
    coatings : dict name -> CoatingResult
        The template coated onto each instance (object mm of that instance).
    model : ShapeModel or None
    metrics : ModelMetrics or None
        Compactness, generalization, specificity.
    findings : list of Finding
        Failed quality gates (:mod:`ssm_addon.model.quality`), in stage order.
    outlier_scores : dict name -> dict
        Leave-one-out Mahalanobis distance and reconstruction error per instance.
    timings_s : dict
        Wall time per stage.
    streamed : dict
        After a streamed build (:func:`stream_instances`): instances taken from the cache
        (``cached``) and coated (``computed``).
    coating_start : dict name -> CoatingStart
        How each instance's correspondence began (where it differs from its coating's own
        ``fit.start``: the model method's start).
    correspondence_rounds : list of RoundFigures
        The model method's refinement rounds.
    correspondence_check : CorrespondenceCheck or None
        The correspondence self-check (landmark transfer error) of the coatings.
    template_choice : dict
        The model method's choice of the template's instance (``template_choice =
        "medoid"``): ``given``, ``medoid``, their landmark transfer errors (mm) and ``kept``.
    """

    instances: tuple[InstanceSpec, ...]
    template_instance: str = ""
    params: StudyParams = field(default_factory=StudyParams)
    volumes: dict[str, ObjectVolume] = field(default_factory=dict)
    frames: dict[str, ObjectFrame] = field(default_factory=dict)
    template: Template | None = None
    coatings: dict[str, CoatingResult] = field(default_factory=dict)
    model: ShapeModel | None = None
    metrics: ModelMetrics | None = None
    findings: list = field(default_factory=list)
    outlier_scores: dict = field(default_factory=dict)
    coating_start: dict[str, CoatingStart] = field(default_factory=dict)
    correspondence_rounds: list = field(default_factory=list)
    correspondence_check: object | None = None
    template_choice: dict = field(default_factory=dict)
    timings_s: dict[str, float] = field(default_factory=dict)
    streamed: dict = field(default_factory=dict)

    def __post_init__(self):
        self.instances = tuple(self.instances)
        names = [i.name for i in self.instances]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise InputError(f"study: instance names are not unique: {', '.join(dup)}")
        if not self.template_instance and names:
            self.template_instance = names[0]
        if names and self.template_instance not in names:
            raise InputError(f"study: the template instance {self.template_instance!r} is not one of the instances")

    @classmethod
    def from_project(cls, project) -> Study:
        """The study of a parsed project file (:func:`ssm_addon.cli.project_build.read_project`)."""
        return cls(instances=project.instances, template_instance=project.template_instance, params=project.params)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(i.name for i in self.instances)

    def instance(self, name: str) -> InstanceSpec:
        for inst in self.instances:
            if inst.name == name:
                return inst
        raise InputError(f"study: no instance named {name!r} (instances: {', '.join(self.names)})")

    def landmarks(self, name: str) -> LandmarkSet | None:
        """The instance's landmarks (world mm of its file), or None."""
        lm = self.instance(name).landmarks
        return lm if lm is not None and len(lm) else None

    def landmarks_object(self, name: str, frame: ObjectFrame | None = None) -> dict[str, np.ndarray]:
        """The instance's landmarks by name, (3,) mm in its object frame (``frame``, default
        :meth:`frame`); empty without landmarks."""
        lm = self.landmarks(name)
        if lm is None:
            return {}
        return dict(zip(lm.names, (frame or self.frame(name)).to_object(lm.points_world)))

    def frame(self, name: str) -> ObjectFrame:
        """The instance's object frame (paper 2): its volume's, else a known one."""
        if name in self.volumes:
            return self.volumes[name].frame
        if name in self.frames:
            return self.frames[name]
        raise InputError(f"study: instance {name!r} is not imported yet (no object frame)")

    def volume(self, name: str) -> ObjectVolume:
        if name not in self.volumes:
            raise InputError(f"study: instance {name!r} is not imported yet")
        return self.volumes[name]


STAGES = ("import", "template", "coating", "model", "metrics")


def study_parameters(study: Study, landmark_names: Sequence[str] = ()) -> dict:
    """Every parameter of the study as JSON-ready values (what ``model.npz`` records).

    Deterministic: the same study gives the same dict (no times, dates or paths of the
    machine), so identical builds give identical model files.
    """
    return {
        "spacing_mm": float(study.params.template.spacing_mm),
        "frame_method": study.params.template.frame,
        "template_instance": study.template_instance,
        "template": study.params.template.to_dict(),
        "coating": study.params.coating.to_dict(),
        "model": dataclasses.asdict(study.params.model),
        "landmarks": list(landmark_names),
        "versions": versions(),
    }


# ----------------------------------------------------------------------------- stages
def import_instances(study: Study, *, names: Sequence[str] | None = None, jobs: int = 1,
                     progress: ProgressFn = None, cancelled: CancelledFn = None) -> dict[str, ObjectVolume]:
    """Read every instance, compute its object frame and resample it (paper 2).

    Label maps shared by several instances (one file, several labels) are read once.
    With ``jobs`` > 1 the instances are processed in threads (the numeric work releases
    the GIL); the result does not depend on ``jobs``.

    Returns
    -------
    dict name -> ObjectVolume, in study order (only ``names``, default all).
    """
    todo = [study.instance(n) for n in (study.names if names is None else names)]
    n = len(todo)
    tp = study.params.template
    shared = {}
    paths = [inst.volume_path for inst in todo if inst.volume_path is not None]
    for path in sorted({p for p in paths if paths.count(p) > 1}):
        check_cancelled(cancelled)
        try:
            shared[path] = read_label_map(path)
        except InputError as err:
            raise InputError(f"instances using {path.name}: {err}") from None
    done = [0]

    def one(inst: InstanceSpec) -> ObjectVolume:
        check_cancelled(cancelled)
        ov = import_instance(inst, spacing_mm=tp.spacing_mm, frame_method=tp.frame,
                             label_map=shared.get(inst.volume_path), cancelled=cancelled)
        done[0] += 1
        report(progress, done[0] / n, f"imported {inst.name} ({done[0]}/{n}): {ov.mask.shape} voxels at "
                                      f"{ov.spacing_mm:g} mm, frame {ov.frame.method}")
        return ov

    workers = max(1, min(int(jobs or 1), n))
    if workers == 1:
        volumes = [one(inst) for inst in todo]
    else:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            volumes = list(pool.map(one, todo))
    return {inst.name: ov for inst, ov in zip(todo, volumes)}


def make_template(study: Study, *, progress: ProgressFn = None, cancelled: CancelledFn = None) -> Template:
    """The template (paper 3) from the study's template instance."""
    name = study.template_instance
    try:
        template = build_template(study.volume(name), study.params.template, progress=progress, cancelled=cancelled)
    except InputError as err:
        raise InputError(f"template from instance {name!r}: {err}") from None
    study_with = Study(instances=study.instances, template_instance=name, template=template, frames={
        name: study.frame(name)})
    return dataclasses.replace(template, landmark_locations=template_landmark_locations(study_with))


def common_landmark_names(study: Study, names: Sequence[str]) -> tuple[str, ...]:
    """The landmark names of the template instance that every one of ``names`` also has.

    In the template instance's order; the landmark warp (eq. 2) uses exactly these.
    """
    ref = study.landmarks(study.template_instance)
    if ref is None:
        raise InputError(f"coating: the template's instance {study.template_instance!r} has no landmarks")
    missing = [n for n in names if study.landmarks(n) is None]
    if missing:
        raise InputError(f"coating: instance(s) without landmarks: {', '.join(missing)}")
    sets = [study.landmarks(n) for n in names]
    common = tuple(x for x in ref.names if all(x in s.names for s in sets))
    if len(common) < 4:
        raise InputError(f"coating: only {len(common)} landmark name(s) shared by {study.template_instance} and "
                         f"{', '.join(names)}; the landmark warp (eq. 2) needs at least 4")
    return common


def _landmarks_object(study: Study, name: str, common: Sequence[str]) -> np.ndarray:
    lm = study.landmarks(name).subset(common)
    return study.frame(name).to_object(lm.points_world)


def coat_instances(study: Study, *, names: Sequence[str] | None = None, jobs: int = 1,
                   progress: ProgressFn = None, cancelled: CancelledFn = None,
                   on_coated: Callable[[str], None] | None = None, executor=None) -> dict[str, CoatingResult]:
    """Coat the template onto instances (paper 4), ``jobs`` processes.

    Parameters
    ----------
    names : instance names (default: every instance).
    on_coated : called with each instance's name as its coating arrives.
    executor : Executor, optional
        Where the coatings run (default: ``jobs`` local processes).

    Returns
    -------
    dict name -> CoatingResult (object mm of each instance). Cancelling raises
    :class:`~ssm_addon.coating.coating.CoatingCancelled` whose ``results`` keep the finished ones.

    Raises
    ------
    InputError
        Before any coating, when a landmark lies farther than ``[quality]
        max_landmark_distance_mm`` from its instance's surface (a wrong file, an offset,
        LPS read as RAS: the message says which).
    """
    if study.template is None:
        raise InputError("coating: build the template first")
    names = list(study.names if names is None else names)
    common = common_landmark_names(study, names)
    for name in dict.fromkeys([study.template_instance, *names]):  # landmarks on their instance's surface
        inst = study.instance(name)
        check_landmarks_on_surface(name, study.volume(name), study.landmarks(name), study.params.quality,
                                   source=str(inst.landmarks_path) if inst.landmarks_path is not None else "")
    src = _landmarks_object(study, study.template_instance, common)
    targets = [study.volume(n) for n in names]
    lms = [_landmarks_object(study, n, common) for n in names]
    results = coat_all(study.template, src, targets, lms, params=study.params.coating, jobs=jobs,
                       progress=progress, cancelled=cancelled, names=names, on_coated=on_coated, executor=executor)
    return dict(zip(names, results))


def _coat_from_frames_job(args):
    from ..coating.coating import coat_from_start

    template, target, params, name = args
    return coat_from_start(template, target, params=params, name=name)


def coat_from_frames(study: Study, names: Sequence[str], *, jobs: int = 1, cancelled: CancelledFn = None,
                     executor=None) -> dict[str, CoatingResult]:
    """Coat the template onto instances from the object frames alone (no landmarks; paper 2's
    alignment, then the coating's registration, projection and relaxation), on ``executor``
    (default: ``jobs`` local processes)."""
    from ..meshutil import Mesh

    mesh = Mesh(study.template.points_object, study.template.faces)
    args = [(mesh, study.volume(n), study.params.coating, n) for n in names]
    with executor_or_local(executor, jobs, len(args)) as pool:
        results = pool.map(_coat_from_frames_job, args, labels=list(names), verb="coated", cancelled=cancelled)
    return dict(zip(names, results))


def start_coatings(study: Study, names: Sequence[str] | None = None, *, jobs: int = 1,
                   cancelled: CancelledFn = None, executor=None) -> dict[str, CoatingResult]:
    """The first coatings of the model method: by landmarks where given, else from the
    model of the landmarked instances, else from the frames.

    Instances with landmarks are coated by them (paper 4) when at least two instances have
    landmarks (the template instance and another). The others start from the model of
    those coatings fitted to their surface and relaxed onto it
    (:func:`ssm_addon.fitting.correspondence.start_from_model`, paper 7); when only the template
    instance has landmarks, from the object frames (paper 2). ``study.coating_start``
    records which start each instance had.

    Raises
    ------
    InputError
        The template instance has no landmarks (they name the places carried to every
        instance).
    """
    from ..fitting.correspondence import correspondence_fit_params, starts_from_model

    names = list(study.names if names is None else names)
    with_lm = [n for n in study.names if study.landmarks(n) is not None]
    if study.template_instance not in with_lm:
        raise InputError(f"[correspondence] method = \"model\": the template instance {study.template_instance!r} "
                         "needs landmarks (they name the places carried to every other instance)")
    landmarked = with_lm if len(with_lm) > 1 else []
    # the model of the landmarked instances needs their coatings, asked for or not
    need = [n for n in landmarked if n in names or n not in study.coatings]
    coated = coat_instances(study, names=need, jobs=jobs, cancelled=cancelled, executor=executor) if need else {}
    rest = [n for n in names if n not in landmarked]
    if rest and landmarked:
        cp = study.params.correspondence
        stack = np.stack([(coated.get(n) or study.coatings[n]).points_object for n in landmarked])
        coated.update(starts_from_model(stack, study.template.faces, study.template.points_object,
                                        template_landmark_locations(study), {n: study.volume(n) for n in rest},
                                        fit=correspondence_fit_params(cp),
                                        coating=study.params.coating, template_frame=study.frame(study.template_instance),
                                        jobs=jobs, cancelled=cancelled, executor=executor))
    else:
        coated.update(coat_from_frames(study, rest, jobs=jobs, cancelled=cancelled, executor=executor))
    # each coating's own record: the landmark warp or the model fit, or the object frames
    # where the registration fell back from either
    study.coating_start.update({n: coated[n].fit.start for n in names})
    return {n: coated[n] for n in names}


def refine_correspondence(study: Study, *, jobs: int = 1, progress: ProgressFn = None, cancelled: CancelledFn = None,
                          log: Log = None, executor=None, on_coated: Callable[[str], None] | None = None) -> StageResult:
    """The model method's coating (``[correspondence] method = "model"``), on a copy of ``study``.

    Instances not coated yet get their start (:func:`start_coatings`); then the rounds of
    :func:`ssm_addon.fitting.correspondence.refine_rounds` (the mean shape as template, each
    instance fitted by the model of the others and relaxed onto its surface). ``study`` is
    not changed: the coatings, their starts, the mean-shape template and the rounds come
    back as the coating stage's result (:func:`apply_stage` puts them into a study).
    ``on_coated(name)``: as each round's coating of an instance arrives.
    """
    from ..fitting.correspondence import refine_rounds

    say = log or (lambda _m: None)
    t0 = time.perf_counter()
    missing = [n for n in study.names if n not in study.coatings]
    work = dataclasses.replace(study, coatings=dict(study.coatings), coating_start=dict(study.coating_start),
                               volumes=dict(study.volumes), frames=dict(study.frames), findings=list(study.findings),
                               correspondence_rounds=list(study.correspondence_rounds), timings_s={})
    choice = {}
    # one pool of processes for every step (starts, template choice, rounds)
    with executor_or_local(executor, jobs, len(study.names)) as pool:
        if missing:
            work.coatings.update(start_coatings(work, missing, jobs=jobs, cancelled=cancelled, executor=pool))
            starts = [work.coating_start[n] for n in missing]
            say(f"coating: {starts.count('landmark warp')} by landmarks, {starts.count('model fit')} from the "
                f"landmarked instances' model, {starts.count('object frames')} from the object frames; refining "
                "with the model")
        if study.params.correspondence.template_choice == "medoid":
            work, choice, first_fits = medoid_template(work, jobs=jobs, executor=pool, cancelled=cancelled, log=say)
        else:
            first_fits = {}
        rounds, check = refine_rounds(work, study.params.correspondence, jobs=jobs, progress=progress,
                                      cancelled=cancelled, log=say, executor=pool, on_coated=on_coated,
                                      first_fits=first_fits)
    coated = {n: work.coatings[n] for n in study.names}
    kept = "the start" if check.kept_round == 0 else f"round {check.kept_round}'s coatings"
    say(f"correspondence: {check.stop or 'no rounds'}; kept {kept}; landmark transfer error {check.study_mm:.3f} mm")
    findings = (check_landmark_transfer(check, study.params.quality)
                + check_correspondence_rounds(rounds, check, study.params.correspondence.tolerance_mm))
    result = coating_result(study, coated, {n: work.coating_start.get(n, coated[n].fit.start) for n in coated},
                            time.perf_counter() - t0, template=work.template, rounds=tuple(rounds), check=check,
                            extra_findings=tuple(findings))
    if choice:
        result.product["template_choice"] = choice
        result.product["template_instance"] = work.template_instance
    return result


def population_medoid(study: Study, candidates: Sequence[str]) -> tuple[str, dict[str, float]]:
    """The instance of ``candidates`` whose coating is nearest the mean shape of every coating.

    The coatings are put onto the template instance's by their correspondence (rigidly:
    object frames may disagree by a turn); the distance is the RMS over the points, mm.
    Ties go to the earlier instance in study order.

    Returns
    -------
    (name, {instance: RMS distance from the mean, mm})
    """
    from ..fitting.correspondence import aligned_to

    names = list(study.names)
    points = np.stack([study.coatings[n].points_object for n in names])
    aligned = aligned_to(points, points[names.index(study.template_instance)])
    rms = np.sqrt(((aligned - aligned.mean(axis=0)) ** 2).sum(axis=2).mean(axis=1))
    distance = {n: float(d) for n, d in zip(names, rms)}
    return min(candidates, key=lambda n: (distance[n], names.index(n))), distance


def medoid_template(study: Study, *, jobs: int = 1, executor=None, cancelled: CancelledFn = None,
                    log: Log = None) -> tuple[Study, dict, dict]:
    """The study with its template built again from the population's medoid, when that helps.

    Paper 3.3: a template from one arbitrary instance makes the model depend on it. The
    medoid (:func:`population_medoid`) among the instances with every template landmark
    given is the one most like the mean shape, so every other coating deforms it least.
    Its template (paper 3) is coated onto every instance as the start was (landmarks, or the
    landmarked instances' model), and kept when it lowers the landmark transfer error
    (:func:`ssm_addon.fitting.correspondence.round_helps`: by 1 %, the instances together).

    Returns
    -------
    (the study to refine: a copy with the medoid's template and coatings, or ``study``;
    the record: ``given``, ``medoid``, ``transfer_given_mm``, ``transfer_medoid_mm``, ``kept``;
    the landmarked instances' fits that judged the study returned
    (:func:`ssm_addon.fitting.correspondence.round_fits`), which are its first round's)
    """
    from ..fitting.correspondence import CorrespondenceCheck, correspondence_fit_params, round_fits, round_helps

    say = log or (lambda _m: None)
    wanted = study.template.landmark_locations.names
    complete = [n for n in study.names if study.landmarks(n) is not None
                and set(wanted) <= set(study.landmarks(n).names)]
    if len(complete) < 2 or not len(wanted) or len(study.names) < 3:  # the rounds need 3 instances
        return study, {}, {}
    medoid, distance = population_medoid(study, complete)
    record = {"given": study.template_instance, "medoid": medoid,
              "rms_from_mean_mm": {study.template_instance: distance[study.template_instance], medoid: distance[medoid]}}
    if medoid == study.template_instance:
        say(f"correspondence: the template's instance {medoid} is the population's medoid already")
        return study, {**record, "kept": True}, {}
    check_cancelled(cancelled)
    other = dataclasses.replace(study, template_instance=medoid, coatings={}, coating_start={},
                                volumes=dict(study.volumes), frames=dict(study.frames))
    other.template = make_template(other, cancelled=cancelled)
    other.coatings.update(start_coatings(other, list(other.names), jobs=jobs, cancelled=cancelled, executor=executor))
    fit = correspondence_fit_params(study.params.correspondence)
    landmarked = [n for n in study.names if study.landmarks_object(n)]
    fits = [round_fits(s, landmarked, fit=fit, jobs=jobs, executor=executor, cancelled=cancelled, verb="checked")
            for s in (study, other)]
    before, after = (CorrespondenceCheck.from_landmarks({n: f.transfer for n, f in found.items()}) for found in fits)
    kept = round_helps(after, before)
    record.update(transfer_given_mm=before.study_mm, transfer_medoid_mm=after.study_mm, kept=kept)
    say(f"correspondence: template from the medoid {medoid} ({distance[medoid]:.2f} mm RMS from the mean shape, "
        f"{study.template_instance} {distance[study.template_instance]:.2f} mm): landmark transfer error "
        f"{before.study_mm:.3f} -> {after.study_mm:.3f} mm, {'kept' if kept else 'not kept'}")
    return (other if kept else study), record, fits[1] if kept else fits[0]


# ----------------------------------------------------------------------------- streamed build
@dataclass(frozen=True)
class InstanceJob:
    """Everything a worker needs to import and coat one instance (small and serialisable).

    The worker reads the instance's file itself: paths travel, volumes do not.

    Attributes
    ----------
    spec : InstanceSpec
        Source, label and landmarks (world mm).
    spacing_mm, frame_method : import settings (paper 2).
    shared_file : bool
        The label map holds several instances (read once per worker process).
    template_points, template_faces : the template (object mm of its instance; paper 3).
    template_landmarks_object : (L, 3) mm, the template instance's landmarks ``landmark_names``.
    landmark_names : names used by the landmark warp (eq. 2), in order.
    coating_params, quality_params : parameters.
    """

    spec: InstanceSpec
    spacing_mm: float
    frame_method: str
    shared_file: bool
    template_points: np.ndarray
    template_faces: np.ndarray
    template_landmarks_object: np.ndarray
    landmark_names: tuple
    coating_params: CoatingParams
    quality_params: QualityParams

    def key(self) -> str:
        """The cache key (:mod:`ssm_addon.pipeline.cache`): every input that determines the product."""
        from ..pipeline.cache import digest, file_digest

        spec, qp = self.spec, self.quality_params
        lm = spec.landmarks.subset(self.landmark_names)
        return digest("instance", {"source": file_digest(spec.source), "kind": "volume" if spec.volume_path else "mesh",
                                   "label": spec.label, "mesh_spacing": spec.mesh_spacing_mm},
                      {"names": list(lm.names), "points_world": np.asarray(lm.points_world, float)},
                      {"spacing_mm": self.spacing_mm, "frame": self.frame_method},
                      np.asarray(self.template_points, float), np.asarray(self.template_faces, np.int64),
                      np.asarray(self.template_landmarks_object, float), self.coating_params.to_dict(),
                      {"min_voxels": qp.min_voxels, "max_second_component": qp.max_second_component,
                       "max_landmark_distance_mm": qp.max_landmark_distance_mm})


_LABEL_MAP_MEMO: dict = {}


def _label_map_once(path) -> object:
    """A shared label map, read once per process (the last one kept)."""
    from pathlib import Path

    st = Path(path).stat()
    key = (str(path), st.st_size, st.st_mtime_ns)
    if key not in _LABEL_MAP_MEMO:
        _LABEL_MAP_MEMO.clear()
        _LABEL_MAP_MEMO[key] = read_label_map(path)
    return _LABEL_MAP_MEMO[key]


def coat_from_source(job: InstanceJob):
    """Import one instance from its file and coat the template onto it (paper 2 and 4).

    A pure function of ``job`` (runs in any process or on any Dask worker); the same
    calls as :func:`import_instances` + :func:`coat_instances`, so the numbers are
    identical. Returns an :class:`~ssm_addon.pipeline.cache.InstanceProduct`; the volume is
    dropped when the function returns.
    """
    from ..coating.coating import coat
    from ..meshutil import Mesh
    from ..pipeline.cache import InstanceProduct

    spec, qp = job.spec, job.quality_params
    label_map = None
    if job.shared_file and spec.volume_path is not None:
        try:
            label_map = _label_map_once(spec.volume_path)
        except InputError as err:
            raise InputError(f"instances using {spec.volume_path.name}: {err}") from None
    ov = import_instance(spec, spacing_mm=job.spacing_mm, frame_method=job.frame_method, label_map=label_map)
    findings = check_volume(spec.name, ov, qp)
    check_landmarks_on_surface(spec.name, ov, spec.landmarks, qp,
                               source=str(spec.landmarks_path) if spec.landmarks_path is not None else "")
    lm = ov.frame.to_object(spec.landmarks.subset(job.landmark_names).points_world)
    result = coat(Mesh(job.template_points, job.template_faces), job.template_landmarks_object, ov, lm,
                  params=job.coating_params, name=spec.name)
    return InstanceProduct(name=spec.name, frame=ov.frame, volume_mm3=float(ov.volume_mm3),
                           voxels=int(np.count_nonzero(ov.mask)), coating=result, findings=findings)


def template_key(study: Study) -> str:
    """Cache key of the template: its instance's inputs, the import and template parameters."""
    from ..pipeline.cache import digest, file_digest

    spec = study.instance(study.template_instance)
    lm = spec.landmarks
    return digest("template", {"source": file_digest(spec.source), "label": spec.label,
                               "mesh_spacing": spec.mesh_spacing_mm},
                  {"names": list(lm.names), "points_world": np.asarray(lm.points_world, float)} if lm else None,
                  study.params.template.to_dict())


def stream_instances(study: Study, executor, *, cache=None, progress: ProgressFn = None,
                     cancelled: CancelledFn = None, log: Log = None) -> StageResult:
    """Import, template and coating with bounded memory (the landmarks method).

    Only the template instance's volume is held in this process; every other instance
    is read, framed, resampled and coated by :func:`coat_from_source` on ``executor``
    (:class:`~ssm_addon.base.compute.Executor`) and only its points come back, so memory
    grows with n·N, not with the volumes. With ``cache`` (:class:`~ssm_addon.pipeline.cache.BuildCache`)
    the template and every finished coating are stored at once and taken from there on
    a rerun. ``study`` is not changed: the result (stage ``"coating"``) carries the template,
    the coatings, frames and starts, the import and coating findings, the three stages'
    timings and the counts ``streamed = {"cached": k, "computed": m}``.
    """
    say = log or (lambda _m: None)
    names = list(study.names)
    common = common_landmark_names(study, names)
    tname = study.template_instance
    t0 = time.perf_counter()
    timings, volumes, frames = {}, {}, {}
    tkey = template_key(study) if cache is not None else None
    template = cache.get_template(tkey) if cache is not None else None
    for note in cache.take_notes() if cache is not None else ():
        say(note)
    if template is None:
        tspec = study.instance(tname)
        report(progress, 0.0, f"import: {tname} (template instance)")
        ov = import_instance(tspec, spacing_mm=study.params.template.spacing_mm,
                             frame_method=study.params.template.frame, cancelled=cancelled)
        volumes[tname], frames[tname] = ov, ov.frame
        check_volume(tname, ov, study.params.quality)  # a few voxels is the cause, not the landmarks (its findings
        # are the worker's to report)
        check_landmarks_on_surface(tname, ov, study.landmarks(tname), study.params.quality,
                                   source=str(tspec.landmarks_path) if tspec.landmarks_path is not None else "")
        timings["import"] = time.perf_counter() - t0
        say(f"import: {tname} (the template instance) in {timings['import']:.2f} s; the coating workers read "
            "the other instances")
        t0 = time.perf_counter()
        check_cancelled(cancelled)
        report(progress, 0.05, f"template: from {tname}")
        with_volume = dataclasses.replace(study, volumes={**study.volumes, tname: ov}, frames={**study.frames, **frames})
        template = make_template(with_volume, progress=sub_progress(progress, 0.05, 0.2), cancelled=cancelled)
        if cache is not None:
            cache.put_template(tkey, template)
        say(f"template: {len(template.points_object)} points, {len(template.faces)} triangles, genus "
            f"{genus(len(template.points_object), template.faces)} from {tname} in {time.perf_counter() - t0:.2f} s")
    else:
        say("import: the coating workers read every instance (the template is in the cache)")
        say(f"template: {len(template.points_object)} points from the cache ({tname})")
    timings["template"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    # the template's frame is its instance's object frame (the same numbers as study.frame)
    src = template.frame.to_object(study.landmarks(tname).subset(common).points_world)
    uses = Counter(i.volume_path for i in study.instances if i.volume_path is not None)
    order = sorted(range(len(names)), key=lambda i: (str(study.instances[i].source), i))  # one file's labels together
    jobs = [InstanceJob(spec=study.instances[i], spacing_mm=study.params.template.spacing_mm,
                        frame_method=study.params.template.frame,
                        shared_file=uses.get(study.instances[i].volume_path, 0) > 1,
                        template_points=template.points_object, template_faces=template.faces,
                        template_landmarks_object=src, landmark_names=common, coating_params=study.params.coating,
                        quality_params=study.params.quality) for i in order]
    products: dict = {}
    keys = [job.key() for job in jobs] if cache is not None else [None] * len(jobs)
    todo = []
    for job, key in zip(jobs, keys):
        hit = cache.get_instance(key, job.spec.name, len(template.points_object)) if cache is not None else None
        if hit is not None:
            products[job.spec.name] = hit
        else:
            todo.append((job, key))
    cached = len(products)
    if cache is not None:
        for note in cache.take_notes():
            say(note)
        say(f"coating: {cached} of {len(jobs)} instance(s) taken from the cache {cache.folder}, {len(todo)} to coat")

    def arrived(i, product):
        products[product.name] = product
        if cache is not None:
            cache.put_instance(todo[i][1], product)

    report(progress, 0.2, f"coating: {len(todo)} instance(s) on {executor.describe()}")
    executor.map(coat_from_source, [j for j, _k in todo], on_result=arrived, labels=[j.spec.name for j, _k in todo],
                 verb="coated", progress=sub_progress(progress, 0.2, 1.0), cancelled=cancelled)
    for note in cache.take_notes() if cache is not None else ():
        say(note)
    findings = [f for name in names for f in products[name].findings]
    findings += check_volumes_together({n: products[n].volume_mm3 for n in names}, study.params.quality)
    findings += check_duplicate_instances(instance_sources(study, names),
                                          {n: content_digest(products[n].coating.points_object) for n in names})
    findings = [dataclasses.replace(f, stage="import") for f in findings]
    frames.update({n: products[n].frame for n in names})
    coatings = {n: products[n].coating for n in names}
    check, found = self_check(study, coatings, template=template, frames=frames, executor=executor,
                              cancelled=cancelled)
    result = coating_result(study, coatings, {n: c.fit.start for n, c in coatings.items()}, time.perf_counter() - t0,
                            counts=f"{len(todo)} coated, {cached} from the cache; ", check=check, extra_findings=found)
    counts = {"cached": cached, "computed": len(todo)}
    return dataclasses.replace(
        result, product={**result.product, "template": template, "volumes": volumes, "frames": frames,
                         "streamed": counts},
        findings=tuple(findings) + result.findings, timings_s={**timings, **result.timings_s})


def make_model(study: Study, *, names: Sequence[str] | None = None, progress: ProgressFn = None,
               cancelled: CancelledFn = None) -> ShapeModel:
    """PCA of the coated instances (paper 5, eqs. 4–6), in study order.

    Parameters
    ----------
    names : instances to use (default: every coated instance, in study order).
    """
    if names is None:
        names = [n for n in study.names if n in study.coatings]
    names = list(names)
    missing = [n for n in names if n not in study.coatings]
    if missing:
        raise InputError(f"model: instance(s) not coated yet: {', '.join(missing)}")
    if len(names) < 2:
        raise InputError(f"model: need at least 2 coated instances, have {len(names)}")
    if study.template is None:
        raise InputError("model: no template")
    pts = np.stack([study.coatings[n].points_object for n in names])
    world = np.stack([study.frame(n).to_world(study.coatings[n].points_object) for n in names])
    common = ()
    try:
        common = common_landmark_names(study, names)
    except InputError:
        pass
    params = study_parameters(study, common)
    params["landmark_locations"] = template_landmark_locations(study).to_dict()
    params["fit"] = {n: {k: v for k, v in study.coatings[n].fit.to_dict().items() if k != "time_s"} for n in names}
    mp = study.params.model
    return build_model(pts, study.template.faces, names, instance_points_world=world, alignment=mp.alignment,
                       n_modes=mp.n_modes, variance_fraction=mp.variance_fraction, solver=mp.solver,
                       precision=mp.precision, params=params, progress=progress, cancelled=cancelled)


def template_landmark_locations(study: Study) -> LandmarkLocations:
    """The template instance's landmarks as points of the template mesh (triangle, barycentric).

    With the template's connectivity they are the same points of every coated instance
    and of the mean shape: the landmarks a model knows (``ssm fit --landmarks``) and the
    ones written for every instance. Located once, on the template built from the
    template instance (kept in ``template.landmark_locations`` when the mean shape takes
    its place).
    """
    if study.template is not None and len(study.template.landmark_locations):
        return study.template.landmark_locations
    lm = study.landmarks(study.template_instance)
    if lm is None or study.template is None:
        return LandmarkLocations.none()
    pts = study.frame(study.template_instance).to_object(lm.points_world)
    return LandmarkLocations.locate(lm.names, study.template.points_object, study.template.faces, pts)


def carried_landmarks(study: Study) -> dict[str, LandmarkSet]:
    """The template instance's landmarks carried over to every coated instance (world mm).

    Each landmark is a fixed point of the template's triangles
    (:func:`template_landmark_locations`); on an instance it is that point of the
    instance's coating, in the instance's file-world frame. These are the landmarks a
    build writes for review (``landmarks/<name>.<ext>``), also for instances that had none.
    """
    loc = template_landmark_locations(study)
    if not len(loc):
        return {}
    out = {}
    for name in study.names:
        if name not in study.coatings:
            continue
        pts = study.frame(name).to_world(loc.evaluate(study.coatings[name].points_object, study.template.faces))
        out[name] = LandmarkSet(loc.names, pts, f"{name} (carried over by the coating)")
    return out


def landmark_distances(study: Study, carried: dict[str, LandmarkSet]) -> dict[str, dict[str, float]]:
    """Per instance with given landmarks: distance (mm) of each carried-over landmark to the given one."""
    out = {}
    for name, lm in carried.items():
        given = study.landmarks(name)
        if given is None:
            continue
        g = given.as_dict()
        out[name] = {n: float(np.linalg.norm(p - g[n])) for n, p in zip(lm.names, lm.points_world) if n in g}
    return out


def evaluate_model(study: Study, *, progress: ProgressFn = None, cancelled: CancelledFn = None) -> ModelMetrics:
    """Compactness, generalization and specificity of the study's model."""
    from ..model import metrics

    if study.model is None:
        raise InputError("metrics: build the model first")
    mp = study.params.model
    return metrics.evaluate(study.model, n_samples=mp.specificity_samples, seed=mp.seed, max_loo=mp.max_loo,
                            progress=progress, cancelled=cancelled)


# ----------------------------------------------------------------------------- stage results
@dataclass(frozen=True)
class StageResult:
    """What one stage made: its product, its quality findings, its time and its summary.

    Both front ends apply the same result: the command line with :func:`apply_stage` and
    its log, Blender by writing the product into the scene and the findings into the
    panel (``operators/scene.record_findings``), so both show the same findings.

    Attributes
    ----------
    stage : str
        One of :data:`STAGES` (a streamed build's result is ``"coating"`` and covers three).
    product : dict
        The study fields the stage sets (``volumes``, ``template``, ``coatings``, ...);
        dict-valued fields are merged into the study's, ``correspondence_rounds`` extended.
    findings : tuple of Finding
        The stage's failed quality gates (:mod:`ssm_addon.model.quality`).
    timings_s : dict
        Wall time (s) per stage.
    summary : tuple of str
        The stage's summary lines (what the command line prints after the findings).
    """

    stage: str
    product: dict
    findings: tuple = ()
    timings_s: dict = field(default_factory=dict)
    summary: tuple[str, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, "findings", tuple(f if f.stage else dataclasses.replace(f, stage=self.stage)
                                                   for f in self.findings))

    def lines(self) -> list[str]:
        """The log lines of the result: one ``WARNING`` per finding, then the summary."""
        return [f"WARNING {f.instance or 'study'} [{f.gate}]: {f.message}" for f in self.findings] + list(self.summary)


def apply_stage(study: Study, result: StageResult) -> Study:
    """Put a stage's product, findings and timings into ``study`` (in place) and return it.

    A finding replaces an earlier one of the same instance and gate.
    """
    for key, value in result.product.items():
        if key == "correspondence_rounds":
            study.correspondence_rounds = list(study.correspondence_rounds) + list(value)
        elif isinstance(getattr(study, key), dict):
            getattr(study, key).update(value)
        else:
            setattr(study, key, value)
    keep = {(f.instance, f.gate) for f in result.findings}
    study.findings = [f for f in study.findings if (f.instance, f.gate) not in keep] + list(result.findings)
    study.timings_s.update(result.timings_s)
    return study


def merge_findings(recorded: Sequence[Finding], result: StageResult) -> list[Finding]:
    """Findings kept across runs of single stages (Blender): ``recorded`` updated by ``result``.

    A stage's result replaces the earlier findings of that stage for the instances it
    covers (the volumes or coatings it made; every instance for the template, model and
    metrics), so an instance coated again without a problem loses its old coating finding.
    """
    product = result.product
    covered = set(product.get("coatings", {})) | set(product.get("volumes", {}))
    if result.stage not in ("import", "coating"):
        covered = None

    def replaced(f: Finding) -> bool:
        return f.stage == result.stage and (covered is None or f.instance in covered or not f.instance)

    return [f for f in recorded if not replaced(f)] + list(result.findings)


def instance_sources(study: Study, names) -> dict[str, tuple]:
    """``{name: (file, label)}`` of instances: what makes two of them the same input."""
    out = {}
    for n in names:
        spec = study.instance(n)
        path = spec.volume_path if spec.volume_path is not None else spec.mesh_path
        out[n] = (str(Path(path).resolve()) if path is not None else f"<{n}>", spec.label)
    return out


def import_result(study: Study, volumes: dict[str, ObjectVolume], seconds: float) -> StageResult:
    """The import stage's result for ``volumes`` just imported: the import gates on them.

    The volume-consistency gate compares every instance imported so far (``study.volumes``
    and ``volumes``).
    """
    qp = study.params.quality
    findings = [f for name, ov in volumes.items() for f in check_volume(name, ov, qp)]
    every = {**study.volumes, **volumes}
    findings += check_volumes_together({n: every[n].volume_mm3 for n in study.names if n in every}, qp)
    names = [n for n in study.names if n in every]
    findings += check_duplicate_instances(instance_sources(study, names),
                                          {n: content_digest(every[n].mask, every[n].frame.matrix_world) for n in names})
    return StageResult("import", {"volumes": dict(volumes), "frames": {n: v.frame for n, v in volumes.items()}},
                       tuple(findings), {"import": seconds}, (f"import: {len(volumes)} instances in {seconds:.2f} s",))


def import_stage(study: Study, *, names: Sequence[str] | None = None, jobs: int = 1, progress: ProgressFn = None,
                 cancelled: CancelledFn = None) -> StageResult:
    """Import (paper 2): :func:`import_instances` and the import gates."""
    t0 = time.perf_counter()
    volumes = import_instances(study, names=names, jobs=jobs, progress=progress, cancelled=cancelled)
    return import_result(study, volumes, time.perf_counter() - t0)


def template_stage(study: Study, *, progress: ProgressFn = None, cancelled: CancelledFn = None) -> StageResult:
    """The template (paper 3): :func:`make_template` and its summary line."""
    t0 = time.perf_counter()
    t = make_template(study, progress=progress, cancelled=cancelled)
    seconds = time.perf_counter() - t0
    return StageResult("template", {"template": t}, (), {"template": seconds},
                       (f"template: {len(t.points_object)} points, {len(t.faces)} triangles, "
                        f"genus {genus(len(t.points_object), t.faces)} from {study.template_instance} in "
                        f"{seconds:.2f} s",))


def coating_result(study: Study, coated: dict[str, CoatingResult], starts: dict[str, str], seconds: float, *,
                   template: Template | None = None, rounds: tuple = (), counts: str = "", check=None,
                   extra_findings: tuple = ()) -> StageResult:
    """The coating stage's result for ``coated`` instances: the coating gates and the summary.

    ``template`` (the mean shape of the model method), ``rounds`` (its refinement rounds)
    and ``check`` (the correspondence self-check, :func:`self_check`) join the product
    when given; ``extra_findings`` (the self-check's and the rounds' gates) the findings.
    """
    findings = tuple(f for n, c in coated.items() for f in check_coating(n, c.fit, study.params.quality))
    findings += tuple(extra_findings)
    product = {"coatings": dict(coated), "coating_start": dict(starts)}
    if template is not None:
        product["template"] = template
    if rounds:
        product["correspondence_rounds"] = tuple(rounds)
    if check is not None:
        product["correspondence_check"] = check
    every = {**study.coatings, **coated}
    worst = max((c.fit.max_distance_mm for c in every.values()), default=float("nan"))
    lines = [f"coating: {len(coated)} instances in {seconds:.2f} s ({counts}largest surface distance {worst:.2f} mm)"]
    if check is not None and check.instance_mm:
        worst_n = max(check.instance_mm, key=check.instance_mm.get)
        lines.append(f"coating: correspondence self-check, landmark transfer error {check.study_mm:.2f} mm (mean over "
                     f"{len(check.instance_mm)} landmarked instances; largest {worst_n} "
                     f"{check.instance_mm[worst_n]:.2f} mm)")
    return StageResult("coating", product, findings, {"coating": seconds}, tuple(lines))


def self_check(study: Study, coatings: dict[str, CoatingResult], *, template: Template | None = None,
               frames: dict | None = None, jobs: int = 1, executor=None, cancelled: CancelledFn = None):
    """The correspondence self-check of the single pass (``[correspondence] self_check``):
    :func:`ssm_addon.fitting.correspondence.check_correspondence` on every instance's coating.

    Returns ``(CorrespondenceCheck, findings)``, or ``(None, ())`` when it does not apply
    (switched off, fewer than 3 instances or instances not all coated, no landmarks).
    """
    from ..fitting.correspondence import check_correspondence, correspondence_fit_params
    from ..model.quality import check_landmark_transfer

    template = template or study.template
    names = list(study.names)
    if (not study.params.correspondence.self_check or len(names) < 3 or template is None
            or any(n not in coatings for n in names)):
        return None, ()
    frames = {**study.frames, **(frames or {})}
    given = {n: study.landmarks_object(n, frames.get(n)) for n in names}
    fit = correspondence_fit_params(study.params.correspondence)
    check = check_correspondence({n: coatings[n].points_object for n in names}, template.faces,
                                 template.landmark_locations, given, fit=fit, executor=executor, jobs=jobs,
                                 cancelled=cancelled)
    return check, tuple(check_landmark_transfer(check, study.params.quality))


def coating_stage(study: Study, *, names: Sequence[str] | None = None, jobs: int = 1, progress: ProgressFn = None,
                  cancelled: CancelledFn = None, log: Log = None, executor=None,
                  on_coated: Callable[[str], None] | None = None) -> StageResult:
    """Coating (paper 4) by the study's correspondence method, and the coating gates.

    ``method = "landmarks"``: :func:`coat_instances` (the paper's single pass, ``names``);
    ``"model"``: :func:`refine_correspondence` (every instance). ``on_coated(name)`` is
    called as each coating arrives (for counting; progress lines are for people).
    """
    if study.params.correspondence.method != "landmarks":
        return refine_correspondence(study, jobs=jobs, progress=progress, cancelled=cancelled, log=log,
                                     executor=executor, on_coated=on_coated)
    t0 = time.perf_counter()
    coated = coat_instances(study, names=names, jobs=jobs, progress=progress, cancelled=cancelled,
                            on_coated=on_coated)
    check, found = self_check(study, {**study.coatings, **coated}, jobs=jobs, executor=executor, cancelled=cancelled)
    return coating_result(study, coated, {n: c.fit.start for n, c in coated.items()}, time.perf_counter() - t0,
                          check=check,
                          extra_findings=found)


def model_stage(study: Study, *, progress: ProgressFn = None, cancelled: CancelledFn = None) -> StageResult:
    """The model (paper 5): :func:`make_model`, its leave-one-out outlier scores and the model gates."""
    t0 = time.perf_counter()
    model = make_model(study, progress=progress, cancelled=cancelled)
    findings, scores = check_model(model, study.params.quality)
    names = list(model.instance_names)
    findings = check_frames(names, np.stack([study.coatings[n].points_object for n in names]),
                            study.template_instance, study.params.model.alignment) + list(findings)
    seconds = time.perf_counter() - t0
    return StageResult("model", {"model": model, "outlier_scores": scores}, tuple(findings), {"model": seconds},
                       (f"model: {model.n_modes} modes, {model.n_points} points in {seconds:.2f} s",))


def metrics_stage(study: Study, *, progress: ProgressFn = None, cancelled: CancelledFn = None) -> StageResult:
    """Compactness, generalization and specificity (:func:`evaluate_model`)."""
    t0 = time.perf_counter()
    metrics = evaluate_model(study, progress=progress, cancelled=cancelled)
    seconds = time.perf_counter() - t0
    return StageResult("metrics", {"metrics": metrics}, (), {"metrics": seconds},
                       (f"metrics: compactness, generalization, specificity in {seconds:.2f} s",))


def run(study: Study, *, stages: Sequence[str] = STAGES, jobs: int = 1, progress: ProgressFn = None,
        cancelled: CancelledFn = None, log: Log = None, executor=None, cache=None) -> Study:
    """Run ``stages`` in order on ``study``, applying each stage's result, and return it.

    Progress: import 0–15 %, template 15–30 %, coating 30–85 %, model 85–90 %, metrics
    90–95 % of ``progress``; ``log`` receives each result's lines (:meth:`StageResult.lines`).

    With an ``executor`` (:class:`~ssm_addon.base.compute.Executor`), the landmarks method
    and the import, template and coating stages all asked for, those stages run streamed
    (:func:`stream_instances`: bounded memory, ``cache`` for resuming); the numbers are
    the same. ``study.streamed`` then holds the cache counts.
    """
    say = log or (lambda _m: None)
    n = len(study.instances)
    unknown = [s for s in stages if s not in STAGES]
    if unknown:
        raise InputError(f"study: unknown stage(s) {', '.join(unknown)} (stages: {', '.join(STAGES)})")

    def applied(result: StageResult) -> None:
        apply_stage(study, result)
        for line in result.lines():
            say(line)

    if (executor is not None and study.params.correspondence.method == "landmarks"
            and all(s in stages for s in ("import", "template", "coating"))):
        report(progress, 0.0, f"import, template and coating: {n} instances on {executor.describe()}")
        applied(stream_instances(study, executor, cache=cache, progress=sub_progress(progress, 0.0, 0.85),
                                 cancelled=cancelled, log=say))
        stages = [s for s in stages if s not in ("import", "template", "coating")]
    if "import" in stages:
        report(progress, 0.0, f"import: {n} instances at {study.params.template.spacing_mm:g} mm")
        applied(import_stage(study, jobs=jobs, progress=sub_progress(progress, 0.0, 0.15), cancelled=cancelled))
    if "template" in stages:
        check_cancelled(cancelled)
        report(progress, 0.15, f"template: from {study.template_instance}")
        applied(template_stage(study, progress=sub_progress(progress, 0.15, 0.3), cancelled=cancelled))
    if "coating" in stages:
        check_cancelled(cancelled)
        report(progress, 0.3, f"coating: {n} instances, {jobs} job(s)")
        coat_prog = sub_progress(progress, 0.3, 0.85)
        if study.params.correspondence.method == "landmarks":  # one progress line per instance, as it arrives
            t0, arrived = time.perf_counter(), []

            def coated(name: str) -> None:
                arrived.append(name)
                left = time_left_text(len(arrived), n, time.perf_counter() - t0)
                report(coat_prog, len(arrived) / n, f"coated {name} ({len(arrived)}/{n})" + (f", {left}" if left else ""))

            applied(coating_stage(study, jobs=jobs, cancelled=cancelled, log=say, executor=executor,
                                  on_coated=coated if progress else None))
        else:
            applied(coating_stage(study, jobs=jobs, progress=coat_prog, cancelled=cancelled, log=say,
                                  executor=executor))
    if "model" in stages:
        check_cancelled(cancelled)
        report(progress, 0.85, "model: PCA")
        applied(model_stage(study, cancelled=cancelled))
    if "metrics" in stages:
        check_cancelled(cancelled)
        report(progress, 0.9, "metrics: compactness, generalization, specificity")
        applied(metrics_stage(study, cancelled=cancelled))
    return study
