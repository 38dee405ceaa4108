"""The coating stage by the model method (``[correspondence] method = "model"``): the starts,
the medoid template and the rounds of :mod:`ssm_addon.correspondence` on a study (paper 3.3, 7)."""

from __future__ import annotations

import contextlib
import dataclasses
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import wait
from contextlib import contextmanager

import numpy as np

from ..base.compute import executor_or_local
from ..base.errors import Cancelled, InputError, SSMError, check_cancelled
from ..base.progress import CancelledFn, ProgressFn
from ..coating.coating import CoatingResult, CoatingStart
from ..coating.distance_map import DistanceMap
from ..correspondence.frames import (
    TURN_NAMES,
    TURNED_FACTOR,
    FramesStart,
    nearest_frame_rotation,
    population_turns,
)
from ..correspondence.frames import coat_without_landmarks as frames_coat
from ..correspondence.rounds import (
    CorrespondenceCheck,
    Population,
    aligned_to,
    correspondence_fit_params,
    refine_rounds,
    round_fits,
    round_helps,
    starts_from_model,
)
from ..fitting.fit import weighted_pose
from ..meshutil import Mesh
from ..model.quality import (
    Finding,
    check_correspondence_rounds,
    check_landmark_transfer,
)
from .stages import coat_from_frames, coat_instances, coating_result, make_template
from .study import Log, StageResult, Study, template_landmark_locations

#: The landmark medoid is confirmed when its RMS distance from the mean shape of its own
#: coatings is at most this many times the nearest instance's (a near tie is a tie: the mean
#: shape is an estimate, and the coatings' distances differ by a few per cent between templates)
MEDOID_TIE = 1.05
#: Without landmarks the medoid's template replaces the given one only when the given instance lies
#: more than this many times as far from the mean shape of the first coatings: those distances carry
#: the coatings' own error and rank near ties wrongly (``docs/history.md``, "The template from the
#: medoid without landmarks")
NO_LANDMARK_TIE = 1.10

__all__ = ["MEDOID_TIE", "NO_LANDMARK_TIE", "POINT_COUNT_TOLERANCE", "coat_without_landmarks_stage", "template_of_count", "confirmed_landmark_medoid", "landmarked", "distance_maps_ahead", "distance_maps_kept", "keep_distance_map", "landmark_medoid", "landmark_medoid_template",
           "medoid_template", "medoid_without_landmarks", "population", "population_medoid", "refine_correspondence", "start_coatings"]


def start_coatings(study: Study, names: Sequence[str] | None = None, *, jobs: int = 1,
                   cancelled: CancelledFn = None, executor=None) -> dict[str, CoatingResult]:
    """The first coatings of the model method: by landmarks where given, else from the
    model of the landmarked instances, else from the frames.

    Instances with landmarks are coated by them (paper 4) when at least two instances have
    landmarks (the template instance and another). The others start from the model of
    those coatings fitted to their surface and relaxed onto it
    (:func:`ssm_addon.correspondence.rounds.start_from_model`, paper 7); when only the template
    instance has landmarks, from the object frames (paper 2). ``study.coating_start``
    records which start each instance had.

    Raises
    ------
    InputError
        The template instance has no landmarks (they name the places carried to every
        instance).
    """
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
        try:
            coated.update(starts_from_model(stack, study.template.faces, study.template.points_object,
                                            template_landmark_locations(study), {n: study.volume(n) for n in rest},
                                            fit=correspondence_fit_params(cp), coating=study.params.coating,
                                            template_frame=study.frame(study.template_instance), jobs=jobs,
                                            cancelled=cancelled, executor=executor))
        except Cancelled:
            raise
        except SSMError as err:  # an optional refinement falls back, it does not fail the build
            study.fallbacks.append(Finding("", "fallback", f"the starts from the landmarked instances' model failed "
                                           f"({err}); {len(rest)} instance(s) start from the object frames"))
            coated.update(coat_from_frames(study, rest, jobs=jobs, cancelled=cancelled, executor=executor))
    else:
        coated.update(coat_from_frames(study, rest, jobs=jobs, cancelled=cancelled, executor=executor))
        if rest:  # from the frames alone: a coating the population disagrees with tried in the other turns
            coated.update(_turned_back(study, coated, rest, jobs=jobs, executor=executor, cancelled=cancelled))
    # each coating's own record: the landmark warp or the model fit, or the object frames
    # where the registration fell back from either
    study.coating_start.update({n: coated[n].fit.start for n in names})
    return {n: coated[n] for n in names}


