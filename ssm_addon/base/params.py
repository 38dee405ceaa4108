"""The parameters of every stage, each defined once.

Each stage's parameters are a frozen dataclass whose fields carry their description
(:func:`param`): unit, default, range, choices and help text. Everything else is derived
from these definitions, so it cannot drift:

* the project file's tables and their validation (:func:`from_table`, :func:`to_table`,
  used by :mod:`ssm_addon.pipeline.project_build`);
* the command line's options (:func:`add_arguments`, :func:`from_arguments`);
* the Blender properties and panels (``operators/properties.py`` builds one property
  group per class from :func:`specs`).

Every length is in mm, every angle in degrees. ``None`` is a valid value only where a
field says what it means (``none_means``); Blender shows such a field with an "Auto"
toggle.

Examples
--------
>>> p = CoatingParams(k1=0.3)
>>> to_table(p)["k1"]
0.3
>>> from_table(CoatingParams, {"k2": 2.0}, where="[coating]").k2
2.0
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .compute import check_scheduler
from .errors import InputError

#: Object frame methods of paper 2 (:mod:`ssm_addon.instances.frame`).
FRAME_METHODS = ("auto", "patient", "moments")
#: Model alignments (:func:`ssm_addon.model.pca.build_model`): object frame only, Procrustes.
ALIGNMENTS = ("none", "rigid", "similarity")

__all__ = [
    "ALIGNMENTS",
    "JointParams",
    "SegmentParams",
    "FRAME_METHODS",
    "type_name",
    "AnalysisParams",
    "CoatingParams",
    "ComputeParams",
    "CorrespondenceParams",
    "FitParams",
    "ModelParams",
    "OutputParams",
    "QualityParams",
    "SECTIONS",
    "Spec",
    "StudyParams",
    "TABLES",
    "TemplateParams",
    "add_arguments",
    "check",
    "from_arguments",
    "from_table",
    "param",
    "shortest_float32",
    "specs",
    "to_table",
]



@dataclass(frozen=True)
class Spec:
    """The description of one parameter field.

    Attributes
    ----------
    name : str
        The dataclass field (and Blender property) name.
    key : str
        Its key in the project file (usually ``name``).
    kind : {"float", "int", "bool", "choice", "str", "floats", "strs"}
        ``floats`` is a tuple of floats (``size`` fixed, or any length when None); ``strs``
        a tuple of strings (e.g. column names).
    default : object
    label : str
        Short name for panels.
    help : str
        One sentence: what it does, with unit.
    unit : str
        "mm", "deg", "" ...
    minimum, maximum : float or None
        Allowed range (inclusive unless ``exclusive_minimum``).
    exclusive_minimum : bool
        True: the value must be strictly greater than ``minimum``.
    choices : tuple of str
        Allowed values of a ``choice``.
    none_means : str or None
        When set, ``None`` is allowed and means this (e.g. "r_min_mm").
    off : str
        For an optional field whose default is a value: the word that gives ``None`` in a
        project file, on the command line and in stored parameters (``"off"``), since
        leaving the key out gives the default. Empty: leaving the key out gives ``None``.
    size : int or None
        Length of a fixed ``floats`` tuple.
    advanced : bool
        Shown in the panel's "Advanced" sub-panel.
    aliases : tuple of str
        Other accepted project keys.
    metavar : str
        The command line's name for a value (``NAME``, ``FILE``, ``WHERE``); default from the
        kind and unit (``MM``, ``N``, ``X``, ``TEXT``).
    """

    name: str
    key: str
    kind: str
    default: Any
    label: str
    help: str
    unit: str = ""
    minimum: float | None = None
    maximum: float | None = None
    exclusive_minimum: bool = False
    choices: tuple = ()
    none_means: str | None = None
    size: int | None = None
    advanced: bool = False
    aliases: tuple = ()
    metavar: str = ""
    off: str = ""

    @property
    def optional(self) -> bool:
        return self.none_means is not None

    def range_text(self) -> str:
        """The allowed values in words, for messages and help."""
        if self.kind == "choice":
            return "one of " + ", ".join(repr(c) for c in self.choices)
        if self.kind == "bool":
            return "true or false"
        lo, hi = self.minimum, self.maximum
        unit = f" {self.unit}" if self.unit and self.unit != "deg" else ("°" if self.unit == "deg" else "")
        parts = []
        if lo is not None:
            parts.append(f"{'>' if self.exclusive_minimum else '>='} {_num(lo)}{unit}")
        if hi is not None:
            parts.append(f"<= {_num(hi)}{unit}")
        what = {"int": "an integer", "float": "a number", "floats": "numbers", "str": "a string",
                "strs": "a list of strings"}[self.kind]
        if self.kind == "floats" and self.size:
            what = f"{self.size} numbers"
        text = what + (" " + " and ".join(parts) if parts else "")
        if self.off:
            text += f" (or {self.off!r}: {self.none_means.removeprefix(self.off + ': ')})"
        elif self.optional:
            text += f" (or omitted: {self.none_means})"
        return text


def _num(x) -> str:
    x = float(x)
    return str(int(x)) if x.is_integer() and abs(x) < 1e12 else f"{x:g}"


def param(default, *, help: str, label: str | None = None, unit: str = "", minimum=None, maximum=None,
          exclusive_minimum: bool = False, choices=(), none_means: str | None = None, size: int | None = None,
          advanced: bool = False, key: str | None = None, aliases=(), kind: str | None = None, metavar: str = "",
          off: str = ""):
    """A dataclass field with its parameter description (see :class:`Spec`)."""
    if off and (default is None or none_means is None):
        raise TypeError("off= is for an optional parameter (none_means) whose default is a value")
    meta = {"ssm": {"label": label, "help": help, "unit": unit, "minimum": minimum, "maximum": maximum,
                    "exclusive_minimum": exclusive_minimum, "choices": tuple(choices), "none_means": none_means,
                    "size": size, "advanced": advanced, "key": key, "aliases": tuple(aliases), "kind": kind,
                    "metavar": metavar, "off": off}}
    return field(default=default, metadata=meta)


def _kind(default, meta) -> str:
    if meta["kind"]:
        return meta["kind"]
    if meta["choices"]:
        return "choice"
    for kind, types in (("bool", bool), ("int", int), ("float", float), ("str", str), ("floats", tuple)):
        if isinstance(default, types):
            return kind
    raise TypeError(f"parameter kind of default {default!r} unknown; give kind=")


def specs(cls) -> tuple[Spec, ...]:
    """The :class:`Spec` of every parameter field of a parameter class, in definition order."""
    cache = cls.__dict__.get("_specs_cache")
    if cache is not None:
        return cache
    out = []
    for f in dataclasses.fields(cls):
        meta = f.metadata.get("ssm")
        if meta is None:
            continue
        label = meta["label"] or f.name.removesuffix("_mm").removesuffix("_deg").replace("_", " ").capitalize()
        out.append(Spec(name=f.name, key=meta["key"] or f.name, kind=_kind(f.default, meta), default=f.default,
                        label=label, help=meta["help"], unit=meta["unit"], minimum=meta["minimum"],
                        maximum=meta["maximum"], exclusive_minimum=meta["exclusive_minimum"],
                        choices=meta["choices"], none_means=meta["none_means"], size=meta["size"],
                        advanced=meta["advanced"], aliases=meta["aliases"], metavar=meta.get("metavar", ""),
                        off=meta.get("off", "")))
    out = tuple(out)
    setattr(cls, "_specs_cache", out)  # noqa: B010 - a class attribute, not a field
    return out


def spec(cls, name: str) -> Spec:
    """The :class:`Spec` of one field."""
    for s in specs(cls):
        if s.name == name:
            return s
    raise KeyError(name)


# ------------------------------------------------------------------------------ checks
def type_name(value) -> str:
    """The TOML name of ``value``'s type, for messages (``integer``, ``table``, ...)."""
    return {bool: "boolean", int: "integer", float: "float", str: "string", list: "array", tuple: "array",
            dict: "table"}.get(type(value), type(value).__name__)


