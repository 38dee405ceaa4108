"""A study's outputs in a folder the build owns: the build's writer, for both front ends.

:func:`owned_output_folder` holds the rules of every command that writes a folder (refuse
a folder holding inputs or files no SSM command wrote, write into a temporary folder beside
it, move the result in whole, keep a manifest). :func:`write_study` writes everything a
built study gives (template and coated meshes, carried landmarks, the model files, plots,
tables, ``report.json`` from one :class:`~ssm_addon.pipeline.report.Report`, ``report.html``);
:func:`save_study_outputs` is both together. ``ssm build`` and Blender's *Save Model* call
them on their study, so the two reports differ only in what is genuinely Blender's.
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
from pathlib import Path

import numpy as np

try:  # the output folder's lock (output_lock); Windows: an exclusive create stands in
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

from ..base.compute import done_future
from ..base.errors import InputError, check_cancelled
from ..base.params import OutputParams
from ..base.progress import CancelledFn, ProgressFn, report
from ..formats.landmarks import landmark_format, write_landmarks
from ..formats.meshes import write_ply
from ..formats.vtk import write_vtp
from ..instances.importing import file_names
from ..model.figures import optimisation_figure, render_modes_figure
from ..model.files import write_model_files
from ..model.metrics import display_axes, write_plots
from ..segmentation.appearance import write_appearance_h5
from ..version import __version__
from .appearance import appearance_stage
from .report import Absent, Report, joint_report, model_report, study_report, write_report_html
from .study import Study, apply_stage, carried_landmarks

__all__ = ["MANIFEST", "absolute_files", "check_output_folder", "check_writable", "drawing_copy", "owned_output_folder", "peak_memory_mb",
           "relative_files", "save_joint_outputs", "save_study_outputs", "start_drawings", "study_inputs", "write_joint", "write_outputs", "write_study"]


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
def owned_output_folder(out_dir: Path, inputs, *, force: bool = False, what: str = "building",
                        cancelled: CancelledFn = None):
    """The output rules of every command that writes a folder, as one context manager.

    Refuses ``out_dir`` before any work (:func:`check_output_folder`: it holds an input, or
    files no SSM command wrote, unless ``force``); yields a temporary folder beside it to
    write into; on success puts exactly those files in place (files it did not write are
    kept, never replaced) with a manifest; on any error or cancel removes the temporary
    folder and leaves ``out_dir`` as it was. ``cancelled()`` is asked once more just before
    the files are moved into place.
    """
    out_dir = Path(out_dir).expanduser().resolve()
    check_output_folder(out_dir, [p for p in inputs if p], force=force)
    check_writable(out_dir)
    with output_lock(out_dir):
        tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.{what}-", dir=out_dir.parent))
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes it private; the output folder follows the umask
        try:
            yield tmp
            check_cancelled(cancelled)
            _final_move(tmp, out_dir)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise


@contextlib.contextmanager
def output_lock(out_dir: Path):
    """Hold ``.<name>.lock`` beside ``out_dir`` while a command writes it: a second command
    given the same folder is refused at once, naming the first one's process, instead of both
    saying "done" with the later one's files left. The lock is the operating system's (it ends
    with the process, however that ends); the file is removed when the writing ends."""
    path = out_dir.parent / f".{out_dir.name}.lock"
    while True:
        if fcntl is None:
            try:
                fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_RDWR, 0o644)
            except FileExistsError:
                raise InputError(f"{out_dir}: another SSM command is writing it now ({_lock_owner(path)}); wait "
                                 f"for it to end or give another output folder (a crashed one's lock: delete "
                                 f"{path})") from None
            break
        fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise InputError(f"{out_dir}: another SSM command is writing it now ({_lock_owner(path)}); wait for "
                             "it to end or give another output folder") from None
        try:  # the file may have been removed by the holder between our open and our lock: lock the new one
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()}\n".encode())
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)
        os.close(fd)


def _lock_owner(path: Path) -> str:
    try:
        return path.read_text().strip() or "process unknown"
    except OSError:
        return "process unknown"


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def relative_files(files: dict, folder: Path) -> dict:
    """``files`` (output name -> path or list of paths) relative to ``folder`` (POSIX form), as
    ``report.json`` lists them: where they are after the build's final move."""
    folder = Path(folder)

    def rel(p):
        p = Path(p)
        return (p.relative_to(folder) if p.is_absolute() and folder in p.parents else p).as_posix()

    return {k: ([rel(x) for x in v] if isinstance(v, list | tuple) else rel(v)) for k, v in files.items()}


