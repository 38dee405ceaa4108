"""Attributes of the instances: groups (categories) and covariates (numbers).

An attribute table has one row per instance, joined by instance name. It comes from a
project's ``attributes = { group = "patient", age = 63 }`` inline tables, from a CSV file
(``[study] attributes``, ``ssm analyze --attributes``) or from both (the CSV's values
fill what the project leaves out). A column whose every given value is a number is a
covariate; any other column is a category. Missing values are allowed (an empty cell or
``NA``) and are said where they exclude an instance from an analysis.

>>> t = attributes_from_tables({"a": {"group": "x", "age": 60}, "b": {"group": "y"}})
>>> t.kinds["age"], t.kinds["group"], t.column("age").tolist()
('number', 'category', [60.0, nan])
"""

from __future__ import annotations

import csv
import difflib
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..base.errors import InputError

__all__ = ["MISSING_TOKENS", "NAME_COLUMNS", "Attributes", "attributes_from_tables", "read_attributes",
           "write_attributes"]

#: Cell texts read as a missing value (case-insensitive).
MISSING_TOKENS = frozenset({"", "na", "n/a", "nan", "null", "none", "."})
_DECIMAL_COMMA = re.compile(r"^([+-]?\d+),(\d+)$")

#: Header names taken as the instance-name column (case-insensitive); otherwise the first column.
NAME_COLUMNS = ("name", "instance", "subject", "id")


