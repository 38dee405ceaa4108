"""The project file and the headless build pipeline (paper sections 2–5 end to end).

A project file (TOML) lists the instances of a shape population and the parameters of
every stage; :func:`read_project` parses and validates it (every problem is an
:class:`~ssm_addon.errors.InputError` naming the file, line, key or instance) and
:func:`build` runs import → landmarks → template → coating → model → metrics and writes
the outputs atomically: everything goes into a temporary folder next to the output
folder and is moved into place only when the whole build succeeded.

Example::

    [template]
    instance = "L1"        # the instance that gives the template (default: the first)
    spacing = 1.0          # mm, isotropic resampling along the object axes
    r_min = 2.0            # any TemplateParams field

    [coating]
    kernel = "biharmonic"  # any CoatingParams field

    [model]
    alignment = "none"     # none | rigid | similarity
    n_modes = 8

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
import platform
import re
import resource
import shutil
import sys
import tempfile
import time
import tomllib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from . import __version__
from .errors import InputError, check_cancelled
from .progress import CancelledFn, ProgressFn, report

# --------------------------------------------------------------------------------------
# schema of the project file

INSTANCE_KEYS = {
    "name": "str",
    "volume": "path",
    "label": "int",
    "mesh": "path",
    "mesh_spacing": "float",
    "landmarks": "path",
}
#: [template] keys besides the TemplateParams fields.
TEMPLATE_PROJECT_KEYS = {"instance": "str", "spacing": "float", "frame": "str"}
FRAME_METHODS = ("auto", "patient", "moments")
#: [model] keys: the model and its metrics (paper 5; compactness, generalization, specificity).
MODEL_KEYS = {
    "alignment": "str",
    "n_modes": "int",
    "specificity_samples": "int",
    "max_loo": "int",
    "seed": "int",
}
ALIGNMENTS = ("none", "rigid", "similarity")
#: [output] keys (all optional).
OUTPUT_KEYS = {
    "coated_meshes": "bool",
    "statismo": "bool",
    "blend": "bool",
    "picture": "bool",
    "picture_modes": "int",
}
OUTPUT_DEFAULTS = {"coated_meshes": True, "statismo": True, "blend": True, "picture": True, "picture_modes": 2}
MODEL_DEFAULTS = {"alignment": "none", "n_modes": None, "specificity_samples": 500, "max_loo": 100, "seed": 0}
SECTIONS = ("instances", "template", "coating", "model", "output")


def _param_classes():
    from .coating import CoatingParams
    from .template import TemplateParams

    return TemplateParams, CoatingParams


def _kind_of_field(f: dataclasses.Field) -> str:
    """'bool' | 'int' | 'float' | 'str' | 'tuple' from a dataclass field's annotation."""
    ann = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
    for kind in ("bool", "tuple", "float", "int", "str"):
        if re.search(rf"\b{kind}\b", ann):
            return kind
    default = f.default if f.default is not dataclasses.MISSING else None
    for kind, types in (("bool", bool), ("int", int), ("float", float), ("str", str), ("tuple", tuple)):
        if isinstance(default, types):
            return kind
    return "any"


def _with_spacing(cls, options: dict, spacing_mm: float) -> dict:
    """``options`` plus ``spacing_mm`` when the parameter class has that field."""
    names = {f.name for f in dataclasses.fields(cls)}
    return {**options, "spacing_mm": float(spacing_mm)} if "spacing_mm" in names else dict(options)


def params_schema(cls) -> dict[str, str]:
    """The TOML keys a parameter dataclass accepts, with their kind (from its fields)."""
    return {f.name: _kind_of_field(f) for f in dataclasses.fields(cls) if f.init}


# --------------------------------------------------------------------------------------
# the parsed project


