"""The headless build: a project's stages end to end, with owned outputs.

:func:`build` runs the study's stages (:mod:`ssm_addon.pipeline.study`) on a parsed project
(:func:`ssm_addon.pipeline.project.read_project`) and writes the outputs atomically:
everything goes into a temporary folder next to the output folder and is moved into place
only when the whole build succeeded.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..analysis.attributes import write_attributes
from ..analysis.files import analysis_summary, run_analysis
from ..base.compute import Executor
from ..base.errors import InputError, check_cancelled
from ..base.progress import CancelledFn, ProgressFn, report, sub_progress
from ..formats.meshes import read_mesh
from ..model.quality import QualityError, warnings_text
from .cache import BuildCache
from .joint import JointStudy, run_joint
from .outputs import absolute_files, check_output_folder, check_writable, owned_output_folder, write_joint, write_study
from .project import Project, project_text, read_project, write_project  # noqa: F401 (the flat layout's imports)
from .runner import run
from .study import Study


@dataclass(frozen=True)
class BuildResult:
    """What :func:`build` produced.

    Attributes
    ----------
    out_dir : Path
        The output folder (final location).
    project : Project
    study : Study
        Every stage's product (volumes, template, coatings, model, metrics).
    files : dict
        Output name -> path (final location).
    report : dict
        The content of ``report.json``.
    joint : JointStudy or None
        A multi-structure project's joint study (``study`` is then its first structure's, holding
        the joint model).
    """

    out_dir: Path
    project: Project
    study: Study
    files: dict
    report: dict
    joint: JointStudy | None = None

    @property
    def template(self):
        return self.study.template

    @property
    def model(self):
        return self.study.model

    @property
    def metrics(self):
        """The model's :class:`~ssm_addon.model.metrics.ModelMetrics`."""
        return self.study.metrics

    @property
    def timings_s(self) -> dict:
        """Seconds per stage (a joint build: per structure, then the joint model's stages)."""
        if self.joint is not None:
            return dict(self.report.get("timings_s") or {})
        return self.study.timings_s


def write_analysis_files(project: Project, model, folder: Path, *, timings: dict | None = None, log=None,
                         progress=None, cancelled=None) -> tuple[dict, dict | None]:
    """The project's attributes (``attributes.csv``) and, with an ``[analysis]`` group or
    covariates, the analysis of the built ``model`` (``analysis/``; a joint model's with the
    effects on the structures' relative pose). Returns the files written and ``report.json``'s
    ``analysis`` entry (None without an analysis); its time goes into ``timings["analysis"]``.
    An analysis that fails is a loud warning: the model stays."""
    say = log or (lambda _msg: None)
    if project.attributes is None:
        return {}, None

    names = [str(n) for n in model.instance_names]
    aligned, _ = project.attributes.aligned(names)
    write_attributes(aligned, folder / "attributes.csv")
    files = {"attributes": "attributes.csv"}
    if not project.params.analysis.requested:
        return files, None
    t0 = time.perf_counter()
    report(progress, 0.97, "analysis: groups and covariates")
    try:
        result, adoc, _ = run_analysis(model, project.attributes, project.params.analysis, folder / "analysis",
                                       model_path="model.npz", cancelled=cancelled)
    except InputError as err:
        say(f"WARNING analysis: not run: {err}")
        return files, {"error": str(err)}
    for line in analysis_summary(result):
        say(f"analysis: {line}")
    for w in result.warnings:
        say(f"WARNING analysis: {w}")
    files["analysis"] = "analysis"
    if timings is not None:
        timings["analysis"] = time.perf_counter() - t0
    return files, adoc


def _check_before_build(project: Project, out_dir: Path, *, force: bool, what: str) -> list[Path]:
    """The checks before any work: the output folder (never an input, never another tool's files
    unless forced, writable) and enough ``what`` (instances, subjects) for a model with its
    metrics. Returns the project's input files."""
    inputs = [project.path, *project.input_files]
    if project.params.analysis.attributes:
        inputs.append(Path(project.params.analysis.attributes))
    check_output_folder(out_dir, inputs, force=force)
    check_writable(out_dir)
    if len(project.instances) < 3:
        raise InputError(f"{project.path}: {len(project.instances)} {what}; a model with its metrics (leave-one-out "
                         "generalization) needs at least 3")
    return inputs


@contextlib.contextmanager
def _executor(project: Project, jobs: int, scheduler: str | None, say):
    """The build's executor (``scheduler`` or the project's ``[compute]``), its note said; its
    workers draw the pictures while the files are written."""
    with Executor(scheduler or project.params.compute.scheduler, jobs, tasks=len(project.instances),
                  connect_timeout_s=project.params.compute.connect_timeout_s) as executor:
        if executor.note:
            say(f"compute: {executor.note}")
        yield executor