def _turned_back(study: Study, coated: dict, rest: Sequence[str], *, jobs: int = 1, executor=None,
                 cancelled: CancelledFn = None) -> dict:
    """Coatings from the object frames (``rest``) that lie far from the population's mean shape,
    coated again from the turns of the template's axes and kept when nearer
    (:func:`~ssm_addon.correspondence.frames.population_turns`); the changed ones, each with a
    fallback-style note in ``study.fallbacks``."""
    template = Mesh(study.template.points_object, study.template.faces)
    every = {n: (c, FramesStart("frames", {}, 1.0)) for n, c in coated.items()}
    if study.template_instance not in every and study.template_instance in study.coatings:
        every[study.template_instance] = (study.coatings[study.template_instance], FramesStart("frames", {}, 1.0))
    if study.template_instance not in every or len(every) < 3:
        return {}

    def retry(suspects):
        suspects = [n for n in suspects if n in rest]
        return frames_coat(template, {n: study.volume(n) for n in suspects}, coating=study.params.coating,
                           template_frame=None, turns={n: tuple(range(1, len(TURN_NAMES))) for n in suspects}, jobs=jobs, executor=executor,
                           cancelled=cancelled)

    kept, changed, _unresolved = population_turns(every, study.template_instance, retry)
    for n, (before, after) in changed.items():
        study.fallbacks.append(Finding(n, "turned", f"its start from the object frames lay {before:.1f} mm from the "
                                                    f"others' mean shape: coated again {kept[n][1].turn} "
                                                    f"({after:.1f} mm)"))
    return {n: kept[n][0] for n in changed}


def refine_correspondence(study: Study, *, jobs: int = 1, progress: ProgressFn = None, cancelled: CancelledFn = None,
                          log: Log = None, executor=None, on_coated: Callable[[str], None] | None = None) -> StageResult:
    """The model method's coating (``[correspondence] method = "model"``), on a copy of ``study``.

    Instances not coated yet get their start (:func:`start_coatings`); then the rounds of
    :func:`ssm_addon.correspondence.rounds.refine_rounds` (the mean shape as template, each
    instance fitted by the model of the others and relaxed onto its surface). ``study`` is
    not changed: the coatings, their starts, the mean-shape template and the rounds come
    back as the coating stage's result (:func:`apply_stage` puts them into a study).
    ``on_coated(name)``: as each round's coating of an instance arrives.
    """
    say = log or (lambda _m: None)
    t0 = time.perf_counter()
    missing = [n for n in study.names if n not in study.coatings]
    work = dataclasses.replace(study, coatings=dict(study.coatings), coating_start=dict(study.coating_start),
                               volumes=dict(study.volumes), frames=dict(study.frames), findings=list(study.findings),
                               correspondence_rounds=list(study.correspondence_rounds), timings_s={}, fallbacks=[])
    choice, first_fits = {}, {}
    template_choice = study.params.correspondence.template_choice
    # one pool of processes for every step (starts, template choice, rounds); each instance's
    # distance map computed once and read by its later coatings
    with executor_or_local(executor, jobs, len(study.names)) as pool, distance_maps_kept(work):
        if template_choice == "landmark-medoid":
            work, choice = landmark_medoid_template(work, cancelled=cancelled, log=say)
        elif template_choice == "medoid":
            work, choice = confirmed_landmark_medoid(work, jobs=jobs, executor=pool, cancelled=cancelled, log=say)
        if missing:
            if any(n not in work.coatings for n in missing):
                work.coatings.update(start_coatings(work, missing, jobs=jobs, cancelled=cancelled, executor=pool))
            starts = [work.coating_start[n] for n in missing]
            say(f"coating: {starts.count('landmark warp')} by landmarks, {starts.count('model fit')} from the "
                f"landmarked instances' model, {starts.count('object frames')} from the object frames; refining "
                "with the model")
        if template_choice == "medoid" and not choice.get("confirmed"):
            work, route, first_fits = medoid_template(work, jobs=jobs, executor=pool, cancelled=cancelled, log=say)
            choice = route | ({"landmark_medoid": choice} if choice else {})
        refined = population(work)
        try:
            rounds, check = refine_rounds(refined, study.params.correspondence, jobs=jobs, progress=progress,
                                          cancelled=cancelled, log=say, executor=pool, on_coated=on_coated,
                                          first_fits=first_fits)
            work.coatings, work.template = refined.coatings, refined.template
        except Cancelled:
            raise
        except SSMError as err:  # the rounds are a refinement: the start's coatings stay
            rounds, check = [], CorrespondenceCheck(stop="failed")
            work.fallbacks.append(Finding("", "fallback", f"the model method's rounds failed ({err}); the start's "
                                          "coatings are kept (where every instance has landmarks: the paper's single "
                                          "pass)"))
        for f in work.fallbacks:  # a start turned back is said, not a finding (it was mended)
            say(f"correspondence: {f.instance} {f.message}" if f.gate == "turned" else
                f"WARNING {f.instance or 'study'} [{f.gate}]: {f.message}")
        coated = {n: work.coatings[n] for n in study.names}
        kept = "the start" if check.kept_round == 0 else f"round {check.kept_round}'s coatings"
        say(f"correspondence: {check.stop or 'no rounds'}; kept {kept}; landmark transfer error {check.study_mm:.3f} mm")
        findings = (check_landmark_transfer(check, study.params.quality)
                    + check_correspondence_rounds(rounds, check, study.params.correspondence.tolerance_mm)
                    + [f for f in work.fallbacks if f.gate != "turned"])
        # (the input meshes are measured against their coatings on the same pool)
        result = coating_result(study, coated, {n: work.coating_start.get(n, coated[n].fit.start) for n in coated},
                                time.perf_counter() - t0, template=work.template, rounds=tuple(rounds), check=check,
                                extra_findings=tuple(findings), executor=pool, cancelled=cancelled)
    if choice:
        result.product["template_choice"] = choice
        result.product["template_instance"] = work.template_instance
    return result