@dataclass(frozen=True)
class InstanceSpec:
    """One ``[[instances]]`` entry, paths absolute.

    Attributes
    ----------
    name : str
    volume : Path or None
        Label map file (NIfTI/NRRD/MetaImage), or None for a mesh instance.
    label : int or None
        Label picked from the label map (None: all non-zero voxels).
    mesh : Path or None
        Closed surface mesh (STL/PLY/OBJ) in world mm, voxelized at ``mesh_spacing``.
    mesh_spacing : float or None
        Voxelization spacing in mm (None: the template spacing).
    landmarks : Path
        Landmark file (world mm).
    landmark_set : LandmarkSet
        The landmarks as read, in the project's common name order.
    """

    name: str
    landmarks: Path
    volume: Path | None = None
    label: int | None = None
    mesh: Path | None = None
    mesh_spacing: float | None = None
    landmark_set: Any = None

    @property
    def source(self) -> Path:
        return self.volume if self.volume is not None else self.mesh


@dataclass(frozen=True)
class Project:
    """A parsed and validated project file.

    Attributes
    ----------
    path : Path
        The project file (absolute).
    instances : tuple of InstanceSpec
    template_instance : str
        Name of the instance that gives the template.
    spacing_mm : float
        Isotropic resampling spacing (mm) of every instance (paper 2).
    frame_method : str
        Object frame method: auto | patient | moments.
    template_options, coating_options : dict
        The TemplateParams / CoatingParams fields set in the file (others default).
    model_options : dict
        alignment, n_modes, specificity_samples, max_loo, seed (defaults filled in).
    output_options : dict
        What to write (defaults filled in).
    landmark_names : tuple of str
        The common landmark names, in the order of the first instance's file.
    """

    path: Path
    instances: tuple[InstanceSpec, ...]
    template_instance: str
    spacing_mm: float = 1.0
    frame_method: str = "auto"
    template_options: dict = field(default_factory=dict)
    coating_options: dict = field(default_factory=dict)
    model_options: dict = field(default_factory=lambda: dict(MODEL_DEFAULTS))
    output_options: dict = field(default_factory=lambda: dict(OUTPUT_DEFAULTS))
    landmark_names: tuple[str, ...] = ()

    @property
    def template_params(self):
        """TemplateParams with the file's values (lengths in mm; spacing_mm = the project's spacing)."""
        cls = _param_classes()[0]
        return cls(**_with_spacing(cls, self.template_options, self.spacing_mm))

    @property
    def coating_params(self):
        """CoatingParams with the file's values."""
        return _param_classes()[1](**self.coating_options)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(i.name for i in self.instances)


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


def _type_name(value) -> str:
    return {bool: "boolean", int: "integer", float: "float", str: "string", list: "array", dict: "table"}.get(
        type(value), type(value).__name__
    )


_KIND_TEXT = {
    "str": "a string",
    "path": "a file path (string)",
    "int": "an integer",
    "float": "a number",
    "bool": "true or false",
    "tuple": "an array",
}


def _convert(value, kind: str, what: str, ctx: _Context, line: int | None):
    ok = {
        "str": isinstance(value, str),
        "path": isinstance(value, str),
        "int": isinstance(value, int) and not isinstance(value, bool),
        "float": isinstance(value, (int, float)) and not isinstance(value, bool),
        "bool": isinstance(value, bool),
        "tuple": isinstance(value, list),
        "any": True,
    }[kind]
    if not ok:
        raise ctx.error(f"{what} must be {_KIND_TEXT[kind]}, got {_type_name(value)} {value!r}", line)
    if kind == "float":
        return float(value)
    if kind == "tuple":
        return tuple(value)
    return value


def _check_keys(table: dict, allowed, section: str, ctx: _Context, where: tuple) -> None:
    for key in table:
        if key not in allowed:
            close = difflib.get_close_matches(key, list(allowed), n=1, cutoff=0.6)
            hint = f" (did you mean {close[0]!r}?)" if close else f" (allowed: {', '.join(sorted(allowed))})"
            raise ctx.error(f"{section}: unknown key {key!r}{hint}", ctx.lines.key(*where, key))


def _resolve(value: str, base: Path) -> Path:
    p = Path(os.path.expanduser(value))
    return p if p.is_absolute() else (base / p).resolve()


