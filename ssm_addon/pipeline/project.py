"""The project file: the instances of a shape population and every stage's parameters.

A project file (TOML) lists the instances of a shape population and the parameters of
every stage; :func:`read_project` parses and validates it (every problem is an
:class:`~ssm_addon.base.errors.InputError` naming the file, line, key or instance and the
allowed values) and :func:`build` runs the study's stages (:mod:`ssm_addon.pipeline.study`) and
writes the outputs atomically: everything goes into a temporary folder next to the
output folder and is moved into place only when the whole build succeeded.

The tables ``[template]``, ``[coating]``, ``[model]`` and ``[output]`` hold the fields of
:class:`~ssm_addon.base.params.TemplateParams`, :class:`~ssm_addon.base.params.CoatingParams`,
:class:`~ssm_addon.base.params.ModelParams` and :class:`~ssm_addon.base.params.OutputParams`
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
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..analysis.attributes import attributes_from_tables, read_attributes
from ..analysis.shape_analysis import CENTROID_SIZE
from ..base import params as P
from ..base.errors import InputError
from ..base.params import AnalysisParams, StudyParams
from ..fitting.batch import FitTarget
from ..formats.landmarks import LandmarkSet, match_landmarks, read_landmarks
from ..instances.importing import InstanceSpec, file_names, landmark_space

__all__ = ["STRUCTURE_KEYS", "Project", "Structure", "project_text", "read_project", "structure_overrides",
           "targets_from_project", "toml_value", "write_project"]

#: Keys of an instance that holds several structures: a table structure name -> file or label.
STRUCTURE_KEYS = {
    "meshes": "a table of structure name -> mesh file, e.g. { femur = \"S001_Femur.ply\" }",
    "labels": "a table of structure name -> label of the instance's volume, e.g. { L1 = 20, L2 = 21 }",
}
#: Tables a [[structures]] entry may set over the project's, for that structure alone.
STRUCTURE_TABLES = ("template", "coating", "correspondence")
#: [study] keys: the attribute table may also be given there (the same as [analysis] attributes).
STUDY_KEYS = ("attributes",)

INSTANCE_KEYS = {
    "name": "a string",
    "volume": "a file path (string)",
    "label": "an integer",
    "mesh": "a file path (string)",
    "mesh_spacing": "a number",
    "landmarks": "a file path (string)",
    "space": "\"RAS\" or \"LPS\" (the convention of this instance's files that state none)",
    "image": "a file path (string): the instance's grey-value image (CT), whose boundary appearance the build learns",
    "side": "\"left\" or \"right\": the instance's side; an instance of the other side than the template instance's "
            "is mirrored into the template's side before it is coated",
    **STRUCTURE_KEYS,
    "attributes": "a table of attributes, e.g. { group = \"patient\", age = 63 }",
}
#: Spellings of a side a project may give, and the side they mean.
SIDE_NAMES = {"left": "left", "right": "right", "l": "left", "r": "right"}
#: Longest instance name: it names output files (``coated/<name>.ply``, ``landmarks/<name>.mrk.json``),
#: and file systems allow 255 bytes per file name.
MAX_NAME_CHARS = 200
#: [template] keys besides the TemplateParams fields.
STUDY_TEMPLATE_KEYS = ("instance",)
SECTIONS = ("instances", *P.SECTIONS, "study", "structures")


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
    params : StudyParams
        Every table's parameters (defaults for what the file leaves out; ``params.analysis``
        with its ``attributes`` path absolute).
    landmark_names : tuple of str
        The common landmark names, in the order of the first instance's file.
    instance_attributes : dict name -> dict
        Each instance's own ``attributes`` table, as written.
    attributes : Attributes or None
        The instances' attributes: their own tables, filled from the CSV file of
        ``[analysis]`` (or ``[study]``) ``attributes``; None when there are none.
    structures : dict name -> Structure
        A project whose instances hold several structures (``meshes = {femur = …, tibia =
        …}``, or ``volume`` with ``labels = {L1 = 20, …}``): each structure's own study, its
        instances named by subject, in the order of the structure names. Empty for a project
        of one structure (then ``instances`` is that structure's).
    """

    path: Path
    instances: tuple[InstanceSpec, ...]
    template_instance: str
    params: StudyParams = field(default_factory=StudyParams)
    landmark_names: tuple[str, ...] = ()
    instance_attributes: dict = field(default_factory=dict)
    attributes: Any = None
    structures: dict = field(default_factory=dict)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(i.name for i in self.instances)

    @property
    def input_files(self) -> list[Path]:
        """Every file the project reads (label maps, meshes, landmark files), each structure's too."""
        specs = [i for st in self.structures.values() for i in st.instances] or list(self.instances)
        return [p for i in specs for p in (i.volume_path, i.mesh_path, i.landmarks_path) if p is not None]