def open_cache(project: Project, out_dir: Path, cache=None):
    """The build's :class:`~ssm_addon.pipeline.cache.BuildCache`, or None when it is off.

    ``cache``: a folder, "auto" (``DIR.cache`` beside ``out_dir``), "off", or None for
    the project's ``[compute] cache``.

    Raises
    ------
    InputError
        The cache folder is the output folder or inside it (a build replaces that
        folder), or it is an input file.
    """
    setting = project.params.compute.cache if cache is None else str(cache)
    if setting == "off":
        return None
    folder = out_dir.parent / f"{out_dir.name}.cache" if setting == "auto" else Path(setting).expanduser().resolve()
    if folder == out_dir or out_dir in folder.parents:
        raise InputError(f"--cache {folder}: inside the output folder {out_dir}, which a build replaces; put the "
                         "cache beside it")
    inputs = {p.resolve() for i in project.instances for p in (i.volume_path, i.mesh_path, i.landmarks_path) if p is not None}
    if folder in inputs or any(folder in p.parents for p in inputs):
        raise InputError(f"--cache {folder}: holds the study's input files; choose another folder")
    return BuildCache(folder)


def build(
    project: Project,
    out_dir,
    *,
    jobs: int = 1,
    progress: ProgressFn = None,
    cancelled: CancelledFn = None,
    log: Callable[[str], None] | None = print,
    blend: bool | None = None,
    blender_hook: Callable | None = None,
    force: bool = False,
    scheduler: str | None = None,
    cache=None,
) -> BuildResult:
    """Run the whole pipeline and write the outputs into ``out_dir`` atomically.

    The stages of :func:`ssm_addon.pipeline.runner.run`: import and object frames (paper 2) →
    template (paper 3) → coating (paper 4, ``jobs`` processes) → model (paper 5, eqs.
    4–6) → compactness, generalization, specificity → files.

    Parameters
    ----------
    project : Project
        From :func:`read_project`.
    out_dir : path
        Output folder. Everything is written into a temporary folder beside it and moved
        into place only when the build succeeded; a failing or cancelled build leaves
        ``out_dir`` untouched.
    jobs : int
        Parallel workers for the per-instance work (import: threads; coating:
        processes). Results equal the serial run.
    progress, cancelled : callables
        ``progress(fraction, message)`` once per step and per instance.
    log : callable or None
        Receives one summary line per finished stage.
    blend : bool or None
        Also write ``model.blend`` and ``modes.png`` through ``blender_hook``; None: when
        a hook is given and the project's ``[output] blend`` says so.
    blender_hook : callable, optional
        ``hook(result, tmp_dir, log) -> dict of written files``, called before the final
        move (the command line passes the Blender writer when ``bpy`` is importable; the
        core never imports ``bpy`` itself).
    force : bool
        Write into an existing folder that holds files an SSM build did not write (they
        are kept; see :func:`check_output_folder`).
    scheduler : str, optional
        Where the per-instance work runs (:mod:`ssm_addon.base.compute`); default the
        project's ``[compute] scheduler``.
    cache : path, "auto", "off" or None
        The per-instance cache (:mod:`ssm_addon.pipeline.cache`); None: the project's ``[compute]
        cache`` ("auto": ``DIR.cache`` beside ``out_dir``). A rerun takes every entry
        whose inputs and parameters are unchanged from there.

    The output folder then holds exactly this build's files (listed in
    ``.ssm-build.json``): outputs of an earlier build that this one does not write are
    removed, files the build did not write are never touched.
    """
    say = log or (lambda _msg: None)
    out_dir = Path(out_dir).expanduser().resolve()
    if project.structures:
        return build_joint(project, out_dir, jobs=jobs, progress=progress, cancelled=cancelled, log=say, force=force,
                           scheduler=scheduler, cache=cache, blend=blend, blender_hook=blender_hook)
    inputs = _check_before_build(project, out_dir, force=force, what="instances")
    t_total = time.perf_counter()
    study = Study.from_project(project)
    build_cache = open_cache(project, out_dir, cache)
    if project.params.correspondence.method == "model" and build_cache is not None:
        say("cache: not used by [correspondence] method = \"model\" (its rounds depend on every instance)")
        build_cache = None
    with owned_output_folder(out_dir, inputs, force=force, cancelled=cancelled) as tmp:
        with _executor(project, jobs, scheduler, say) as executor:  # open until the files are written
            run(study, jobs=jobs, progress=sub_progress(progress, 0.0, 0.95), cancelled=cancelled, log=say,
                executor=executor, cache=build_cache)
            check_cancelled(cancelled)
            if project.params.quality.strict and study.findings:
                raise QualityError(f"{len(study.findings)} quality gate(s) failed and [quality] strict is set; "
                                   f"nothing was written to {out_dir}:\n" + warnings_text(study.findings))
            use_blend = project.params.output.blend if blend is None else blend
            compute = {"scheduler": executor.scheduler, "workers": executor.jobs,
                       "cache": str(build_cache.folder) if build_cache is not None else None,
                       "from_cache": study.streamed.get("cached", 0),
                       "computed": study.streamed.get("computed", len(study.names))}
            files, final_report = write_study(
                study, tmp, output=project.params.output, project=str(project.path),
                title=f"SSM Builder: {project.path.stem}", blender_hook=blender_hook if use_blend else None,
                analysis=lambda folder: write_analysis_files(project, study.model, folder, timings=study.timings_s,
                                                             log=say, progress=progress, cancelled=cancelled),
                extra={"compute": compute}, log=say, progress=progress, cancelled=cancelled, t_start=t_total,
                executor=executor)
        result = BuildResult(out_dir=out_dir, project=project, study=study, files={}, report={})
    final = absolute_files(files, out_dir)
    report(progress, 1.0, f"done: {out_dir}")
    return dataclasses.replace(result, files=final, report=final_report.to_dict())