def write_outputs(model, out_dir, *, metrics=None, per_instance: dict | None = None, extra: dict | None = None,
                  plots: bool = True, statismo: bool = True, statismo_name: str = "model.h5", report: bool = True,
                  tables: bool = True, gltf: bool = True, vtk: bool = True, exchange_modes: int = 5,
                  why: str = "a model on its own, without the study it was built from") -> dict:
    """Write a model's own outputs into ``out_dir``: its files, the plots and (``report``) ``report.json``.

    For a model without its study (a model file): ``model.npz`` and statismo
    (:func:`ssm_addon.model.files.write_model_files`), the fig. 9 plots and a report whose
    study sections are absent because ``why``. Returns the written paths (``plots_skipped``
    when matplotlib is missing) and the :class:`Report` under ``"report_object"``.
    """
    out_dir = Path(out_dir)
    written = write_model_files(model, out_dir, statismo=statismo, statismo_name=statismo_name, tables=tables,
                                gltf=gltf, vtk=vtk, exchange_modes=exchange_modes)
    plot_info = write_plots(model, out_dir, metrics) if plots else {"files": []}
    written["plots"] = plot_info["files"]
    if "skipped" in plot_info:
        written["plots_skipped"] = plot_info["skipped"]
    files = relative_files({k: v for k, v in written.items() if k != "plots_skipped"}, out_dir)
    if report:
        files["report"] = "report.json"
    doc = model_report(model, metrics=metrics, per_instance=per_instance, why=why,
                       extra={**(extra or {}), "files": files})
    if report:
        (out_dir / "report.json").write_text(json.dumps(doc.to_dict(), indent=1))
        written["report"] = str(out_dir / "report.json")
    written["report_object"] = doc
    return written


def _picture_job(args) -> str | None:
    """Draw ``modes.png``; None, or why it could not (matplotlib missing)."""
    model, path, n_modes = args
    try:
        render_modes_figure(model, path, n_modes=n_modes)
    except ImportError as err:  # matplotlib draws the labels
        return str(err)
    return None


def _plots_job(args) -> dict:
    model, folder, metrics, coordinate = args
    return write_plots(model, folder, metrics, coordinate=coordinate)


def drawing_copy(model, n_modes: int):
    """What a worker draws from: the model without its training shapes and without the modes after
    the first ``n_modes`` (at 10^4 instances those are most of it), and the coordinates'
    concentration of variability (eq. 8, paper fig. 9's dashed curve) computed here from the
    shapes the copy no longer holds."""
    coordinate = model.variability_concentration("coordinate")[: max(model.n_modes, 1)]
    drawn = dataclasses.replace(model, modes=model.modes[:n_modes], instance_points=model.instance_points[:, :0],
                                instance_points_world=model.instance_points_world[:, :0],
                                params={**model.params, "display_axes": display_axes(model).tolist()})
    return drawn, coordinate


def start_drawings(model, metrics, output: OutputParams, folder: Path, files: dict, *, plots: bool = True,
                   executor=None) -> Callable[[Callable[[str], None]], dict]:
    """Begin the build's pictures: ``modes.png`` (paper fig. 10, drawn by the core when no Blender
    step wrote it: the same layout, labels and scale bar) and the fig. 9 plots.

    With an ``executor`` (:class:`~ssm_addon.base.compute.Executor`) they are drawn on its local
    workers, which are idle once the model is built, while this process writes the other files;
    without, here and now. The pictures are the same either way. Returns ``finish(say)``, which
    waits for them, adds ``modes.png`` to ``files``, says what was drawn or skipped, and returns
    the plots' ``{"files": [...]}`` (``"skipped"`` without matplotlib).
    """
    folder = Path(folder)
    submit = executor.submit if executor is not None else done_future
    n_modes = int(output.picture_modes)
    # what a worker is sent: no picture reads the instances' points nor the modes after the drawn
    # ones (at 10^4 instances those are most of the model)
    drawn, coordinate = drawing_copy(model, n_modes)
    picture = None
    if output.picture and "picture" not in files and model.n_modes > 0:
        picture = submit(_picture_job, (drawn, folder / "modes.png", n_modes))
    plotted = submit(_plots_job, (drawn, folder, metrics, coordinate)) if plots else None

    def finish(say: Callable[[str], None]) -> dict:
        if picture is not None:
            why = picture.result()
            if why is None:
                files["picture"] = "modes.png"
                say("picture: modes.png (mean and ±2σ of the first modes, axial / sagittal / coronal; drawn without "
                    "Blender)")
            else:
                say(f"picture: modes.png skipped ({why})")
        return plotted.result() if plotted is not None else {"files": []}

    return finish


