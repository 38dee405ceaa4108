"""Landmark sets, their file formats and matching by name (paper 4.1).

The coating of paper section 4 is guided by a small set of corresponding landmarks
(the paper used 15 per vertebra): pairs (P_i^s, P_i^d) on the template and on each
instance, from which the landmark warp of eq. (2) is computed. This module reads and
writes such sets and puts them into one common order (the *schema*); proposing a set
for a new instance is :mod:`ssm_addon.correspondence.proposal`.

Frames and units
----------------
* ``LandmarkSet.points_world`` are *world* mm, RAS (the frame of the instance's input
  file, as in :mod:`ssm_addon.instances.volume`);
* 3D Slicer files may be stored in LPS (``CoordinateSystem = LPS`` / ``"coordinateSystem":
  "LPS"``): x and y are negated on read and on write;

File formats (chosen by extension)
----------------------------------
``.fcsv``      3D Slicer markups fiducial CSV (versions 4.x): ``#`` header lines with
               ``CoordinateSystem = LPS|RAS|0|1`` (0 = RAS, 1 = LPS) and ``columns = ...``;
               the ``label`` column gives the name.
``.mrk.json``  3D Slicer markups JSON: ``markups[0].coordinateSystem`` and
               ``markups[0].controlPoints[].label/position``.
``.csv``       ``name,x,y,z`` in world mm (RAS), optional header line.
``.json``      Scalismo-style ``[{"id": name, "coordinates": [x, y, z]}, ...]`` in world mm
               (a ``.json`` holding a Slicer markups document is read as one).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..base.errors import InputError
from .registry import extensions, format_of, registered_extension

__all__ = [
    "LANDMARK_PRESETS",
    "LandmarkSet",
    "landmark_format",
    "match_landmarks",
    "order_by_schema",
    "read_landmarks",
    "write_landmarks",
]

# The 14 extremal-direction names of ../shared/data/verse004/landmarks: the six patient
# axes and the eight diagonals, in the order of those files.
_EXTREMAL_14 = (
    "right",
    "left",
    "anterior",
    "posterior",
    "superior",
    "inferior",
    "right-anterior-superior",
    "right-anterior-inferior",
    "right-posterior-superior",
    "right-posterior-inferior",
    "left-anterior-superior",
    "left-anterior-inferior",
    "left-posterior-superior",
    "left-posterior-inferior",
)

# An anatomical set of 15 for a lumbar vertebra (the paper used 15 landmarks).
_LUMBAR_15 = (
    "spinous-process-tip",
    "transverse-process-right-tip",
    "transverse-process-left-tip",
    "superior-articular-process-right",
    "superior-articular-process-left",
    "inferior-articular-process-right",
    "inferior-articular-process-left",
    "pedicle-right",
    "pedicle-left",
    "body-anterior-superior",
    "body-anterior-inferior",
    "body-posterior-superior",
    "body-posterior-inferior",
    "body-right-mid",
    "body-left-mid",
)

LANDMARK_PRESETS: dict[str, tuple[str, ...]] = {
    "extremal-14": _EXTREMAL_14,
    "lumbar-vertebra": _LUMBAR_15,
}
"""Named landmark schemas: preset name -> ordered landmark names."""

_SLICER_DEFAULT_COLUMNS = ("id", "x", "y", "z", "ow", "ox", "oy", "oz", "vis", "sel", "lock", "label", "desc", "associatedNodeID")
_LPS_FLIP = np.array([-1.0, -1.0, 1.0])


@dataclass(frozen=True, eq=False)
class LandmarkSet:
    """Named landmarks of one instance.

    Attributes
    ----------
    names : tuple of str
        Landmark names, unique, in the set's order.
    points_world : (L, 3) float ndarray
        Positions in world mm (RAS), row i belongs to ``names[i]``.
    source : str
        The file (or Blender object) the set came from, for messages.
    coordinates : str
        How the file's coordinates were taken ("LPS, stated in the file", "RAS, none
        stated", ...); empty for sets not read from a file.
    """

    names: tuple[str, ...]
    points_world: np.ndarray
    source: str = ""
    coordinates: str = ""

    def __post_init__(self):
        names = tuple(str(n) for n in self.names)
        pts = np.asarray(self.points_world, dtype=float).reshape(-1, 3) if np.size(self.points_world) else np.zeros((0, 3))
        where = self.source or "landmark set"
        if len(names) != len(pts):
            raise InputError(f"{where}: {len(names)} names but {len(pts)} points")
        dup = _duplicates(names)
        if dup:
            raise InputError(f"{where}: duplicate landmark name(s) {', '.join(repr(d) for d in dup)}")
        if not np.all(np.isfinite(pts)):
            bad = [names[i] for i in np.flatnonzero(~np.all(np.isfinite(pts), axis=1))]
            raise InputError(f"{where}: non-finite coordinates for {', '.join(repr(b) for b in bad)}")
        pts.setflags(write=False)
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "points_world", pts)

    def __len__(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        """Row of landmark ``name`` (InputError if absent)."""
        try:
            return self.names.index(name)
        except ValueError:
            raise InputError(f"{self.source or 'landmark set'}: no landmark named {name!r}") from None

    def point(self, name: str) -> np.ndarray:
        """(3,) world mm position of landmark ``name``."""
        return self.points_world[self.index(name)]

    def as_dict(self) -> dict[str, np.ndarray]:
        """``{name: (3,) world mm}``."""
        return {n: self.points_world[i] for i, n in enumerate(self.names)}

    def subset(self, names) -> LandmarkSet:
        """The landmarks ``names`` (all must be present), in that order."""
        idx = [self.index(n) for n in names]
        return LandmarkSet(tuple(names), self.points_world[idx], self.source, self.coordinates)


def _duplicates(names) -> list[str]:
    seen, dup = set(), []
    for n in names:
        if n in seen and n not in dup:
            dup.append(n)
        seen.add(n)
    return dup


# --------------------------------------------------------------------------------------
# formats
_EXTENSIONS_TEXT = ", ".join(extensions("landmarks")[:-1]) + " or " + extensions("landmarks")[-1]


def landmark_format(path) -> str:
    """The format of a landmark file from its name: ``fcsv``, ``mrk.json``, ``csv`` or ``json``.

    Raises
    ------
    InputError
        For any other extension.
    """
    fmt = format_of(path, "landmarks")
    if fmt is None:
        raise InputError(f"{os.fspath(path)}: unknown landmark file extension (use {_EXTENSIONS_TEXT})")
    return registered_extension(path)[1:]


def _number(text: str, path, line: int, what: str) -> float:
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise InputError(f"{path}, line {line}: {what} {text!r} is not a number") from None
    if not math.isfinite(value):
        raise InputError(f"{path}, line {line}: {what} {text!r} is not a finite number")
    return value


def _coordinate_system(value, path, where: str) -> str:
    text = str(value).strip().upper()
    mapping = {"LPS": "LPS", "RAS": "RAS", "0": "RAS", "1": "LPS"}
    if text not in mapping:
        raise InputError(f"{path}, {where}: unknown coordinate system {value!r} (expected LPS, RAS, 0 or 1)")
    return mapping[text]


def _read_fcsv(path: Path, text: str) -> LandmarkSet:
    columns = list(_SLICER_DEFAULT_COLUMNS)
    system = "LPS"  # Slicer >= 4.11 default; older files without the line were RAS but wrote "0"
    saw_system = False
    names, points = [], []
    lines = text.splitlines()
    for lineno, raw in enumerate(lines, start=1):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#"):
            body = line.lstrip("#").strip()
            key, sep, value = body.partition("=")
            key = key.strip().lower()
            if sep and key == "coordinatesystem":
                system = _coordinate_system(value, path, f"line {lineno}")
                saw_system = True
            elif sep and key == "columns":
                columns = [c.strip() for c in value.split(",")]
            continue
        fields = next(csv.reader([raw]))
        lower = [c.lower() for c in columns]
        try:
            ix, iy, iz = lower.index("x"), lower.index("y"), lower.index("z")
        except ValueError:
            raise InputError(f"{path}: the columns line has no x, y, z columns ({', '.join(columns)})") from None
        il = lower.index("label") if "label" in lower else None
        iid = lower.index("id") if "id" in lower else None
        if len(fields) <= max(ix, iy, iz):
            raise InputError(f"{path}, line {lineno}: expected at least {max(ix, iy, iz) + 1} fields, found {len(fields)}")
        xyz = [_number(fields[i], path, lineno, c) for i, c in zip((ix, iy, iz), "xyz")]
        name = fields[il].strip() if il is not None and il < len(fields) else ""
        if not name and iid is not None and iid < len(fields):
            name = fields[iid].strip()
        if not name:
            raise InputError(f"{path}, line {lineno}: landmark without a label")
        names.append(name)
        points.append(xyz)
    if not saw_system:
        # Slicer wrote no CoordinateSystem line before 4.11: those files are RAS.
        system = "RAS"
    pts = np.array(points, dtype=float).reshape(-1, 3)
    if system == "LPS":
        pts = pts * _LPS_FLIP
    return _finish(names, pts, path, f"{system}, stated in the file" if saw_system else
                   "RAS, as 3D Slicer before 4.11 wrote files without a CoordinateSystem line")


def _json_load(path: Path, text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise InputError(f"{path}, line {err.lineno}: invalid JSON ({err.msg})") from None


def _read_slicer_json(path: Path, doc) -> LandmarkSet:
    markups = doc.get("markups") if isinstance(doc, dict) else None
    if not isinstance(markups, list) or not markups:
        raise InputError(f"{path}: no 'markups' list in this Slicer markups file")
    node = markups[0]
    system = _coordinate_system(node.get("coordinateSystem", "LPS"), path, "markups[0].coordinateSystem")
    names, points = [], []
    for i, cp in enumerate(node.get("controlPoints") or []):
        where = f"markups[0].controlPoints[{i}]"
        if cp.get("positionStatus", "defined") not in ("defined", "preview"):
            continue  # a point of the list that has not been placed yet
        pos = cp.get("position")
        if not isinstance(pos, list) or len(pos) != 3:
            raise InputError(f"{path}, {where}: 'position' must be a list of 3 numbers, got {pos!r}")
        xyz = []
        for c, v in zip("xyz", pos):
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise InputError(f"{path}, {where}: {c} {v!r} is not a finite number")
            xyz.append(float(v))
        name = str(cp.get("label") or cp.get("id") or "").strip()
        if not name:
            raise InputError(f"{path}, {where}: control point without a label")
        names.append(name)
        points.append(xyz)
    pts = np.array(points, dtype=float).reshape(-1, 3)
    if system == "LPS":
        pts = pts * _LPS_FLIP
    return _finish(names, pts, path, f"{system}, stated in the file")


def _read_scalismo_json(path: Path, doc) -> LandmarkSet:
    if not isinstance(doc, list):
        raise InputError(f"{path}: expected a JSON list of {{'id': ..., 'coordinates': [x, y, z]}} objects")
    names, points = [], []
    for i, item in enumerate(doc):
        where = f"entry {i}"
        if not isinstance(item, dict) or "coordinates" not in item:
            raise InputError(f"{path}, {where}: expected an object with 'id' and 'coordinates'")
        pos = item["coordinates"]
        if not isinstance(pos, list) or len(pos) != 3:
            raise InputError(f"{path}, {where}: 'coordinates' must be a list of 3 numbers, got {pos!r}")
        xyz = []
        for c, v in zip("xyz", pos):
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise InputError(f"{path}, {where}: {c} {v!r} is not a finite number")
            xyz.append(float(v))
        name = str(item.get("id", "")).strip()
        if not name:
            raise InputError(f"{path}, {where}: landmark without an 'id'")
        names.append(name)
        points.append(xyz)
    return _finish(names, np.array(points, dtype=float).reshape(-1, 3), path)


def _read_csv(path: Path, text: str) -> LandmarkSet:
    cols = (0, 1, 2, 3)
    names, points = [], []
    first = True
    for lineno, fields in enumerate(csv.reader(io.StringIO(text)), start=1):
        if not fields or not "".join(fields).strip() or fields[0].lstrip().startswith("#"):
            continue
        fields = [f.strip() for f in fields]
        if first:
            first = False
            lower = [f.lower() for f in fields]
            if {"x", "y", "z"} <= set(lower):  # a header line; find the columns by name
                name_col = next((lower.index(k) for k in ("name", "label", "id") if k in lower), 0)
                cols = (name_col, lower.index("x"), lower.index("y"), lower.index("z"))
                continue
        if len(fields) <= max(cols):
            raise InputError(f"{path}, line {lineno}: expected name,x,y,z, found {len(fields)} field(s)")
        xyz = [_number(fields[i], path, lineno, c) for i, c in zip(cols[1:], "xyz")]
        name = fields[cols[0]]
        if not name:
            raise InputError(f"{path}, line {lineno}: landmark without a name")
        names.append(name)
        points.append(xyz)
    return _finish(names, np.array(points, dtype=float).reshape(-1, 3), path)


def _finish(names, pts, path, coordinates: str = "") -> LandmarkSet:
    if not names:
        raise InputError(f"{path}: the file holds no landmark points")
    return LandmarkSet(tuple(names), pts, str(path), coordinates)


def _unstated(landmarks: LandmarkSet, space: str | None, why: str) -> LandmarkSet:
    """A set read from a file that states no convention, taken in ``space`` (None: RAS)."""
    space = (space or "RAS").upper()
    if space not in ("LPS", "RAS"):
        raise InputError(f"{landmarks.source}: unknown coordinate convention {space!r} (RAS or LPS)")
    pts = landmarks.points_world * _LPS_FLIP if space == "LPS" else landmarks.points_world
    return LandmarkSet(landmarks.names, pts, landmarks.source, f"{space}, none stated ({why})")


def read_landmarks(path, *, space: str | None = None, why: str = "") -> LandmarkSet:
    """Read a landmark file; the format follows the extension.

    Parameters
    ----------
    path : str or Path
        A ``.fcsv`` / ``.mrk.json`` (3D Slicer markups, LPS or RAS as the file says),
        ``.csv`` (``name,x,y,z``, optional header) or ``.json`` (Scalismo-style list)
        file.
    space : {"RAS", "LPS"}, optional
        The convention of a file that states none (CSV, Scalismo JSON: they are in the frame
        of the mesh or image they were clicked on); None takes them as RAS.
    why : str
        Where ``space`` came from, for the set's ``coordinates`` note.

    Returns
    -------
    LandmarkSet
        Names in file order, ``points_world`` (L, 3) in world mm (RAS), ``coordinates``
        saying how the file's coordinates were taken.

    Raises
    ------
    InputError
        Missing file, unknown extension, malformed numbers (with the line number),
        duplicate names, a file with no points; the message names the file.
    """
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a landmark file ({', '.join(extensions('landmarks'))})")
    fmt = landmark_format(path)
    if not path.is_file():
        raise InputError(f"{path}: landmark file not found")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"{path}: cannot read landmark file ({err})") from None
    if fmt == "fcsv":
        return _read_fcsv(path, text)
    if fmt == "csv":
        return _unstated(_read_csv(path, text), space, why or ("given" if space else "taken as RAS"))
    doc = _json_load(path, text)
    if isinstance(doc, dict) and "markups" in doc:
        return _read_slicer_json(path, doc)
    if fmt == "mrk.json":
        raise InputError(f"{path}: no 'markups' list in this Slicer markups file")
    return _unstated(_read_scalismo_json(path, doc), space, why or ("given" if space else "taken as RAS"))


def _fmt(value: float) -> str:
    return repr(float(value))


def write_landmarks(path, landmarks: LandmarkSet, coordinate_system: str | None = None) -> Path:
    """Write a landmark set; the format follows the extension (see :func:`read_landmarks`).

    Parameters
    ----------
    path : str or Path
        Output file (``.fcsv``, ``.mrk.json``, ``.csv`` or ``.json``).
    landmarks : LandmarkSet
        Names and world mm (RAS) positions.
    coordinate_system : {"LPS", "RAS"}, optional
        For the Slicer formats: the coordinate system written into the file (default
        ``"LPS"``, Slicer's own default). CSV and Scalismo JSON are always world RAS.

    Returns
    -------
    Path
        The file written. Coordinates are written with full float precision (round trip
        is exact).
    """
    path = Path(path)
    fmt = landmark_format(path)
    if len(landmarks) == 0:
        raise InputError(f"{path}: refusing to write an empty landmark set")
    slicer = fmt in ("fcsv", "mrk.json")
    system = "LPS" if coordinate_system is None and slicer else (coordinate_system or "RAS").upper()
    if system not in ("LPS", "RAS"):
        raise InputError(f"{path}: coordinate system must be LPS or RAS, got {coordinate_system!r}")
    if not slicer and system != "RAS":
        raise InputError(f"{path}: .{fmt} landmark files are world RAS; {system} is only for Slicer files")
    pts = np.asarray(landmarks.points_world, float)
    if system == "LPS":
        pts = pts * _LPS_FLIP
    buf = io.StringIO()
    if fmt == "fcsv":
        buf.write("# Markups fiducial file version = 4.11\n")
        buf.write(f"# CoordinateSystem = {system}\n")
        buf.write("# columns = " + ",".join(_SLICER_DEFAULT_COLUMNS) + "\n")
        writer = csv.writer(buf, lineterminator="\n")
        for i, (name, p) in enumerate(zip(landmarks.names, pts)):
            writer.writerow([f"vtkMRMLMarkupsFiducialNode_{i}", *map(_fmt, p), 0, 0, 0, 1, 1, 1, 0, name, "", ""])
    elif fmt == "csv":
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(["name", "x", "y", "z"])
        for name, p in zip(landmarks.names, pts):
            writer.writerow([name, *map(_fmt, p)])
    elif fmt == "mrk.json":
        doc = {
            "@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/Schema/markups-schema-v1.0.3.json#",
            "markups": [
                {
                    "type": "Fiducial",
                    "coordinateSystem": system,
                    "coordinateUnits": "mm",
                    "locked": False,
                    "labelFormat": "%N-%d",
                    "controlPoints": [
                        {
                            "id": str(i + 1),
                            "label": name,
                            "description": "",
                            "associatedNodeID": "",
                            "position": [float(v) for v in p],
                            "orientation": [-1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0],
                            "selected": True,
                            "locked": False,
                            "visibility": True,
                            "positionStatus": "defined",
                        }
                        for i, (name, p) in enumerate(zip(landmarks.names, pts))
                    ],
                }
            ],
        }
        buf.write(json.dumps(doc, indent=2) + "\n")
    else:
        doc = [{"id": name, "coordinates": [float(v) for v in p]} for name, p in zip(landmarks.names, pts)]
        buf.write(json.dumps(doc, indent=2) + "\n")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(buf.getvalue(), encoding="utf-8")
    except OSError as err:
        raise InputError(f"{path}: cannot write landmark file ({err})") from None
    return path


# --------------------------------------------------------------------------------------
# matching


def match_landmarks(sets, names=None, allow_extra: bool = False) -> list[LandmarkSet]:
    """Put landmark sets into one common order of names (the schema).

    Parameters
    ----------
    sets : sequence of LandmarkSet
        One set per instance.
    names : sequence of str, optional
        The schema. Default: the names of the first set, in its order.
    allow_extra : bool
        If True, names that are not in the schema are dropped; else they are errors.

    Returns
    -------
    list of LandmarkSet
        Each with ``names == tuple(names)`` and rows in that order (row i of every set is
        the same landmark: the correspondence the warp of eq. (2) needs).

    Raises
    ------
    InputError
        Listing, per file, the schema names it lacks and the names it has that are not
        in the schema.
    """
    sets = list(sets)
    if names is None:
        if not sets:
            return []
        names = sets[0].names
    names = tuple(str(n) for n in names)
    dup = _duplicates(names)
    if dup:
        raise InputError(f"landmark schema: duplicate name(s) {', '.join(repr(d) for d in dup)}")
    if not names:
        raise InputError("landmark schema is empty")
    schema = set(names)
    problems = []
    for i, s in enumerate(sets):
        have = set(s.names)
        missing = [n for n in names if n not in have]
        unknown = [] if allow_extra else [n for n in s.names if n not in schema]
        if missing or unknown:
            parts = []
            if missing:
                parts.append("missing " + ", ".join(missing))
            if unknown:
                parts.append("not in the schema " + ", ".join(unknown))
            problems.append(f"{s.source or f'set {i}'}: {'; '.join(parts)}")
    if problems:
        raise InputError("landmarks do not match the schema:\n  " + "\n  ".join(problems))
    return [s.subset(names) for s in sets]


def order_by_schema(landmarks: LandmarkSet, names, allow_missing: bool = True, allow_extra: bool = False) -> LandmarkSet:
    """One instance's landmarks in schema order (for importing a partial set).

    Parameters
    ----------
    landmarks : LandmarkSet
        The instance's landmarks.
    names : sequence of str
        The schema.
    allow_missing : bool
        If True, schema names the set lacks are left out of the result (to be placed
        later); else they are errors.
    allow_extra : bool
        If True, names not in the schema are appended after the schema's names in the
        set's order; else they are errors.

    Returns
    -------
    LandmarkSet
        The landmarks whose names are in the schema, in schema order (then the extras).

    Raises
    ------
    InputError
        Listing the names not in the schema (and the missing ones when not allowed).
    """
    names = tuple(str(n) for n in names)
    have = set(landmarks.names)
    schema = set(names)
    missing = [n for n in names if n not in have]
    unknown = [n for n in landmarks.names if n not in schema]
    parts = []
    if missing and not allow_missing:
        parts.append("missing " + ", ".join(missing))
    if unknown and not allow_extra:
        parts.append("not in the schema " + ", ".join(unknown))
    if parts:
        raise InputError(f"{landmarks.source or 'landmark set'}: {'; '.join(parts)}")
    return landmarks.subset([n for n in names if n in have] + unknown)