@dataclass(frozen=True)
class Structure:
    """One structure of a multi-structure project: its instances (one per subject, named by the
    subject), the instance its template comes from, its parameters (the project's, with the
    structure's own ``[[structures]]`` tables over them) and its landmark names."""

    name: str
    instances: tuple[InstanceSpec, ...]
    template_instance: str
    params: StudyParams
    landmark_names: tuple[str, ...] = ()


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
    return ctx.error(f"{what} must be {expected}, got {P.type_name(value)} {value!r}", line)


def _existing_file(value, key, what, ctx, where, base) -> Path:
    line = ctx.lines.key(*where, key)
    if not isinstance(value, str):
        raise _kind_error(ctx, f"{what}: {key}", INSTANCE_KEYS[key], value, line)
    if "\0" in value or any(ord(c) < 32 for c in value):
        raise ctx.error(f"{what}: {key} {value!r} holds a control character (NUL, tab or newline): not a file path",
                        line)
    try:
        path = _resolve(value, base)
        exists = path.is_file()
    except RuntimeError:  # Path.resolve on a symbolic link that points back at itself
        raise ctx.error(f"{what}: {key} {value!r} is a symbolic link loop (it points back at itself)", line) from None
    except (OSError, ValueError) as err:
        raise ctx.error(f"{what}: {key} {value!r}: cannot be used as a path ({err})", line) from None
    if not exists:
        if path.is_dir():
            raise ctx.error(f"{what}: {key} {path} is a folder, not a file", line)
        if os.path.islink(path):
            raise ctx.error(f"{what}: {key} {path} is a symbolic link to nothing (or a link loop)", line)
        raise ctx.error(f"{what}: {key} file not found: {path}", line)
    return path


#: Keys of earlier versions, read as today's: [table] -> {old key: (new key, {old value: new value})}.
LEGACY_KEYS = {"correspondence": {"exact_landmarks": ("landmark_noise_mm", {True: 0.0, False: None})}}


def _params(cls, doc: dict, section: str, ctx: _Context, extra=()):
    table = doc.get(section, {})
    if not isinstance(table, dict):
        raise ctx.error(f"[{section}] must be a table, got {P.type_name(table)}", ctx.lines.key(section))
    for old, (new, values) in LEGACY_KEYS.get(section, {}).items():
        if old in table:
            line = ctx.lines.key(section, old)
            if new in table:
                raise ctx.error(f"[{section}] {old} (of earlier versions) and {new} are the same setting; give {new}",
                                line)
            value = table[old]
            if not isinstance(value, bool):
                raise _kind_error(ctx, f"[{section}] {old}", "true or false", value, line)
            table = {k: v for k, v in table.items() if k != old}
            if values[value] is not None:
                table[new] = values[value]
    allowed = {*P.keys(cls), *extra}
    _check_keys(table, allowed, f"[{section}]", ctx, (section,))
    values = {k: v for k, v in table.items() if k not in extra}
    lines = {k: f"{ctx.at(ctx.lines.key(section, k))}: [{section}]" for k in values}
    return P.from_table(cls, values, where=f"{ctx.at(ctx.lines.table(section))}: [{section}]", lines=lines)