def study_inputs(study: Study) -> list[Path]:
    """The study's input files (label maps, meshes, landmark files): never written over."""
    return [p for i in study.instances for p in (i.volume_path, i.mesh_path, i.landmarks_path) if p is not None]


def _write_model_outputs(model, folder: Path, files: dict, *, output: OutputParams, say, drawn: Callable,
                         analysis: Callable | None, extra: dict | None, npz_extra: dict | None = None) -> dict:
    """The model's files and tables, the analysis, and the pictures begun by :func:`start_drawings`
    (``drawn``: its ``finish``) into ``folder``; adds what it wrote to ``files`` and returns the
    report's further entries (``extra`` with the analysis's)."""
    if (output.gltf or output.vtk) and output.exchange_modes > model.n_modes:
        say(f"note: [output] exchange_modes = {output.exchange_modes}: the model has {model.n_modes} modes; "
            f"model.glb and vtk/ hold {model.n_modes}")
    written = write_model_files(model, folder, statismo=output.statismo, tables=output.scores, gltf=output.gltf,
                                vtk=output.vtk, exchange_modes=output.exchange_modes, npz_extra=npz_extra)
    entries = dict(extra or {})
    found = entry = None
    if analysis is not None:
        found, entry = analysis(folder)
    plot_info = drawn(say)
    written["plots"] = plot_info["files"]
    if "skipped" in plot_info:
        say(f"plots: {plot_info['skipped']}")
    files.update(relative_files(written, folder))
    files.update(found or {})
    if entry is not None:
        entries["analysis"] = entry
    return entries


def _outward(faces: np.ndarray, mirrored: bool) -> np.ndarray:
    """The template's triangles facing outwards on points written in their instance's own world: turned
    for an instance mirrored into the model's side (a mirror image reverses every triangle)."""
    return faces[:, ::-1] if mirrored else faces


