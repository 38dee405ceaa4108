"""The headless build: a project's stages end to end, with owned outputs.

:func:`build` runs the study's stages (:mod:`ssm_addon.pipeline.study`) on a parsed project
(:func:`ssm_addon.pipeline.project.read_project`) and writes the outputs atomically:
everything goes into a temporary folder next to the output folder and is moved into place
only when the whole build succeeded.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import resource
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__
from ..analysis.attributes import write_attributes
from ..analysis.files import analysis_summary, run_analysis
from ..base.compute import Executor
from ..base.errors import InputError, check_cancelled
from ..base.params import OutputParams
from ..base.progress import CancelledFn, ProgressFn, report, sub_progress
from ..base.records import jsonable
from ..cli.report import write_outputs, write_report_html
from ..formats.landmarks import landmark_format, write_landmarks
from ..formats.meshes import write_ply
from ..instances.importing import file_names
from ..meshutil import genus
from ..model.quality import QualityError, warnings_text
from ..pipeline.cache import BuildCache
from ..pipeline.project import Project, project_text, read_project, write_project  # noqa: F401 (the flat layout's imports)
from ..pipeline.runner import run
from ..pipeline.study import Study, carried_landmarks, landmark_distances, study_parameters

# --------------------------------------------------------------------------------------
# the build


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
    """

    out_dir: Path
    project: Project
    study: Study
    files: dict
    report: dict

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
        return self.study.timings_s


def peak_memory_mb() -> dict:
    """Peak resident memory (MB) of this process and of its finished child processes."""
    scale = 1.0 / 1024 if sys.platform != "darwin" else 1.0 / (1024 * 1024)
    return {
        "self_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale, 1),
        "children_mb": round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * scale, 1),
    }


MANIFEST = ".ssm-build.json"
"""The list of files a build wrote into its output folder (so a rebuild knows what is its own)."""


def _files_under(folder: Path) -> list[str]:
    out = []
    for dirpath, _dirs, files in os.walk(folder):
        for f in files:
            out.append((Path(dirpath) / f).relative_to(folder).as_posix())
    return sorted(out)


def _previous_outputs(out_dir: Path) -> set[str]:
    """The files the previous build wrote into ``out_dir`` (its manifest), or none."""
    path = out_dir / MANIFEST
    if not path.is_file():
        return set()
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        files = doc["files"]
        if doc.get("tool") != "ssm-builder" or not all(isinstance(f, str) for f in files):
            raise ValueError("not an SSM Builder manifest")
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise InputError(f"{path}: unreadable build manifest ({err}); give a new output folder") from None
    return {f for f in files if not Path(f).is_absolute() and ".." not in Path(f).parts}


def check_output_folder(out_dir: Path, inputs, *, force: bool = False) -> None:
    """Refuse an output folder the build would not own, before any work.

    * ``out_dir`` may not be, or contain, an input file (project, label maps, meshes,
      landmarks): a build never writes where its inputs are;
    * an existing ``out_dir`` holding files an earlier build did not write (no manifest
      entry) is refused unless ``force``; even then those files are kept, never
      overwritten or deleted.
    """
    for path in inputs:
        path = Path(path).resolve()
        if path == out_dir or out_dir in path.parents:
            raise InputError(f"{out_dir}: the output folder holds an input of the build ({path}); choose another "
                             "--out (a build never writes where its inputs are)")
    if not out_dir.exists():
        return
    if not out_dir.is_dir():
        raise InputError(f"{out_dir}: output path exists and is not a folder")
    ours = _previous_outputs(out_dir) | {MANIFEST}
    foreign = [f for f in _files_under(out_dir) if f not in ours]
    if foreign and not force:
        shown = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3 else "")
        raise InputError(f"{out_dir}: the output folder holds {len(foreign)} file(s) an SSM build did not write "
                         f"({shown}); give a new or empty folder, or --force to write beside them (they are kept)")


def _final_move(tmp: Path, out_dir: Path) -> None:
    """Put the finished build in place: exactly this build's files, nothing else touched.

    A new ``out_dir`` is the renamed temporary folder. In an existing one, the files of
    the previous build (its manifest) are removed, the new ones moved in, and files the
    build did not write stay; a new output that would replace such a file is refused.
    """
    new = _files_under(tmp)
    (tmp / MANIFEST).write_text(json.dumps({"tool": "ssm-builder", "version": __version__, "files": new}, indent=1)
                                + "\n", encoding="utf-8")
    if not out_dir.exists():
        os.replace(tmp, out_dir)
        return
    ours = _previous_outputs(out_dir)
    clash = [f for f in new if (out_dir / f).exists() and f not in ours]
    if clash:
        raise InputError(f"{out_dir}: would replace {len(clash)} file(s) an SSM build did not write ({', '.join(clash[:3])}"
                         f"{' ...' if len(clash) > 3 else ''}); they are kept: give another output folder")
    for f in sorted(ours):
        target = out_dir / f
        if target.is_file() or target.is_symlink():
            target.unlink()
    for f in new + [MANIFEST]:
        target = out_dir / f
        target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(tmp / f, target)
    for dirpath, _dirs, _files in sorted(os.walk(out_dir), key=lambda e: -len(e[0])):  # empty folders we left
        d = Path(dirpath)
        if d != out_dir and not any(d.iterdir()) and any(Path(f).parent == d.relative_to(out_dir) for f in ours):
            d.rmdir()
    shutil.rmtree(tmp, ignore_errors=True)