def _instances(doc: dict, ctx: _Context, base: Path,
               study_space: str = "auto") -> list[InstanceSpec]:
    raw = doc.get("instances")
    if raw is None or (isinstance(raw, list) and not raw):
        raise ctx.error("no [[instances]]: a build needs at least 3 instances, each with name, volume (or mesh) "
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
        if any(ord(c) < 32 or ord(c) == 127 for c in name):
            raise ctx.error(f"{label_txt}: name {name!r} holds a control character (NUL, tab, newline); an instance "
                            "name must be printable (it names files and Blender objects)", ctx.lines.key(*where, "name"))
        if len(name) > MAX_NAME_CHARS:
            raise ctx.error(f"{label_txt}: name is {len(name)} characters; at most {MAX_NAME_CHARS} (it names the "
                            f"instance's output files): {name[:40]!r}…", ctx.lines.key(*where, "name"))
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
        if has_mesh and "label" in table:
            raise ctx.error(f"{what}: 'label' applies to volumes, not meshes", ctx.lines.key(*where, "label"))
        if has_volume and "mesh_spacing" in table:
            raise ctx.error(f"{what}: 'mesh_spacing' applies to meshes, not volumes",
                            ctx.lines.key(*where, "mesh_spacing"))
        mesh_spacing = float(table["mesh_spacing"]) if "mesh_spacing" in table else None
        if mesh_spacing is not None and not (np.isfinite(mesh_spacing) and 0 < mesh_spacing <= 50):
            raise ctx.error(f"{what}: mesh_spacing must be a number > 0 mm and <= 50 mm, got {mesh_spacing!r}",
                            ctx.lines.key(*where, "mesh_spacing"))
        space = table.get("space")
        if space is not None and (not isinstance(space, str) or space.upper() not in ("RAS", "LPS")):
            raise ctx.error(f"{what}: space must be \"RAS\" or \"LPS\", got {space!r}", ctx.lines.key(*where, "space"))
        space = space.upper() if space is not None else None
        side = table.get("side")
        if side is not None:
            if not isinstance(side, str) or side.strip().lower() not in SIDE_NAMES:
                raise ctx.error(f"{what}: side must be \"left\" or \"right\", got {side!r}",
                                ctx.lines.key(*where, "side"))
            side = SIDE_NAMES[side.strip().lower()]
        volume = _existing_file(table["volume"], "volume", what, ctx, where, base) if has_volume else None
        mesh = _existing_file(table["mesh"], "mesh", what, ctx, where, base) if has_mesh else None
        image = _existing_file(table["image"], "image", what, ctx, where, base) if "image" in table else None
        lm_path, lms = None, None
        if "landmarks" in table:
            lm_path = _existing_file(table["landmarks"], "landmarks", what, ctx, where, base)
            lm_space, why = landmark_space(InstanceSpec(name=name, mesh_path=mesh, space=space), study_space)
            try:
                lms = read_landmarks(lm_path, space=lm_space, why=why)
            except InputError as err:
                raise ctx.error(f"{what}: {err}", ctx.lines.key(*where, "landmarks")) from None
            lms = LandmarkSet(lms.names, lms.points_world, source=f"instance {name!r} ({lm_path.name})",
                              coordinates=lms.coordinates)
        if "attributes" in table:
            attrs = table["attributes"]
            line = ctx.lines.key(*where, "attributes")
            if not isinstance(attrs, dict):
                raise _kind_error(ctx, f"{what}: attributes", INSTANCE_KEYS["attributes"], attrs, line)
            for k, v in attrs.items():
                if isinstance(v, dict | list) or not isinstance(v, str | int | float | bool):
                    raise ctx.error(f"{what}: attribute {k!r} must be a number or a string, got {P.type_name(v)} "
                                    f"{v!r}", line)
        out.append(InstanceSpec(name=name, landmarks_path=lm_path, volume_path=volume, label=table.get("label"), mesh_path=mesh,
                                mesh_spacing_mm=mesh_spacing, landmarks=lms, space=space, image_path=image,
                                side=side))
    return out


def _sides(instances: list[InstanceSpec], template_instance: str, ctx: _Context, tables: dict,
           structure: str = "") -> list[InstanceSpec]:
    """``mirror`` of every instance: True where its given side differs from the template instance's,
    False where it is the same (and for the template instance), None (found by the coating stage,
    :mod:`ssm_addon.correspondence.sides`) where none is given and ``[correspondence] sides =
    "detect"``, else False. In a project of several structures a side is the subject's: each
    structure's instance of a subject gives it, and a subject's sides are found for all its
    structures at once (:func:`~ssm_addon.pipeline.joint.joint_sides`)."""
    given = {i.name: i.side for i in instances if i.side is not None}
    template_side = given.get(template_instance)
    if given and template_side is None:
        first = next(n for n in given)
        raise ctx.error(f"{f'structure {structure!r}: ' if structure else ''}instance {first!r} gives side = {given[first]!r} but the template instance "
                        f"{template_instance!r} gives none: give the template instance's side (the model's side)",
                        ctx.lines.table("instances", [i.name for i in instances].index(template_instance)))
    detect = tables["correspondence"].sides == "detect"
    out = []
    for inst in instances:
        if inst.name == template_instance:
            mirror = False
        elif inst.side is not None:
            mirror = inst.side != template_side
        else:
            mirror = None if detect else False
        out.append(dataclasses.replace(inst, mirror=mirror))
    return out


def _attributes(doc: dict, ctx: _Context, base: Path, names) -> tuple[AnalysisParams, dict, Any]:
    """The [analysis] table (attributes path absolute), the instances' own attribute tables and
    the merged attribute table (None when there is none)."""
    study = doc.get("study", {})
    if not isinstance(study, dict):
        raise ctx.error(f"[study] must be a table, got {P.type_name(study)}", ctx.lines.key("study"))
    _check_keys(study, STUDY_KEYS, "[study]", ctx, ("study",))
    analysis = _params(AnalysisParams, doc, "analysis", ctx)
    csv_path, line = analysis.attributes, ctx.lines.key("analysis", "attributes")
    if "attributes" in study:
        if csv_path:
            raise ctx.error("attributes given in both [study] and [analysis]; give one",
                            ctx.lines.key("study", "attributes"))
        csv_path, line = study["attributes"], ctx.lines.key("study", "attributes")
        if not isinstance(csv_path, str):
            raise _kind_error(ctx, "[study] attributes", "a file path (string)", csv_path, line)
    inline = {inst["name"]: dict(inst["attributes"]) for inst in doc.get("instances", []) if "attributes" in inst}
    table = attributes_from_tables(inline, source=f"{ctx.path}: instance attributes") if inline else None
    if csv_path:
        path = _resolve(csv_path, base)
        if not path.is_file():
            raise ctx.error(f"attributes file not found: {path}", line)
        try:
            from_csv = read_attributes(path)
        except InputError as err:
            raise ctx.error(str(err), line) from None
        unknown = [n for n in from_csv.names if n not in set(names)]
        if len(unknown) == len(from_csv.names):
            raise ctx.error(f"{path}: no row of the attribute table names an instance of the project (rows: "
                            f"{', '.join(map(repr, from_csv.names[:4]))}…)", line)
        table = from_csv if table is None else table.merged(from_csv)
        analysis = dataclasses.replace(analysis, attributes=str(path))
    if analysis.requested and table is None:
        raise ctx.error("[analysis] needs attributes: give each instance an attributes table or [analysis] "
                        "attributes = \"subjects.csv\"", ctx.lines.table("analysis"))
    if table is not None and analysis.requested:  # a typo is an error now; what the data allow, the build says

        for column in ([analysis.group] if analysis.group else []) + list(analysis.covariates):
            if column != CENTROID_SIZE:
                try:
                    table.require(column)
                except InputError as err:
                    raise ctx.error(f"[analysis]: {err}", ctx.lines.table("analysis")) from None
    return analysis, inline, table


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
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a project file (give the .toml file inside it)")
    if not path.is_file():
        raise InputError(f"{path}: project file not found")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"{path}: cannot read project file ({err})") from None
    text = text.removeprefix("\ufeff")  # a byte-order mark (Notepad writes one): TOML has none; read past it
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise InputError(f"{path}: TOML syntax error: {err}") from None
    ctx = _Context(path, text)

    for key in doc:
        if key not in SECTIONS:
            line = ctx.lines.table(key) or ctx.lines.table(key, 0) or ctx.lines.key(key)
            raise ctx.error(f"unknown table or key {key!r}{_suggest(key, SECTIONS)}", line)

    tables = {section: _params(cls, doc, section, ctx, extra=STUDY_TEMPLATE_KEYS if section == "template" else ())
              for section, cls in P.TABLES.items()}  # [analysis] with the attributes, below
    compute = tables["compute"]
    if compute.cache not in ("auto", "off") and not Path(compute.cache).is_absolute():
        tables["compute"] = dataclasses.replace(compute, cache=str((path.parent / compute.cache).resolve()))

    structures = _structure_names(doc, ctx)
    if not structures:
        instances, template_instance, lm_names = _study_instances(doc, ctx, path, tables)
        per_structure = {}
    else:
        per_structure = {}
        overrides = _structure_tables(doc, ctx, structures)
        for st in structures:
            sub = _structure_doc(doc, st, overrides.get(st, {}), ctx)
            st_tables = {**tables, **{t: _params(P.TABLES[t], sub, t, ctx, extra=STUDY_TEMPLATE_KEYS if t == "template"
                                                 else ()) for t in STRUCTURE_TABLES}}
            specs, tpl, lm_names = _study_instances(sub, ctx, path, st_tables, structure=st)
            per_structure[st] = Structure(name=st, instances=tuple(specs), template_instance=tpl,
                                          params=StudyParams(**st_tables), landmark_names=lm_names)
        first = per_structure[structures[0]]
        instances, template_instance, lm_names = list(first.instances), first.template_instance, first.landmark_names
        _check_structures(per_structure, tables, ctx)
    names = [i.name for i in instances]
    analysis, inline_attributes, attributes = _attributes(doc, ctx, path.parent, names)

    params = StudyParams(**tables, analysis=analysis)
    per_structure = {st: dataclasses.replace(v, params=v.params.replace(analysis=analysis))
                     for st, v in per_structure.items()}
    return Project(path=path, instances=tuple(instances), template_instance=template_instance, params=params,
                   landmark_names=lm_names, instance_attributes=inline_attributes, attributes=attributes,
                   structures=per_structure)