def _check_joint_meshes(project: Project) -> None:
    """Every structure's mesh of every subject read before anything is coated: an empty or flat mesh is
    refused naming the subject, the structure and the file (one structure's fault would otherwise stop
    the build after the others were coated)."""
    for name, structure in project.structures.items():
        for spec in structure.instances:
            if spec.mesh_path is None:
                continue
            where = f"subject {spec.name!r}, structure {name!r}: {spec.mesh_path}"
            try:
                vertices, faces = read_mesh(spec.mesh_path, space=spec.given_space(structure.params.template.space))
            except InputError as err:
                raise InputError(f"subject {spec.name!r}, structure {name!r}: {err}") from None
            if len(faces) == 0 or len(vertices) < 4:
                raise InputError(f"{where}: the mesh is empty ({len(vertices)} vertices, {len(faces)} triangles)")
            extent = np.ptp(np.asarray(vertices, float), axis=0)
            if np.sort(extent)[0] <= 1e-6 * max(float(extent.max()), 1e-12):
                raise InputError(f"{where}: the mesh is flat (its extent is {', '.join(f'{e:.3g}' for e in extent)} "
                                 "mm): a closed surface of the structure is needed")


def build_joint(project: Project, out_dir: Path, *, jobs: int = 1, progress: ProgressFn = None,
                cancelled: CancelledFn = None, log: Callable[[str], None] | None = None, force: bool = False,
                scheduler: str | None = None, cache=None, blend: bool | None = None,
                blender_hook: Callable | None = None) -> BuildResult:
    """:func:`build` of a project whose instances hold several structures: every structure's study,
    then the joint model (:mod:`ssm_addon.pipeline.joint`), with the same output rules.
    ``blender_hook(joint, output, folder, log)`` gets the :class:`JointStudy` and writes ``modes.png``
    of the joint model and a ``model.blend`` with every structure's instances, landmarks and coated
    meshes and the joint model (when ``blend``, or the project's ``[output] blend`` if None)."""
    say = log or (lambda _msg: None)
    inputs = _check_before_build(project, out_dir, force=force, what="subjects")
    _check_joint_meshes(project)
    t_total = time.perf_counter()
    joint = JointStudy.from_project(project)
    build_cache = open_cache(project, out_dir, cache)
    if any(st.params.correspondence.method == "model" for st in project.structures.values()):
        build_cache = None
    with owned_output_folder(out_dir, inputs, force=force, cancelled=cancelled) as tmp:
        with _executor(project, jobs, scheduler, say) as executor:
            run_joint(joint, jobs=jobs, progress=sub_progress(progress, 0.0, 0.95), cancelled=cancelled, log=say,
                      executor=executor, cache=build_cache)
            check_cancelled(cancelled)
            every = [f for study in joint.structures.values() for f in study.findings] + joint.findings
            if project.params.quality.strict and every:
                raise QualityError(f"{len(every)} quality gate(s) failed and [quality] strict is set; nothing was written "
                                   f"to {out_dir}:\n" + warnings_text(every))
            first = next(iter(joint.structures.values()))
            blender_files = {}
            use_blend = project.params.output.blend if blend is None else blend
            if blender_hook is not None and use_blend:
                t_blender = time.perf_counter()
                report(progress, 0.95, "Blender: model.blend and pictures")
                blender_files = blender_hook(joint, project.params.output, tmp, say) or {}
                joint.timings_s["blender"] = time.perf_counter() - t_blender
            files, final_report = write_joint(joint, tmp, output=project.params.output, project=str(project.path),
                                              files=blender_files,
                                              title=f"SSM Builder: {project.path.stem} (joint)", log=say,
                                              progress=progress, cancelled=cancelled, t_start=t_total,
                                              analysis=lambda folder: write_analysis_files(
                                                  project, joint.model, folder, timings=joint.timings_s, log=say,
                                                  progress=progress, cancelled=cancelled),
                                              extra={"compute": {"scheduler": executor.scheduler, "workers": executor.jobs}},
                                              executor=executor)
    final = absolute_files(files, out_dir)
    report(progress, 1.0, f"done: {out_dir}")
    first.model = joint.model
    first.metrics = joint.metrics
    return BuildResult(out_dir=out_dir, project=project, study=first, files=final, report=final_report.to_dict(),
                       joint=joint)