def check_writable(out_dir: Path) -> None:
    """``out_dir``'s parent exists (made if need be) and the folder can be written, or a clear error."""
    try:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(f"{out_dir}: cannot create the output folder's parent ({err.strerror})") from None
    if not os.access(out_dir.parent, os.W_OK) or (out_dir.exists() and not os.access(out_dir, os.W_OK)):
        raise InputError(f"{out_dir}: not writable (check the folder's permissions)")


@contextlib.contextmanager
def owned_output_folder(out_dir: Path, inputs, *, force: bool = False, what: str = "building"):
    """The output rules of every command that writes a folder, as one context manager.

    Refuses ``out_dir`` before any work (:func:`check_output_folder`: it holds an input, or
    files no SSM command wrote, unless ``force``); yields a temporary folder beside it to
    write into; on success puts exactly those files in place (files it did not write are
    kept, never replaced) with a manifest; on any error or cancel removes the temporary
    folder and leaves ``out_dir`` as it was.
    """
    out_dir = Path(out_dir).expanduser().resolve()
    check_output_folder(out_dir, [p for p in inputs if p], force=force)
    check_writable(out_dir)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.{what}-", dir=out_dir.parent))
    os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes it private; the output folder follows the umask
    try:
        yield tmp
        _final_move(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_study_files(study: Study, folder: Path, *, output: OutputParams, project_path: Path | None = None,
                      extra: dict | None = None) -> tuple[dict, dict]:
    """Write the study's products into ``folder``; returns ({output name: file name}, the report).

    ``model.npz``, ``model.h5`` (statismo), the plots, ``template.ply``
    and ``coated/<name>.ply`` (world mm); the report comes back in memory and the build writes
    ``report.json`` once, with its final timings.
    """
    files: dict = {}
    tpl = study.template
    tframe = study.frame(study.template_instance)
    write_ply(folder / "template.ply", tframe.to_world(tpl.points_object), tpl.faces)
    files["template"] = "template.ply"
    names = list(study.model.instance_names)
    safe = file_names(names)
    if output.coated_meshes:
        (folder / "coated").mkdir()
        for name, pw in zip(names, study.model.instance_points_world):
            write_ply(folder / "coated" / f"{safe[name]}.ply", np.asarray(pw, float), tpl.faces)
        files["coated"] = "coated"
    carried = carried_landmarks(study)
    if output.landmarks and carried:
        given = study.instance(study.template_instance).landmarks_path
        ext = landmark_format(given) if given is not None else "fcsv"
        (folder / "landmarks").mkdir()
        for name in names:
            write_landmarks(folder / "landmarks" / f"{safe[name]}.{ext}", carried[name])
        files["landmarks"] = "landmarks"
    # one source for how each coating started: the study's record (a round's coating says
    # "landmark warp" of its own warp, the study how the instance's correspondence began)
    per_instance = {n: dataclasses.replace(study.coatings[n].fit,
                                           start=study.coating_start.get(n, study.coatings[n].fit.start))
                    for n in names}
    cp = study.params.correspondence
    correspondence = {
        "method": cp.method,
        "template_instance": study.template_instance,
        "template_choice": jsonable(study.template_choice),
        "start": {n: study.coating_start.get(n, study.coatings[n].fit.start) for n in names},
        "rounds": [r.to_dict() for r in study.correspondence_rounds],
        "stop": study.correspondence_check.stop if study.correspondence_check is not None else "",
        "self_check": study.correspondence_check.to_dict() if study.correspondence_check is not None else None,
        "carried_landmark_distance_mm": landmark_distances(study, carried),
    }
    info = {
        "project": str(project_path) if project_path else "",
        "parameters": study_parameters(study, study.model.params.get("landmarks", ())),
        "template": {"instance": study.template_instance, "points": int(len(tpl.points_object)),
                     "triangles": int(len(tpl.faces)), "genus": int(genus(len(tpl.points_object), tpl.faces))},
        "correspondence": correspondence,
        "quality": {"parameters": dataclasses.asdict(study.params.quality),
                    "findings": [f.to_dict() for f in study.findings],
                    "outlier_scores": study.outlier_scores},
        **(extra or {}),
    }
    written = write_outputs(study.model, folder, metrics=study.metrics, per_instance=per_instance, extra=info,
                            plots=True, statismo=output.statismo, report=False, tables=output.scores,
                            gltf=output.gltf, vtk=output.vtk, exchange_modes=output.exchange_modes)
    doc = written.pop("document")
    for key, value in written.items():
        if key == "plots":
            files["plots"] = [Path(v).name for v in value]
        elif isinstance(value, str) and Path(value).exists():
            files[key] = Path(value).name
    return files, doc


def write_analysis_files(project: Project, study: Study, folder: Path, doc: dict, *, log=None, progress=None,
                         cancelled=None) -> dict:
    """The project's attributes (``attributes.csv``) and, with an ``[analysis]`` group or
    covariates, the analysis of the built model (``analysis/``); its summary goes into ``doc``
    (``report.json``'s ``analysis``). An analysis that fails is a loud warning: the model stays."""
    say = log or (lambda _msg: None)
    if project.attributes is None:
        return {}

    names = [str(n) for n in study.model.instance_names]
    aligned, _ = project.attributes.aligned(names)
    write_attributes(aligned, folder / "attributes.csv")
    files = {"attributes": "attributes.csv"}
    if not project.params.analysis.requested:
        return files
    t0 = time.perf_counter()
    report(progress, 0.97, "analysis: groups and covariates")
    try:
        result, adoc, _ = run_analysis(study.model, project.attributes, project.params.analysis, folder / "analysis",
                                       model_path="model.npz", cancelled=cancelled)
    except InputError as err:
        say(f"WARNING analysis: not run: {err}")
        doc["analysis"] = {"error": str(err)}
        return files
    for line in analysis_summary(result):
        say(f"analysis: {line}")
    for w in result.warnings:
        say(f"WARNING analysis: {w}")
    doc["analysis"] = adoc
    files["analysis"] = "analysis"
    study.timings_s["analysis"] = time.perf_counter() - t0
    return files


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
    inputs = [project.path] + [p for i in project.instances for p in (i.volume_path, i.mesh_path, i.landmarks_path) if p is not None]
    if project.params.analysis.attributes:
        inputs.append(Path(project.params.analysis.attributes))
    check_output_folder(out_dir, inputs, force=force)
    check_writable(out_dir)
    t_total = time.perf_counter()
    if len(project.instances) < 3:
        raise InputError(f"{project.path}: {len(project.instances)} instances; a model with its metrics (leave-one-out "
                         "generalization) needs at least 3")
    study = Study.from_project(project)
    build_cache = open_cache(project, out_dir, cache)
    if project.params.correspondence.method == "model" and build_cache is not None:
        say("cache: not used by [correspondence] method = \"model\" (its rounds depend on every instance)")
        build_cache = None
    with owned_output_folder(out_dir, inputs, force=force) as tmp:
        with Executor(scheduler or project.params.compute.scheduler, jobs, tasks=len(project.instances),
                      connect_timeout_s=project.params.compute.connect_timeout_s) as executor:  # closed before the files
            if executor.note:
                say(f"compute: {executor.note}")
            run(study, jobs=jobs, progress=sub_progress(progress, 0.0, 0.95), cancelled=cancelled, log=say,
                executor=executor, cache=build_cache)
        check_cancelled(cancelled)
        if project.params.quality.strict and study.findings:
            raise QualityError(f"{len(study.findings)} quality gate(s) failed and [quality] strict is set; nothing "
                               f"was written to {out_dir}:\n" + warnings_text(study.findings))
        report(progress, 0.95, "writing outputs")
        t0 = time.perf_counter()
        result = BuildResult(out_dir=out_dir, project=project, study=study, files={}, report={})
        files: dict = {}
        use_blend = project.params.output.blend if blend is None else blend
        if blender_hook is not None and use_blend:
            t1 = time.perf_counter()
            report(progress, 0.96, "Blender: model.blend and pictures")
            files.update(blender_hook(study, project.params.output, tmp, say) or {})
            study.timings_s["blender"] = time.perf_counter() - t1
        check_cancelled(cancelled)
        extra = {"timings_s": dict(study.timings_s), "peak_memory": peak_memory_mb(),
                 "compute": {"scheduler": executor.scheduler, "workers": executor.jobs,
                             "cache": str(build_cache.folder) if build_cache is not None else None,
                             "from_cache": study.streamed.get("cached", 0),
                             "computed": study.streamed.get("computed", len(study.names))}}
        written, doc = write_study_files(study, tmp, output=project.params.output, project_path=project.path, extra=extra)
        files.update(written)
        files.update(write_analysis_files(project, study, tmp, doc, log=say, progress=progress, cancelled=cancelled))
        study.timings_s["write"] = time.perf_counter() - t0 - study.timings_s.get("blender", 0.0)
        study.timings_s["total"] = time.perf_counter() - t_total
        t_html = time.perf_counter()
        doc["timings_s"] = dict(study.timings_s)
        doc["peak_memory"] = peak_memory_mb()
        (tmp / "report.json").write_text(json.dumps(doc, indent=1))  # the one write, with the final timings
        files["report"] = "report.json"
        write_report_html(tmp, study.model, doc=doc, title=f"SSM Builder: {project.path.stem}")
        files["html"] = "report.html"
        study.timings_s["report_html"] = time.perf_counter() - t_html
        check_cancelled(cancelled)
    final = {k: ([str(out_dir / x) for x in v] if isinstance(v, list) else str(out_dir / v)) for k, v in files.items()}
    report(progress, 1.0, f"done: {out_dir}")
    return dataclasses.replace(result, files=final, report=doc)