@contextmanager
def distance_maps_kept(study: Study) -> Iterator[str]:
    """For the time of the block, the study's volumes name a new scratch folder (yielded) in
    which each instance's distance map is kept when first computed and read by the
    instance's later coatings (the model method coats every instance two or three times:
    the start, the medoid's template, the rounds). After the block the study has its own
    volumes back and the folder is removed with the maps in it.

    The maps read back are the arrays computed (:meth:`~ssm_addon.coating.distance_map.DistanceMap.from_object_volume`),
    so the coatings are the same as without the folder; a worker on another machine
    (Dask) does not see the folder and computes its maps as before. Volumes that all name one
    folder already (:func:`distance_maps_ahead`'s) keep it, and it is left to its owner.
    """
    stores = {v.distance_map_store for v in study.volumes.values()}
    if len(stores) == 1 and all(stores):  # the caller's folder (distance_maps_ahead)
        yield next(iter(stores))
        return
    folder = tempfile.mkdtemp(prefix="ssm-distance-maps-")
    given = dict(study.volumes)
    study.volumes.update({n: dataclasses.replace(v, distance_map_store=folder) for n, v in given.items()})
    try:
        yield folder
    finally:
        study.volumes.update(given)
        shutil.rmtree(folder, ignore_errors=True)


def keep_distance_map(volume) -> None:
    """Compute an instance's distance map into the folder its volume names (paper 4.2; read there by
    its coatings, :func:`distance_maps_kept`); nothing comes back."""
    DistanceMap.from_object_volume(volume)


@contextmanager
def distance_maps_ahead(study: Study, executor) -> Iterator[None]:
    """:func:`distance_maps_kept` for the template stage and the model method's coating after it,
    with every instance's distance map computed meanwhile on ``executor``'s local workers, which
    are idle while this process builds the template; the coatings then read them.

    Only for local processes (:meth:`~ssm_addon.base.compute.Executor.submit`) and a study with
    its volumes imported; otherwise the block runs as it is. The maps are the arrays the
    coatings would compute, so the model is the same; on leaving, maps not begun are dropped and
    those being computed are waited for before the folder is removed.
    """
    if executor is None or executor.scheduler != "processes" or len(study.volumes) < 2:
        yield
        return
    with distance_maps_kept(study):
        futures = [executor.submit(keep_distance_map, study.volumes[n]) for n in study.names if n in study.volumes]
        try:
            yield
        finally:
            for future in futures:
                future.cancel()
            wait(futures)


def _candidates(study: Study) -> list[str]:
    """The medoids' candidates: the instances with every template landmark given; none when a
    choice of the template does not apply (no template landmarks, fewer than 2 candidates or 3
    instances: the rounds need 3)."""
    wanted = set(study.template.landmark_locations.names)
    complete = [n for n in study.names if study.landmarks(n) is not None and wanted <= set(study.landmarks(n).names)]
    return complete if wanted and len(complete) >= 2 and len(study.names) >= 3 else []


def _from_template_of(study: Study, instance: str, *, fallbacks: list, coat: bool, jobs: int = 1, executor=None,
                      cancelled: CancelledFn = None) -> Study:
    """A copy of ``study`` with the template built from ``instance`` (paper 3) and, with
    ``coat``, every instance's start coated from it (:func:`start_coatings`); raises what they raise."""
    other = dataclasses.replace(study, template_instance=instance, coatings={}, coating_start={},
                                volumes=dict(study.volumes), frames=dict(study.frames), fallbacks=fallbacks)
    other.template = template_of_count(other, len(study.template.points_object) if study.template is not None else 0,
                                       cancelled=cancelled)
    if coat:
        other.coatings.update(start_coatings(other, list(other.names), jobs=jobs, cancelled=cancelled,
                                             executor=executor))
    return other


#: The template from another instance keeps the given template's point count within this share
POINT_COUNT_TOLERANCE = 0.02
POINT_COUNT_TRIES = 4