def convert(s: Spec, value, where: str = ""):
    """``value`` as the field's Python type, or InputError naming ``where`` and the field.

    Accepts what TOML, JSON and the command line give (int for float, list for tuple).
    """
    what = f"{where} {s.key}".strip()
    if s.off and isinstance(value, str) and value.strip().lower() == s.off:
        return None
    if value is None:
        if s.optional:
            return None
        raise InputError(f"{what} must be {s.range_text()}, got nothing")
    bad = InputError(f"{what} must be {s.range_text()}, got {type_name(value)} {value!r}")
    if s.kind == "bool":
        if not isinstance(value, bool | np.bool_):
            raise bad
        return bool(value)
    if s.kind == "int":
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise bad
        return int(value)
    if s.kind == "float":
        if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
            raise bad
        return float(value)
    if s.kind in ("choice", "str"):
        if not isinstance(value, str):
            raise bad
        return value
    if s.kind == "strs":
        if isinstance(value, str):
            value = [v.strip() for v in value.split(",") if v.strip()]
        if not isinstance(value, list | tuple) or not all(isinstance(v, str) for v in value):
            raise bad
        return tuple(value)
    if s.kind == "floats":
        if isinstance(value, str) or not isinstance(value, list | tuple | np.ndarray):
            raise bad
        out = []
        for v in value:
            if isinstance(v, bool) or not isinstance(v, int | float | np.integer | np.floating):
                raise bad
            out.append(float(v))
        return tuple(out)
    raise AssertionError(s.kind)  # pragma: no cover


def _check_number(s: Spec, value, what: str) -> None:
    v = float(value)
    if not math.isfinite(v):
        raise InputError(f"{what} must be {s.range_text()}, got {value!r}")
    lo, hi = s.minimum, s.maximum
    if lo is not None and (v <= lo if s.exclusive_minimum else v < lo):
        raise InputError(f"{what} must be {s.range_text()}, got {value!r}")
    if hi is not None and v > hi:
        raise InputError(f"{what} must be {s.range_text()}, got {value!r}")


def check_value(s: Spec, value, where: str = "") -> None:
    """Raise InputError when ``value`` (already converted) is outside the field's range."""
    what = f"{where} {s.key}".strip()
    if value is None:
        if not s.optional:
            raise InputError(f"{what} must be {s.range_text()}, got nothing")
        return
    if s.kind == "choice" and value not in s.choices:
        raise InputError(f"{what} must be {s.range_text()}, got {value!r}")
    if s.kind in ("float", "int"):
        _check_number(s, value, what)
    if s.kind == "floats":
        if s.size is not None and len(value) != s.size:
            raise InputError(f"{what} must be {s.range_text()}, got {len(value)}: {list(value)!r}")
        for v in value:
            _check_number(s, v, what)


def check(params, where: str = "") -> None:
    """Validate every field of a parameter object and its cross-field rules.

    Raises
    ------
    InputError
        Naming ``where`` (e.g. ``"[coating]"``), the key, the allowed range and the value.
    """
    for s in specs(type(params)):
        check_value(s, getattr(params, s.name), where)
    rules = getattr(params, "consistency", None)
    if rules is not None:
        problem = rules()
        if problem:
            raise InputError(f"{where} {problem}".strip())


# ----------------------------------------------------------------------- project tables
def keys(cls) -> dict[str, Spec]:
    """Project key (and alias) -> Spec."""
    out = {}
    for s in specs(cls):
        out[s.key] = s
        for a in s.aliases:
            out[a] = s
    return out


def from_table(cls, table: Mapping, *, where: str = "", lines: Mapping | None = None):
    """Parameters from a project table (keys as in the file), validated.

    A class may say what a table that leaves a key out means beyond its default
    (``cls.implied(names given) -> {name: value}``: a ``[template]`` table that states
    eq. 1's radii and no tolerance keeps eq. 1).

    Parameters
    ----------
    cls : parameter class
    table : mapping
        Only known keys (see :func:`keys`); unknown keys are the caller's to report.
    where : str
        Prefix of messages, e.g. ``"project.toml: [coating]"``.
    lines : mapping, optional
        key -> "file:line" prefix used instead of ``where`` for that key.
    """
    by_key = keys(cls)
    values: dict[str, Any] = {}
    seen: dict[str, str] = {}
    for key, value in table.items():
        s = by_key[key]
        at = (lines or {}).get(key) or where
        if s.name in values and seen[s.name] != key:
            raise InputError(f"{at} {key} and {seen[s.name]} are the same setting; give one")
        converted = convert(s, value, at)
        check_value(s, converted, at)
        values[s.name], seen[s.name] = converted, key
    implied = getattr(cls, "implied", None)
    if implied is not None:
        for name, value in implied(frozenset(values)).items():
            values.setdefault(name, value)
    try:
        params = cls(**values)
    except InputError as err:
        raise InputError(f"{where} {str(err).removeprefix(cls._where).strip()}".strip()) from None
    return params


def to_table(params, *, only_changed: bool = False) -> dict[str, Any]:
    """``{project key: value}`` of every field (TOML-ready: tuples as lists; None left out, or
    written as the field's ``off`` word where leaving it out would give its default)."""
    out = {}
    for s in specs(type(params)):
        v = getattr(params, s.name)
        if v is None and s.off and not (only_changed and v == s.default):
            out[s.key] = s.off
            continue
        if v is None or (only_changed and v == s.default):
            continue
        out[s.key] = list(v) if isinstance(v, tuple) else v
    implied = getattr(type(params), "implied", None)
    if only_changed and implied is not None:  # a left-out key must read back as it is, not as it is implied
        by_name = {s.name: s for s in specs(type(params))}
        written = frozenset(n for n, s in by_name.items() if s.key in out)
        for name, value in implied(written).items():
            actual = getattr(params, name)
            if actual != value:
                out[by_name[name].key] = by_name[name].off if actual is None and by_name[name].off else actual
    return out


def shortest_float32(value: float) -> float:
    """The shortest decimal that reads back as the same float32 (what the user typed).

    Blender stores float properties in single precision: 0.2 is kept as
    0.20000000298023224. This returns 0.2 again, so a value typed in Blender and the same
    value typed in a project file are the same float64.

    >>> shortest_float32(0.20000000298023224)
    0.2
    """
    v = np.float32(value)
    if not np.isfinite(v):
        return float(v)
    return float(np.format_float_positional(v, unique=True, trim="-")) if abs(v) < 1e16 else float(repr(v))


# -------------------------------------------------------------------------- command line
def _flag(prefix: str, s: Spec) -> str:
    return "--" + (f"{prefix}-" if prefix else "") + s.key.replace("_", "-")


def _or_word(typ, word: str):
    """An argparse type: ``typ`` of the text, or ``word`` itself (an optional field's 'off')."""
    def parse(text: str):
        return word if text.strip().lower() == word else typ(text)
    parse.__name__ = typ.__name__  # argparse names the type in its error message
    return parse


