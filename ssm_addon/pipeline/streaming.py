"""The streamed build: import, template and coating with bounded memory on an executor, each
instance read and coated by a worker, with the per-instance cache (the landmarks method)."""

from __future__ import annotations

import dataclasses
import time
from collections import Counter
from dataclasses import dataclass

import numpy as np

from ..base.errors import check_cancelled
from ..base.params import CoatingParams, QualityParams
from ..base.progress import CancelledFn, ProgressFn, report, sub_progress
from ..coating.coating import coat
from ..instances.importing import InstanceSpec, import_instance
from ..meshutil import Mesh
from ..model.metrics import import_plotting_in_background
from ..model.quality import (
    check_duplicate_instances,
    check_landmarks_on_surface,
    check_volume,
    check_volumes_together,
    content_digest,
)
from ..pipeline.cache import InstanceProduct, digest, file_digest
from .stages import coating_result, label_map_once, make_template, self_check, template_line
from .study import Log, StageResult, Study, common_landmark_names, instance_sources

__all__ = ["InstanceJob", "coat_from_source", "stream_instances", "template_key"]


@dataclass(frozen=True)
class InstanceJob:
    """Everything a worker needs to import and coat one instance (small and serialisable).

    The worker reads the instance's file itself: paths travel, volumes do not.

    Attributes
    ----------
    spec : InstanceSpec
        Source, label and landmarks (world mm).
    spacing_mm, frame_method, space : import settings (paper 2; ``[template] space``).
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
    space: str = "auto"

    def key(self) -> str:
        """The cache key (:mod:`ssm_addon.pipeline.cache`): every input that determines the product."""
        spec, qp = self.spec, self.quality_params
        lm = spec.landmarks.subset(self.landmark_names)
        return digest("instance", {"source": file_digest(spec.source), "kind": "volume" if spec.volume_path else "mesh",
                                   "label": spec.label, "mesh_spacing": spec.mesh_spacing_mm, "mirror": bool(spec.mirror),
                                   **({"space": spec.given_space(self.space)} if spec.mesh_path is not None else {})},
                      {"names": list(lm.names), "points_world": np.asarray(lm.points_world, float)},
                      {"spacing_mm": self.spacing_mm, "frame": self.frame_method},
                      np.asarray(self.template_points, float), np.asarray(self.template_faces, np.int64),
                      np.asarray(self.template_landmarks_object, float), self.coating_params.to_dict(),
                      {"min_voxels": qp.min_voxels, "max_second_component": qp.max_second_component,
                       "max_landmark_distance_mm": qp.max_landmark_distance_mm})


def coat_from_source(job: InstanceJob):
    """Import one instance from its file and coat the template onto it (paper 2 and 4).

    A pure function of ``job`` (runs in any process or on any Dask worker); the same
    calls as :func:`import_instances` + :func:`coat_instances`, so the numbers are
    identical. Returns an :class:`~ssm_addon.pipeline.cache.InstanceProduct`; the volume is
    dropped when the function returns.
    """
    spec, qp = job.spec, job.quality_params
    label_map = label_map_once(spec.volume_path) if job.shared_file and spec.volume_path is not None else None
    ov = import_instance(spec, spacing_mm=job.spacing_mm, frame_method=job.frame_method, label_map=label_map,
                         space=job.space)
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
    spec = study.instance(study.template_instance)
    lm = spec.landmarks
    return digest("template", {"source": file_digest(spec.source), "label": spec.label,
                               "mesh_spacing": spec.mesh_spacing_mm, **({"space": spec.space} if spec.space else {})},
                  {"names": list(lm.names), "points_world": np.asarray(lm.points_world, float)} if lm else None,
                  study.params.template.to_dict())


def stream_instances(study: Study, executor, *, cache=None, progress: ProgressFn = None,
                     cancelled: CancelledFn = None, log: Log = None, template=None) -> StageResult:
    """Import, template and coating with bounded memory (the landmarks method).

    Only the template instance's volume is held in this process; every other instance
    is read, framed, resampled and coated by :func:`coat_from_source` on ``executor``
    (:class:`~ssm_addon.base.compute.Executor`) and only its points come back, so memory
    grows with n·N, not with the volumes. With ``cache`` (:class:`~ssm_addon.pipeline.cache.BuildCache`)
    the template and every finished coating are stored at once and taken from there on
    a rerun. ``template``: coat this one (the template refined across the population), not the
    one its instance and parameters give. ``study`` is not changed: the result (stage
    ``"coating"``) carries the template, the coatings, frames and starts, the import and coating findings, the three stages'
    timings and the counts ``streamed = {"cached": k, "computed": m}``.
    """
    say = log or (lambda _m: None)
    names = list(study.names)
    common = common_landmark_names(study, names)
    tname = study.template_instance
    t0 = time.perf_counter()
    timings, volumes, frames = {}, {}, {}
    given = template is not None
    tkey = template_key(study) if cache is not None and not given else None
    if tkey is not None:
        template = cache.get_template(tkey)
        for note in cache.take_notes():
            say(note)
    if template is None:
        if len(names) > 1:  # the workers start (and import) while this process makes the template
            executor.start_workers(("ssm_addon.pipeline.streaming",))
        tspec = study.instance(tname)
        report(progress, 0.0, f"import: {tname} (template instance)")
        ov = import_instance(tspec, spacing_mm=study.params.template.spacing_mm,
                             frame_method=study.params.template.frame, space=study.params.template.space,
                             cancelled=cancelled)
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
        say(template_line(template, tname, study.params.template, time.perf_counter() - t0))
    elif not given:
        say("import: the coating workers read every instance (the template is in the cache)")
        say(f"template: {len(template.points_object)} points from the cache ({tname})")
    if not given:
        timings["template"] = time.perf_counter() - t0
    import_plotting_in_background()  # for the plots after the model, while the workers coat
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
                        quality_params=study.params.quality, space=study.params.template.space) for i in order]
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
    t_check = time.perf_counter()
    check, found = self_check(study, coatings, template=template, frames=frames, executor=executor,
                              cancelled=cancelled)
    result = coating_result(study, coatings, {n: c.fit.start for n, c in coatings.items()}, time.perf_counter() - t0,
                            template=template, frames=frames,
                            counts=f"{len(todo)} coated, {cached} from the cache; ", check=check, extra_findings=found,
                            executor=executor, cancelled=cancelled, check_seconds=time.perf_counter() - t_check)
    counts = {"cached": cached, "computed": len(todo)}
    return dataclasses.replace(
        result, product={**result.product, "template": template, "volumes": volumes, "frames": frames,
                         "streamed": counts},
        findings=tuple(findings) + result.findings, timings_s={**timings, **result.timings_s})