@dataclass(frozen=True)
class Attributes:
    """Per-instance attributes.

    Attributes
    ----------
    names : tuple of str
        Instance names, one per row.
    values : dict column -> tuple
        A covariate's values as floats (``nan`` where missing); a category's as str
        (``None`` where missing).
    kinds : dict column -> {"number", "category"}
    source : str
        Where the table came from (file or project), for messages.
    """

    names: tuple[str, ...]
    values: dict = field(default_factory=dict)
    kinds: dict = field(default_factory=dict)
    source: str = "attributes"

    @property
    def columns(self) -> tuple[str, ...]:
        return tuple(self.values)

    def column(self, name: str) -> np.ndarray:
        """A column as an array: float (nan = missing) for a covariate, object (None = missing) otherwise."""
        self.require(name)
        if self.kinds[name] == "number":
            return np.asarray(self.values[name], dtype=float)
        return np.asarray(self.values[name], dtype=object)

    def require(self, name: str) -> None:
        """InputError naming the table and the closest column when ``name`` is not a column."""
        if name not in self.values:
            close = difflib.get_close_matches(name, self.columns, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            have = ", ".join(repr(c) for c in self.columns) or "none"
            raise InputError(f"{self.source}: no attribute column {name!r}{hint}; columns: {have}")

    def not_numbers(self, name: str) -> list[tuple[str, str]]:
        """``(instance, cell)`` of column ``name``'s given cells that are not numbers (words,
        ``inf``): what keeps a mostly numeric column from being a covariate."""
        self.require(name)
        return [(n, v) for n, v in zip(self.names, self.values[name]) if not _is_missing(v) and _number(v) is None]

    def missing(self, name: str) -> np.ndarray:
        """(n,) bool: where column ``name`` has no value."""
        col = self.column(name)
        return np.isnan(col) if self.kinds[name] == "number" else np.array([v is None for v in col], bool)

    def aligned(self, instance_names) -> tuple[Attributes, tuple[str, ...]]:
        """The table in ``instance_names``' order (rows it lacks all missing) and the names it has
        that are not instances.

        Raises
        ------
        InputError
            When no row names an instance (the message lists a few of each).
        """
        instance_names = tuple(str(s) for s in instance_names)
        row = {n: i for i, n in enumerate(self.names)}
        unknown = tuple(n for n in self.names if n not in set(instance_names))
        if not any(n in row for n in instance_names):
            raise InputError(f"{self.source}: no row names an instance of the model (rows: "
                             f"{_few(self.names)}; instances: {_few(instance_names)})")
        values = {}
        for col, vals in self.values.items():
            empty = math.nan if self.kinds[col] == "number" else None
            values[col] = tuple(vals[row[n]] if n in row else empty for n in instance_names)
        return Attributes(instance_names, values, dict(self.kinds), self.source), unknown

    def merged(self, other: Attributes) -> Attributes:
        """This table with ``other``'s values filling what this one lacks (rows and columns)."""
        names = tuple(dict.fromkeys(self.names + other.names))
        tables = {n: {} for n in names}
        for t in (other, self):  # self wins
            for col, vals in t.values.items():
                for n, v in zip(t.names, vals):
                    if not _is_missing(v):
                        tables[n][col] = v
        return attributes_from_tables(tables, source=f"{self.source} + {other.source}")


def _few(names, k: int = 4) -> str:
    names = list(names)
    text = ", ".join(repr(n) for n in names[:k])
    return text + (f" … ({len(names)} in all)" if len(names) > k else "")


def _is_missing(v) -> bool:
    return v is None or (isinstance(v, float) and math.isnan(v)) or (isinstance(v, str) and
                                                                       v.strip().lower() in MISSING_TOKENS)


def _number(v):
    """A float for a number or a numeric text; None otherwise."""
    if isinstance(v, bool):
        return None
    if isinstance(v, int | float | np.integer | np.floating):
        return float(v)
    if isinstance(v, str):
        try:
            x = float(v.strip())
        except ValueError:
            return None
        return x if math.isfinite(x) else None
    return None


def attributes_from_tables(tables: Mapping[str, Mapping], *, source: str = "attributes") -> Attributes:
    """An :class:`Attributes` from ``{instance name: {column: value}}``.

    A column is a covariate when every value given is a number (or numeric text), a
    category otherwise; booleans are categories (``"true"``/``"false"``).
    """
    names = tuple(str(n) for n in tables)
    columns = list(dict.fromkeys(c for row in tables.values() for c in row))
    values, kinds = {}, {}
    for col in columns:
        if not isinstance(col, str) or not col.strip():
            raise InputError(f"{source}: an attribute column needs a name, got {col!r}")
        raw = [tables[n].get(col) for n in tables]
        given = [v for v in raw if not _is_missing(v)]
        for v in given:
            if isinstance(v, dict | list | tuple):
                raise InputError(f"{source}: attribute {col!r} must be a number or a text, got {v!r}")
        if given and all(_number(v) is not None for v in given):
            kinds[col] = "number"
            values[col] = tuple(math.nan if _is_missing(v) else _number(v) for v in raw)
        else:
            kinds[col] = "category"
            values[col] = tuple(None if _is_missing(v) else (str(v).lower() if isinstance(v, bool) else str(v).strip())
                                for v in raw)
    return Attributes(names, values, kinds, source)


def read_attributes(path) -> Attributes:
    """Read a CSV attribute table (comma, semicolon or tab separated; a header row).

    In a semicolon- or tab-separated file a cell such as ``51,5`` is the number 51.5 (the
    decimal comma of the spreadsheets that write such files).

    The instance names are the column called ``name``, ``instance``, ``subject`` or ``id``
    (case-insensitive), else the first column.

    Raises
    ------
    InputError
        For a missing or unreadable file, no header, a row of the wrong length, an
        empty or repeated instance name, and repeated column names; each names the
        file and the line.
    """
    path = Path(path).expanduser()
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not an attribute table (give the CSV file)")
    if not path.is_file():
        raise InputError(f"{path}: attribute table not found")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"{path}: cannot read the attribute table ({err})") from None
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise InputError(f"{path}: the attribute table is empty (expected a header row such as name,group,age)")
    delimiter = max((",", ";", "\t"), key=lambda d: lines[0].count(d))
    rows = list(csv.reader(lines, delimiter=delimiter))
    header = [h.strip() for h in rows[0]]
    if len(header) < 2:
        raise InputError(f"{path}: the header {lines[0]!r} has one column; expected a name column and at least one "
                         "attribute (comma, semicolon or tab separated)")
    if len(set(header)) != len(header):
        twice = sorted({h for h in header if header.count(h) > 1})
        raise InputError(f"{path}: column {twice[0]!r} appears twice in the header")
    lower = [h.lower() for h in header]
    key = next((lower.index(c) for c in NAME_COLUMNS if c in lower), 0)
    if delimiter != ",":  # a decimal comma (51,5) where the comma does not separate cells
        rows = [rows[0]] + [[_DECIMAL_COMMA.sub(r"\1.\2", c.strip()) for c in row] for row in rows[1:]]
    tables: dict[str, dict] = {}
    for lineno, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise InputError(f"{path}: line {lineno}: {len(row)} cells, the header has {len(header)}")
        name = row[key].strip()
        if not name:
            raise InputError(f"{path}: line {lineno}: empty instance name in column {header[key]!r}")
        if name in tables:
            raise InputError(f"{path}: line {lineno}: instance {name!r} appears twice")
        tables[name] = {h: v for i, (h, v) in enumerate(zip(header, row)) if i != key}
    if not tables:
        raise InputError(f"{path}: the attribute table has a header and no rows")
    return attributes_from_tables(tables, source=str(path))


def write_attributes(table: Attributes, path) -> Path:
    """Write an attribute table as CSV (``name`` first; missing values empty), readable by
    :func:`read_attributes`."""
    path = Path(path)
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["name", *table.columns])
        for i, name in enumerate(table.names):
            row = []
            for col in table.columns:
                v = table.values[col][i]
                row.append("" if _is_missing(v) else (f"{v:.10g}" if isinstance(v, float) else v))
            w.writerow([name, *row])
    return path