def add_arguments(parser: argparse.ArgumentParser | argparse._ArgumentGroup, cls, *, prefix: str = "",
                  skip=()) -> None:
    """One command-line option per field of ``cls`` (``--<prefix>-<key>``), default: unset.

    Values are checked by :func:`from_arguments` with the same messages as the project file.
    """
    for s in specs(cls):
        if s.name in skip:
            continue
        dest = f"{prefix}__{s.name}"
        unit = f" ({s.unit})" if s.unit else ""
        shown = (s.none_means if s.default is None and s.none_means else
                 f"{s.default!r} ({s.off!r}: {s.none_means.removeprefix(s.off + ': ')})" if s.off else
                 ("on" if s.default else "off") if s.kind == "bool" else repr(s.default))
        text = f"{s.help}{unit}; default {shown}".replace("%", "%%")
        if s.kind == "bool":
            parser.add_argument(_flag(prefix, s), dest=dest, action=argparse.BooleanOptionalAction, default=None,
                                help=text)
        elif s.kind == "floats":
            parser.add_argument(_flag(prefix, s), dest=dest, type=float, nargs=s.size or "+", default=None,
                                metavar="MM" if s.unit == "mm" else "X", help=text)
        elif s.kind == "strs":
            parser.add_argument(_flag(prefix, s), dest=dest, nargs="+", default=None, metavar="NAME", help=text)
        elif s.kind == "choice":
            parser.add_argument(_flag(prefix, s), dest=dest, choices=s.choices, default=None, help=text)
        else:
            typ = {"int": int, "float": float, "str": str}[s.kind]
            if s.off:
                typ = _or_word(typ, s.off)
            metavar = s.metavar or ("MM" if s.unit == "mm" else {"int": "N", "float": "X", "str": "TEXT"}[s.kind])
            parser.add_argument(_flag(prefix, s), dest=dest, type=typ, default=None, metavar=metavar, help=text)


def from_arguments(args: argparse.Namespace, cls, *, prefix: str = "", base=None):
    """Parameters of ``cls``: ``base`` (or defaults) with the options given on the command line."""
    values = {}
    for s in specs(cls):
        v = getattr(args, f"{prefix}__{s.name}", None)
        if v is not None:
            values[s.key] = v
    merged = {**(to_table(base) if base is not None else {}), **values}
    return from_table(cls, merged, where=f"command line {'--' + prefix + '-*' if prefix else ''}".strip())


# ------------------------------------------------------------------------- the classes


@dataclass(frozen=True)
class TemplateParams:
    """Import and template parameters (paper 2 and 3); the project's ``[template]`` table.

    The default density follows from one tolerance (``max_distance_mm``, 1 mm: the paper's
    section 3.1 hope, "the maximal allowed distance between a triangle in the surface
    triangulation and the actual object surface"); ``max_distance_mm = "off"`` gives the
    radii of eq. 1 from ``r_min_mm``, ``r_max_mm`` and ``p``. All lengths in mm.
    """

    max_distance_mm: float | None = param(1.0, kind="float", unit="mm", minimum=0.0, exclusive_minimum=True,
                                          maximum=100.0, none_means="off: the radii of eq. 1 (r_min, r_max, p)",
                                          off="off", label="Max distance",
                                          help="the template's density from one tolerance: the largest distance "
                                               "between its triangles and the surface (radii from the curvature, "
                                               "then refined where a triangle lies farther; r_max caps them). A "
                                               "table that states r_min_mm, r_max_mm or p and no max_distance_mm "
                                               "keeps eq. 1, as projects written before the tolerance mean")
    spacing_mm: float = param(1.0, key="spacing", aliases=("spacing_mm",), unit="mm", minimum=0.0,
                              exclusive_minimum=True, maximum=50.0, label="Spacing",
                              help="isotropic resampling step of every instance along its object axes (paper 2)")
    frame: str = param("auto", choices=FRAME_METHODS, label="Frame",
                       help="object frame: 'patient' pairs the principal axes with R, A, S; 'moments' uses "
                            "eigenvalue order and third-moment signs; 'auto' picks patient for images and for "
                            "meshes in a known convention (stated in the file, or 'space'), moments for others")
    space: str = param("auto", choices=("auto", "RAS", "LPS"), label="Coordinates",
                       help="coordinate convention of mesh files, and of landmark files (CSV, Scalismo JSON), that "
                            "state none; 'auto': a mesh file's own statement (SPACE=LPS as 3D Slicer writes), a "
                            "landmark file takes its instance's mesh's, and what states nothing is RAS. Files that "
                            "state their convention are read in it; LPS is turned into RAS")
    normal_radius_mm: float = param(5.0, unit="mm", minimum=0.0, exclusive_minimum=True, maximum=100.0,
                                    label="Normal radius", advanced=True,
                                    help="sphere radius of the normal estimate (paper 3.2)")
    patch_radius_mm: float = param(7.0, unit="mm", minimum=0.0, exclusive_minimum=True, maximum=100.0,
                                   label="Patch radius", advanced=True,
                                   help="patch radius of the curvature fit (paper 3.2)")
    curvature_form: str = param("quadric", choices=("quadric", "paper"), label="Curvature fit", advanced=True,
                                help="'quadric': z = ax² + 2bxy + cy² + dx + ey + f with bias corrections; "
                                     "'paper': z = ax² + 2bxy + cy² (noisier on voxel surfaces)")
    selection: str = param("curvature", choices=("curvature", "random"), label="Selection",
                           help="candidate order of the point density reduction: highest curvature first, "
                                "or seeded random (paper 3.1)")
    radius: str = param("curvature", choices=("curvature", "constant"), label="Radius",
                        help="reduction radius from the curvature by eq. (1), or constant r_max")
    r_min_mm: float = param(4.0, unit="mm", minimum=0.0, exclusive_minimum=True, maximum=1000.0, label="r min",
                            help="smallest reduction radius, surface distance (eq. 1)")
    r_max_mm: float = param(10.0, unit="mm", minimum=0.0, exclusive_minimum=True, maximum=1000.0, label="r max",
                            help="largest reduction radius, surface distance (eq. 1)")
    p: float = param(2.0, minimum=0.0, exclusive_minimum=True, maximum=100.0, label="p",
                     help="non-linearity of eq. (1): p > 1 gives more small radii")
    curvature_percentiles: tuple = param((2.0, 98.0), size=2, minimum=0.0, maximum=100.0,
                                         label="c percentiles", advanced=True,
                                         help="percentiles of the curvature used as c_min and c_max in eq. (1)")
    seed: int = param(0, minimum=0, maximum=2**32 - 1, label="Seed",
                      help="seed of the random selection and of tie-breaking")
    topology_radius_mm: float | None = param(None, kind="float", unit="mm", minimum=0.0, maximum=1000.0,
                                             none_means="r_min", label="Topology radius", advanced=True,
                                             help="closing radius of the topology cleaning (tunnels and cavities "
                                                  "below the point spacing are closed; opening at a third of it; "
                                                  "under the tolerance they change the shape only where they change "
                                                  "the topology or no deeper than twice the tolerance)")
    max_refinements: int = param(30, minimum=0, maximum=1000, label="Max refinements", advanced=True,
                                 help="rounds of seed insertion where the geodesic Voronoi regions are not disks")
    refine_where_cut_off: bool = param(True, label="Refine where cut off",
                                       help="when the coating of an instance given as a mesh cuts off a part of its "
                                            "surface (farther than [quality] max_input_distance_mm, and not lost at "
                                            "the import), build the template again with smaller radii where those "
                                            "parts lie on it and coat every instance again, once; the second coatings "
                                            "are kept when fewer meshes are cut off and no other finding is added")
    _where = "template parameters:"

    #: eq. 1's own parameters: a table that states one of them and no tolerance means eq. 1
    EQ1_KEYS = frozenset({"r_min_mm", "r_max_mm", "p"})

    def __post_init__(self):
        check(self, self._where)

    @classmethod
    def implied(cls, given: frozenset) -> dict:
        """What a ``[template]`` table that leaves ``max_distance_mm`` out means: eq. 1 when it
        states eq. 1's radii or exponent (projects and stored models written before the
        tolerance, whose ``r_min_mm``/``r_max_mm`` were eq. 1's), else the default tolerance."""
        if "max_distance_mm" not in given and given & cls.EQ1_KEYS:
            return {"max_distance_mm": None}
        return {}

    @classmethod
    def inactive(cls, value) -> frozenset:
        """The fields that the others leave unused (``value(name)`` gives a field's value): under
        a tolerance eq. 1's exponent, radius rule and curvature percentiles (r_min_mm still sets
        the topology radius, r_max_mm caps the radii). The panel greys them out."""
        if value("max_distance_mm") is not None:
            return frozenset({"p", "radius", "curvature_percentiles"})
        return frozenset()

    def consistency(self) -> str:
        if self.r_min_mm > self.r_max_mm:
            return f"r_min_mm ({self.r_min_mm:g}) must not exceed r_max_mm ({self.r_max_mm:g})"
        lo, hi = self.curvature_percentiles
        if not lo < hi:
            return f"curvature_percentiles must be increasing (lo < hi), got {list(self.curvature_percentiles)}"
        return ""

    @property
    def closing_radius_mm(self) -> float:
        """The closing radius of the topology cleaning in mm."""
        return self.r_min_mm if self.topology_radius_mm is None else float(self.topology_radius_mm)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["curvature_percentiles"] = [float(x) for x in self.curvature_percentiles]
        return d


