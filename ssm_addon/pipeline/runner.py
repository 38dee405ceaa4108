"""``run``: the stages of a study in order (the loop both the command line and scripts use), and
the coating stage by the study's correspondence method."""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Callable, Sequence

from ..base.compute import time_left_text
from ..base.errors import InputError, check_cancelled
from ..base.progress import CancelledFn, ProgressFn, report, sub_progress
from ..model.metrics import import_plotting_in_background
from .appearance import appearance_stage
from .model_method import coat_without_landmarks_stage, distance_maps_ahead, landmarked, refine_correspondence
from .optimisation import optimisation_stage
from .sides import decide_sides, sides_first, with_sides, with_sides_product
from .stages import (
    coat_instances,
    coating_result,
    import_stage,
    metrics_stage,
    model_stage,
    self_check,
    template_stage,
)
from .streaming import stream_instances, template_key
from .study import STAGES, Log, StageResult, Study, apply_stage
from .template_refinement import with_template_refined

__all__ = ["coating_stage", "run"]


def coating_stage(study: Study, *, names: Sequence[str] | None = None, jobs: int = 1, progress: ProgressFn = None,
                  cancelled: CancelledFn = None, log: Log = None, executor=None,
                  on_coated: Callable[[str], None] | None = None) -> StageResult:
    """Coating (paper 4) by the study's correspondence method, and the coating gates.

    ``method = "landmarks"``: :func:`coat_instances` (the paper's single pass, ``names``);
    ``"model"``: :func:`refine_correspondence` (every instance). ``on_coated(name)`` is
    called as each coating arrives (for counting; progress lines are for people). When every
    instance is coated and some coatings cut off parts of their meshes, the template is refined
    there and every instance coated again (:func:`with_template_refined`; ``[template]
    refine_where_cut_off``). First, each instance whose side is not given is found a mirror image
    of the template's side or not, and mirrored into it (:func:`~ssm_addon.pipeline.sides.sides_first`).
    """
    sided, decisions, t_sides = sides_first(study, names, jobs=jobs, executor=executor, cancelled=cancelled)

    def coat(s: Study) -> StageResult:
        return _coating_once(s, names=names, jobs=jobs, progress=progress, cancelled=cancelled, log=log,
                             executor=executor, on_coated=on_coated)

    first = coat(sided)
    if names is None or set(names) == set(study.names):
        first = with_template_refined(sided, first, coat, log=log, progress=progress, cancelled=cancelled)
    return with_sides_product(sided, first, decisions, t_sides)


def _coating_once(study: Study, *, names: Sequence[str] | None = None, jobs: int = 1, progress: ProgressFn = None,
                  cancelled: CancelledFn = None, log: Log = None, executor=None,
                  on_coated: Callable[[str], None] | None = None) -> StageResult:
    """The coating stage by the study's correspondence method with its template as it is."""
    with_landmarks = landmarked(study)
    if not with_landmarks:
        return coat_without_landmarks_stage(study, jobs=jobs, executor=executor, cancelled=cancelled)
    if study.params.correspondence.method != "landmarks" or len(with_landmarks) < len(study.names):
        if study.params.correspondence.method == "landmarks" and log is not None:
            without = [n for n in study.names if n not in with_landmarks]
            log(f"correspondence: landmarks on {len(with_landmarks)} of {len(study.names)} instances (none on "
                f"{', '.join(without[:5])}{', …' if len(without) > 5 else ''}): the model method supplies theirs "
                "(paper 7's bootstrap)")
        return refine_correspondence(study, jobs=jobs, progress=progress, cancelled=cancelled, log=log,
                                     executor=executor, on_coated=on_coated)
    t0 = time.perf_counter()
    coated = coat_instances(study, names=names, jobs=jobs, progress=progress, cancelled=cancelled,
                            on_coated=on_coated)
    t_check = time.perf_counter()
    check, found = self_check(study, {**study.coatings, **coated}, jobs=jobs, executor=executor, cancelled=cancelled)
    return coating_result(study, coated, {n: c.fit.start for n, c in coated.items()}, time.perf_counter() - t0,
                          check=check, extra_findings=found, executor=executor, cancelled=cancelled,
                          check_seconds=time.perf_counter() - t_check)