def template_of_count(study: Study, count: int, *, cancelled: CancelledFn = None):
    """The template (paper 3) of the study's template instance with ``count`` points (within
    :data:`POINT_COUNT_TOLERANCE`; 0: as the parameters give it).

    The same parameters give another instance of the population another number of points (eq. 1
    follows its curvature; on real femurs 2,939 against 4,079): a template from the medoid would
    then sample every instance more coarsely or finely than the given one. The radii of eq. (1)
    (``r_min_mm``, ``r_max_mm``) are scaled by the square root of the ratio of the counts, the
    topology cleaning's radius kept at the parameters' own, until the count is within the
    tolerance (at most :data:`POINT_COUNT_TRIES` templates; the nearest is kept). The study's
    parameters, and so the report's, are unchanged.

    With a tolerance (``[template] max_distance_mm``) the count is the one the tolerance gives on
    this instance's surface: the template's triangles keep within it there, which a count taken
    from another instance would break (lumbar vertebrae: 1,411 points matched to the given
    template's 1,422 reached 1.05 mm, against 1.00 at their own count).
    """
    tp = study.params.template
    template = make_template(study, cancelled=cancelled)
    if count <= 0 or tp.max_distance_mm is not None:
        return template
    best = template
    fixed = dataclasses.replace(tp, topology_radius_mm=tp.topology_radius_mm if tp.topology_radius_mm is not None
                                else tp.r_min_mm)
    factor = 1.0
    for _ in range(POINT_COUNT_TRIES - 1):
        have = len(template.points_object)
        if abs(have / count - 1.0) <= POINT_COUNT_TOLERANCE:
            break
        check_cancelled(cancelled)
        factor *= float(np.sqrt(have / count))
        scaled = dataclasses.replace(fixed, r_min_mm=tp.r_min_mm * factor, r_max_mm=tp.r_max_mm * factor)
        template = make_template(study, cancelled=cancelled, params=scaled)
        if abs(len(template.points_object) - count) < abs(len(best.points_object) - count):
            best = template
    return best


def _points(study: Study, other: Study) -> dict:
    """The point counts of the given template and of ``other``'s (the medoid's)."""
    return {"given": int(len(study.template.points_object)), "medoid": int(len(other.template.points_object))}


def _points_note(study: Study, other: Study) -> str:
    p = _points(study, other)
    return f"; {p['medoid']} points, the given template {p['given']}"


def population_medoid(study: Study, candidates: Sequence[str]) -> tuple[str, dict[str, float]]:
    """The instance of ``candidates`` whose coating is nearest the mean shape of every coating.

    The coatings are put onto the template instance's by their correspondence (rigidly:
    object frames may disagree by a turn); the distance is the RMS over the points, mm.
    Ties go to the earlier instance in study order.

    Returns
    -------
    (name, {instance: RMS distance from the mean, mm})
    """
    names = list(study.names)
    points = np.stack([study.coatings[n].points_object for n in names])
    aligned = aligned_to(points, points[names.index(study.template_instance)])
    rms = np.sqrt(((aligned - aligned.mean(axis=0)) ** 2).sum(axis=2).mean(axis=1))
    distance = {n: float(d) for n, d in zip(names, rms)}
    return min(candidates, key=lambda n: (distance[n], names.index(n))), distance


def landmark_medoid(study: Study, candidates: Sequence[str]) -> tuple[str, dict[str, float]]:
    """The instance of ``candidates`` whose given landmarks are nearest their mean configuration.

    The candidates' landmarks named by the template (each candidate has all of them), in
    their object frames, put onto the template instance's by their names (rigidly: object
    frames may disagree by a turn); the distance is the RMS over the landmarks, mm. Ties go
    to the earlier instance in study order.

    Returns
    -------
    (name, {candidate: RMS distance from the mean configuration, mm})
    """
    wanted = study.template.landmark_locations.names
    names = [n for n in study.names if n in set(candidates)]
    points = np.stack([[study.landmarks_object(n)[k] for k in wanted] for n in names])
    aligned = aligned_to(points, points[names.index(study.template_instance)] if study.template_instance in names
                         else points[0])
    rms = np.sqrt(((aligned - aligned.mean(axis=0)) ** 2).sum(axis=2).mean(axis=1))
    distance = {n: float(d) for n, d in zip(names, rms)}
    return min(names, key=lambda n: (distance[n], names.index(n))), distance


