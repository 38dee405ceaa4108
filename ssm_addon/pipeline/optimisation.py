"""The correspondence optimisation on a study (``[correspondence] optimise``): the stage after
the coating that slides every instance's points along its own surface
(:mod:`ssm_addon.correspondence.optimisation`)."""

from __future__ import annotations

import contextlib
import dataclasses
import time

import numpy as np

from ..base.errors import InputError
from ..base.progress import CancelledFn, ProgressFn
from ..correspondence.optimisation import (
    InstanceSource,
    Optimisation,
    landmark_holds,
    optimise_correspondence,
)
from ..meshutil import LandmarkLocations
from ..model.quality import check_coating
from .model_method import distance_maps_kept
from .stages import self_check
from .study import StageResult, Study

__all__ = ["hold_weight", "optimisation_result", "optimisation_stage"]


def optimisation_stage(study: Study, *, jobs: int = 1, executor=None, progress: ProgressFn = None,
                       cancelled: CancelledFn = None, on_step=None) -> StageResult:
    """The correspondence optimisation (``[correspondence] optimise``): every instance's points
    slide along its own surface (:func:`ssm_addon.correspondence.optimisation.optimise_correspondence`),
    the given landmarks held where the coating's warp put them, as firmly as their uncertainty
    allows (:func:`hold_weight`). The self-check is measured again on the result when the coating
    measured it.

    Instances whose volume the study does not hold (a streamed build keeps one) are imported
    again by the worker that moves their points. ``on_step(step)``: each iteration's figures as
    it ends. Cancelling raises :class:`~ssm_addon.correspondence.optimisation.OptimisationCancelled`,
    whose ``result`` (the last complete iteration) :func:`optimisation_result` turns into a
    stage result.
    """
    if study.template is None or any(n not in study.coatings for n in study.names):
        raise InputError("optimisation: coat every instance first")
    t0 = time.perf_counter()
    names = list(study.names)
    tp = study.params.template
    given = {n: study.landmarks(n).names if study.landmarks(n) is not None else () for n in names}
    holds = landmark_holds(study.template.landmark_locations, study.template.faces,
                           {n: study.coatings[n].warped_points_object for n in names}, given)
    several = study.params.correspondence.population_weight > 0  # a map per iteration: keep the distance maps
    with distance_maps_kept(study) if several else contextlib.nullcontext("") as store:
        surfaces = {n: study.volumes[n] if n in study.volumes else
                    InstanceSource(study.instance(n), tp.spacing_mm, tp.frame, tp.space, distance_map_store=store)
                    for n in names}
        params = dataclasses.replace(study.params.correspondence, landmark_hold=hold_weight(study))
        result = optimise_correspondence({n: study.coatings[n].points_object for n in names}, study.template.faces,
                                         surfaces, params=params, coating=study.params.coating,
                                         holds=holds, jobs=jobs, executor=executor, progress=progress,
                                         cancelled=cancelled, on_step=on_step)
    return optimisation_result(study, result, time.perf_counter() - t0, jobs=jobs, executor=executor,
                               cancelled=cancelled)


def hold_weight(study: Study) -> float:
    """The landmarks' hold, ``landmark_hold * h² / (h² + σ_c²)``: as given for exact landmarks, weaker
    the farther a given landmark may be from the anatomy. h is the study's voxel spacing (mm: what
    a coating resolves), σ_c the click error per axis: ``[correspondence] landmark_noise_mm`` when
    given, else the model method's estimate of its last round, else 0 (the single pass treats the
    landmarks as exact: its warp, eq. 2, interpolates them).

    On the dense-truth sets, holding clicks off by 1.5 mm per axis as if exact put points up to
    1.5 % farther from their true places (``docs/history.md``)."""
    cp = study.params.correspondence
    click = cp.landmark_noise_mm
    if click is None:
        rounds = [r for r in study.correspondence_rounds if getattr(r, "landmark_noise", None) is not None]
        click = rounds[-1].landmark_noise.click_mm if rounds else 0.0
    h = float(study.params.template.spacing_mm)
    return float(cp.landmark_hold) * h * h / (h * h + float(click) ** 2)


def _residuals(study: Study, name: str, coating, points) -> dict:
    """The fit figures' landmark residuals of the optimised points, against the given landmarks (the
    coating's own measure), where the coating measured every one against a given landmark."""
    locations = study.template.landmark_locations
    names = tuple(coating.fit.landmark_names)
    if not names and len(coating.fit.landmark_residuals_mm) == len(locations):  # the single pass: every one
        names = tuple(locations.names)
    given = study.landmarks_object(name)
    if not names or not given or any(x not in given or x not in locations.names for x in names):
        return {}
    index = [locations.names.index(x) for x in names]
    at = LandmarkLocations(names, locations.triangles[index], locations.bary[index]).evaluate(
        np.asarray(points, float), study.template.faces)
    return {"landmark_residuals_mm": tuple(float(d) for d in np.linalg.norm(at - np.stack([given[x] for x in names]),
                                                                            axis=1))}


def optimisation_result(study: Study, result: Optimisation, seconds: float, *, jobs: int = 1, executor=None,
                        cancelled: CancelledFn = None) -> StageResult:
    """The optimisation stage's result: the coatings with the optimised points (their fit figures
    measured again, paper 4.2's exact surface distance), the record, the coating gates and, when
    the coating had one, the self-check of the optimised points."""
    coated = {}
    for n, c in study.coatings.items():
        if n not in result.points:
            continue
        fit = dataclasses.replace(c.fit, folded_after=int(result.folds.get(n, c.fit.folded_after)),
                                  **{k: float(v[n]) for k, v in (("mean_distance_mm", result.surface_mean_mm),
                                                                 ("max_distance_mm", result.surface_distance_mm))
                                     if n in v}, **_residuals(study, n, c, result.points[n]))
        coated[n] = dataclasses.replace(c, points_object=np.asarray(result.points[n], float), fit=fit)
    qp = study.params.quality
    findings = tuple(f for n, c in coated.items() for f in check_coating(n, c.fit, qp))
    product = {"coatings": coated, "optimisation": result}
    before = study.correspondence_check
    lines = []
    if before is not None and getattr(before, "instance_mm", None) and result.stop != "cancelled":
        check, found = self_check(study, {**study.coatings, **coated}, jobs=jobs, executor=executor,
                                  cancelled=cancelled)
        if check is not None:
            product["correspondence_check"] = dataclasses.replace(check, stop=before.stop,
                                                                  kept_round=before.kept_round)
            findings += tuple(found)
            lines.append(f"optimisation: landmark transfer error {before.study_mm:.3f} -> {check.study_mm:.3f} mm")
    last = result.steps[-1] if result.steps else None
    moved = max(result.instance_movement_mm.values(), default=0.0)
    lines.insert(0, f"optimisation: {result.iterations} iteration(s) in {seconds:.2f} s, {result.stop}; objective "
                    f"{result.steps[0].objective:.4f} -> {last.objective:.4f}, entropy {result.steps[0].entropy_nats:.2f}"
                    f" -> {last.entropy_nats:.2f} nats; points moved {moved:.3f} mm RMS at most")
    return StageResult("optimisation", product, findings, {"optimisation": seconds}, tuple(lines))