KERNELS = ("biharmonic", "thin-plate", "hardy")
REST_LENGTHS = ("projected", "warped", "template-scaled")


@dataclass(frozen=True)
class CoatingParams:
    """Parameters of the coating (paper 4); the project's ``[coating]`` table.

    Lengths in mm, time in steps of ``dt``. The relaxation integrates m a + g v = F of
    eq. (3) by semi-implicit Euler.
    """

    kernel: str = param("biharmonic", choices=KERNELS, label="Kernel",
                        help="radial basis U(r) of the landmark warp, eq. (2): 'biharmonic' r (3D), "
                             "'thin-plate' r² ln r, 'hardy' (r² + s²)^a")
    hardy_a: float = param(0.5, minimum=0.0, exclusive_minimum=True, maximum=5.0, label="Hardy a", advanced=True,
                           help="exponent a of the Hardy kernel")
    hardy_s_mm: float | None = param(None, kind="float", unit="mm", minimum=0.0, exclusive_minimum=True,
                                     maximum=10000.0, none_means="median landmark distance", label="Hardy s",
                                     advanced=True, help="stiffness radius s of the Hardy kernel")
    regularization: float = param(0.0, minimum=0.0, maximum=1e9, label="Warp smoothing",
                                  help="λ added to the warp's kernel matrix (0: exact at the landmarks)")
    projection_iterations: int = param(3, minimum=0, maximum=100, label="Projection steps", advanced=True,
                                       help="Newton-like projection steps on the distance map")
    k1: float = param(0.2, minimum=0.0, maximum=100.0, label="k1 (edges)",
                      help="spring constant of the triangle edges, eq. (3)")
    k2: float = param(1.0, minimum=0.0, exclusive_minimum=True, maximum=100.0, label="k2 (surface)",
                      help="zero-length spring pulling each vertex onto the surface, eq. (3); must exceed k1")
    mass: float = param(1.0, minimum=0.0, exclusive_minimum=True, maximum=1e6, label="Mass", advanced=True,
                        help="vertex mass m")
    damping: float = param(1.0, minimum=0.0, maximum=1e6, label="Damping", advanced=True,
                           help="damping coefficient g of m a + g v = F")
    dt: float = param(0.4, minimum=0.0, exclusive_minimum=True, maximum=2.0, label="Step", advanced=True,
                      help="integration time step")
    velocity_tol_mm: float = param(0.005, unit="mm", minimum=0.0, maximum=100.0, label="Velocity tolerance",
                                   advanced=True, help="the relaxation stops when the largest speed is below this")
    max_iterations: int = param(2000, minimum=0, maximum=100000, label="Max iterations",
                                help="most relaxation steps in all, a safety limit: it stops earlier, converged, "
                                     "when the largest speed falls below the velocity tolerance")
    fold_iterations: int = param(100, minimum=0, maximum=100000, label="Fold steps", advanced=True,
                                 help="first steps with the paper's fold handling (vertices of folded triangles lose "
                                      "the surface force); then every vertex is held to the surface and the mesh "
                                      "settles. The umbrella force spreads about one edge ring per few steps, so a "
                                      "denser template needs more of them to unfold the same patch")
    springs: str = param("tension", choices=("tension", "linear"), label="Springs",
                         help="'linear': eq. (3) as printed; 'tension': an edge spring pulls when stretched and never "
                              "pushes, so a compressed mesh cannot buckle into folds when it settles")
    fold_angle_deg: float = param(90.0, unit="deg", minimum=0.0, exclusive_minimum=True, maximum=180.0,
                                  label="Fold angle", advanced=True,
                                  help="a triangle is folded when its normal and the surface normal differ by more")
    rest_lengths: str = param("projected", choices=REST_LENGTHS, label="Rest lengths",
                              help="spring rest lengths: of the registered template projected onto the surface "
                                   "('projected': the springs keep the registration's spacing and act where the "
                                   "fold handling moved vertices), of the registered template before projection "
                                   "scaled to the surface's area ('warped'), or the template's own scaled to the "
                                   "instance's size ('template-scaled', the paper's d0)")
    tangential_springs: bool = param(False, label="Tangential springs", advanced=True,
                                     help="apply only the tangential part of the edge forces")
    k3: float = param(0.0, minimum=0.0, maximum=100.0, label="k3 (smoothing)", advanced=True,
                      help="umbrella (Laplacian) smoothing force of the relaxation")
    registration_sigmas_mm: tuple = param((16.0, 8.0, 4.0, 2.0), unit="mm", minimum=0.0, exclusive_minimum=True,
                                          maximum=1000.0, label="Registration widths",
                                          help="Gaussian widths of the coarse-to-fine surface registration between "
                                               "warp and projection (empty: the paper's scheme)")
    carry_sigmas_mm: tuple = param((48.0,), unit="mm", minimum=0.0, exclusive_minimum=True, maximum=1000.0,
                                   label="Carry widths",
                                   help="Gaussian widths of a smooth registration that carries a start without "
                                        "landmarks onto the instance before the registration, its pulls along "
                                        "the surface too, so a part longer or wider than the template's is met "
                                        "by the template's same part (empty: off)")
    registration_iterations: int = param(5, minimum=0, maximum=1000, label="Registration steps", advanced=True,
                                         help="iterations per registration width")
    reach_mm: float = param(2.5, unit="mm", minimum=0.0, maximum=100.0, label="Reach", advanced=True,
                            help="after the registration, parts of the surface at least a voxel thick (a process "
                                 "longer than the template's) farther than this from the mesh pull their nearest "
                                 "points in full until reached (0: off)")
    final_projection: bool = param(True, label="Final projection", advanced=True,
                                   help="project every vertex onto the surface after the relaxation")
    fold_free_warp: bool = param(True, label="Fold-free warp",
                                 help="smooth the warp just enough that inconsistent landmarks do not fold "
                                      "the template")
    fold_smoothing: float = param(1.0, minimum=0.0, maximum=100.0, label="Fold smoothing", advanced=True,
                                  help="Laplacian force on vertices of folded triangles (their surface force is off)")
    fold_normal_sigma_mm: float = param(3.0, unit="mm", minimum=0.0, maximum=100.0, label="Fold normal width",
                                        advanced=True,
                                        help="smoothing of the surface normal the fold test compares with; a "
                                             "triangle is folded when it turns from this and from the raw "
                                             "normal (0: the raw gradient alone)")
    fold_check_interval: int = param(5, minimum=1, maximum=10000, label="Fold check interval", advanced=True,
                                     help="the relaxation re-detects folds every this many steps")
    untangle_iterations: int = param(60, minimum=0, maximum=100000, label="Untangle rounds", advanced=True,
                                     help="rounds of local unfolding after the relaxation (0: off)")
    untangle_rings: int = param(1, minimum=0, maximum=100, label="Untangle rings", advanced=True,
                                help="neighbour rings around folded triangles that the unfolding moves")
    frame_start_fold_fraction: float = param(0.05, minimum=0.0, maximum=1.01, label="Frame start threshold",
                                             advanced=True,
                                             help="fraction of folded triangles after the coarse registration "
                                                  "above which the object-frame start is tried too (> 1: never)")

    _where = "coating parameters:"

    def __post_init__(self):
        check(self, self._where)

    def consistency(self) -> str:
        if not self.k2 > self.k1:
            return f"k2 ({self.k2:g}) must exceed k1 ({self.k1:g}) so that vertices settle on the surface (paper 4.2)"
        limit = self.stable_dt()
        if self.dt >= limit:
            return (f"dt ({self.dt:g}) is beyond the relaxation's stability bound: with k1 = {self.k1:g}, k2 = "
                    f"{self.k2:g}, k3 = {self.k3:g}, fold_smoothing = {self.fold_smoothing:g}, mass = {self.mass:g} and "
                    f"damping = {self.damping:g} the integrator needs dt < {limit:.3g}")
        return ""

    def stable_dt(self) -> float:
        """The largest stable time step of the relaxation's semi-implicit Euler integrator.

        The stiffest mode of a vertex is bounded by k2 + k3 + fold_smoothing + 2·k1·d with
        d = 10 neighbours (the graph Laplacian's largest eigenvalue is at most twice the
        degree); the update of m x'' + g x' + k x = 0 is stable while the spectral radius
        of its 2 × 2 step matrix is below 1.
        """
        k = self.k2 + self.k3 + self.fold_smoothing + 2.0 * self.k1 * 10.0
        m, g = self.mass, self.damping

        def radius(dt):
            a = np.array([[1 - dt * dt * k / m, dt * (1 - dt * g / m)], [-dt * k / m, 1 - dt * g / m]])
            return float(np.abs(np.linalg.eigvals(a)).max())

        lo, hi = 0.0, 1.0
        while radius(hi) < 1.0 - 1e-12 and hi < 1e6:
            lo, hi = hi, hi * 2.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if radius(mid) < 1.0 - 1e-12 else (lo, mid)
        return lo

    def validate(self) -> None:
        """Raise InputError for values that cannot work (checked on construction too)."""
        check(self, self._where)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["registration_sigmas_mm"] = list(self.registration_sigmas_mm)
        d["carry_sigmas_mm"] = list(self.carry_sigmas_mm)
        return d