def run(study: Study, *, stages: Sequence[str] = STAGES, jobs: int = 1, progress: ProgressFn = None,
        cancelled: CancelledFn = None, log: Log = None, executor=None, cache=None) -> Study:
    """Run ``stages`` in order on ``study``, applying each stage's result, and return it.

    Progress: import 0–15 %, template 15–30 %, coating 30–80 %, optimisation 80–85 % (when
    ``[correspondence] optimise``; a line per iteration with its objective), model 85–90 %,
    metrics 90–95 % of ``progress``; ``log`` receives each result's lines
    (:meth:`StageResult.lines`).

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
            and len(landmarked(study)) == len(study.names)
            and all(s in stages for s in ("import", "template", "coating"))):
        report(progress, 0.0, f"import, template and coating: {n} instances on {executor.describe()}")
        # streamed, no instance's volume is here before it is coated: sides by landmarks alone
        t_sides = time.perf_counter()
        decisions = decide_sides(study, surface=False)
        if decisions:
            study.instances = with_sides(study, decisions).instances
        t_sides = time.perf_counter() - t_sides
        streamed = with_sides_product(study, stream_instances(study, executor, cache=cache, cancelled=cancelled,
                                                             progress=sub_progress(progress, 0.0, 0.8), log=say),
                                      decisions, t_sides)
        with_volume = dataclasses.replace(study, template=streamed.product["template"],
                                          volumes={**study.volumes, **streamed.product["volumes"]})
        applied(with_template_refined(
            with_volume, streamed,
            lambda s: stream_instances(s, executor, cache=cache, template=s.template, cancelled=cancelled, log=say,
                                       progress=sub_progress(progress, 0.0, 0.8)),
            log=say, cancelled=cancelled, cache=cache, cache_key=template_key(study) if cache is not None else None))
        stages = [s for s in stages if s not in ("import", "template", "coating")]
    if "import" in stages:
        report(progress, 0.0, f"import: {n} instances at {study.params.template.spacing_mm:g} mm")
        applied(import_stage(study, jobs=jobs, progress=sub_progress(progress, 0.0, 0.15), cancelled=cancelled,
                             executor=executor))
    # the model method: its instances' distance maps computed on the idle workers while this
    # process builds the template, and read by the coatings (the same maps)
    ahead = (distance_maps_ahead(study, executor)
             if study.params.correspondence.method == "model" and "template" in stages and "coating" in stages
             else contextlib.nullcontext())
    with ahead:
        if "template" in stages:
            check_cancelled(cancelled)
            report(progress, 0.15, f"template: from {study.template_instance}")
            applied(template_stage(study, progress=sub_progress(progress, 0.15, 0.3), cancelled=cancelled))
        if "coating" in stages:
            check_cancelled(cancelled)
            report(progress, 0.3, f"coating: {n} instances, {jobs} job(s)")
            import_plotting_in_background()  # for the plots after the model, while the workers coat
            coat_prog = sub_progress(progress, 0.3, 0.8)
            if study.params.correspondence.method == "landmarks" and len(landmarked(study)) == n:  # a line per instance
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
    if "optimisation" in stages and study.params.correspondence.optimise:
        check_cancelled(cancelled)
        iterations = study.params.correspondence.optimise_iterations
        report(progress, 0.8, f"optimisation: up to {iterations} iterations, population weight "
                              f"{study.params.correspondence.population_weight:g}")
        opt_prog = sub_progress(progress, 0.8, 0.85)

        def step_line(step) -> None:
            report(opt_prog, step.iteration / iterations,
                   f"optimisation: iteration {step.iteration}/{iterations}: objective {step.objective:.4f}, entropy "
                   f"{step.entropy_nats:.2f} nats, landmarks {step.landmark_mm:.3f} mm, moved {step.movement_mm:.4f} mm")

        applied(optimisation_stage(study, jobs=jobs, executor=executor, cancelled=cancelled, on_step=step_line))
    if "model" in stages:
        check_cancelled(cancelled)
        report(progress, 0.85, "model: PCA")
        applied(model_stage(study, cancelled=cancelled))
    if "appearance" in stages and study.model is not None and any(i.image_path is not None for i in study.instances):
        check_cancelled(cancelled)
        report(progress, 0.88, "appearance: boundary profiles from the instances' images")
        applied(appearance_stage(study))
    if "metrics" in stages:
        check_cancelled(cancelled)
        report(progress, 0.9, "metrics: compactness, generalization, specificity")
        applied(metrics_stage(study, cancelled=cancelled))
    return study