def landmark_medoid_template(study: Study, *, cancelled: CancelledFn = None, log: Log = None) -> tuple[Study, dict]:
    """The study with its template built from the landmark medoid (:func:`landmark_medoid`),
    before any instance is coated (``template_choice = "landmark-medoid"``).

    Paper 3.3: a template from one arbitrary instance makes the model depend on it. Here the
    instance most like the others is chosen by its given landmarks alone, so the start is
    coated once, from that instance's template; ``"medoid"`` chooses by the start's coatings
    and coats every instance a second time to compare. Nothing changes when an instance is
    coated already, fewer than 3 instances or 2 with every template landmark are given, or
    the medoid's template fails (a fallback finding).

    Returns
    -------
    (the study to coat: a copy with the medoid's template, or ``study``; the record:
    ``given``, ``medoid``, ``by`` ("landmarks"), ``rms_from_mean_mm`` and ``kept``)
    """
    say = log or (lambda _m: None)
    complete = _candidates(study)
    if not complete:
        return study, {}
    if study.coatings:
        say(f"correspondence: {len(study.coatings)} instance(s) coated already: the template of "
            f"{study.template_instance} is kept (template_choice = \"landmark-medoid\" chooses before the first coating)")
        return study, {}
    medoid, distance = landmark_medoid(study, complete)
    record = {"given": study.template_instance, "medoid": medoid, "by": "landmarks",
              "rms_from_mean_mm": {n: distance[n] for n in dict.fromkeys((study.template_instance, medoid))
                                   if n in distance}}
    if medoid == study.template_instance:
        say(f"correspondence: the template's instance {medoid} has the landmarks nearest their mean already")
        return study, {**record, "kept": True}
    check_cancelled(cancelled)
    try:
        other = _from_template_of(study, medoid, fallbacks=list(study.fallbacks), coat=False, cancelled=cancelled)
    except Cancelled:
        raise
    except SSMError as err:  # the medoid's template is a refinement: the given one stays
        study.fallbacks.append(Finding(medoid, "fallback", f"the landmark medoid {medoid!r} gave no template "
                                       f"({err}); the given template of {study.template_instance!r} is kept"))
        return study, {**record, "kept": False, "failed": str(err)}
    given = distance.get(study.template_instance)
    say(f"correspondence: template from the landmark medoid {medoid} (its landmarks {distance[medoid]:.2f} mm RMS from "
        f"their mean" + (f", {study.template_instance}'s {given:.2f} mm)" if given is not None else ")")
        + _points_note(study, other))
    return other, {**record, "kept": True, "points": _points(study, other)}


def confirmed_landmark_medoid(study: Study, *, jobs: int = 1, executor=None, cancelled: CancelledFn = None,
                              log: Log = None) -> tuple[Study, dict]:
    """The first step of ``template_choice = "medoid"``: the landmark medoid's template, coated
    onto every instance, kept when those coatings confirm it as the population's medoid.

    Paper 3.3 asks for the template from the instance nearest the mean shape, which only the
    coatings tell. The instance whose given landmarks are nearest their mean
    (:func:`landmark_medoid`) is the guess: its template (paper 3) is coated onto every
    instance as the start is (:func:`start_coatings`), and when the medoid of those coatings
    (:func:`population_medoid`) is that instance again, the study is at the paper's choice in
    one coating pass (or when it is within :data:`MEDOID_TIE` of the nearest: a tie).
    Otherwise, or when the landmark medoid is the given instance, an
    instance is coated already, fewer than 3 instances or 2 with every template landmark are
    given, or its template or coatings fail, nothing changes and :func:`medoid_template`
    decides from the given template's coatings (their distance maps are kept, so the pass
    spent here costs them less).

    Returns
    -------
    (the study: a copy with the landmark medoid's template and every coating when confirmed,
    else ``study``; the record: ``given``, ``medoid`` (the landmark medoid), ``by``
    ("landmarks"), ``rms_from_mean_mm`` (of the landmarks, mm), ``coatings_medoid`` and
    ``coatings_rms_from_mean_mm`` (of its coatings' points, mm), ``confirmed``; or ``{}`` when
    it does not apply)
    """
    say = log or (lambda _m: None)
    complete = _candidates(study)
    if not complete or study.coatings:
        return study, {}
    medoid, distance = landmark_medoid(study, complete)
    if medoid == study.template_instance:
        return study, {}
    record = {"given": study.template_instance, "medoid": medoid, "by": "landmarks",
              "rms_from_mean_mm": {n: distance[n] for n in (study.template_instance, medoid) if n in distance}}
    check_cancelled(cancelled)
    try:
        other = _from_template_of(study, medoid, fallbacks=list(study.fallbacks), coat=True, jobs=jobs,
                                  executor=executor, cancelled=cancelled)
    except Cancelled:
        raise
    except SSMError as err:  # a guess: the medoid's route from the given template decides
        say(f"correspondence: the landmark medoid {medoid} gave no template or coatings ({err}); the medoid is "
            "found from the given template's coatings")
        return study, {**record, "confirmed": False, "failed": str(err)}
    found, from_mean = population_medoid(other, complete)
    confirmed = from_mean[medoid] <= MEDOID_TIE * from_mean[found]
    record.update(coatings_medoid=found, coatings_rms_from_mean_mm={n: from_mean[n] for n in dict.fromkeys((medoid, found))},
                  confirmed=confirmed)
    if not confirmed:
        say(f"correspondence: the landmark medoid {medoid}'s coatings have {found} nearest their mean shape "
            f"({from_mean[found]:.2f} mm RMS, {medoid} {from_mean[medoid]:.2f} mm): the medoid is found from the given "
            "template's coatings")
        return study, record
    say(f"correspondence: template from the medoid {medoid} (its landmarks nearest their mean, {distance[medoid]:.2f} "
        f"mm RMS; its coatings confirm it nearest the mean shape, {from_mean[medoid]:.2f} mm"
        + (f", {found} {from_mean[found]:.2f} mm, a tie)" if found != medoid else ")") + _points_note(study, other))
    return other, {**record, "kept": True, "points": _points(study, other)}