@dataclass(frozen=True)
class ModelParams:
    """Parameters of the model and its metrics (paper 5); the project's ``[model]`` table."""

    alignment: str = param("rigid", choices=ALIGNMENTS, label="Alignment",
                           help="'rigid': generalized Procrustes of the coatings, so object frames that disagree "
                                "(a flip, a turn, another scanner's pose) never enter the model as shape; "
                                "'similarity': also scale; 'none': the object frames only, as the paper")
    n_modes: int | None = param(None, kind="int", minimum=1, maximum=100000, none_means="every non-zero mode",
                                label="Modes", help="number of modes kept")
    variance_fraction: float | None = param(None, kind="float", minimum=0.0, exclusive_minimum=True, maximum=1.0,
                                            none_means="no limit", label="Variance kept",
                                            help="keep the fewest leading modes explaining this fraction of the "
                                                 "total variance (with n_modes, the smaller)")
    solver: str = param("auto", choices=("auto", "exact", "randomized"), label="Solver", advanced=True,
                        help="'exact': Gram eigenproblem (eq. 6); 'randomized': randomized SVD for the leading modes "
                             "(needs n_modes or variance_fraction); 'auto': randomized for large studies with a mode "
                             "limit")
    precision: str = param("float64", choices=("float64", "float32"), label="Precision", advanced=True,
                           help="'float32' halves the memory of the instance points for very large studies")
    specificity_samples: int = param(500, minimum=1, maximum=1_000_000, label="Specificity samples", advanced=True,
                                     help="random shapes drawn for the specificity metric")
    max_loo: int = param(100, minimum=1, maximum=1_000_000, label="Max leave-one-out", advanced=True,
                         help="leave-one-out generalization up to this many instances, 10-fold beyond")
    seed: int = param(0, minimum=0, maximum=2**32 - 1, label="Seed", advanced=True,
                      help="seed of the specificity samples")

    _where = "model parameters:"

    def __post_init__(self):
        check(self, self._where)


@dataclass(frozen=True)
class OutputParams:
    """What a build writes besides ``model.npz`` and ``report.json``; the ``[output]`` table."""

    coated_meshes: bool = param(True, label="Coated meshes", help="write coated/<name>.ply per instance")
    landmarks: bool = param(True, label="Carried landmarks",
                            help="write landmarks/<name>.<ext> per instance: the template instance's landmarks "
                                 "where the coating carried them (for review and correction)")
    statismo: bool = param(True, label="Statismo file", help="write model.h5 (statismo 0.9 layout)")
    scores: bool = param(True, label="Score tables",
                         help="write scores.csv (each instance's mode weights in SD and mm) and eigenvalues.csv")
    gltf: bool = param(True, label="glTF",
                       help="write model.glb: the mean with one morph target per mode, in metres (glTF's unit)")
    vtk: bool = param(True, label="VTK meshes",
                      help="write vtk/mean.vtp (and .vtk) with the per-point variance, and the mean ±2 SD along "
                           "each of the first modes (for ParaView, 3D Slicer, ShapeWorks)")
    exchange_modes: int = param(5, minimum=1, maximum=100, label="Exchange modes", advanced=True,
                                help="modes written as glTF morph targets and VTK ±2 SD meshes")
    blend: bool = param(True, label="Blender file", help="write model.blend when bpy is available")
    picture: bool = param(True, label="Mode picture", help="write modes.png (paper fig. 10) when bpy is available")
    picture_modes: int = param(2, minimum=1, maximum=10, label="Picture modes",
                               help="modes shown in modes.png")

    _where = "output parameters:"

    def __post_init__(self):
        check(self, self._where)


POSE_STEPS = ("joint", "alternating")


