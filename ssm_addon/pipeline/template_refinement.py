"""The template refined across the population (``[template] refine_where_cut_off``): where the
coatings cut off parts of the instances' own meshes, the template is built again, denser there,
and every instance is coated again, once.

The template's tolerance (paper 3.1, ``[template] max_distance_mm``) holds on its own instance's
surface. Another instance can hold a part larger than the template instance's (a longer process):
the coating stretches the template's triangles over it and cuts it off (the ``input_surface``
finding). Those parts, carried back to the template through the coating's triangles, say where
its radii must be smaller (:func:`~ssm_addon.pipeline.stages.cut_off_places`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

from ..base.errors import Cancelled
from ..base.progress import CancelledFn, ProgressFn, report
from ..instances.importing import import_instance
from .cache import digest
from .stages import cut_off_places, make_template
from .study import Log, StageResult, Study

__all__ = ["CUT_OFF_SHARE", "cut_off_instances", "with_template_refined"]

#: A part cut off, not the whole surface: an instance with more than this share of its mesh's
#: vertices far from its coating has a wrong coating (or a gate set too tight), which a denser
#: template does not mend (the lumbar levels' cut-off tips: 2–14 of about 30,000 vertices)
CUT_OFF_SHARE = 0.1


def cut_off_instances(result: StageResult) -> list[str]:
    """The instances of a coating result whose ``input_surface`` finding is the coating's: more of
    their mesh's vertices lie beyond ``[quality] max_input_distance_mm`` than the import's voxels
    lost (``beyond["voxels"]``), and at most :data:`CUT_OFF_SHARE` of them."""
    distances = result.product.get("input_distances") or {}
    out = []
    for f in result.findings:
        if f.gate != "input_surface" or f.instance not in distances:
            continue
        beyond = distances[f.instance]["from_input"].get("beyond") or {}
        count = int(beyond.get("count", 0))
        if count > int((beyond.get("voxels") or {}).get("count", 0)) and float(beyond.get("share", 1.0)) <= CUT_OFF_SHARE:
            out.append(f.instance)
    return out


def _worst(result: StageResult) -> tuple[int, float, int]:
    """How many ``input_surface`` findings a coating result has, the largest distance of a mesh
    from its coating (mm), and how many other findings."""
    far = [float(d["from_input"]["max_mm"]) for d in (result.product.get("input_distances") or {}).values()]
    cut = sum(f.gate == "input_surface" for f in result.findings)
    return cut, max(far, default=0.0), len(result.findings) - cut


#: A refinement is kept only if no instance's mesh lies farther than this (mm) beyond its largest
#: distance from the first coating: it must bring the meshes nearer everywhere it looked.
FARTHER_TOLERANCE_MM = 0.05


def _farther(first: StageResult, second: StageResult) -> list[tuple[str, float, float]]:
    """The instances whose mesh lies farther from the second coating than from the first (largest
    distance, mm, beyond ``FARTHER_TOLERANCE_MM``): (name, first, second), the largest growth first."""
    a = first.product.get("input_distances") or {}
    b = second.product.get("input_distances") or {}
    out = [(n, float(a[n]["from_input"]["max_mm"]), float(b[n]["from_input"]["max_mm"])) for n in sorted(a) if n in b]
    out = [t for t in out if t[2] > t[1] + FARTHER_TOLERANCE_MM]
    return sorted(out, key=lambda t: (t[1] - t[2], t[0]))


def with_template_refined(study: Study, first: StageResult, coat: Callable[[Study], StageResult], *,
                          log: Log = None, progress: ProgressFn = None, cancelled: CancelledFn = None,
                          cache=None, cache_key: str | None = None) -> StageResult:
    """The coating result ``first`` (every instance of ``study`` coated), or the one of a template
    refined where it cut off parts of the instances' meshes.

    When ``[template] refine_where_cut_off`` is on and some instances' coatings cut off a part of
    their mesh (:func:`cut_off_instances`), the template is built again from its instance with its
    radii smaller at those places (:func:`~ssm_addon.pipeline.stages.cut_off_places`,
    ``denser_at`` of :func:`~ssm_addon.template.template.build_template`) and ``coat`` (the same
    coating as ``first``'s, on a copy of ``study`` with that template and no coatings) runs again.
    Its result is kept when it has fewer ``input_surface`` findings, no more findings of other
    gates (a refinement that only brings a mesh nearer, its finding left, is not worth the change
    of the template) and no instance's mesh farther from its coating (``FARTHER_TOLERANCE_MM``); it then carries the refined template (the model method's mean shape of it) with ``params["refined_at"]``: the instances, places and point
    counts. Esc during the refinement (the template or the second coating) keeps ``first``.

    ``cache`` (:class:`~ssm_addon.pipeline.cache.BuildCache`) with ``cache_key`` (the unrefined
    template's key): the refined template is stored and taken from there.
    """
    say = log or (lambda _m: None)
    names = cut_off_instances(first)
    if not study.params.template.refine_where_cut_off or not names:
        return first
    t0 = time.perf_counter()
    product = first.product
    instance = product.get("template_instance", study.template_instance)
    coated_from = product.get("template") or study.template
    # the places on the template built from the instance (the model method's coatings come from its
    # mean shape, with the same triangles; a template chosen from another instance: its mean shape)
    built = study.template if instance == study.template_instance and study.template is not None else coated_from
    places, factors, counts = cut_off_places(product["coatings"], product.get("cut_off") or {}, built, names,
                                             coated_from=coated_from)
    if not len(places):
        return first
    volumes = {**study.volumes, **product.get("volumes", {})}
    cp = study.params.correspondence
    params = study.params if instance == study.template_instance else dataclasses.replace(
        study.params, correspondence=dataclasses.replace(cp, template_choice="given"))
    frames = {**study.frames, **product.get("frames", {})}
    again = dataclasses.replace(study, template_instance=instance, params=params, volumes=volumes, frames=frames,
                                coatings={}, coating_start={}, correspondence_rounds=[], input_distances={}, cut_off={},
                                findings=list(study.findings), timings_s={}, fallbacks=[])
    say(f"template: the coatings of {len(counts)} instance(s) cut off parts of their meshes "
        f"({', '.join(f'{n} {k:,} vertex' if k == 1 else f'{n} {k:,} vertices' for n, k in counts.items())}); "
        f"the template again, denser at {len(places):,} place(s) (radii × {float(factors.min()):.2f}–{float(factors.max()):.2f})")
    report(progress, 0.0, f"template: again, denser where {len(counts)} coating(s) cut off parts")
    key = digest("refined template", cache_key, places, factors) if cache is not None and cache_key else None
    try:
        refined = cache.get_template(key) if key is not None else None
        if refined is None:
            if instance not in again.volumes:  # the streamed build took the template from its cache
                tp = study.params.template
                again.volumes[instance] = import_instance(study.instance(instance), spacing_mm=tp.spacing_mm,
                                                          frame_method=tp.frame, space=tp.space, cancelled=cancelled)
            refined = make_template(again, cancelled=cancelled, denser_at=(places, factors))
            if key is not None:
                cache.put_template(key, refined)
        t_template = time.perf_counter() - t0
        again.template = refined
        second = coat(again)
    except Cancelled:
        return dataclasses.replace(first, summary=tuple(first.summary) + (
            "template: the refinement was cancelled: the first coatings kept",))
    n0, n1 = len(built.points_object), len(refined.points_object)
    before, after = _worst(first), _worst(second)
    farther = _farther(first, second)
    kept = after[0] < before[0] and after[2] <= before[2] and not farther
    grew = ", ".join(f"{n} {a:.2f} → {b:.2f} mm" for n, a, b in farther[:3])
    if len(farther) > 3:
        grew += f" and {len(farther) - 3} more"
    line = (f"template: refined where {len(counts)} coating(s) cut off parts, {n0:,} → {n1:,} points in "
            f"{t_template:.2f} s; input_surface findings {before[0]} → {after[0]}, largest mesh distance "
            f"{before[1]:.2f} → {after[1]:.2f} mm" + (f" (farther from its coating on {grew})" if grew else "") + ": ")
    timings = {"template_refinement": t_template,
               "coating": float(first.timings_s.get("coating", 0.0)) + float(second.timings_s.get("coating", 0.0))}
    if not kept:
        return dataclasses.replace(first, timings_s={**first.timings_s, **timings},
                                   summary=tuple(first.summary) + (line + "the first coatings kept",))
    info = {"instances": counts, "places": int(len(places)), "points_before": int(n0), "points": int(n1),
            "factors": [round(float(factors.min()), 4), round(float(factors.max()), 4)],
            "input_surface_findings": [int(before[0]), int(after[0])],
            "largest_distance_mm": [round(before[1], 4), round(after[1], 4)]}
    template = second.product.get("template") or refined
    template = dataclasses.replace(template, params={**(template.params or {}), "refined_at": info})
    carried = {k: product[k] for k in ("template_choice", "template_instance") if k in product}
    out = {**carried, **second.product, "template": template}
    return dataclasses.replace(second, product=out, timings_s={**first.timings_s, **second.timings_s, **timings},
                               summary=tuple(second.summary) + (line + "kept",))