def medoid_template(study: Study, *, jobs: int = 1, executor=None, cancelled: CancelledFn = None,
                    log: Log = None) -> tuple[Study, dict, dict]:
    """The study with its template built again from the population's medoid, when that helps.

    Paper 3.3: a template from one arbitrary instance makes the model depend on it. The
    medoid (:func:`population_medoid`) among the instances with every template landmark
    given is the one most like the mean shape, so every other coating deforms it least.
    Its template (paper 3) is coated onto every instance as the start was (landmarks, or the
    landmarked instances' model), and kept when it lowers the landmark transfer error
    (:func:`ssm_addon.correspondence.rounds.round_helps`: by 1 %, the instances together).

    Returns
    -------
    (the study to refine: a copy with the medoid's template and coatings, or ``study``;
    the record: ``given``, ``medoid``, ``transfer_given_mm``, ``transfer_medoid_mm``, ``kept``;
    the landmarked instances' fits that judged the study returned
    (:func:`ssm_addon.correspondence.rounds.round_fits`), which are its first round's)
    """
    say = log or (lambda _m: None)
    complete = _candidates(study)
    if not complete:
        return study, {}, {}
    medoid, distance = population_medoid(study, complete)
    record = {"given": study.template_instance, "medoid": medoid,
              "rms_from_mean_mm": {study.template_instance: distance[study.template_instance], medoid: distance[medoid]}}
    if medoid == study.template_instance:
        say(f"correspondence: the template's instance {medoid} is the population's medoid already")
        return study, {**record, "kept": True}, {}
    check_cancelled(cancelled)
    try:
        other = _from_template_of(study, medoid, fallbacks=[], coat=True, jobs=jobs, executor=executor,
                                  cancelled=cancelled)
    except Cancelled:
        raise
    except SSMError as err:  # the medoid's template is a refinement: the given one stays
        study.fallbacks.append(Finding(medoid, "fallback", f"the population's medoid {medoid!r} gave no template "
                                       f"({err}); the given template of {study.template_instance!r} is kept"))
        return study, {**record, "kept": False, "failed": str(err)}, {}
    fit = correspondence_fit_params(study.params.correspondence)
    landmarked = [n for n in study.names if study.landmarks_object(n)]
    fits = [round_fits(population(s), landmarked, fit=fit, jobs=jobs, executor=executor, cancelled=cancelled, verb="checked")
            for s in (study, other)]
    before, after = (CorrespondenceCheck.from_landmarks({n: f.transfer for n, f in found.items()}) for found in fits)
    kept = round_helps(after, before)
    record.update(transfer_given_mm=before.study_mm, transfer_medoid_mm=after.study_mm, kept=kept,
                  points=_points(study, other))
    say(f"correspondence: template from the medoid {medoid} ({distance[medoid]:.2f} mm RMS from the mean shape, "
        f"{study.template_instance} {distance[study.template_instance]:.2f} mm): landmark transfer error "
        f"{before.study_mm:.3f} -> {after.study_mm:.3f} mm, {'kept' if kept else 'not kept'}"
        + _points_note(study, other))
    return (other if kept else study), record, fits[1] if kept else fits[0]


def population(study: Study) -> Population:
    """The study's coated instances as the rounds read them (:class:`~ssm_addon.correspondence.rounds.Population`):
    the template, the coatings, the imported volumes and the given landmarks in each object frame (mm)."""
    names = study.names
    return Population(names=names, template_instance=study.template_instance, template=study.template,
                      coatings=dict(study.coatings), volumes=dict(study.volumes),
                      landmarks={n: study.landmarks_object(n) for n in names}, coating_params=study.params.coating)


def landmarked(study: Study) -> list[str]:
    """The instances with landmarks, in study order."""
    return [n for n in study.names if study.landmarks(n) is not None]