@dataclass(frozen=True)
class FitParams:
    """Fitting a model to new data (``ssm fit``, and the model-driven coating).

    The fit minimises Σ w |T(p̄ + Q b) − y|²/σ² + η Σ b_k²/λ_k over the pose T and the
    mode weights b (paper eq. 7 with the model's Gaussian prior).
    """

    noise_mm: float = param(1.0, unit="mm", minimum=0.0, exclusive_minimum=True, maximum=1000.0,
                            label="Noise", help="standard deviation of the target's points around the shape: "
                                                "larger trusts the prior more")
    prior_weight: float = param(1.0, minimum=0.0, maximum=1e9, label="Prior weight",
                                help="weight η of the model's Gaussian prior (1: as the model says; 0: none)")
    n_modes: int | None = param(None, kind="int", minimum=1, maximum=100000, none_means="every mode of the model",
                                label="Modes", help="modes used by the fit")
    scale: bool = param(False, label="Scale", help="fit a similarity pose (with scale), not only a rigid one")
    iterations: int = param(60, minimum=1, maximum=10000, label="Iterations", advanced=True,
                            help="most correspondence and solve steps")
    tolerance_mm: float = param(0.001, unit="mm", minimum=0.0, maximum=100.0, label="Tolerance", advanced=True,
                                help="stop when the shape's points move less than this (RMS); a partial target "
                                     "without landmarks also stops when its distance stops falling")
    landmark_weight: float = param(10.0, minimum=0.0, maximum=1e9, label="Landmark weight",
                                   help="weight of one landmark against one surface correspondence")
    pose_step: str = param("joint", choices=POSE_STEPS, label="Pose step", advanced=True,
                           help="joint: pose and mode weights in one point-to-plane step (a pose that must slide "
                                "along a smooth surface gets there); alternating: a point-to-point pose, then the "
                                "weights (stays nearer the start pose)")
    pose_freedom: bool = param(True, label="Pose freedom", advanced=True,
                               help="a partial target: the fit is turned about the given part's long axis and "
                                    "fitted again; the turns and the search's other starts that fit nearly as well "
                                    "are the pose's uncertainty, said and added to the posterior SD")
    model_error: bool = param(True, label="Model error", advanced=True,
                              help="the posterior SD includes the model's own error (its training instances' "
                                   "leave-one-out residuals), not only the target's noise: for a partial target "
                                   "as a smooth Gaussian process fitted with the modes, otherwise added per point")

    _where = "fit parameters:"

    def __post_init__(self):
        check(self, self._where)


EVIDENCES = ("auto", "learned", "gradient")
SEARCH_LEVELS = 3
"""The segmentation's resolutions, coarse to fine (``segmentation.appearance.LEVEL_SIGMAS_MM``)."""


@dataclass(frozen=True)
class SegmentParams:
    """Segmenting an image with a model (``ssm segment``): the active shape model search.

    Each level (coarse to fine, the image blurred by 2, 1 and 0.5 mm) looks for the boundary along the
    shape's normals and fits the pose and the mode weights to what it found (Cootes et al. 1995).
    """

    search_mm: tuple = param((12.0, 6.0, 3.0), size=SEARCH_LEVELS, unit="mm", minimum=0.0, exclusive_minimum=True,
                             maximum=1000.0, label="Search", advanced=True,
                             help="how far each level looks along the normals, both ways (coarse to fine)")
    search_step_mm: float = param(0.5, unit="mm", minimum=0.0, exclusive_minimum=True, maximum=100.0,
                                  label="Search step", advanced=True, help="candidate spacing along the normal")
    iterations: int = param(12, minimum=1, maximum=10000, label="Steps", advanced=True,
                            help="most search-and-fit steps per level")
    tolerance_mm: float = param(0.1, unit="mm", minimum=0.0, maximum=100.0, label="Tolerance", advanced=True,
                                help="a level ends when the points move less than this (RMS)")
    noise_mm: float = param(1.0, unit="mm", minimum=0.0, exclusive_minimum=True, maximum=1000.0, label="Noise",
                            help="standard deviation of a found boundary point around the shape: larger trusts "
                                 "the model more")
    prior_weight: float = param(1.0, minimum=0.0, maximum=1e9, label="Prior weight",
                                help="weight η of the model's Gaussian prior (1: as the model says)")
    n_modes: int | None = param(None, kind="int", minimum=1, maximum=100000, none_means="every mode of the model",
                                label="Modes", help="modes used by the search")
    turns_deg: float = param(15.0, unit="deg", minimum=0.0, maximum=180.0, label="Turns", advanced=True,
                             help="the coarse level also starts from the typical pose turned by ± this about each "
                                  "axis")
    placement_mm: float = param(8.0, unit="mm", minimum=0.0, maximum=200.0, label="Placement", advanced=True,
                                help="the mean shape is first placed on a grid within ± this of the start (4 mm "
                                     "steps); the best places start the pose search")
    deviation: bool = param(True, label="Deviation",
                            help="let the surface leave the model's span as far as the model's error and the "
                                 "evidence allow")
    evidence: str = param("auto", choices=EVIDENCES, label="Evidence",
                          help="the boundary evidence: the model's learned appearance when it has one and it "
                               "applies to the image (auto), the learned appearance, or the image's gradient")

    _where = "segment parameters:"

    def __post_init__(self):
        check(self, self._where)


CORRESPONDENCE_METHODS = ("landmarks", "model")
TEMPLATE_CHOICES = ("medoid", "landmark-medoid", "given")
SIDES = ("detect", "given")
ROUND_TEMPLATES = ("instance", "mean")


@dataclass(frozen=True)
class CorrespondenceParams:
    """How correspondence is found; the project's ``[correspondence]`` table.

    ``"landmarks"`` is the paper's single pass: the template coated onto every instance
    by its landmarks. ``"model"`` continues with the mean shape as template (paper 3.3)
    and refines every instance with a model built without it, fitted to its surface
    (paper 7's bootstrap); instances without landmarks start from the model of the
    landmarked ones (from the object frames when only the template instance has them),
    and the given landmarks move towards the population's prediction by the share their
    click error calls for. A round is kept only when it lowers the landmark transfer error
    (the self-check).
    """

    method: str = param("landmarks", choices=CORRESPONDENCE_METHODS, label="Method",
                        help="'landmarks': the paper's single pass; 'model': mean-shape template and "
                             "model-driven refinement, landmarks optional but on the template instance")
    iterations: int = param(3, minimum=1, maximum=100, label="Rounds",
                            help="most refinement rounds of the 'model' method")
    sides: str = param("detect", choices=SIDES, label="Sides",
                       help="'detect': an instance without a given side that is a mirror image of the template's "
                            "(a right bone among left ones; found by its landmarks, else its surface) is mirrored into "
                            "the template's side before it is coated; 'given': only instances whose side is given and "
                            "differs from the template instance's are mirrored")
    tolerance_mm: float = param(0.1, unit="mm", minimum=0.0, maximum=100.0, label="Stop below",
                                help="stop the refinement when the mean shape moves less than this (RMS; a "
                                     "tenth of the default 1 mm voxel)")
    template_choice: str = param("medoid", choices=TEMPLATE_CHOICES, label="Template from",
                                 help="'medoid': the template is built from the landmarked instance nearest the "
                                      "population's mean shape (paper 3.3: the model should not depend on the "
                                      "template's instance): the instance whose landmarks are nearest their mean, "
                                      "kept when its coatings confirm it, else the medoid of the given template's "
                                      "coatings, kept when the self-check improves; 'landmark-medoid': "
                                      "from the instance whose landmarks are nearest their mean, not confirmed: "
                                      "no pass from the given template when the coatings disagree; without "
                                      "landmarks on any instance, 'medoid' builds it from the instance whose first "
                                      "coating is nearest the mean shape and coats every instance again from it; "
                                      "'given': the [template] instance")
    round_template: str = param("instance", choices=ROUND_TEMPLATES, label="Round template",
                                help="what each round coats: 'instance', the template (its instance's points) "
                                     "with the landmarks the fit gives; 'mean', the mean shape (paper 3.3), "
                                     "re-sampled at the template's points")
    landmark_weight: float = param(10.0, minimum=0.0, maximum=1e9, label="Landmark weight",
                                   help="weight of a given landmark in the model fit, against one surface "
                                        "point (0: landmarks ignored)")
    landmark_noise_mm: float | None = param(None, kind="float", unit="mm", minimum=0.0, maximum=100.0,
                                            none_means="estimated from the population", label="Landmark error",
                                            help="how far the given landmarks are from where the anatomy is (SD per "
                                                 "axis): each round moves a given landmark towards the other "
                                                 "instances' prediction of it by the share this calls for; 0: exact "
                                                 "landmarks, kept where given")
    self_check: bool = param(True, label="Self-check",
                             help="measure the landmark transfer error (each instance's given landmarks predicted "
                                  "by the other instances' model) after the coating; the model method always does")
    fit_noise_mm: float = param(1.0, unit="mm", minimum=0.0, exclusive_minimum=True, maximum=1000.0,
                                label="Fit noise", advanced=True,
                                help="noise σ of the model fit to each instance's surface")
    optimise: bool = param(False, label="Optimise",
                           help="after the coating, slide each instance's points along its own surface to lower "
                                "the population's objective (entropy of the shapes, springs, landmarks held); off by "
                                "default: on real bones with known correspondence it brought points nearer their "
                                "true places by under 1 % (docs/history.md)")
    optimise_iterations: int = param(10, minimum=1, maximum=1000, label="Optimisation iterations",
                                     help="most iterations of the correspondence optimisation")
    population_weight: float = param(0.0, minimum=0.0, maximum=1000.0, label="Population weight",
                                     help="weight of the population term (the shapes' entropy) against one spring "
                                          "of the regularity; 0: springs and landmarks only")
    min_variance: float = param(0.001, minimum=0.0, exclusive_minimum=True, maximum=1.0,
                                label="Negligible variance", advanced=True,
                                help="share of the total variance below which a mode counts as noise that the "
                                     "population term removes (its floor α)")
    landmark_hold: float = param(1.0, minimum=0.0, maximum=1000.0, label="Landmark hold",
                                 help="weight of a given landmark's pull to its place against one spring during "
                                      "the optimisation (0: landmarks slide with the rest)")
    optimise_tolerance_mm: float = param(0.01, unit="mm", minimum=0.0, maximum=100.0, label="Optimisation stop",
                                         advanced=True,
                                         help="stop the optimisation when an iteration moves the points less than "
                                              "this (RMS)")

    _where = "correspondence parameters:"

    def __post_init__(self):
        check(self, self._where)


