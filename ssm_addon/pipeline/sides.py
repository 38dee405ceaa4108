"""The sides of a study's instances, decided before they are coated
(:mod:`ssm_addon.correspondence.sides`): each instance whose side is not given is found a
mirror image of the template's side or not, by its landmarks or its surface, and a mirror image
is mirrored into the template's side (its spec's ``mirror`` and its volume), so that every
later stage (coating, rounds, optimisation, model) sees one side."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence

from ..base.compute import executor_or_local
from ..base.progress import CancelledFn
from ..correspondence.sides import SIDE_FACTOR, SideDecision, landmark_side, surface_side
from ..instances.volume import mirrored
from .study import StageResult, Study

__all__ = ["decide_sides", "given_sides", "landmark_sides", "model_side", "sides_first", "sides_line", "with_sides", "with_sides_product"]


def _surface_job(args) -> SideDecision:
    points, faces, volume, frame = args
    return surface_side(points, faces, volume, template_frame=frame)


def landmark_sides(study: Study, names: Sequence[str]) -> dict[str, SideDecision]:
    """Sides found by landmarks (:func:`~ssm_addon.correspondence.sides.landmark_side`) for the
    instances among ``names`` whose side is undecided and which share at least four landmarks
    with the template instance; those the landmarks cannot tell are left out."""
    tpl = study.landmarks(study.template_instance)
    out = {}
    if tpl is None:
        return out
    for n in names:
        lm = study.landmarks(n)
        if lm is None or study.instance(n).mirror is not None or n == study.template_instance:
            continue
        common = [k for k in tpl.names if k in lm.names]
        found = landmark_side(tpl.subset(common).points_world, lm.subset(common).points_world)
        if found is not None and found.by != "undecided":
            out[n] = found
    return out


def decide_sides(study: Study, names: Sequence[str] | None = None, *, jobs: int = 1, executor=None,
                 cancelled: CancelledFn = None, surface: bool = True) -> dict[str, SideDecision]:
    """The side of every instance among ``names`` (default all but the template's) whose spec's
    ``mirror`` is None: by landmarks where they tell, else by the surface against the study's
    template (``surface``; on ``executor``), else taken as the template's side
    (``by = "undecided"``). Instances whose side is given or decided already are left out; none
    is decided where ``[correspondence] sides = "given"``."""
    if study.params.correspondence.sides != "detect":
        return {}
    names = [n for n in (study.names if names is None else names)
             if n != study.template_instance and study.instance(n).mirror is None]
    found = landmark_sides(study, names)
    rest = [n for n in names if n not in found]
    if rest and surface and study.template is not None:
        frame = study.frame(study.template_instance)
        args = [(study.template.points_object, study.template.faces, study.volume(n), frame) for n in rest]
        with executor_or_local(executor, jobs, len(args)) as pool:
            decided = pool.map(_surface_job, args, labels=rest, verb="sided", cancelled=cancelled)
        found.update(zip(rest, decided))
    for n in rest:
        found.setdefault(n, SideDecision(False, "undecided"))
    return {n: found[n] for n in names}


def with_sides(study: Study, decisions: dict[str, SideDecision]) -> Study:
    """A copy of ``study`` whose instances' ``mirror`` is decided by ``decisions`` and whose
    imported volumes of mirrored instances are mirrored (the lists and records shared)."""
    specs = tuple(dataclasses.replace(i, mirror=decisions[i.name].mirror) if i.name in decisions else i
                  for i in study.instances)
    volumes = dict(study.volumes)
    for n, d in decisions.items():
        if d.mirror and n in volumes:
            volumes[n] = mirrored(volumes[n])
    frames = {**study.frames, **{n: v.frame for n, v in volumes.items() if n in decisions}}
    return dataclasses.replace(study, instances=specs, volumes=volumes, frames=frames,
                               sides={**study.sides, **decisions})


def model_side(study: Study) -> str:
    """The side the model is of (``"left"``, ``"right"`` or ``""`` when not given): the template
    instance's given side, the other one when the template came from an instance mirrored into the
    given template's side (the medoid of a mixed set, :func:`~ssm_addon.pipeline.model_method.medoid_without_landmarks`)."""
    spec = study.instance(study.template_instance)
    if not spec.side:
        return ""
    return {"left": "right", "right": "left"}.get(spec.side, spec.side) if spec.mirror else spec.side


def given_sides(study: Study) -> dict[str, SideDecision]:
    """The decisions the project made: instances whose side is given (``by = "given"``; the template
    instance's only where it was mirrored, a medoid of the other side)."""
    return {i.name: SideDecision(bool(i.mirror), "given", side=i.side) for i in study.instances
            if i.side is not None and (i.name != study.template_instance or i.mirror)}


def sides_line(study: Study, decisions: dict[str, SideDecision]) -> str:
    """One line: which instances were mirrored into the template's side and why, and which
    neither side fitted clearly; empty when none was either."""
    every = {**given_sides(study), **decisions}
    if not every:
        return ""
    tpl = model_side(study)
    flipped = {n: d for n, d in every.items() if d.mirror}
    unclear = [n for n, d in every.items() if d.by == "undecided"]
    side = f" ({tpl})" if tpl else ""
    if not flipped and not unclear:  # one side throughout: report.json's correspondence.sides says how it was found
        return ""
    if flipped:
        text = (f"sides: {len(flipped)} instance(s) mirrored into the template's side{side} before coating: "
                + "; ".join(f"{n}: {d.text()}" for n, d in flipped.items()))
    else:
        text = f"sides: every instance is taken as the template's side{side}"
    if unclear:
        text += (f"; {len(unclear)} near their own mirror image ({', '.join(unclear[:5])}"
                 f"{', …' if len(unclear) > 5 else ''}): neither side fits {SIDE_FACTOR:g}x closer, taken as the "
                 "template's side (a project's side = \"left\" or \"right\" decides)")
    return text


def sides_first(study: Study, names: Sequence[str] | None = None, *, jobs: int = 1, executor=None,
                cancelled: CancelledFn = None) -> tuple[Study, dict[str, SideDecision], float]:
    """The coating stage's first step (both front ends): :func:`decide_sides` and the study with
    them (:func:`with_sides`). Returns (the study to coat, the decisions, seconds)."""
    t0 = time.perf_counter()
    decisions = decide_sides(study, names, jobs=jobs, executor=executor, cancelled=cancelled)
    return (with_sides(study, decisions) if decisions else study), decisions, time.perf_counter() - t0


def with_sides_product(sided: Study, result: StageResult, decisions: dict, seconds: float) -> StageResult:
    """A coating stage's ``result`` with the sides decided before it: the instances' specs and
    mirrored volumes in its product, the decisions under ``sides`` and their line first in its
    summary."""
    line = sides_line(sided, decisions)
    if not decisions and not line:
        return result
    product = dict(result.product)
    if decisions:
        product["instances"] = sided.instances
        flipped = {n: sided.volumes[n] for n, d in decisions.items() if d.mirror and n in sided.volumes}
        product["volumes"] = {**flipped, **product.get("volumes", {})}
        product["frames"] = {**{n: v.frame for n, v in flipped.items()}, **product.get("frames", {})}
        product["sides"] = dict(decisions)
    summary = ((f"{line} ({seconds:.1f} s)",) if decisions and line else (line,) if line else ()) + tuple(result.summary)
    timings = {**result.timings_s, "sides": seconds} if decisions else dict(result.timings_s)
    return dataclasses.replace(result, product=product, summary=summary, timings_s=timings)