def _frames_pass(study: Study, pool, *, jobs: int, cancelled: CancelledFn, screened: dict | None):
    """The study's template coated onto every instance from its object frames without landmarks
    (``screened``: per instance, the rotations to try; default all), and the population's turns
    (:func:`~ssm_addon.correspondence.frames.population_turns`):
    (name -> (CoatingResult, FramesStart), changed, unresolved)."""
    names = list(study.names)
    template = Mesh(study.template.points_object, study.template.faces)
    coating = study.params.coating
    coated = frames_coat(template, {n: study.volume(n) for n in names}, coating=coating,
                         template_frame=study.frame(study.template_instance), turns=screened or None, jobs=jobs,
                         executor=pool, cancelled=cancelled)

    def retry(suspects):
        turns = {n: tuple(k for k, t in enumerate(TURN_NAMES) if t != coated[n][1].turn) for n in suspects}
        return frames_coat(template, {n: study.volume(n) for n in suspects}, coating=coating,
                           template_frame=None, turns=turns, jobs=jobs, executor=pool, cancelled=cancelled)

    return population_turns(coated, study.template_instance, retry)


def medoid_without_landmarks(study: Study, coated: dict, *, jobs: int = 1, executor=None,
                             cancelled: CancelledFn = None, log: Log = None):
    """The template built again from the population's medoid and coated onto every instance,
    without landmarks (``[correspondence] template_choice = "medoid"``).

    Paper 3.3: a template from one arbitrary instance makes the model depend on it; without
    landmarks the dependence is larger, because what a coating leaves wrong grows with the
    instance's difference from the template's shape (its points slide where shapes differ, and
    nothing pins them). The medoid (:func:`population_medoid`: the instance whose first coating is
    nearest the mean shape, RMS after a rigid alignment) deforms least onto the others. Its
    template (paper 3, :func:`template_of_count`) is coated onto every instance as the first one
    was, when the given template's instance lies more than :data:`NO_LANDMARK_TIE` times as far
    from the mean shape as the medoid, and kept when the medoid's own coatings put it nearer the
    mean than the given instance too. Without landmarks nothing measures the correspondence, so the
    medoid is taken by that rule (the truth on femur10 and knee30: ``docs/history.md``, "The
    template from the medoid without landmarks"). An instance mirrored into the template's side
    is a candidate as any other: its template is built from its mirrored volume, so the model
    stays of the given template's side (:func:`~ssm_addon.pipeline.sides.model_side`) and a set
    coated with half its instances mirrored is the mirror image of the one-sided set's.
    ``coated``: the first pass, name -> (CoatingResult, FramesStart).

    Returns
    -------
    (the study the coatings came from: a copy with the medoid's template, or ``study``;
    its pass (coated, changed, unresolved), or None when the first pass stays; the record:
    ``given``, ``medoid``, ``by`` ("coatings"), ``tie``, ``rms_from_mean_mm`` (of the first coatings)
    and, when the medoid's pass ran, ``rms_from_mean_second_mm`` and ``confirmed``; ``kept``)
    """
    say = log or (lambda _m: None)
    names = list(study.names)
    if len(names) < 3:
        return study, None, {}
    first = dataclasses.replace(study, coatings={n: c for n, (c, _h) in coated.items()})
    medoid, distance = population_medoid(first, names)
    given = study.template_instance
    record = {"given": given, "medoid": medoid, "by": "coatings", "tie": NO_LANDMARK_TIE,
              "rms_from_mean_mm": {n: round(distance[n], 4) for n in dict.fromkeys((given, medoid))}}
    if medoid == given or distance[given] <= NO_LANDMARK_TIE * distance[medoid]:
        say(f"correspondence: the template's instance {given} is the population's medoid"
            + (" already" if medoid == given else f" within {NO_LANDMARK_TIE:g}x ({medoid} {distance[medoid]:.2f} mm RMS "
                                                   f"from the mean shape, {given} {distance[given]:.2f} mm)"))
        return study, None, {**record, "kept": False}
    check_cancelled(cancelled)
    try:
        other = _from_template_of(study, medoid, fallbacks=[], coat=False, cancelled=cancelled)
    except Cancelled:
        raise
    except SSMError as err:  # the medoid's template is a refinement: the given one stays
        say(f"correspondence: the population's medoid {medoid} gave no template ({err}); the given template of "
            f"{given} is kept")
        return study, None, {**record, "kept": False, "failed": str(err)}
    # each instance's rotation against the medoid, from the first coatings (a similarity of the
    # corresponding points; the medoid's template lies on its surface in its object frame): the
    # rotation of the frame's axes nearest it is the one the start screens (with the input pose)
    ref = first.coatings[medoid].points_object
    turns = {n: (nearest_frame_rotation(weighted_pose(ref, first.coatings[n].points_object, np.ones(len(ref)),
                                                      scale=True).rotation),) for n in names}
    again = _frames_pass(other, executor, jobs=jobs, cancelled=cancelled, screened=turns)
    # confirmed by the second coatings: each pass's own template instance is coated exactly and
    # the others towards its shape, so the two passes must agree that the medoid is nearer
    second = dataclasses.replace(other, coatings={n: c for n, (c, _h) in again[0].items()})
    _m, distance2 = population_medoid(second, names)
    kept = distance2[given] > distance2[medoid]
    record.update(rms_from_mean_second_mm={n: round(distance2[n], 4) for n in (given, medoid)}, confirmed=kept)
    say(f"correspondence: template from the population's medoid {medoid} ({distance[medoid]:.2f} mm RMS from the "
        f"mean shape of the first coatings, {given} {distance[given]:.2f} mm; of the medoid's coatings "
        f"{distance2[medoid]:.2f} and {distance2[given]:.2f} mm): "
        + ("every instance coated from it" if kept else "not confirmed, the given template's coatings kept")
        + _points_note(study, other))
    if not kept:
        return study, None, {**record, "kept": False, "points": _points(study, other)}
    return other, again, {**record, "kept": True, "points": _points(study, other)}