@dataclass(frozen=True)
class QualityParams:
    """Thresholds of the quality gates (``ssm_addon.model.quality``); the project's ``[quality]`` table.

    An instance that fails a gate is named with the reason: last in the command's
    output (WARNINGS), in ``report.json`` and ``report.html``, and in the Blender panel.
    """

    strict: bool = param(False, label="Strict",
                         help="fail the build (non-zero exit, the output folder untouched) when any gate fails")
    min_voxels: int = param(64, minimum=1, maximum=10**9, label="Min voxels", advanced=True,
                            help="an instance with fewer voxels at the study's spacing is an error")
    max_second_component: float = param(0.05, minimum=0.0, maximum=1.0, label="Max second part", advanced=True,
                                        help="largest share of the voxels a second connected part may hold")
    max_volume_ratio: float = param(3.0, minimum=1.0, maximum=1000.0, label="Max volume ratio", advanced=True,
                                    help="largest factor between an instance's volume and the study's median")
    max_landmark_distance_mm: float = param(10.0, unit="mm", minimum=0.0, exclusive_minimum=True, maximum=10000.0,
                                            label="Max landmark distance",
                                            help="a landmark farther from its instance's surface is an error")
    max_landmark_residual_mm: float = param(20.0, unit="mm", minimum=0.0, maximum=10000.0,
                                            label="Max landmark residual",
                                            help="largest distance between a coated landmark and the given one")
    max_landmark_transfer_mm: float = param(15.0, unit="mm", minimum=0.0, exclusive_minimum=True, maximum=10000.0,
                                            label="Max landmark transfer",
                                            help="largest distance between a given landmark and its prediction by "
                                                 "the other instances' model (the correspondence self-check)")
    max_folded_triangles: int = param(0, minimum=0, maximum=10**9, label="Max folds",
                                      help="folded triangles allowed on a coated instance")
    max_surface_distance_vox: float = param(1.0, minimum=0.0, maximum=1000.0, label="Max surface distance (voxels)",
                                            help="largest distance of a coated vertex from the surface, in voxels "
                                                 "of the study's spacing")
    max_input_distance_mm: float = param(3.0, unit="mm", minimum=0.0, exclusive_minimum=True, maximum=1000.0,
                                         label="Max input distance",
                                         help="largest distance of an input mesh's vertices from its coating: beyond "
                                              "it, a part of the user's surface (a thin process) is cut off by the "
                                              "template's points (use a denser template or a finer spacing)")
    require_convergence: bool = param(True, label="Require convergence", advanced=True,
                                      help="flag a relaxation that stopped at its iteration limit")
    outlier_probability: float = param(0.99, minimum=0.5, maximum=1.0, exclusive_minimum=True,
                                       label="Outlier quantile", advanced=True,
                                       help="probability of the prediction region (F test of the leave-one-out "
                                            "Mahalanobis distance) outside which an instance is an outlier")
    outlier_variance_fraction: float = param(0.95, minimum=0.0, maximum=1.0, exclusive_minimum=True,
                                             label="Outlier modes (variance)", advanced=True,
                                             help="the outlier score uses the modes that hold this share of the "
                                                  "variance")
    max_loo_error_ratio: float = param(3.0, minimum=1.0, maximum=1000.0, label="Max reconstruction ratio",
                                       advanced=True,
                                       help="largest leave-one-out reconstruction error relative to the median; "
                                            "an instance beyond it is named when a population of this size also "
                                            "holds one so far out rarely (p below 1 - the outlier quantile)")
    max_outlier_instances: int = param(100_000, minimum=3, maximum=10**7, label="Outlier scores up to", advanced=True,
                                       help="leave-one-out outlier scores are computed up to this many instances")

    _where = "quality parameters:"

    def __post_init__(self):
        check(self, self._where)


#: The parameter classes by project table.
@dataclass(frozen=True)
class ComputeParams:
    """Where a build's per-instance work runs and where it keeps its cache; the ``[compute]`` table.

    Not shown in Blender, which keeps local processes. See :mod:`ssm_addon.base.compute` and
    :mod:`ssm_addon.pipeline.cache`.
    """

    scheduler: str = param("processes", kind="str", label="Scheduler", metavar="WHERE",
                           help="'processes' (local, --jobs of them), 'dask-local' (a Dask LocalCluster of --jobs "
                                "workers), 'serial', or a Dask scheduler address such as tcp://host:8786")
    cache: str = param("auto", kind="str", label="Cache", metavar="PATH",
                       help="per-instance cache folder for resuming: 'auto' (DIR.cache beside the output folder), "
                            "'off', or a folder (relative to the project file)")
    connect_timeout_s: float = param(10.0, unit="s", minimum=0.5, maximum=600.0, label="Connect timeout",
                                     advanced=True,
                                     help="how long a Dask scheduler address may take to answer its handshake "
                                          "before the build stops with an error")

    _where = "compute parameters:"

    def __post_init__(self):
        check(self, self._where)
        check_scheduler(self.scheduler, f"{self._where} scheduler")
        if not str(self.cache).strip():
            raise InputError(f"{self._where} cache: empty; use 'auto', 'off' or a folder")