def write_study(study: Study, folder, *, output: OutputParams, project: str | Absent, title: str,
                blender_hook: Callable | None = None, analysis: Callable | None = None, plots: bool = True,
                timings_unknown: dict | None = None, metrics_absent: str = "not computed", extra: dict | None = None,
                log: Callable[[str], None] | None = None, progress: ProgressFn = None,
                cancelled: CancelledFn = None, t_start: float | None = None, executor=None) -> tuple[dict, Report]:
    """Write a built study's outputs into ``folder``: the build's writer, for ``ssm build`` and
    Blender's *Save Model* alike.

    ``template.ply``, ``coated/<name>.ply`` and ``landmarks/`` (world mm, each instance's input
    frame), the model files and tables (``model.npz``, statismo, glTF, VTK), the fig. 9 plots,
    ``model.blend`` and ``modes.png`` through ``blender_hook(study, output, folder, log)`` when
    given, the analysis through ``analysis(folder) -> (files, report entry or None)`` when given, then ``report.json`` once (one
    :class:`~ssm_addon.pipeline.report.Report`, with the final timings) and ``report.html``.
    ``executor``: the build's, whose local workers draw the pictures meanwhile
    (:func:`start_drawings`).

    Returns
    -------
    (files, report)
        ``{output name: path relative to folder}`` and the report written.
    """
    say = log or (lambda _msg: None)
    folder = Path(folder)
    t0 = time.perf_counter()
    report(progress, 0.95, "writing outputs")
    files: dict = {}
    if blender_hook is not None:
        t1 = time.perf_counter()
        report(progress, 0.96, "Blender: model.blend and pictures")
        files.update(blender_hook(study, output, folder, say) or {})
        study.timings_s["blender"] = time.perf_counter() - t1
    check_cancelled(cancelled)
    drawn = start_drawings(study.model, study.metrics, output, folder, files, plots=plots, executor=executor)
    tpl, model = study.template, study.model
    tframe = study.frame(study.template_instance)  # on its instance, in its own side, facing outwards there
    write_ply(folder / "template.ply", tframe.to_world(tpl.points_object), _outward(tpl.faces, tframe.mirrored),
              space="RAS")
    files["template"] = "template.ply"
    names = list(model.instance_names)
    safe = file_names(names)
    if output.coated_meshes:
        # each coating in its instance's own world and side: a mirrored instance's triangles turned
        # back so that they face outwards there
        mirrored = set(model.params.get("mirrored") or ())
        faces = {n: _outward(tpl.faces, n in mirrored) for n in names}
        (folder / "coated").mkdir()
        for name, pw in zip(names, model.instance_points_world):
            write_ply(folder / "coated" / f"{safe[name]}.ply", np.asarray(pw, float), faces[name], space="RAS")
        files["coated"] = "coated"
        if output.vtk:  # the same coatings for VTK readers (ParaView, 3D Slicer, ShapeWorks Studio)
            (folder / "vtk" / "coated").mkdir(parents=True)
            for name, pw in zip(names, model.instance_points_world):
                write_vtp(folder / "vtk" / "coated" / f"{safe[name]}.vtp", np.asarray(pw, float), faces[name], {})
    carried = carried_landmarks(study)
    if output.landmarks and carried:
        given = study.instance(study.template_instance).landmarks_path
        ext = landmark_format(given) if given is not None else "fcsv"
        (folder / "landmarks").mkdir()
        for name in names:
            write_landmarks(folder / "landmarks" / f"{safe[name]}.{ext}", carried[name])
        files["landmarks"] = "landmarks"
    if study.optimisation is not None and len(study.optimisation.point_movement_mm) == len(model.mean) and plots:
        try:
            optimisation_figure(model.mean, tpl.faces, study.optimisation.point_movement_mm, study.optimisation.steps,
                                folder / "optimisation.png")
            files["optimisation"] = "optimisation.png"
        except ImportError as err:
            say(f"picture: optimisation.png skipped ({err})")
    if study.appearance_record is None:  # the appearance stage has not run (Blender's Save Model), or no images
        learned = appearance_stage(study)
        apply_stage(study, learned)
        for line in learned.lines():
            say(line)
    appearance, appearance_doc = study.appearance, study.appearance_record
    entries = _write_model_outputs(model, folder, files, output=output, say=say, drawn=drawn, analysis=analysis,
                                   extra=extra, npz_extra=appearance.to_arrays() if appearance is not None else None)
    if appearance is not None:  # in model.npz beside the shape model (above), and in the statismo file as
        if "statismo" in files:  # in full (segments as model.npz does), and as Scalismo's active shape model
            write_appearance_h5(folder / files["statismo"], appearance)
        entries["appearance"] = appearance_doc
    study.timings_s["write"] = time.perf_counter() - t0 - study.timings_s.get("blender", 0.0)
    if t_start is not None:
        study.timings_s["total"] = time.perf_counter() - t_start
    t_html = time.perf_counter()
    files["report"] = "report.json"
    files["html"] = "report.html"
    final = study_report(study, project=project, timings_unknown=timings_unknown, metrics_absent=metrics_absent,
                         extra={**entries, "peak_memory": peak_memory_mb(), "files": dict(files)})
    (folder / "report.json").write_text(json.dumps(final.to_dict(), indent=1))  # the one write, with the final timings
    write_report_html(folder, model, final, title=title)
    study.timings_s["report_html"] = time.perf_counter() - t_html
    check_cancelled(cancelled)
    return files, final


def absolute_files(files: dict, out_dir: Path) -> dict:
    """``files`` (names relative to the output folder, or lists of them) as full paths."""
    return {k: ([str(out_dir / x) for x in v] if isinstance(v, list) else str(out_dir / v)) for k, v in files.items()}


def save_joint_outputs(joint, out_dir, *, force: bool = False, inputs=(), **kw) -> tuple[Path, dict, Report]:
    """:func:`write_joint` into ``out_dir`` under the build's ownership rules, as
    :func:`save_study_outputs` writes a study: a folder holding any structure's inputs is refused.

    Returns (the output folder, ``{output name: absolute path}``, the report).
    """
    every = [p for study in joint.structures.values() for p in study_inputs(study)]
    return _save_outputs(write_joint, joint, out_dir, [*every, *inputs], force=force, **kw)