def _existing_file(value, key, what, ctx, where, base) -> Path:
    line = ctx.lines.key(*where, key)
    path = _resolve(_convert(value, "path", f"{what}: {key}", ctx, line), base)
    if not path.is_file():
        raise ctx.error(f"{what}: {key} file not found: {path}", line)
    return path


def _params_table(table, cls_schema: dict, extra: dict, section: str, ctx: _Context) -> tuple[dict, dict]:
    """Validate a parameter table; return (dataclass options, extra options)."""
    if not isinstance(table, dict):
        raise ctx.error(f"[{section}] must be a table, got {_type_name(table)}")
    allowed = {**cls_schema, **extra}
    _check_keys(table, allowed, f"[{section}]", ctx, (section,))
    opts, more = {}, {}
    for key, value in table.items():
        line = ctx.lines.key(section, key)
        converted = _convert(value, allowed[key], f"[{section}] {key}", ctx, line)
        (more if key in extra else opts)[key] = converted
    return opts, more


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
        got), missing files, duplicate instance names, no instances, an unknown template
        instance, bad parameter values and landmark names that do not match across
        instances. The message starts with ``<file>:<line>:`` where a line is known.
    """
    from .landmarks import LandmarkSet, match_landmarks, read_landmarks

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
    base = path.parent

    for key in doc:
        if key not in SECTIONS:
            close = difflib.get_close_matches(key, SECTIONS, n=1, cutoff=0.6)
            hint = f" (did you mean {close[0]!r}?)" if close else f" (allowed: {', '.join(SECTIONS)})"
            line = ctx.lines.table(key) or ctx.lines.table(key, 0) or ctx.lines.key(key)
            raise ctx.error(f"unknown table or key {key!r}{hint}", line)

    TemplateParams, CoatingParams = _param_classes()
    t_schema = params_schema(TemplateParams)
    c_schema = params_schema(CoatingParams)

    # [template]
    t_opts, t_more = _params_table(doc.get("template", {}), t_schema, TEMPLATE_PROJECT_KEYS, "template", ctx)
    if "spacing_mm" in t_opts and "spacing" in t_more and t_opts["spacing_mm"] != t_more["spacing"]:
        raise ctx.error(
            f"[template] spacing ({t_more['spacing']}) and spacing_mm ({t_opts['spacing_mm']}) are the same setting "
            "and differ; give one", ctx.lines.key("template", "spacing_mm"))
    spacing = t_more.get("spacing", t_opts.pop("spacing_mm", 1.0))
    t_opts.pop("spacing_mm", None)
    if not spacing > 0:
        raise ctx.error(f"[template] spacing must be > 0 mm, got {spacing}", ctx.lines.key("template", "spacing"))
    frame = t_more.get("frame", "auto")
    if frame not in FRAME_METHODS:
        raise ctx.error(
            f"[template] frame must be one of {', '.join(FRAME_METHODS)}, got {frame!r}", ctx.lines.key("template", "frame")
        )
    try:
        TemplateParams(**_with_spacing(TemplateParams, t_opts, spacing))
    except (TypeError, ValueError) as err:
        raise ctx.error(f"[template]: {err}", ctx.lines.table("template")) from None

    # [coating]
    c_opts, _ = _params_table(doc.get("coating", {}), c_schema, {}, "coating", ctx)
    try:
        cp = CoatingParams(**c_opts)
        if hasattr(cp, "validate"):
            cp.validate()
    except (TypeError, ValueError) as err:
        raise ctx.error(f"[coating]: {err}", ctx.lines.table("coating")) from None

    # [model]
    _, m_more = _params_table(doc.get("model", {}), {}, MODEL_KEYS, "model", ctx)
    model_opts = {**MODEL_DEFAULTS, **m_more}
    if model_opts["alignment"] not in ALIGNMENTS:
        raise ctx.error(
            f"[model] alignment must be one of {', '.join(ALIGNMENTS)}, got {model_opts['alignment']!r}",
            ctx.lines.key("model", "alignment"),
        )
    if model_opts["n_modes"] is not None and model_opts["n_modes"] < 1:
        raise ctx.error(f"[model] n_modes must be >= 1, got {model_opts['n_modes']}", ctx.lines.key("model", "n_modes"))
    for key in ("specificity_samples", "max_loo"):
        if model_opts[key] < 1:
            raise ctx.error(f"[model] {key} must be >= 1, got {model_opts[key]}", ctx.lines.key("model", key))

    # [output]
    _, o_more = _params_table(doc.get("output", {}), {}, OUTPUT_KEYS, "output", ctx)
    output_opts = {**OUTPUT_DEFAULTS, **o_more}

    # [[instances]]
    raw = doc.get("instances")
    if raw is None or (isinstance(raw, list) and not raw):
        raise ctx.error("no [[instances]]: a project needs at least two instances, each with name, volume (or mesh) and landmarks")
    if not isinstance(raw, list) or not all(isinstance(t, dict) for t in raw):
        raise ctx.error("instances must be an array of tables ([[instances]])", ctx.lines.key("instances"))
    instances: list[InstanceSpec] = []
    seen: dict[str, int] = {}
    for i, table in enumerate(raw):
        where = ("instances", i)
        head = ctx.lines.table(*where)
        label_txt = f"[[instances]] #{i + 1}"
        _check_keys(table, INSTANCE_KEYS, label_txt, ctx, where)
        if "name" not in table:
            raise ctx.error(f"{label_txt}: missing key 'name'", head)
        name = _convert(table["name"], "str", f"{label_txt} name", ctx, ctx.lines.key(*where, "name"))
        if not name.strip():
            raise ctx.error(f"{label_txt}: empty name", ctx.lines.key(*where, "name"))
        what = f"instance {name!r}"
        if name in seen:
            raise ctx.error(
                f"duplicate instance name {name!r} (instances #{seen[name] + 1} and #{i + 1})",
                ctx.lines.key(*where, "name"),
            )
        seen[name] = i
        for key in ("label", "mesh_spacing"):
            if key in table:
                _convert(table[key], INSTANCE_KEYS[key], f"{what}: {key}", ctx, ctx.lines.key(*where, key))
        has_volume, has_mesh = "volume" in table, "mesh" in table
        if has_volume == has_mesh:
            problem = "both volume and mesh" if has_volume else "neither volume nor mesh"
            raise ctx.error(f"{what}: give exactly one of 'volume' (label map) or 'mesh', got {problem}", head)
        if "landmarks" not in table:
            raise ctx.error(f"{what}: missing key 'landmarks' (a .fcsv, .mrk.json, .csv or .json file)", head)
        if has_mesh and "label" in table:
            raise ctx.error(f"{what}: 'label' applies to volumes, not meshes", ctx.lines.key(*where, "label"))
        if has_volume and "mesh_spacing" in table:
            raise ctx.error(f"{what}: 'mesh_spacing' applies to meshes, not volumes", ctx.lines.key(*where, "mesh_spacing"))
        mesh_spacing = float(table["mesh_spacing"]) if "mesh_spacing" in table else None
        if mesh_spacing is not None and not mesh_spacing > 0:
            raise ctx.error(f"{what}: mesh_spacing must be > 0 mm", ctx.lines.key(*where, "mesh_spacing"))
        volume = _existing_file(table["volume"], "volume", what, ctx, where, base) if has_volume else None
        mesh = _existing_file(table["mesh"], "mesh", what, ctx, where, base) if has_mesh else None
        lm_path = _existing_file(table["landmarks"], "landmarks", what, ctx, where, base)
        try:
            lms = read_landmarks(lm_path)
        except InputError as err:
            raise ctx.error(f"{what}: {err}", ctx.lines.key(*where, "landmarks")) from None
        lms = LandmarkSet(lms.names, lms.points_world, source=f"instance {name!r} ({lm_path.name})")
        instances.append(
            InstanceSpec(name=name, landmarks=lm_path, volume=volume, label=table.get("label"), mesh=mesh,
                         mesh_spacing=mesh_spacing, landmark_set=lms)
        )
    if len(instances) < 2:
        raise ctx.error(f"only one instance ({instances[0].name!r}): a shape model needs at least two", ctx.lines.table("instances", 0))

    try:
        matched = match_landmarks([inst.landmark_set for inst in instances])
    except InputError as err:
        raise ctx.error(f"landmark names differ between instances (reference: instance {instances[0].name!r}): {err}") from None
    if len(matched[0]) < 4:
        raise ctx.error(f"{len(matched[0])} landmarks: the landmark warp (eq. 2) needs at least 4 per instance")
    instances = [dataclasses.replace(inst, landmark_set=lm) for inst, lm in zip(instances, matched)]

    template_instance = t_more.get("instance", instances[0].name)
    if template_instance not in seen:
        close = difflib.get_close_matches(template_instance, list(seen), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ctx.error(f"[template] instance {template_instance!r} is not an instance name{hint}", ctx.lines.key("template", "instance"))

    return Project(
        path=path,
        instances=tuple(instances),
        template_instance=template_instance,
        spacing_mm=float(spacing),
        frame_method=frame,
        template_options=t_opts,
        coating_options=c_opts,
        model_options=model_opts,
        output_options=output_opts,
        landmark_names=matched[0].names,
    )


# --------------------------------------------------------------------------------------
# writing


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, Path):
        value = value.as_posix()
    return json.dumps(str(value), ensure_ascii=False)


def _relative(path: Path, base: Path) -> str:
    try:
        return Path(os.path.relpath(Path(path).resolve(), base.resolve())).as_posix()
    except ValueError:  # another drive on Windows
        return Path(path).resolve().as_posix()


def write_project(path, project: Project) -> Path:
    """Write ``project`` as a TOML project file at ``path`` (paths relative to it).

    Only the parameters set in ``project`` (``*_options``) are written; the rest keep
    their defaults when the file is read back.
    """
    path = Path(path).expanduser().resolve()
    base = path.parent
    lines = ["# SSM Builder project (paths relative to this file)", "", "[template]"]
    lines.append(f"instance = {_toml_value(project.template_instance)}")
    lines.append(f"spacing = {_toml_value(float(project.spacing_mm))}")
    if project.frame_method != "auto":
        lines.append(f"frame = {_toml_value(project.frame_method)}")
    lines += [f"{k} = {_toml_value(v)}" for k, v in project.template_options.items() if v is not None]
    lines += ["", "[coating]"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in project.coating_options.items() if v is not None]
    lines += ["", "[model]"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in project.model_options.items() if v is not None]
    changed = {k: v for k, v in project.output_options.items() if OUTPUT_DEFAULTS.get(k) != v}
    if changed:
        lines += ["", "[output]"] + [f"{k} = {_toml_value(v)}" for k, v in changed.items()]
    for inst in project.instances:
        lines += ["", "[[instances]]", f"name = {_toml_value(inst.name)}"]
        if inst.volume is not None:
            lines.append(f"volume = {_toml_value(_relative(inst.volume, base))}")
            if inst.label is not None:
                lines.append(f"label = {int(inst.label)}")
        else:
            lines.append(f"mesh = {_toml_value(_relative(inst.mesh, base))}")
            if inst.mesh_spacing is not None:
                lines.append(f"mesh_spacing = {_toml_value(float(inst.mesh_spacing))}")
        lines.append(f"landmarks = {_toml_value(_relative(inst.landmarks, base))}")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
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
    objects : tuple of ObjectVolume
        Every instance resampled in its object frame (paper 2), in project order.
    landmarks_world : tuple of LandmarkSet
        Every instance's landmarks (world mm), in the project's common order.
    template : Template
        The template (paper 3) in the template instance's object frame.
    coatings : tuple of CoatingResult
        The template coated onto every instance (paper 4), object mm of each instance.
    model : ShapeModel
        The model (paper 5).
    metrics : dict
        Compactness, generalization, specificity.
    timings_s : dict
        Wall time per stage (s).
    files : dict
        Output name -> path (final location).
    report : dict
        The content of ``report.json``.
    """

    out_dir: Path
    project: Project
    objects: tuple
    landmarks_world: tuple
    template: Any
    coatings: tuple
    model: Any
    metrics: dict
    timings_s: dict
    files: dict
    report: dict