@dataclass(frozen=True)
class JointParams:
    """A model of several structures per subject (a joint, a spine): the ``[joint]`` table.

    Used only by projects whose instances hold several structures (``meshes = { … }`` or
    ``labels = { … }``); see :mod:`ssm_addon.pipeline.joint`.
    """

    reference: str = param("", kind="str", label="Reference structure", metavar="NAME",
                           help="the structure whose object frame holds the joint model (with [model] alignment = "
                                "\"none\") and against which the others' relative pose is measured; empty: the first")
    align_on: str = param("all", choices=("all", "reference"), label="Align on",
                          help="[model] alignment of each subject computed on all structures together, or on the "
                               "reference structure alone (the others follow it)")
    collision_samples: int = param(200, minimum=0, maximum=100000, label="Collision samples", advanced=True,
                                   help="random shapes of the model (besides ±3 SD along each mode) in which the "
                                        "structures are checked for overlap")
    penetration_mm: float = param(0.5, unit="mm", minimum=0.0, exclusive_minimum=True, maximum=100.0,
                                  label="Penetration", advanced=True,
                                  help="a structure reaching this far into another counts as a collision")
    max_collision_excess: float = param(0.2, minimum=0.0, maximum=1.0, label="Max collision excess",
                                        help="a pair of structures colliding in this share more of the model's "
                                             "samples than of the training subjects is a finding")


@dataclass(frozen=True)
class AnalysisParams:
    """Shape analysis of the built model by groups and covariates; the ``[analysis]`` table.

    Runs after the model when ``group`` or ``covariates`` is given (``ssm analyze`` runs it on a
    built model). See :mod:`ssm_addon.analysis`.
    """

    attributes: str = param("", kind="str", label="Attributes", metavar="FILE",
                            help="CSV of per-instance attributes joined by instance name (relative to the project "
                                 "file); fills what the instances' own 'attributes' tables leave out")
    group: str = param("", kind="str", label="Group", metavar="COLUMN", help="attribute column whose groups are compared ('' none)")
    covariates: tuple = param((), kind="strs", label="Covariates",
                              help="attribute columns modelled with the group (numbers; 'centroid_size' in mm is "
                                   "always available)")
    reference: str = param("", kind="str", label="Reference group", metavar="GROUP",
                           help="the group the others are compared to ('' the first in sorted order)")
    permutations: int = param(1000, minimum=99, maximum=1_000_000, label="Permutations",
                              help="random permutations of every test (p-values resolve 1/(permutations+1))")
    seed: int = param(0, minimum=0, maximum=2**31 - 1, label="Seed", advanced=True,
                      help="seed of the permutations (the same seed gives the same p-values)")
    size_removed: bool = param(False, label="Remove size",
                               help="scale every shape to the mean centroid size before the analysis")
    lda_modes: int = param(10, minimum=1, maximum=1000, label="Discriminant modes", advanced=True,
                           help="leading modes the linear discriminant of the groups uses")

    _where = "analysis parameters:"

    def __post_init__(self):
        check(self, self._where)

    @property
    def requested(self) -> bool:
        """True when the table asks for an analysis (a group or covariates)."""
        return bool(self.group or self.covariates)


@dataclass(frozen=True)
class StudyParams:
    """Every stage's parameters of a study: one field per project-file table.

    The one bundle the study (:class:`ssm_addon.pipeline.study.Study`), the project file
    (:class:`ssm_addon.pipeline.project.Project`) and the Blender scene (one property
    group per field, ``Scene.ssm_<table>``) hold, so a new table is added here once.

    Examples
    --------
    >>> p = StudyParams().replace(coating=CoatingParams(k1=0.3))
    >>> p.coating.k1, p.template.spacing_mm
    (0.3, 1.0)
    >>> [section for section, _ in StudyParams().tables()][:3]
    ['template', 'coating', 'correspondence']
    """

    template: TemplateParams = field(default_factory=TemplateParams)
    coating: CoatingParams = field(default_factory=CoatingParams)
    correspondence: CorrespondenceParams = field(default_factory=CorrespondenceParams)
    model: ModelParams = field(default_factory=ModelParams)
    output: OutputParams = field(default_factory=OutputParams)
    quality: QualityParams = field(default_factory=QualityParams)
    compute: ComputeParams = field(default_factory=ComputeParams)
    analysis: AnalysisParams = field(default_factory=AnalysisParams)
    joint: JointParams = field(default_factory=JointParams)

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if type(value) is not SECTIONS[f.name]:
                raise InputError(f"study parameters: [{f.name}] must be {SECTIONS[f.name].__name__}, got "
                                 f"{type(value).__name__}")

    def tables(self) -> tuple[tuple[str, Any], ...]:
        """``((table name, parameter object), ...)`` in project-file order."""
        return tuple((f.name, getattr(self, f.name)) for f in dataclasses.fields(self))

    def to_tables(self) -> dict[str, dict[str, Any]]:
        """``{table name: {project key: value}}`` of every table (JSON- and TOML-ready)."""
        return {section: to_table(params) for section, params in self.tables()}

    @classmethod
    def from_tables(cls, tables: Mapping, *, where: str = "") -> StudyParams:
        """The bundle of ``{table name: {project key: value}}`` (absent tables take defaults), validated."""
        unknown = sorted(set(tables) - set(SECTIONS))
        if unknown:
            raise InputError(f"{where} unknown table(s) {', '.join(unknown)}".strip())
        return cls(**{section: from_table(SECTIONS[section], table, where=f"{where} [{section}]".strip())
                      for section, table in tables.items()})

    def replace(self, **tables) -> StudyParams:
        """A copy with the given tables replaced (``replace(coating=CoatingParams(k1=0.3))``)."""
        unknown = sorted(set(tables) - set(SECTIONS))
        if unknown:
            raise InputError(f"study parameters: unknown table(s) {', '.join(unknown)} (tables: "
                             f"{', '.join(SECTIONS)})")
        return dataclasses.replace(self, **tables)


#: Table name -> parameter class of every table of a study (the fields of :class:`StudyParams`).
SECTIONS = {"template": TemplateParams, "coating": CoatingParams, "correspondence": CorrespondenceParams,
            "model": ModelParams, "output": OutputParams, "quality": QualityParams,
            "compute": ComputeParams, "analysis": AnalysisParams, "joint": JointParams}
#: The tables ``ssm build`` takes as ``--<table>-<key>`` options (the analysis runs with ``ssm analyze``).
TABLES = {k: v for k, v in SECTIONS.items() if k != "analysis"}


def markdown_tables() -> str:
    """The parameter reference (``docs/parameters.md``), generated from the definitions."""
    out = ["# Parameters", "",
           "Generated from `ssm_addon/base/params.py` (`python -m ssm_addon params`); the same names are the",
           "project file's keys, the `ssm build --<table>-<key>` options and the SSM sidebar's fields.", ""]
    tables = [(f"[{section}]", cls, "key") for section, cls in SECTIONS.items()]
    tables.append(("`ssm fit` options (and Blender's Fit Model)", FitParams, "option"))
    tables.append(("`ssm segment` options (and Blender's Segment with Model)", SegmentParams, "option"))
    for title, cls, column in tables:
        out += [f"## {title}", "", (cls.__doc__ or "").strip().splitlines()[0], "",
                f"| {column} | default | allowed | meaning |", "|---|---|---|---|"]
        if cls is TemplateParams:
            out.append("| `instance` | first instance | an instance name | the instance the template is built from |")
        for s in specs(cls):
            unit = f" {s.unit}" if s.unit and s.unit != "deg" else ("°" if s.unit == "deg" else "")
            if s.default is None:
                default = f"auto ({s.none_means})"
            elif s.off:
                default = f"`{s.default!r}`{unit}; `\"{s.off}\"`: {s.none_means.removeprefix(s.off + ': ')}"
            else:
                value = list(s.default) if isinstance(s.default, tuple) else s.default
                default = f"`{value!r}`".replace("'", '"') + unit
            allowed = s.range_text().replace("|", "\\|")
            adv = " *(advanced)*" if s.advanced else ""
            name = s.key if column == "key" else _flag("", s)
            out.append(f"| `{name}` | {default} | {allowed} | {s.help}{adv} |")
        out.append("")
    return "\n".join(out)