def _study_instances(doc: dict, ctx: _Context, path: Path, tables: dict, structure: str = ""):
    """The instances of one structure's study (the project's, or a structure's of a multi-structure
    project): validated, landmarks read and matched; with the template instance and the landmark names."""
    what = f"structure {structure!r}: " if structure else ""
    instances = _instances(doc, ctx, path.parent,
                           study_space=tables["template"].space)
    if len(instances) < 2:
        raise ctx.error(f"only one instance ({instances[0].name!r}): a build needs at least 3 (a model with its "
                        "leave-one-out metrics)",
                        ctx.lines.table("instances", 0))
    marked = [inst for inst in instances if inst.landmarks is not None]
    if not marked:  # no landmarks: the object frames and the shapes anchor the correspondence
        names = [i.name for i in instances]
        try:
            file_names(names)
        except InputError as err:
            raise ctx.error(str(err), ctx.lines.table("instances", 0)) from None
        template_instance = _template_instance(doc, ctx, what, names)
        return _sides(instances, template_instance, ctx, tables, structure), template_instance, ()
    try:
        matched = match_landmarks([inst.landmarks for inst in marked])
    except InputError as err:
        raise ctx.error(f"{what}landmark names differ between instances (reference: instance {marked[0].name!r}): "
                        f"{err}") from None
    if len(matched[0]) < 4:
        raise ctx.error(f"{what}{len(matched[0])} landmarks: the landmark warp (eq. 2) needs at least 4 per instance")
    by_name = {inst.name: lm for inst, lm in zip(marked, matched)}
    instances = [dataclasses.replace(inst, landmarks=by_name.get(inst.name)) for inst in instances]
    names = [i.name for i in instances]
    try:
        file_names(names)
    except InputError as err:
        raise ctx.error(str(err), ctx.lines.table("instances", 0)) from None
    template_instance = _template_instance(doc, ctx, what, names)
    if by_name.get(template_instance) is None:
        raise ctx.error(f"{what}[template] instance {template_instance!r} has no landmarks; the template instance "
                        "needs them when other instances have landmarks (they name the places carried to every "
                        "instance; or give no instance landmarks)", ctx.lines.key("template", "instance"))
    return _sides(instances, template_instance, ctx, tables, structure), template_instance, matched[0].names