def peak_memory_mb() -> dict:
    """Peak resident memory (MB) of this process and of its finished child processes."""
    scale = 1.0 / 1024 if sys.platform != "darwin" else 1.0 / (1024 * 1024)
    return {
        "self_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale, 1),
        "children_mb": round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * scale, 1),
    }


def _versions() -> dict:
    import scipy

    out = {"ssm_builder": __version__, "python": platform.python_version(), "numpy": np.__version__,
           "scipy": scipy.__version__}
    try:
        import skimage

        out["scikit-image"] = skimage.__version__
    except ImportError:  # pragma: no cover - a core dependency
        pass
    return out


def import_instances(project: Project, jobs: int = 1, progress: ProgressFn = None, cancelled: CancelledFn = None):
    """Read every instance, compute its object frame and resample it (paper 2).

    Label maps shared by several instances (one file, several labels) are read once.
    With ``jobs`` > 1 the instances are processed in threads (the numeric work releases
    the GIL); the result does not depend on ``jobs``.

    Returns
    -------
    list of ObjectVolume, in project order.
    """
    from . import volume as vol

    n = len(project.instances)
    maps: dict[Path, Any] = {}
    paths = {inst.volume for inst in project.instances if inst.volume is not None}
    cache_maps = len(paths) < sum(inst.volume is not None for inst in project.instances)
    done = [0]

    def one(i: int):
        check_cancelled(cancelled)
        inst = project.instances[i]
        try:
            if inst.mesh is not None:
                spacing = inst.mesh_spacing or project.spacing_mm
                volume = vol.load_mesh_volume(inst.mesh, spacing, cancelled=cancelled)
            elif cache_maps:
                volume = vol.select_label(maps[inst.volume], inst.label)
            else:
                volume = vol.load_volume(inst.volume, inst.label)
            frame = vol.object_frame(volume, project.frame_method)
            ov = vol.resample(volume, frame, project.spacing_mm, cancelled=cancelled)
        except InputError as err:
            raise InputError(f"instance {inst.name!r}: {err}") from None
        done[0] += 1
        report(progress, done[0] / n, f"imported {inst.name} ({done[0]}/{n}): {ov.mask.shape} voxels at "
                                      f"{ov.spacing_mm:g} mm, frame {frame.method}")
        return ov

    if cache_maps:  # read each shared file once, in order, before going parallel
        for path in sorted(paths):
            check_cancelled(cancelled)
            try:
                maps[path] = vol.read_label_map(path)
            except InputError as err:
                raise InputError(f"instances using {path.name}: {err}") from None
    workers = max(1, min(int(jobs or 1), n))
    if workers == 1:
        return [one(i) for i in range(n)]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(one, range(n)))


