"""The stage functions of the method: import (paper 2), template (3), coating by the single
pass (4), model (5) and metrics, each returning a :class:`~ssm_addon.pipeline.study.StageResult`
(product, findings, timings, summary) that both front ends apply."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from ..base.compute import executor_or_local
from ..base.errors import InputError, check_cancelled
from ..base.progress import CancelledFn, ProgressFn, report
from ..coating.coating import CoatingResult, coat_all, coat_from_start
from ..correspondence.frames import TWIST_FACTOR, TWIST_MIN_DEG, coating_twists, twisted
from ..correspondence.rounds import check_correspondence, correspondence_fit_params
from ..formats.label_maps import read_label_map
from ..formats.meshes import read_mesh
from ..instances.importing import InstanceSpec, import_instance, mesh_coordinates
from ..instances.volume import ObjectVolume, fill_cavities
from ..meshutil import (
    Mesh,
    MeshLocation,
    MeshLocator,
    genus,
    longest_edges,
    marching_cubes,
    outer_surface,
    two_way_distances,
)
from ..model import metrics
from ..model.metrics import ModelMetrics
from ..model.pca import ShapeModel, build_model
from ..model.quality import (
    Finding,
    check_coating,
    check_duplicate_instances,
    check_frames,
    check_input_surface,
    check_landmark_transfer,
    check_landmarks_on_surface,
    check_model,
    check_volume,
    check_volumes_together,
    content_digest,
)
from ..template.template import TOLERANCE_SHRINK, Template, build_template
from .study import (
    StageResult,
    Study,
    common_landmark_names,
    instance_sources,
    study_parameters,
    template_landmark_locations,
)

__all__ = ["coat_from_frames", "coat_instances", "coating_result", "cut_off_places", "evaluate_model", "import_instances", "import_result", "import_stage", "label_map_once", "make_model", "make_template", "metrics_stage", "model_stage", "self_check", "template_stage"]


_LABEL_MAP_MEMO: dict = {}


def label_map_once(path) -> object:
    """A label map that holds several instances, read once per process (the last one kept).

    Raises
    ------
    InputError
        The file cannot be read as a label map (the message names the instances' file)."""
    st = Path(path).stat()
    key = (str(path), st.st_size, st.st_mtime_ns)
    if key not in _LABEL_MAP_MEMO:
        _LABEL_MAP_MEMO.clear()
        try:
            _LABEL_MAP_MEMO[key] = read_label_map(path)
        except InputError as err:
            raise InputError(f"instances using {Path(path).name}: {err}") from None
    return _LABEL_MAP_MEMO[key]


def _import_job(args) -> ObjectVolume:
    inst, spacing_mm, frame_method, space, shared_file = args
    label_map = label_map_once(inst.volume_path) if shared_file else None
    return import_instance(inst, spacing_mm=spacing_mm, frame_method=frame_method, space=space, label_map=label_map)


def import_instances(study: Study, *, names: Sequence[str] | None = None, jobs: int = 1,
                     progress: ProgressFn = None, cancelled: CancelledFn = None,
                     executor=None) -> dict[str, ObjectVolume]:
    """Read every instance, compute its object frame and resample it (paper 2).

    With an ``executor`` (:class:`~ssm_addon.base.compute.Executor`) the instances are
    imported on its workers, each of which reads a label map shared by several instances
    once; without, in this process: shared label maps read once, and with ``jobs`` > 1 the
    instances in threads (the numeric work releases the GIL). The volumes do not depend on
    where they were made.

    Returns
    -------
    dict name -> ObjectVolume, in study order (only ``names``, default all).
    """
    todo = [study.instance(n) for n in (study.names if names is None else names)]
    n = len(todo)
    tp = study.params.template
    paths = [inst.volume_path for inst in todo if inst.volume_path is not None]
    many = {p for p in paths if paths.count(p) > 1}
    if executor is not None and n > 1:
        volumes = executor.map(_import_job, [(inst, tp.spacing_mm, tp.frame, tp.space, inst.volume_path in many)
                                             for inst in todo],
                               labels=[inst.name for inst in todo], verb="imported", progress=progress,
                               cancelled=cancelled)
        return {inst.name: ov for inst, ov in zip(todo, volumes)}
    shared = {}
    for path in sorted(many):
        check_cancelled(cancelled)
        try:
            shared[path] = read_label_map(path)
        except InputError as err:
            raise InputError(f"instances using {path.name}: {err}") from None
    done = [0]

    def one(inst: InstanceSpec) -> ObjectVolume:
        check_cancelled(cancelled)
        ov = import_instance(inst, spacing_mm=tp.spacing_mm, frame_method=tp.frame, space=tp.space,
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


def make_template(study: Study, *, progress: ProgressFn = None, cancelled: CancelledFn = None,
                  params=None, denser_at=None) -> Template:
    """The template (paper 3) from the study's template instance (``params``: template parameters
    other than the study's, e.g. radii scaled to a given point count; ``denser_at``: places and
    factors where it must be denser, :func:`~ssm_addon.template.template.build_template`)."""
    name = study.template_instance
    try:
        template = build_template(study.volume(name), params or study.params.template, progress=progress,
                                  cancelled=cancelled, denser_at=denser_at)
    except InputError as err:
        raise InputError(f"template from instance {name!r}: {err}") from None
    study_with = Study(instances=study.instances, template_instance=name, template=template, frames={
        name: study.frame(name)})
    return dataclasses.replace(template, landmark_locations=template_landmark_locations(study_with))


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

    template, target, params, name = args
    return coat_from_start(template, target, params=params, name=name)


def coat_from_frames(study: Study, names: Sequence[str], *, jobs: int = 1, cancelled: CancelledFn = None,
                     executor=None) -> dict[str, CoatingResult]:
    """Coat the template onto instances from the object frames alone (no landmarks; paper 2's
    alignment, then the coating's registration, projection and relaxation), on ``executor``
    (default: ``jobs`` local processes)."""
    mesh = Mesh(study.template.points_object, study.template.faces)
    args = [(mesh, study.volume(n), study.params.coating, n) for n in names]
    with executor_or_local(executor, jobs, len(args)) as pool:
        results = pool.map(_coat_from_frames_job, args, labels=list(names), verb="coated", cancelled=cancelled)
    return dict(zip(names, results))


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
    # the frames' methods as resolved ("auto": patient for images and meshes in a known convention)
    params["frame_methods"] = sorted({study.frame(n).method for n in names})
    params["fit"] = {n: {k: v for k, v in study.coatings[n].fit.to_dict().items() if k != "time_s"} for n in names}
    # instances mirrored into the template's side: their world points (instance_points_world) are in their own
    params["mirrored"] = [n for n in names if study.frame(n).mirrored]
    mp = study.params.model
    return build_model(pts, study.template.faces, names, instance_points_world=world, alignment=mp.alignment,
                       n_modes=mp.n_modes, variance_fraction=mp.variance_fraction, solver=mp.solver,
                       precision=mp.precision, params=params, progress=progress, cancelled=cancelled)


def evaluate_model(study: Study, *, progress: ProgressFn = None, cancelled: CancelledFn = None,
                   specificity_samples: int | None = None) -> ModelMetrics:
    """Compactness, generalization and specificity of the study's model (``[model]``'s
    samples, seed and leave-one-out limit; ``specificity_samples`` overrides the samples)."""
    if study.model is None:
        raise InputError("metrics: build the model first")
    mp = study.params.model
    n = mp.specificity_samples if specificity_samples is None else int(specificity_samples)
    return metrics.evaluate(study.model, n_samples=n, seed=mp.seed, max_loo=mp.max_loo, progress=progress,
                            cancelled=cancelled)


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
                 cancelled: CancelledFn = None, executor=None) -> StageResult:
    """Import (paper 2): :func:`import_instances` (on ``executor`` when given) and the import gates."""
    t0 = time.perf_counter()
    volumes = import_instances(study, names=names, jobs=jobs, progress=progress, cancelled=cancelled,
                               executor=executor)
    return import_result(study, volumes, time.perf_counter() - t0)


def template_stage(study: Study, *, progress: ProgressFn = None, cancelled: CancelledFn = None) -> StageResult:
    """The template (paper 3): :func:`make_template` and its summary line."""
    t0 = time.perf_counter()
    t = make_template(study, progress=progress, cancelled=cancelled)
    seconds = time.perf_counter() - t0
    return StageResult("template", {"template": t}, (), {"template": seconds},
                       (template_line(t, study.template_instance, study.params.template, seconds),))


def template_line(template: Template, instance: str, params, seconds: float) -> str:
    """The template's summary line, the same in the staged and the streamed build."""
    n = len(template.points_object)
    return (f"template: {n} points, {len(template.faces)} triangles, genus {genus(n, template.faces)} from "
            f"{instance}{template_density(template, params)} in {seconds:.2f} s")


def template_density(template: Template, params) -> str:
    """How the template's density was set, for its summary line: the tolerance and the largest
    distance reached (``[template] max_distance_mm``), or eq. 1's radii; then how far the
    instance's own surface lies from the template's triangles at most (a notch or a tip the
    template cuts off)."""
    found = template.params or {}
    back = found.get("surface_largest_distance_mm")
    back = "" if back is None else f", its surface within {back:.2f} mm of it"
    if params.max_distance_mm is not None and "largest_distance_mm" in found:
        return (f", within {found['largest_distance_mm']:.2f} mm of its surface (mean "
                f"{found.get('mean_distance_mm', float('nan')):.2f} mm; tolerance {params.max_distance_mm:g} mm){back}")
    if params.max_distance_mm is None:
        return f", radii of eq. 1 ({params.r_min_mm:g}-{params.r_max_mm:g} mm){back}"
    return back


def _input_distance_job(args):
    path, convention, points_world, faces, beyond_mm, spec, import_args, template_points = args
    vertices, mesh_faces, cavities = outer_surface(*read_mesh(path, space=convention))
    d, far, location = two_way_distances(points_world, faces, vertices, mesh_faces, beyond_mm=beyond_mm,
                                         return_far=True)
    beyond = d["from_other"].get("beyond")
    if beyond and beyond["count"]:
        beyond["voxels"] = beyond_the_voxels(vertices[far], points_world, faces, spec, import_args)
        beyond["stretch"] = coating_stretch(location.triangles, points_world, faces, template_points)
    figures = {"to_input": d["to_other"], "from_input": d["from_other"]}
    if cavities["components"]:
        figures["cavities"] = cavities
    return figures, location


def coating_stretch(triangles: np.ndarray, points: np.ndarray, faces: np.ndarray,
                    template_points: np.ndarray) -> float:
    """How many times as long as the template's own the coating's triangles are where far points
    lie: the largest ratio of longest edges over ``triangles`` (the far points' nearest triangles
    of the coating) and the triangles around those (sharing a corner: which of two triangles is
    nearest to a point on their common edge does not matter). ``points``, ``faces``: the coating
    (mm); ``template_points``: the template's, any frame, the same ``faces``. Near 1 where the
    coating keeps the template's spacing; well above where the template is stretched over a part
    larger than its instance's, and too sparse for it."""
    faces = np.asarray(faces)
    if not len(triangles):
        return 1.0
    near = faces[np.isin(faces, faces[np.asarray(triangles)]).any(axis=1)]
    return float((longest_edges(points, near) / np.maximum(longest_edges(template_points, near), 1e-12)).max())


def beyond_the_voxels(far: np.ndarray, points_world: np.ndarray, faces: np.ndarray, spec: InstanceSpec,
                       import_args: dict) -> dict:
    """Of a mesh's vertices far from its coating (``far``, world mm), how many are far mostly
    because the import lost the part (``count``): the vertex lies farther from the instance's
    own voxels (the import at the study's spacing, which the coating follows) than the voxel
    surface nearest to it lies from the coating (``points_world``, ``faces``); a part finer
    than a voxel is lost there, not by the coating. ``max_mm``: the largest of those vertices'
    distances to the voxels; ``spacing_mm``: the voxels' edge."""
    ov = import_instance(spec, **import_args)
    grid, grid_faces = marching_cubes(fill_cavities(ov.mask))  # the surface the coating follows
    surface = ov.frame.to_world(ov.voxel_to_object(grid))
    on_voxels, from_voxels, _t, _b = MeshLocator(surface, grid_faces).query(far, k=12)
    _c, voxels_from_coating, _t, _b = MeshLocator(points_world, faces).query(on_voxels, k=12)
    return {"count": int((from_voxels >= voxels_from_coating).sum()), "spacing_mm": float(ov.spacing_mm),
            "max_mm": float(from_voxels.max()) if len(far) else 0.0}


def cut_off_places(coated: dict[str, CoatingResult], cut_off: dict[str, MeshLocation], template: Template,
                   names: Sequence[str], *, coated_from: Template | None = None,
                   ) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """Where the coatings of ``names`` cut off parts of their own meshes, as places of the template,
    and how much denser it must be there.

    ``cut_off``: each instance's mesh vertices beyond ``[quality] max_input_distance_mm``, as their
    nearest points of its coating (:func:`input_distances`' ``cut_off``; a triangle and barycentric
    weights), which are the same places of ``template`` (the same triangles: object mm of the
    template's instance). The factor on the template's radii there is
    :data:`~ssm_addon.template.template.TOLERANCE_SHRINK`, or less where the coating's triangles
    around that one are more than 1/``TOLERANCE_SHRINK`` times as long as ``coated_from``'s (the
    template the coatings were made from, default ``template``): the inverse of that stretch, so
    the coated triangles there come out no longer than the template's are now.

    Returns
    -------
    places : (K, 3) object mm of ``template``
    factors : (K,) in (0, TOLERANCE_SHRINK]
    counts : dict name -> the instance's vertices taken
    """
    faces = np.asarray(template.faces)
    reference = longest_edges(np.asarray((coated_from or template).points_object, float), faces)
    places, factors, counts = [], [], {}
    for name in names:
        location = cut_off.get(name)
        if location is None or name not in coated or not len(location.triangles):
            continue
        ratio = longest_edges(coated[name].points_object, faces) / np.maximum(reference, 1e-12)
        at_vertex = np.zeros(len(coated[name].points_object))
        np.maximum.at(at_vertex, faces.ravel(), np.repeat(ratio, 3))  # the largest ratio of a vertex's triangles
        stretch = at_vertex[faces[location.triangles]].max(axis=1)  # over the triangles sharing a corner
        places.append(location.evaluate(template.points_object, faces))
        factors.append(np.minimum(TOLERANCE_SHRINK, 1.0 / np.maximum(stretch, 1e-12)))
        counts[name] = int(len(location.triangles))
    if not places:
        return np.zeros((0, 3)), np.zeros(0), counts
    return np.concatenate(places), np.concatenate(factors), counts


def input_distances(study: Study, coated: dict[str, CoatingResult], template: Template,
                    frames: dict | None = None, *, executor=None, cancelled: CancelledFn = None,
                    ) -> tuple[dict[str, dict], dict[str, MeshLocation]]:
    """For every coated instance given as a mesh file: the coating against the user's own mesh
    (world mm, the file read as the import reads it; its outer surface: the walls of internal
    cavities, closed parts inside the object, are left out, as the template fills cavities, and
    counted in ``cavities``, :func:`~ssm_addon.meshutil.outer_surface`), both ways (:func:`~ssm_addon.meshutil.two_way_distances`:
    ``to_input`` from the coated points to the mesh, ``from_input`` from the mesh's vertices to
    the coated surface: large where the template's points do not reach a thin process; its
    ``beyond``: the vertices farther than ``[quality] max_input_distance_mm``, how many and where,
    ``beyond["voxels"]``: how many of them are far mostly because the import's spacing, not
    the coating, lost the part, :func:`beyond_the_voxels`; ``beyond["stretch"]``: how many times as
    long as the template's (``template``) the coating's triangles are there, :func:`coating_stretch`).
    Second, ``cut_off``: per instance with such vertices, their nearest points of its coating
    (:class:`~ssm_addon.meshutil.MeshLocation`), where the template's refinement makes it denser.

    ``executor``: where the instances are measured (the build's workers; default this process).
    """
    frames = {**study.frames, **(frames or {})}
    tp = study.params.template
    names, args = [], []
    for name, c in coated.items():
        spec = study.instance(name)
        if spec.mesh_path is None or name not in frames:
            continue
        convention, _note = mesh_coordinates(spec.mesh_path, spec.given_space(tp.space))
        names.append(name)
        args.append((spec.mesh_path, convention, frames[name].to_world(c.points_object), np.asarray(template.faces),
                     float(study.params.quality.max_input_distance_mm), spec,
                     {"spacing_mm": tp.spacing_mm, "frame_method": tp.frame, "space": tp.space},
                     np.asarray(template.points_object)))
    if not args:
        return {}, {}
    with executor_or_local(executor, 1) as pool:
        found = pool.map(_input_distance_job, args, labels=names, verb="measured against its mesh", cancelled=cancelled)
    return ({n: figures for n, (figures, _l) in zip(names, found)},
            {n: location for n, (_f, location) in zip(names, found) if len(location.triangles)})


def coating_result(study: Study, coated: dict[str, CoatingResult], starts: dict[str, str], seconds: float, *,
                   template: Template | None = None, rounds: tuple = (), counts: str = "", check=None,
                   extra_findings: tuple = (), frames: dict | None = None, executor=None,
                   cancelled: CancelledFn = None, check_seconds: float | None = None) -> StageResult:
    """The coating stage's result for ``coated`` instances: the coating gates and the summary.

    ``template`` (the mean shape of the model method), ``rounds`` (its refinement rounds)
    and ``check`` (the correspondence self-check, :func:`self_check`) join the product
    when given; ``extra_findings`` (the self-check's and the rounds' gates) the findings.
    Instances given as meshes are also measured against their own mesh
    (:func:`input_distances` on ``executor``, ``frames``: object frames the study does not hold
    yet) and gated (:func:`~ssm_addon.model.quality.check_input_surface`). ``check_seconds``:
    the self-check's part of ``seconds``, reported as ``coating_self_check``.
    """
    qp = study.params.quality
    findings = tuple(f for n, c in coated.items() for f in check_coating(n, c.fit, qp))
    distances, cut_off = input_distances(study, coated, template if template is not None else study.template, frames,
                                executor=executor, cancelled=cancelled)
    findings += tuple(f for n, d in distances.items() for f in check_input_surface(n, d, qp, study.params.template))
    findings += tuple(extra_findings)
    product = {"coatings": dict(coated), "coating_start": dict(starts), "input_distances": distances,
               "cut_off": cut_off}
    if template is not None:
        product["template"] = template
    if rounds:
        product["correspondence_rounds"] = tuple(rounds)
    if check is not None:
        product["correspondence_check"] = check
    every = {**study.coatings, **coated}
    worst = max((c.fit.max_distance_mm for c in every.values()), default=float("nan"))
    lines = [f"coating: {len(coated)} instances in {seconds:.2f} s ({counts}largest surface distance {worst:.2f} mm)"]
    hollow = {n: d["cavities"] for n, d in distances.items() if d.get("cavities")}
    if hollow:
        each = ", ".join(f"{n} {c['components']}" for n, c in hollow.items())
        lines.append(f"coating: the meshes of {len(hollow)} instance(s) hold internal cavities, closed surfaces inside "
                     f"the object ({each}); the template fills cavities, so their walls are not measured against the "
                     "coatings")
    if check is not None and check.instance_mm:
        worst_n = max(check.instance_mm, key=check.instance_mm.get)
        lines.append(f"coating: correspondence self-check, landmark transfer error {check.study_mm:.2f} mm (mean over "
                     f"{len(check.instance_mm)} landmarked instances; largest {worst_n} "
                     f"{check.instance_mm[worst_n]:.2f} mm)")
    timings = {"coating": seconds} | ({} if check_seconds is None else {"coating_self_check": check_seconds})
    return StageResult("coating", product, findings, timings, tuple(lines))


def self_check(study: Study, coatings: dict[str, CoatingResult], *, template: Template | None = None,
               frames: dict | None = None, jobs: int = 1, executor=None, cancelled: CancelledFn = None):
    """The correspondence self-check of the single pass (``[correspondence] self_check``):
    :func:`ssm_addon.correspondence.rounds.check_correspondence` on every instance's coating.

    Returns ``(CorrespondenceCheck, findings)``, or ``(None, ())`` when it does not apply
    (switched off, fewer than 3 instances or instances not all coated, no landmarks).
    """
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


def model_stage(study: Study, *, progress: ProgressFn = None, cancelled: CancelledFn = None) -> StageResult:
    """The model (paper 5): :func:`make_model`, its leave-one-out outlier scores and the model gates."""
    t0 = time.perf_counter()
    model = make_model(study, progress=progress, cancelled=cancelled)
    findings, scores = check_model(model, study.params.quality)
    names = list(model.instance_names)
    findings = check_frames(names, np.stack([study.coatings[n].points_object for n in names]),
                            study.template_instance, study.params.model.alignment) + list(findings)
    findings += twist_findings(study, names)
    seconds = time.perf_counter() - t0
    return StageResult("model", {"model": model, "outlier_scores": scores}, tuple(findings), {"model": seconds},
                       (f"model: {model.n_modes} modes, {model.n_points} points in {seconds:.2f} s",))


def twist_findings(study: Study, names: Sequence[str], *, twists: dict | None = None) -> list[Finding]:
    """The ``twist`` gate: coatings whose points are turned on their own surface against the others'
    (:func:`~ssm_addon.correspondence.frames.coating_twists`), more than
    :data:`~ssm_addon.correspondence.frames.TWIST_MIN_DEG` and
    :data:`~ssm_addon.correspondence.frames.TWIST_FACTOR` times the median instance's turn.

    Only where some instance has no landmarks: landmarks pin the turn a coating could take on its
    surface (the gate costs about 0.06 s an instance). ``twists``: already measured (a joint
    build measures them for the relative pose's noise)."""
    names = list(names)
    if len(names) < 3 or study.template is None or all(study.landmarks(n) is not None for n in names):
        return []
    reference = study.template_instance if study.template_instance in names else names[0]
    if twists is None:
        twists = coating_twists({n: study.coatings[n].points_object for n in names}, study.template.faces, reference)
    twists = {n: twists[n] for n in names}
    named, limit = twisted(twists)
    median = float(np.median([t.angle_deg for t in twists.values()]))
    return [Finding(n, "twist", f"its coating is turned {t.angle_deg:.1f}° about {t.axis_name} against its own "
                                f"surface's fit to the mean shape (allowed {limit:.1f}°: {TWIST_FACTOR:g}× the median "
                                f"instance's {median:.1f}°, at least {TWIST_MIN_DEG:g}°): its points lie on its surface "
                                "in places turned against the others', which the model reads as shape (or as relative "
                                "pose); give it landmarks (three or more, around that axis)", t.angle_deg, limit)
            for n, t in named.items()]


def metrics_stage(study: Study, *, progress: ProgressFn = None, cancelled: CancelledFn = None,
                  specificity_samples: int | None = None) -> StageResult:
    """Compactness, generalization and specificity (:func:`evaluate_model`)."""
    t0 = time.perf_counter()
    metrics = evaluate_model(study, progress=progress, cancelled=cancelled, specificity_samples=specificity_samples)
    seconds = time.perf_counter() - t0
    return StageResult("metrics", {"metrics": metrics}, (), {"metrics": seconds},
                       (f"metrics: compactness, generalization, specificity in {seconds:.2f} s",))