def coat_without_landmarks_stage(study: Study, *, jobs: int = 1, executor=None,
                                 cancelled: CancelledFn = None) -> StageResult:
    """The coating stage of a study without landmarks on any instance.

    The template is put onto every instance by a similarity registration of the surfaces from
    every rotation of the object frame's axes (:func:`ssm_addon.correspondence.frames.template_start`),
    coated from there (registration, projection, relaxation: paper 4.2), and an instance the
    population disagrees with is coated again from the other rotations
    (:func:`~ssm_addon.correspondence.frames.population_turns`). With ``template_choice =
    "medoid"`` (the default) the template is then built from the population's medoid and every
    instance coated from it the same way (:func:`medoid_without_landmarks`). The summary says
    that no landmarks anchored the correspondence, which instances were turned, and which no
    rotation brought nearer the others (an unusual shape: the model's gates judge it; no frame
    finding).
    """
    t0 = time.perf_counter()
    names = list(study.names)
    lines = []
    # the sides' surface test screened every rotation already: its nearest few are the start's candidates
    screened = {n: study.sides[n].rotations for n in names if n in study.sides and study.sides[n].rotations}
    medoid = study.params.correspondence.template_choice == "medoid" and len(names) >= 3
    with executor_or_local(executor, jobs, len(names)) as pool:
        # a second pass from the medoid's template reads each instance's distance map of the first
        with distance_maps_kept(study) if medoid else contextlib.nullcontext():
            coated, changed, unresolved = _frames_pass(study, pool, jobs=jobs, cancelled=cancelled, screened=screened)
            chosen, choice = study, {}
            if medoid:
                chosen, again, choice = medoid_without_landmarks(study, coated, jobs=jobs, executor=pool,
                                                                 cancelled=cancelled, log=lines.append)
                if again is not None:
                    coated, changed, unresolved = again
        result = coating_result(chosen, {n: c for n, (c, _h) in coated.items()},
                                {n: CoatingStart.OBJECT_FRAMES for n in names}, time.perf_counter() - t0,
                                template=chosen.template if chosen is not study else None,
                                executor=pool, cancelled=cancelled)
    turned = {n: h.turn for n, (_c, h) in coated.items() if h.turn not in ("frames", "input coordinates")}
    lines.insert(0, f"correspondence: no landmarks were given: the template was put onto every instance by its "
                    f"object frame (paper 2) and the rotation of its axes from which a similarity registration fits "
                    f"the surface best, then coated; "
                    f"{len(turned)} instance(s) in a turned pose" + (f" ({', '.join(f'{n}: {t}' for n, t in turned.items())})"
                                                                    if turned else ""))
    for n, (before, after) in changed.items():
        lines.append(f"correspondence: {n} was coated turned against the population ({before:.1f} mm from the others' "
                     f"mean shape); coated again {coated[n][1].turn}: {after:.1f} mm")
    # no rotation brought these nearer the others: an unusual shape, which the model's outlier and
    # reconstruction gates judge, or a coating turned on its own surface, which the twist gate names
    for n, (far, median) in unresolved.items():
        lines.append(f"correspondence: {n} lies {far:.1f} mm (RMS) from the others' mean shape, more than "
                     f"{TURNED_FACTOR:g}x the median instance's {median:.1f} mm, and no other rotation of the "
                     "template brings it nearer: its shape is unlike the others' (the model's gates judge it)")
    product = dict(result.product)
    product["template_choice"] = {"by": "no landmarks", **choice,
                                  "starts": {n: h.to_dict() for n, (_c, h) in coated.items()}}
    if chosen is not study:
        product["template_instance"] = chosen.template_instance
    return dataclasses.replace(result, product=product, summary=tuple(lines) + tuple(result.summary))