def _write_ply(path: Path, vertices, faces) -> None:
    from .meshutil import write_ply

    write_ply(path, np.asarray(vertices, float), np.asarray(faces))


def _final_move(tmp: Path, out_dir: Path) -> None:
    """Move the finished build from ``tmp`` into ``out_dir`` (entry by entry if it exists)."""
    if not out_dir.exists():
        os.replace(tmp, out_dir)
        return
    if not out_dir.is_dir():
        raise InputError(f"{out_dir}: output path exists and is not a folder")
    for entry in sorted(tmp.iterdir()):
        target = out_dir / entry.name
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        os.replace(entry, target)
    tmp.rmdir()


def build(
    project: Project,
    out_dir,
    jobs: int = 1,
    progress: ProgressFn = None,
    cancelled: CancelledFn = None,
    log: Callable[[str], None] | None = print,
    blend: bool | None = None,
    blender_hook: Callable | None = None,
) -> BuildResult:
    """Run the whole pipeline and write the outputs into ``out_dir`` atomically.

    Stages: import and object frames (paper 2) → landmarks into each object frame →
    template from ``project.template_instance`` (paper 3) → coating of every instance
    (paper 4, ``jobs`` processes) → model (paper 5, eqs. 4–6) → compactness,
    generalization, specificity → files.

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

    Files written
    -------------
    ``model.npz``, ``model.h5`` (statismo), ``report.json``, ``spectrum.png``,
    ``cumulative_variance.png`` (and the other metric plots), ``template.ply``,
    ``coated/<name>.ply`` (world mm), and with the hook ``model.blend``, ``modes.png``.
    """
    from . import metrics as met
    from .coating import coat_all
    from .model import build_model
    from .template import build_template

    say = log or (lambda _msg: None)
    out_dir = Path(out_dir).expanduser().resolve()
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"{out_dir}: output path exists and is not a folder")
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    opts = project.output_options
    names = list(project.names)
    n = len(names)
    timings: dict[str, float] = {}
    t_total = time.perf_counter()

    def stage(name: str, start: float, stop: float):
        def prog(fraction: float, message: str) -> None:
            report(progress, start + (stop - start) * fraction, message)

        return prog

    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.building-", dir=out_dir.parent))
    try:
        # 1. import (paper 2)
        report(progress, 0.0, f"import: {n} instances at {project.spacing_mm:g} mm")
        t0 = time.perf_counter()
        objects = import_instances(project, jobs, stage("import", 0.0, 0.15), cancelled)
        timings["import"] = time.perf_counter() - t0
        say(f"import: {n} instances in {timings['import']:.2f} s")

        # 2. landmarks into each object frame
        lm_world = [inst.landmark_set for inst in project.instances]
        lm_object = [ov.frame.to_object(lm.points_world) for ov, lm in zip(objects, lm_world)]

        # 3. template (paper 3)
        check_cancelled(cancelled)
        ti = names.index(project.template_instance)
        report(progress, 0.15, f"template: from {names[ti]}")
        t0 = time.perf_counter()
        try:
            template = build_template(objects[ti], project.template_params, progress=stage("template", 0.15, 0.3),
                                      cancelled=cancelled)
        except InputError as err:
            raise InputError(f"template from instance {names[ti]!r}: {err}") from None
        timings["template"] = time.perf_counter() - t0
        from .meshutil import genus

        say(f"template: {len(template.points_object)} points, {len(template.faces)} triangles, "
            f"genus {genus(len(template.points_object), template.faces)} from {names[ti]} in {timings['template']:.2f} s")

        # 4. coating (paper 4)
        check_cancelled(cancelled)
        report(progress, 0.3, f"coating: {n} instances, {jobs} job(s)")
        t0 = time.perf_counter()
        coat_prog = stage("coating", 0.3, 0.85)

        def coat_progress(fraction: float, message: str) -> None:
            if message.startswith("coated "):
                coat_prog(fraction, message)

        coatings = coat_all(template, lm_object[ti], objects, lm_object, project.coating_params, jobs=jobs,
                            progress=coat_progress if progress else None, cancelled=cancelled, names=names)
        timings["coating"] = time.perf_counter() - t0
        worst = max(c.fit.max_distance_mm for c in coatings)
        say(f"coating: {n} instances in {timings['coating']:.2f} s (largest surface distance {worst:.2f} mm)")

        # 5. model (paper 5)
        check_cancelled(cancelled)
        report(progress, 0.85, "model: PCA")
        t0 = time.perf_counter()
        pts_object = np.stack([c.points_object for c in coatings])
        pts_world = np.stack([ov.frame.to_world(c.points_object) for ov, c in zip(objects, coatings)])
        mo = project.model_options
        params = {
            "project": str(project.path),
            "spacing_mm": project.spacing_mm,
            "frame_method": project.frame_method,
            "template_instance": project.template_instance,
            "template": dataclasses.asdict(project.template_params),
            "coating": dataclasses.asdict(project.coating_params),
            "model": dict(mo),
            "landmarks": list(project.landmark_names),
            "jobs": int(jobs),
            "versions": _versions(),
            "timings_s": dict(timings),
        }
        model = build_model(pts_object, template.faces, names, instance_points_world=pts_world,
                            alignment=mo["alignment"], n_modes=mo["n_modes"], params=params)
        timings["model"] = time.perf_counter() - t0
        say(f"model: {model.modes.shape[0]} modes, {model.mean.shape[0]} points in {timings['model']:.2f} s")

        # 6. metrics
        check_cancelled(cancelled)
        report(progress, 0.9, "metrics: compactness, generalization, specificity")
        t0 = time.perf_counter()
        metrics = met.evaluate(model, n_samples=mo["specificity_samples"], seed=mo["seed"], max_loo=mo["max_loo"],
                               cancelled=cancelled)
        timings["metrics"] = time.perf_counter() - t0
        say(f"metrics: compactness, generalization, specificity in {timings['metrics']:.2f} s")

        # 7. files
        check_cancelled(cancelled)
        report(progress, 0.95, "writing outputs")
        t0 = time.perf_counter()
        files: dict[str, Any] = {}
        frame_t = objects[ti].frame
        _write_ply(tmp / "template.ply", frame_t.to_world(template.points_object), template.faces)
        files["template"] = "template.ply"
        if opts["coated_meshes"]:
            (tmp / "coated").mkdir()
            for name, pw in zip(names, pts_world):
                _write_ply(tmp / "coated" / f"{name}.ply", pw, template.faces)
            files["coated"] = "coated"
        per_instance = {name: c.fit for name, c in zip(names, coatings)}
        extra = {
            "project": str(project.path),
            "parameters": params,
            "template": {"instance": names[ti], "points": int(len(template.points_object)),
                         "triangles": int(len(template.faces)), "genus": int(genus(len(template.points_object), template.faces))},
        }
        result = BuildResult(out_dir=out_dir, project=project, objects=tuple(objects), landmarks_world=tuple(lm_world),
                             template=template, coatings=tuple(coatings), model=model, metrics=metrics,
                             timings_s=timings, files=files, report={})
        use_blend = opts["blend"] if blend is None else blend
        if blender_hook is not None and use_blend:
            check_cancelled(cancelled)
            t1 = time.perf_counter()
            report(progress, 0.96, "Blender: model.blend and pictures")
            files.update(blender_hook(result, tmp, say) or {})
            timings["blender"] = time.perf_counter() - t1
        timings["write"] = time.perf_counter() - t0 - timings.get("blender", 0.0)
        timings["total"] = time.perf_counter() - t_total
        extra["timings_s"] = dict(timings)
        extra["peak_memory"] = peak_memory_mb()
        t1 = time.perf_counter()
        written = met.write_outputs(model, tmp, metrics, per_instance, extra=extra, plots=True)
        timings["write"] += time.perf_counter() - t1
        timings["total"] = time.perf_counter() - t_total
        doc = json.loads((tmp / "report.json").read_text())  # the final figures, incl. writing the report
        doc["timings_s"] = dict(timings)
        doc["peak_memory"] = peak_memory_mb()
        (tmp / "report.json").write_text(json.dumps(doc, indent=1))
        if not opts["statismo"]:
            Path(written.pop("statismo")).unlink()
        for key, value in written.items():
            if key == "plots":
                files["plots"] = [Path(v).name for v in value]
            elif isinstance(value, str) and Path(value).exists():
                files[key] = Path(value).name
        report_doc = json.loads((tmp / "report.json").read_text())
        check_cancelled(cancelled)
        _final_move(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    files = {k: ([str(out_dir / x) for x in v] if isinstance(v, list) else str(out_dir / v)) for k, v in files.items()}
    report(progress, 1.0, f"done: {out_dir}")
    return dataclasses.replace(result, files=files, report=report_doc)