def _save_outputs(write, study, out_dir, inputs, *, force: bool, **kw) -> tuple[Path, dict, Report]:
    """``write(study, folder, **kw)`` into ``out_dir`` under :func:`owned_output_folder`'s rules."""
    out_dir = Path(out_dir).expanduser().resolve()
    with owned_output_folder(out_dir, inputs, force=force, what="saving", cancelled=kw.get("cancelled")) as tmp:
        files, final = write(study, tmp, **kw)
    return out_dir, absolute_files(files, out_dir), final


def save_study_outputs(study: Study, out_dir, *, force: bool = False, inputs=(), **kw) -> tuple[Path, dict, Report]:
    """:func:`write_study` into ``out_dir`` under the build's ownership rules
    (:func:`owned_output_folder`): a folder holding inputs or files no SSM command wrote is
    refused (unless ``force``: they are then kept), the outputs arrive whole or not at all.

    Returns (the output folder, ``{output name: absolute path}``, the report).
    """
    return _save_outputs(write_study, study, out_dir, [*study_inputs(study), *inputs], force=force, **kw)


def write_joint(joint, folder, *, output: OutputParams, project: str | Absent, title: str, extra: dict | None = None,
                log: Callable[[str], None] | None = None, progress: ProgressFn = None, cancelled: CancelledFn = None,
                t_start: float | None = None, analysis: Callable | None = None,
                files: dict | None = None, executor=None) -> tuple[dict, Report]:
    """Write a joint study's outputs into ``folder``: each structure's template, coated meshes and
    carried landmarks (``structures/<name>/``, world mm; ``landmarks/`` where the structure has them), the joint model's files (``model.npz`` with its
    ``structure_names`` and ``structure_offsets``, statismo with its ``/ssm/structures`` group,
    tables, glTF, VTK), the plots, the analysis through ``analysis(folder) -> (files, report
    entry or None)`` when given (as :func:`write_study`), ``report.json`` and ``report.html``.
    ``files``: what was written into ``folder`` before (``model.blend``, ``modes.png``), for the report.
    ``executor``: the build's, whose local workers draw the pictures meanwhile (:func:`start_drawings`)."""
    say = log or (lambda _msg: None)
    folder = Path(folder)
    t0 = time.perf_counter()
    report(progress, 0.95, "writing outputs")
    files = dict(files or {})
    model = joint.model
    drawn = start_drawings(model, joint.metrics, output, folder, files, executor=executor)
    for name, study in joint.structures.items():
        base = folder / "structures" / file_names([name])[name]
        (base / "coated").mkdir(parents=True)
        tpl = study.template
        tframe = study.frame(study.template_instance)  # on its instance, in its own side, facing outwards there
        write_ply(base / "template.ply", tframe.to_world(tpl.points_object), _outward(tpl.faces, tframe.mirrored),
                  space="RAS")
        safe = file_names(joint.subjects)
        sl = model.structure_slice(name)
        for subject, pw in zip(model.instance_names, model.instance_points_world):
            # in the subject's own world and side: a mirrored subject's triangles turned to face outwards there
            faces = _outward(tpl.faces, study.frame(str(subject)).mirrored)
            write_ply(base / "coated" / f"{safe[str(subject)]}.ply", np.asarray(pw[sl], float), faces, space="RAS")
        carried = carried_landmarks(study)  # the template's landmarks where each coating put them, as a single build
        if output.landmarks and carried:
            given = study.instance(study.template_instance).landmarks_path
            ext = landmark_format(given) if given is not None else "fcsv"
            (base / "landmarks").mkdir()
            for subject in joint.subjects:
                if str(subject) in carried:
                    write_landmarks(base / "landmarks" / f"{safe[str(subject)]}.{ext}", carried[str(subject)])
    files["structures"] = "structures"
    check_cancelled(cancelled)
    entries = _write_model_outputs(model, folder, files, output=output, say=say, drawn=drawn,
                                   analysis=analysis, extra=extra)
    joint.timings_s["write"] = time.perf_counter() - t0 - joint.timings_s.get("analysis", 0.0)
    if t_start is not None:
        joint.timings_s["total"] = time.perf_counter() - t_start
    files["report"] = "report.json"
    files["html"] = "report.html"
    final = joint_report(joint, project=project, extra={**entries, "peak_memory": peak_memory_mb(),
                                                        "files": dict(files)})
    (folder / "report.json").write_text(json.dumps(final.to_dict(), indent=1))
    write_report_html(folder, model, final, title=title)
    check_cancelled(cancelled)
    return files, final
