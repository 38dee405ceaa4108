"""The project file and the headless build (paper sections 2–5 end to end).

A project file (TOML) lists the instances of a shape population and the parameters of
every stage; :func:`read_project` parses and validates it (every problem is an
:class:`~ssm_addon.errors.InputError` naming the file, line, key or instance and the
allowed values) and :func:`build` runs the study's stages (:mod:`ssm_addon.study`) and
writes the outputs atomically: everything goes into a temporary folder next to the
output folder and is moved into place only when the whole build succeeded.

The tables ``[template]``, ``[coating]``, ``[model]`` and ``[output]`` hold the fields of
:class:`~ssm_addon.params.TemplateParams`, :class:`~ssm_addon.params.CoatingParams`,
:class:`~ssm_addon.params.ModelParams` and :class:`~ssm_addon.params.OutputParams`
(their one definition); ``[template]`` also takes ``instance``. Example::

    [template]
    instance = "L1"        # the instance that gives the template (default: the first)
    spacing = 1.0          # mm, isotropic resampling along the object axes

    [coating]
    kernel = "biharmonic"

    [model]
    alignment = "none"     # none | rigid | similarity

    [[instances]]
    name = "L1"
    volume = "seg.nii.gz"  # or mesh = "L1.stl" (+ mesh_spacing in mm)
    label = 20
    landmarks = "landmarks/L1.fcsv"

Relative paths resolve against the project file's folder.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import os
import re
import resource
import shutil
import sys
import tempfile
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import __version__
from . import params as P
from .compute import Executor
from .errors import InputError, check_cancelled
from .instances import InstanceSpec, file_names
from .landmarks import LandmarkSet, landmark_format, match_landmarks, read_landmarks, write_landmarks
from .meshutil import genus, write_ply
from .params import (
    CoatingParams,
    ComputeParams,
    CorrespondenceParams,
    ModelParams,
    OutputParams,
    QualityParams,
    TemplateParams,
)
from .progress import CancelledFn, ProgressFn, report, sub_progress
from .quality import QualityError, warnings_text
from .report import write_report_html
from .study import Study, carried_landmarks, landmark_distances, run, study_parameters

__all__ = ["BuildResult", "Project", "build", "read_project", "write_project"]

INSTANCE_KEYS = {
    "name": "a string",
    "volume": "a file path (string)",
    "label": "an integer",
    "mesh": "a file path (string)",
    "mesh_spacing": "a number",
    "landmarks": "a file path (string)",
}
#: [template] keys besides the TemplateParams fields.
STUDY_TEMPLATE_KEYS = ("instance",)
SECTIONS = ("instances", *P.TABLES)


@dataclass(frozen=True)
class Project:
    """A parsed and validated project file.

    Attributes
    ----------
    path : Path
        The project file (absolute).
    instances : tuple of InstanceSpec
        With absolute paths and the landmarks read (world mm, common name order).
    template_instance : str
        Name of the instance that gives the template.
    template, coating, model, output : parameter objects
        The tables (defaults for what the file leaves out).
    landmark_names : tuple of str
        The common landmark names, in the order of the first instance's file.
    """

    path: Path
    instances: tuple[InstanceSpec, ...]
    template_instance: str
    template: TemplateParams = field(default_factory=TemplateParams)
    coating: CoatingParams = field(default_factory=CoatingParams)
    model: ModelParams = field(default_factory=ModelParams)
    output: OutputParams = field(default_factory=OutputParams)
    quality: QualityParams = field(default_factory=QualityParams)
    correspondence: CorrespondenceParams = field(default_factory=CorrespondenceParams)
    compute: ComputeParams = field(default_factory=ComputeParams)
    landmark_names: tuple[str, ...] = ()

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(i.name for i in self.instances)

    @property
    def spacing_mm(self) -> float:
        """Isotropic resampling spacing (mm) of every instance (paper 2)."""
        return self.template.spacing_mm

    @property
    def frame_method(self) -> str:
        return self.template.frame

    @property
    def template_params(self) -> TemplateParams:
        return self.template

    @property
    def coating_params(self) -> CoatingParams:
        return self.coating

    @property
    def model_options(self) -> dict:
        return dataclasses.asdict(self.model)

    @property
    def output_options(self) -> dict:
        return dataclasses.asdict(self.output)


# --------------------------------------------------------------------------------------
# reading


class _Lines:
    """Line numbers of tables and keys in a TOML text (for messages; tomllib has none)."""

    _header = re.compile(r"^\s*(\[\[?)\s*([A-Za-z0-9_.\"' -]+?)\s*\]\]?\s*(#.*)?$")
    _key = re.compile(r"^\s*(\"[^\"]*\"|'[^']*'|[A-Za-z0-9_-]+)\s*=")

    def __init__(self, text: str):
        self.keys: dict[tuple, int] = {}
        self.tables: dict[tuple, int] = {}
        counts: dict[str, int] = {}
        current: tuple = ("",)
        for lineno, line in enumerate(text.splitlines(), start=1):
            m = self._header.match(line)
            if m:
                name = m.group(2).strip().strip("\"'")
                if m.group(1) == "[[":
                    idx = counts.get(name, 0)
                    counts[name] = idx + 1
                    current = (name, idx)
                else:
                    current = (name,)
                self.tables.setdefault(current, lineno)
                continue
            m = self._key.match(line)
            if m:
                self.keys.setdefault((*current, m.group(1).strip("\"'")), lineno)

    def key(self, *where) -> int | None:
        return self.keys.get(tuple(where))

    def table(self, *where) -> int | None:
        return self.tables.get(tuple(where))


class _Context:
    def __init__(self, path: Path, text: str):
        self.path = path
        self.lines = _Lines(text)

    def at(self, line: int | None) -> str:
        return f"{self.path}:{line}" if line else f"{self.path}"

    def error(self, message: str, line: int | None = None) -> InputError:
        return InputError(f"{self.at(line)}: {message}")


def _suggest(key: str, allowed) -> str:
    close = difflib.get_close_matches(key, list(allowed), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else f" (allowed: {', '.join(sorted(allowed))})"


def _check_keys(table: dict, allowed, section: str, ctx: _Context, where: tuple) -> None:
    for key in table:
        if key not in allowed:
            raise ctx.error(f"{section}: unknown key {key!r}{_suggest(key, allowed)}", ctx.lines.key(*where, key))


def _resolve(value: str, base: Path) -> Path:
    p = Path(os.path.expanduser(value))
    return p if p.is_absolute() else (base / p).resolve()


def _kind_error(ctx, what, expected, value, line):
    return ctx.error(f"{what} must be {expected}, got {P._type_name(value)} {value!r}", line)


def _existing_file(value, key, what, ctx, where, base) -> Path:
    line = ctx.lines.key(*where, key)
    if not isinstance(value, str):
        raise _kind_error(ctx, f"{what}: {key}", INSTANCE_KEYS[key], value, line)
    path = _resolve(value, base)
    if not path.is_file():
        raise ctx.error(f"{what}: {key} file not found: {path}", line)
    return path


def _params(cls, doc: dict, section: str, ctx: _Context, extra=()):
    table = doc.get(section, {})
    if not isinstance(table, dict):
        raise ctx.error(f"[{section}] must be a table, got {P._type_name(table)}", ctx.lines.key(section))
    allowed = {*P.keys(cls), *extra}
    _check_keys(table, allowed, f"[{section}]", ctx, (section,))
    values = {k: v for k, v in table.items() if k not in extra}
    lines = {k: f"{ctx.at(ctx.lines.key(section, k))}: [{section}]" for k in values}
    return P.from_table(cls, values, where=f"{ctx.at(ctx.lines.table(section))}: [{section}]", lines=lines)


def _instances(doc: dict, ctx: _Context, base: Path, landmarks_required: bool = True) -> list[InstanceSpec]:
    raw = doc.get("instances")
    if raw is None or (isinstance(raw, list) and not raw):
        raise ctx.error("no [[instances]]: a project needs at least two instances, each with name, volume (or mesh) "
                        "and landmarks")
    if not isinstance(raw, list) or not all(isinstance(t, dict) for t in raw):
        raise ctx.error("instances must be an array of tables ([[instances]])", ctx.lines.key("instances"))
    out: list[InstanceSpec] = []
    seen: dict[str, int] = {}
    for i, table in enumerate(raw):
        where = ("instances", i)
        head = ctx.lines.table(*where)
        label_txt = f"[[instances]] #{i + 1}"
        _check_keys(table, INSTANCE_KEYS, label_txt, ctx, where)
        if "name" not in table:
            raise ctx.error(f"{label_txt}: missing key 'name'", head)
        name = table["name"]
        if not isinstance(name, str):
            raise _kind_error(ctx, f"{label_txt} name", INSTANCE_KEYS["name"], name, ctx.lines.key(*where, "name"))
        if not name.strip():
            raise ctx.error(f"{label_txt}: empty name", ctx.lines.key(*where, "name"))
        what = f"instance {name!r}"
        if name in seen:
            raise ctx.error(f"duplicate instance name {name!r} (instances #{seen[name] + 1} and #{i + 1})",
                            ctx.lines.key(*where, "name"))
        seen[name] = i
        if "label" in table and (isinstance(table["label"], bool) or not isinstance(table["label"], int)):
            raise _kind_error(ctx, f"{what}: label", INSTANCE_KEYS["label"], table["label"],
                              ctx.lines.key(*where, "label"))
        if "mesh_spacing" in table and (isinstance(table["mesh_spacing"], bool)
                                        or not isinstance(table["mesh_spacing"], int | float)):
            raise _kind_error(ctx, f"{what}: mesh_spacing", INSTANCE_KEYS["mesh_spacing"], table["mesh_spacing"],
                              ctx.lines.key(*where, "mesh_spacing"))
        has_volume, has_mesh = "volume" in table, "mesh" in table
        if has_volume == has_mesh:
            problem = "both volume and mesh" if has_volume else "neither volume nor mesh"
            raise ctx.error(f"{what}: give exactly one of 'volume' (label map) or 'mesh', got {problem}", head)
        if "landmarks" not in table and landmarks_required:
            raise ctx.error(f"{what}: missing key 'landmarks' (a .fcsv, .mrk.json, .csv or .json file; optional "
                            "with [correspondence] method = \"model\")", head)
        if has_mesh and "label" in table:
            raise ctx.error(f"{what}: 'label' applies to volumes, not meshes", ctx.lines.key(*where, "label"))
        if has_volume and "mesh_spacing" in table:
            raise ctx.error(f"{what}: 'mesh_spacing' applies to meshes, not volumes",
                            ctx.lines.key(*where, "mesh_spacing"))
        mesh_spacing = float(table["mesh_spacing"]) if "mesh_spacing" in table else None
        if mesh_spacing is not None and not (np.isfinite(mesh_spacing) and 0 < mesh_spacing <= 50):
            raise ctx.error(f"{what}: mesh_spacing must be a number > 0 mm and <= 50 mm, got {mesh_spacing!r}",
                            ctx.lines.key(*where, "mesh_spacing"))
        volume = _existing_file(table["volume"], "volume", what, ctx, where, base) if has_volume else None
        mesh = _existing_file(table["mesh"], "mesh", what, ctx, where, base) if has_mesh else None
        lm_path, lms = None, None
        if "landmarks" in table:
            lm_path = _existing_file(table["landmarks"], "landmarks", what, ctx, where, base)
            try:
                lms = read_landmarks(lm_path)
            except InputError as err:
                raise ctx.error(f"{what}: {err}", ctx.lines.key(*where, "landmarks")) from None
            lms = LandmarkSet(lms.names, lms.points_world, source=f"instance {name!r} ({lm_path.name})")
        out.append(InstanceSpec(name=name, landmarks=lm_path, volume=volume, label=table.get("label"), mesh=mesh,
                                mesh_spacing=mesh_spacing, landmark_set=lms))
    return out


def read_project(path) -> Project:
    """Parse and validate a project file.

    Parameters
    ----------
    path : str or Path
        The TOML project file.

    Returns
    -------
    Project
        With absolute paths (relative ones resolve against the file's folder), the
        landmark files read (world mm) and their names checked to match across
        instances.

    Raises
    ------
    InputError
        For a missing/unreadable file, TOML syntax errors (with line and column), unknown
        tables or keys (with the closest allowed key), wrong value types (expected vs
        got), values out of range (with the allowed range), missing files, duplicate
        instance names, no instances, an unknown template instance and landmark names
        that do not match across instances. The message starts with ``<file>:<line>:``
        where a line is known.
    """
    path = Path(path).expanduser().resolve()
    if not path.is_file():
        raise InputError(f"{path}: project file not found")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"{path}: cannot read project file ({err})") from None
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise InputError(f"{path}: TOML syntax error: {err}") from None
    ctx = _Context(path, text)

    for key in doc:
        if key not in SECTIONS:
            line = ctx.lines.table(key) or ctx.lines.table(key, 0) or ctx.lines.key(key)
            raise ctx.error(f"unknown table or key {key!r}{_suggest(key, SECTIONS)}", line)

    template = _params(TemplateParams, doc, "template", ctx, extra=STUDY_TEMPLATE_KEYS)
    coating = _params(CoatingParams, doc, "coating", ctx)
    model = _params(ModelParams, doc, "model", ctx)
    output = _params(OutputParams, doc, "output", ctx)
    quality = _params(QualityParams, doc, "quality", ctx)
    correspondence = _params(CorrespondenceParams, doc, "correspondence", ctx)
    compute = _params(ComputeParams, doc, "compute", ctx)
    if compute.cache not in ("auto", "off") and not Path(compute.cache).is_absolute():
        compute = dataclasses.replace(compute, cache=str((path.parent / compute.cache).resolve()))

    instances = _instances(doc, ctx, path.parent, landmarks_required=correspondence.method == "landmarks")
    if len(instances) < 2:
        raise ctx.error(f"only one instance ({instances[0].name!r}): a shape model needs at least two",
                        ctx.lines.table("instances", 0))
    marked = [inst for inst in instances if inst.landmark_set is not None]
    if not marked:
        raise ctx.error("no instance has landmarks: the template instance needs them (they name the places "
                        "written for every instance)")
    try:
        matched = match_landmarks([inst.landmark_set for inst in marked])
    except InputError as err:
        raise ctx.error(f"landmark names differ between instances (reference: instance {marked[0].name!r}): "
                        f"{err}") from None
    if len(matched[0]) < 4:
        raise ctx.error(f"{len(matched[0])} landmarks: the landmark warp (eq. 2) needs at least 4 per instance")
    by_name = {inst.name: lm for inst, lm in zip(marked, matched)}
    instances = [dataclasses.replace(inst, landmark_set=by_name.get(inst.name)) for inst in instances]

    names = [i.name for i in instances]
    try:
        file_names(names)
    except InputError as err:
        raise ctx.error(str(err), ctx.lines.table("instances", 0)) from None
    template_instance = doc.get("template", {}).get("instance", names[0])
    line = ctx.lines.key("template", "instance")
    if not isinstance(template_instance, str):
        raise _kind_error(ctx, "[template] instance", "a string", template_instance, line)
    if template_instance not in names:
        close = difflib.get_close_matches(template_instance, names, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ctx.error(f"[template] instance {template_instance!r} is not an instance name{hint}", line)
    if by_name.get(template_instance) is None:
        raise ctx.error(f"[template] instance {template_instance!r} has no landmarks; the template instance needs "
                        "them", line)

    return Project(path=path, instances=tuple(instances), template_instance=template_instance, template=template,
                   coating=coating, model=model, output=output, quality=quality, correspondence=correspondence,
                   compute=compute, landmark_names=matched[0].names)


# --------------------------------------------------------------------------------------
# writing


def toml_value(value) -> str:
    """A TOML literal for a parameter value (floats as their shortest repr)."""
    if isinstance(value, bool | np.bool_):
        return "true" if value else "false"
    if isinstance(value, int | np.integer):
        return str(int(value))
    if isinstance(value, float | np.floating):
        return repr(float(value))
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, Path):
        value = value.as_posix()
    return json.dumps(str(value), ensure_ascii=False)


def _relative(path: Path, base: Path) -> str:
    try:
        return Path(os.path.relpath(Path(path).resolve(), base.resolve())).as_posix()
    except ValueError:  # another drive on Windows
        return Path(path).resolve().as_posix()


def project_text(project: Project, base: Path) -> str:
    """The TOML text of ``project`` with paths relative to ``base``: every parameter
    written explicitly, in definition order (Save -> Open -> Save gives the same bytes)."""
    lines = ["# SSM Builder project (paths relative to this file)", "", "[template]",
             f"instance = {toml_value(project.template_instance)}"]
    for section, params in (("template", project.template), ("coating", project.coating),
                            ("correspondence", project.correspondence), ("model", project.model),
                            ("output", project.output), ("quality", project.quality)):
        if section != "template":
            lines += ["", f"[{section}]"]
        lines += [f"{k} = {toml_value(v)}" for k, v in P.to_table(params).items()]
    compute = P.to_table(project.compute, only_changed=True)  # written only when set (Blender has no such panel)
    if compute:
        if compute.get("cache") not in (None, "auto", "off"):
            compute["cache"] = _relative(Path(compute["cache"]), base)
        lines += ["", "[compute]"] + [f"{k} = {toml_value(v)}" for k, v in compute.items()]
    for inst in project.instances:
        lines += ["", "[[instances]]", f"name = {toml_value(inst.name)}"]
        if inst.volume is not None:
            lines.append(f"volume = {toml_value(_relative(inst.volume, base))}")
            if inst.label is not None:
                lines.append(f"label = {int(inst.label)}")
        else:
            lines.append(f"mesh = {toml_value(_relative(inst.mesh, base))}")
            if inst.mesh_spacing is not None:
                lines.append(f"mesh_spacing = {toml_value(float(inst.mesh_spacing))}")
        if inst.landmarks is not None:
            lines.append(f"landmarks = {toml_value(_relative(inst.landmarks, base))}")
    return "\n".join(lines) + "\n"


def write_project(path, project: Project) -> Path:
    """Write ``project`` as a TOML project file at ``path`` (paths relative to it)."""
    path = Path(path).expanduser().resolve()
    text = project_text(project, path.parent)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
    return path


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
    def metrics(self) -> dict:
        return self.study.metrics

    @property
    def timings_s(self) -> dict:
        return self.study.timings_s

    @property
    def objects(self) -> tuple:
        """Every instance's ObjectVolume, in project order."""
        return tuple(self.study.volumes[n] for n in self.study.names)

    @property
    def coatings(self) -> tuple:
        """Every instance's CoatingResult, in project order."""
        return tuple(self.study.coatings[n] for n in self.study.names)

    @property
    def landmarks_world(self) -> tuple:
        return tuple(i.landmark_set for i in self.study.instances)


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


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_study_files(study: Study, folder: Path, *, output: OutputParams, project_path: Path | None = None,
                      extra: dict | None = None) -> dict:
    """Write the study's products into ``folder``; returns {output name: file name}.

    ``model.npz``, ``model.h5`` (statismo), ``report.json``, the plots, ``template.ply``
    and ``coated/<name>.ply`` (world mm).
    """
    from . import metrics as met

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
        given = study.instance(study.template_instance).landmarks
        ext = landmark_format(given) if given is not None else "fcsv"
        (folder / "landmarks").mkdir()
        for name in names:
            write_landmarks(folder / "landmarks" / f"{safe[name]}.{ext}", carried[name])
        files["landmarks"] = "landmarks"
    per_instance = {n: study.coatings[n].fit for n in names}
    cp = study.correspondence_params
    correspondence = {
        "method": cp.method,
        "start": {n: study.coating_start.get(n, study.coatings[n].fit.start) for n in names},
        "rounds": [r.to_dict() for r in study.correspondence_rounds],
        "carried_landmark_distance_mm": landmark_distances(study, carried),
    }
    info = {
        "project": str(project_path) if project_path else "",
        "parameters": study_parameters(study, study.model.params.get("landmarks", ())),
        "template": {"instance": study.template_instance, "points": int(len(tpl.points_object)),
                     "triangles": int(len(tpl.faces)), "genus": int(genus(len(tpl.points_object), tpl.faces))},
        "correspondence": correspondence,
        "quality": {"parameters": dataclasses.asdict(study.quality_params),
                    "findings": [f.to_dict() for f in study.findings],
                    "outlier_scores": study.outlier_scores},
        **(extra or {}),
    }
    written = met.write_outputs(study.model, folder, metrics=study.metrics, per_instance=per_instance, extra=info,
                                plots=True)
    if not output.statismo:
        Path(written.pop("statismo")).unlink()
    for key, value in written.items():
        if key == "plots":
            files["plots"] = [Path(v).name for v in value]
        elif isinstance(value, str) and Path(value).exists():
            files[key] = Path(value).name
    return files


def open_cache(project: Project, out_dir: Path, cache=None):
    """The build's :class:`~ssm_addon.cache.BuildCache`, or None when it is off.

    ``cache``: a folder, "auto" (``DIR.cache`` beside ``out_dir``), "off", or None for
    the project's ``[compute] cache``.

    Raises
    ------
    InputError
        The cache folder is the output folder or inside it (a build replaces that
        folder), or it is an input file.
    """
    from .cache import BuildCache

    setting = project.compute.cache if cache is None else str(cache)
    if setting == "off":
        return None
    folder = out_dir.parent / f"{out_dir.name}.cache" if setting == "auto" else Path(setting).expanduser().resolve()
    if folder == out_dir or out_dir in folder.parents:
        raise InputError(f"--cache {folder}: inside the output folder {out_dir}, which a build replaces; put the "
                         "cache beside it")
    inputs = {p.resolve() for i in project.instances for p in (i.volume, i.mesh, i.landmarks) if p is not None}
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

    The stages of :func:`ssm_addon.study.run`: import and object frames (paper 2) →
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
        Where the per-instance work runs (:mod:`ssm_addon.compute`); default the
        project's ``[compute] scheduler``.
    cache : path, "auto", "off" or None
        The per-instance cache (:mod:`ssm_addon.cache`); None: the project's ``[compute]
        cache`` ("auto": ``DIR.cache`` beside ``out_dir``). A rerun takes every entry
        whose inputs and parameters are unchanged from there.

    The output folder then holds exactly this build's files (listed in
    ``.ssm-build.json``): outputs of an earlier build that this one does not write are
    removed, files the build did not write are never touched.
    """
    say = log or (lambda _msg: None)
    out_dir = Path(out_dir).expanduser().resolve()
    inputs = [project.path] + [p for i in project.instances for p in (i.volume, i.mesh, i.landmarks) if p is not None]
    check_output_folder(out_dir, inputs, force=force)
    try:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(f"{out_dir}: cannot create the output folder's parent ({err.strerror})") from None
    if not os.access(out_dir.parent, os.W_OK) or (out_dir.exists() and not os.access(out_dir, os.W_OK)):
        raise InputError(f"{out_dir}: not writable (check the folder's permissions)")
    t_total = time.perf_counter()
    if len(project.instances) < 3:
        raise InputError(f"{project.path}: {len(project.instances)} instances; a model with its metrics (leave-one-out "
                         "generalization) needs at least 3")
    study = Study.from_project(project)
    build_cache = open_cache(project, out_dir, cache)
    if project.correspondence.method == "model" and build_cache is not None:
        say("cache: not used by [correspondence] method = \"model\" (its rounds depend on every instance)")
        build_cache = None
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.building-", dir=out_dir.parent))
    os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes it private; the output folder follows the umask
    try:
        with Executor(scheduler or project.compute.scheduler, jobs) as executor:  # closed before the files
            run(study, jobs=jobs, progress=sub_progress(progress, 0.0, 0.95), cancelled=cancelled, log=say,
                executor=executor, cache=build_cache)
        check_cancelled(cancelled)
        if project.quality.strict and study.findings:
            raise QualityError(f"{len(study.findings)} quality gate(s) failed and [quality] strict is set; nothing "
                               f"was written to {out_dir}:\n" + warnings_text(study.findings))
        report(progress, 0.95, "writing outputs")
        t0 = time.perf_counter()
        result = BuildResult(out_dir=out_dir, project=project, study=study, files={}, report={})
        files: dict = {}
        use_blend = project.output.blend if blend is None else blend
        if blender_hook is not None and use_blend:
            t1 = time.perf_counter()
            report(progress, 0.96, "Blender: model.blend and pictures")
            files.update(blender_hook(result, tmp, say) or {})
            study.timings_s["blender"] = time.perf_counter() - t1
        check_cancelled(cancelled)
        extra = {"timings_s": dict(study.timings_s), "peak_memory": peak_memory_mb(),
                 "compute": {"scheduler": executor.scheduler, "workers": executor.jobs,
                             "cache": str(build_cache.folder) if build_cache is not None else None,
                             "from_cache": study.streamed.get("cached", 0),
                             "computed": study.streamed.get("computed", len(study.names))}}
        files.update(write_study_files(study, tmp, output=project.output, project_path=project.path, extra=extra))
        study.timings_s["write"] = time.perf_counter() - t0 - study.timings_s.get("blender", 0.0)
        study.timings_s["total"] = time.perf_counter() - t_total
        t_html = time.perf_counter()
        doc = json.loads((tmp / "report.json").read_text())
        doc["timings_s"] = dict(study.timings_s)
        doc["peak_memory"] = peak_memory_mb()
        (tmp / "report.json").write_text(json.dumps(doc, indent=1))
        write_report_html(tmp, study.model, title=f"SSM Builder: {project.path.stem}")
        files["html"] = "report.html"
        study.timings_s["report_html"] = time.perf_counter() - t_html
        check_cancelled(cancelled)
        _final_move(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    final = {k: ([str(out_dir / x) for x in v] if isinstance(v, list) else str(out_dir / v)) for k, v in files.items()}
    report(progress, 1.0, f"done: {out_dir}")
    return dataclasses.replace(result, files=final, report=doc)