def _template_instance(doc: dict, ctx: _Context, what: str, names: list[str]) -> str:
    """The ``[template] instance`` (default the first instance), checked to be one of ``names``."""
    template_instance = doc.get("template", {}).get("instance", names[0])
    line = ctx.lines.key("template", "instance")
    if not isinstance(template_instance, str):
        raise _kind_error(ctx, f"{what}[template] instance", "a string", template_instance, line)
    if template_instance not in names:
        close = difflib.get_close_matches(template_instance, names, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ctx.error(f"{what}[template] instance {template_instance!r} is not an instance name{hint}", line)
    return template_instance


def _structure_names(doc: dict, ctx: _Context) -> tuple[str, ...]:
    """The structure names of a multi-structure project (the keys of its instances' ``meshes`` or
    ``labels`` tables, in the order of the first instance), or () for a project of one structure."""
    tables = doc.get("instances", [])
    if not isinstance(tables, list):
        return ()
    multi = [i for i, t in enumerate(tables) if isinstance(t, dict) and any(k in t for k in STRUCTURE_KEYS)]
    if not multi:
        return ()
    if len(multi) != len(tables):
        single = next(i for i in range(len(tables)) if i not in multi)
        raise ctx.error(f"[[instances]] #{single + 1}: every instance of a multi-structure project gives its structures "
                        "as meshes = { … } or labels = { … }", ctx.lines.table("instances", single))
    names: tuple[str, ...] = ()
    for i, t in enumerate(tables):
        key = "meshes" if "meshes" in t else "labels"
        if "meshes" in t and ("labels" in t or "volume" in t or "mesh" in t):
            raise ctx.error(f"[[instances]] #{i + 1}: meshes = {{ … }} stands alone (no volume, labels or mesh)",
                            ctx.lines.key("instances", i, "meshes"))
        if "labels" in t and "volume" not in t:
            raise ctx.error(f"[[instances]] #{i + 1}: labels = {{ … }} needs the volume they label",
                            ctx.lines.key("instances", i, "labels"))
        value = t[key]
        if not isinstance(value, dict) or not value:
            raise _kind_error(ctx, f"[[instances]] #{i + 1}: {key}", STRUCTURE_KEYS[key], value,
                              ctx.lines.key("instances", i, key))
        these = tuple(str(k) for k in value)
        if not names:
            names = these
        elif set(these) != set(names):
            raise ctx.error(f"[[instances]] #{i + 1} ({t.get('name', '?')!r}): structures {', '.join(these)}; every "
                            f"instance needs the same ({', '.join(names)})", ctx.lines.key("instances", i, key))
    order = [s.get("name") for s in doc.get("structures", []) if isinstance(s, dict)]
    return tuple(n for n in order if n in names) + tuple(n for n in names if n not in order)


def _check_structures(per_structure: dict, tables: dict, ctx: _Context) -> None:
    """Before anything is coated: the structures' folder names differ, ``[joint] reference`` names one
    of them, and no subject gives two structures the same file and label (a copied entry)."""
    names = list(per_structure)
    try:
        file_names(names)
    except InputError as err:
        raise ctx.error(f"structures: {str(err).replace('instances', 'structures', 1)} (structures/<name>/)",
                        ctx.lines.key("instances", 0)) from None
    reference = tables["joint"].reference
    if reference and reference not in names:
        raise ctx.error(f"[joint] reference {reference!r} is not a structure of the instances ({', '.join(names)})",
                        ctx.lines.key("joint", "reference"))
    for i, subject in enumerate(per_structure[names[0]].instances):
        seen: dict = {}
        for st in names:
            spec = per_structure[st].instances[i]
            key = (str(spec.source), spec.label)
            if key in seen:
                what = f"label {spec.label} of {spec.source}" if spec.label is not None else str(spec.source)
                raise ctx.error(f"subject {subject.name!r}: structures {seen[key]!r} and {st!r} are the same input "
                                f"({what}); each structure needs its own mesh or label", ctx.lines.table("instances", i))
            seen[key] = st


def _structure_tables(doc: dict, ctx: _Context, structures) -> dict:
    """``{structure: {table: {key: value}}}`` of the ``[[structures]]`` entries."""
    out = {}
    entries = doc.get("structures", [])
    if not isinstance(entries, list):
        raise ctx.error("[[structures]] must be an array of tables", ctx.lines.key("structures"))
    for i, entry in enumerate(entries):
        where = ("structures", i)
        if not isinstance(entry, dict) or "name" not in entry:
            raise ctx.error(f"[[structures]] #{i + 1}: needs a name", ctx.lines.table(*where))
        _check_keys(entry, ("name", *STRUCTURE_TABLES), f"[[structures]] #{i + 1}", ctx, where)
        if entry["name"] not in structures:
            raise ctx.error(f"[[structures]] #{i + 1}: {entry['name']!r} is not a structure of the instances "
                            f"({', '.join(structures)})", ctx.lines.key(*where, "name"))
        for t in STRUCTURE_TABLES:
            if t in entry and not isinstance(entry[t], dict):
                raise _kind_error(ctx, f"[[structures]] {entry['name']!r}: {t}", "a table", entry[t],
                                  ctx.lines.key(*where, t))
        out[entry["name"]] = {t: entry[t] for t in STRUCTURE_TABLES if t in entry}
    return out


def _structure_doc(doc: dict, structure: str, override: dict, ctx: _Context) -> dict:
    """The project as a project of ``structure`` alone: each instance with that structure's mesh
    (or its volume's label) and landmark file, the structure's tables over the project's."""
    out = {k: v for k, v in doc.items() if k not in ("instances", "structures")}
    for t, table in override.items():
        out[t] = {**doc.get(t, {}), **table}
    instances = []
    for i, t in enumerate(doc["instances"]):
        single = {k: v for k, v in t.items() if k not in ("meshes", "labels", "landmarks", "attributes")}
        if "meshes" in t:
            single["mesh"] = t["meshes"][structure]
        else:
            single["label"] = t["labels"][structure]
        lm = t.get("landmarks")
        if isinstance(lm, dict):
            if structure in lm:
                single["landmarks"] = lm[structure]
        elif lm is not None:
            raise ctx.error(f"[[instances]] #{i + 1}: landmarks of a multi-structure instance are a table per "
                            "structure, e.g. { femur = \"lm/S001_femur.csv\" }", ctx.lines.key("instances", i, "landmarks"))
        instances.append(single)
    out["instances"] = instances
    return out


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
    for section, params in project.params.tables():
        if section in ("compute", "analysis"):  # written below, only what is set
            continue
        if section != "template":
            lines += ["", f"[{section}]"]
        lines += [f"{k} = {toml_value(v)}" for k, v in P.to_table(params).items()]
    compute = P.to_table(project.params.compute, only_changed=True)  # written only when set (Blender has no such panel)
    if compute:
        if compute.get("cache") not in (None, "auto", "off"):
            compute["cache"] = _relative(Path(compute["cache"]), base)
        lines += ["", "[compute]"] + [f"{k} = {toml_value(v)}" for k, v in compute.items()]
    analysis = P.to_table(project.params.analysis, only_changed=True)
    if analysis:
        if analysis.get("attributes"):
            analysis["attributes"] = _relative(Path(analysis["attributes"]), base)
        lines += ["", "[analysis]"] + [f"{k} = {toml_value(v)}" for k, v in analysis.items()]
    if project.structures:
        return "\n".join(lines + _joint_text(project, base)) + "\n"
    for inst in project.instances:
        lines += ["", "[[instances]]", f"name = {toml_value(inst.name)}"]
        if inst.volume_path is not None:
            lines.append(f"volume = {toml_value(_relative(inst.volume_path, base))}")
            if inst.label is not None:
                lines.append(f"label = {int(inst.label)}")
        else:
            lines.append(f"mesh = {toml_value(_relative(inst.mesh_path, base))}")
            if inst.mesh_spacing_mm is not None:
                lines.append(f"mesh_spacing = {toml_value(float(inst.mesh_spacing_mm))}")
        if inst.landmarks_path is not None:
            lines.append(f"landmarks = {toml_value(_relative(inst.landmarks_path, base))}")
        if inst.space is not None:
            lines.append(f"space = {toml_value(inst.space)}")
        if inst.image_path is not None:
            lines.append(f"image = {toml_value(_relative(inst.image_path, base))}")
        if inst.side is not None:
            lines.append(f"side = {toml_value(inst.side)}")
        own = project.instance_attributes.get(inst.name)
        if own:
            lines.append("attributes = { " + ", ".join(f"{_key(k)} = {toml_value(v)}" for k, v in own.items()) + " }")
    return "\n".join(lines) + "\n"


def structure_overrides(project: Project) -> dict:
    """``{structure: {table: {key: value}}}``: each structure's tables (``STRUCTURE_TABLES``)
    where they differ from the project's, as a ``[[structures]]`` entry states them."""
    out = {}
    for name, st in project.structures.items():
        own = {}
        for t in STRUCTURE_TABLES:
            theirs = P.to_table(getattr(project.params, t))
            diff = {k: v for k, v in P.to_table(getattr(st.params, t)).items() if theirs.get(k) != v}
            if diff:
                own[t] = diff
        out[name] = own
    return out


def _joint_text(project: Project, base: Path) -> list[str]:
    """The ``[[structures]]`` entries (each structure's tables that differ from the project's, its
    template's subject when not the project's) and the ``[[instances]]`` of a joint project:
    ``meshes = { … }``, or one ``volume`` with ``labels = { … }``, and ``landmarks = { … }``."""
    lines = []
    overrides = structure_overrides(project)
    for name, st in project.structures.items():
        own = []
        for t in STRUCTURE_TABLES:
            diff = overrides[name].get(t, {})
            if t == "template" and st.template_instance != project.template_instance:
                diff = {"instance": st.template_instance, **diff}
            if diff:
                own.append(f"{t} = {{ " + ", ".join(f"{k} = {toml_value(v)}" for k, v in diff.items()) + " }")
        lines += ["", "[[structures]]", f"name = {toml_value(name)}", *own]
    by_structure = {name: {i.name: i for i in st.instances} for name, st in project.structures.items()}
    for subject in project.names:
        specs = {name: by_structure[name][subject] for name in project.structures}
        lines += ["", "[[instances]]", f"name = {toml_value(subject)}"]
        volumes = {i.volume_path for i in specs.values()}
        if all(i.mesh_path is not None for i in specs.values()):
            lines.append("meshes = { " + ", ".join(f"{_key(n)} = {toml_value(_relative(i.mesh_path, base))}"
                                                   for n, i in specs.items()) + " }")
        elif len(volumes) == 1 and None not in volumes and all(i.label is not None for i in specs.values()):
            lines.append(f"volume = {toml_value(_relative(volumes.pop(), base))}")
            lines.append("labels = { " + ", ".join(f"{_key(n)} = {int(i.label)}" for n, i in specs.items()) + " }")
        else:
            raise InputError(f"{project.path}: subject {subject!r}: its structures are neither all meshes nor labels "
                             "of one volume, which a joint project cannot state")
        if any(i.landmarks_path is not None for i in specs.values()):
            lines.append("landmarks = { " + ", ".join(f"{_key(n)} = {toml_value(_relative(i.landmarks_path, base))}"
                                                      for n, i in specs.items() if i.landmarks_path is not None)
                         + " }")
        for key in ("space", "side"):  # a subject's, one for all its structures
            given = {getattr(i, key) for i in specs.values()} - {None}
            if len(given) > 1:
                raise InputError(f"{project.path}: subject {subject!r}: its structures give {key}s "
                                 f"{', '.join(sorted(given))}; a joint project states one {key} per subject")
            if given:
                lines.append(f"{key} = {toml_value(given.pop())}")
        own = project.instance_attributes.get(subject)
        if own:
            lines.append("attributes = { " + ", ".join(f"{_key(k)} = {toml_value(v)}" for k, v in own.items()) + " }")
    return lines


def _key(name: str) -> str:
    """A TOML key: bare when it can be, quoted otherwise."""
    return name if re.fullmatch(r"[A-Za-z0-9_-]+", name) else json.dumps(name, ensure_ascii=False)


def write_project(path, project: Project) -> Path:
    """Write ``project`` as a TOML project file at ``path`` (paths relative to it)."""
    path = Path(path).expanduser().resolve()
    text = project_text(project, path.parent)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
    return path


def targets_from_project(path, *, landmarks: bool = True) -> list[FitTarget]:
    """The instances of a project file as targets (with their landmarks unless ``landmarks``
    is false: ``ssm fit --no-landmarks``, so a batch fits the surfaces alone as a single
    fit of the same file does)."""
    proj = read_project(path)
    return [FitTarget(name=i.name, volume=i.volume_path, label=i.label, mesh=i.mesh_path,
                      landmarks=i.landmarks_path if landmarks else None) for i in proj.instances]
