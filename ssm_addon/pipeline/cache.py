"""The build cache: every finished instance's product on disk, keyed by what made it.

A build writes each instance's coating (with its object frame and import figures) to
the cache the moment it arrives, and the template once built. An entry's key is a
SHA-256 of everything that determines it:

* an instance (import + coating, paper 2 and 4): the content of its label map or mesh,
  its label and voxelization step, its landmarks (names and world mm), the import
  parameters (spacing, frame method), the template (points, faces, landmark points),
  the coating parameters and the quality thresholds that can stop an import;
* the template (paper 3): its instance's inputs, the template and import parameters;

and every key the package's version and its own source (:func:`code_digest`), so an entry
written by other code is never read.

So a rerun of a killed build recomputes only what is missing, a new instance costs
only its own coating, and a changed coating parameter invalidates exactly the
coatings (the template stays). Entries are ``.npz`` (read with ``allow_pickle=False``)
written atomically; the folder holds a ``.ssm-cache`` marker and nothing else of
anyone's is ever touched. Deleting the folder is always safe.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..base.errors import InputError
from ..coating.coating import CoatingResult, FitFigures
from ..instances.volume import ObjectFrame, frame_from_arrays, frame_to_arrays
from ..model.quality import Finding
from ..template.template import Template
from ..version import __version__

__all__ = ["BuildCache", "InstanceProduct", "code_digest", "file_digest", "digest"]

FORMAT = 1
"""Cache layout version; part of every key, so a new layout never reads an old entry."""

MARKER = ".ssm-cache"

_FILE_DIGESTS: dict = {}


def file_digest(path) -> str:
    """SHA-256 of a file's content (remembered per path, size and modification time)."""
    path = Path(path)
    try:
        st = path.stat()
    except OSError as err:
        raise InputError(f"{path}: cannot read ({err.strerror})") from None
    memo = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    if memo not in _FILE_DIGESTS:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 22), b""):
                h.update(block)
        _FILE_DIGESTS[memo] = h.hexdigest()
    return _FILE_DIGESTS[memo]


def _feed(h, value) -> None:
    if isinstance(value, np.ndarray):
        a = np.ascontiguousarray(value)
        h.update(f"array{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    elif isinstance(value, dict):
        h.update(b"{")
        for k in sorted(value):
            _feed(h, str(k))
            _feed(h, value[k])
        h.update(b"}")
    elif isinstance(value, list | tuple):
        h.update(b"[")
        for v in value:
            _feed(h, v)
        h.update(b"]")
    else:
        h.update(json.dumps(value, default=str).encode())
        h.update(b";")


@functools.cache
def code_digest() -> str:
    """SHA-256 (hex) of the package's own source: every ``.py`` file under ``ssm_addon``, by its
    path relative to the package and its bytes. Part of every key, so a changed computation never
    reads what older code wrote under the same version number (a source checkout that is
    updated, a development build)."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py"), key=lambda q: q.relative_to(root).as_posix()):
        h.update(path.relative_to(root).as_posix().encode() + b"\0")
        h.update(hashlib.sha256(path.read_bytes()).digest())
    return h.hexdigest()


def digest(*parts) -> str:
    """SHA-256 (hex) of nested dicts, lists, arrays and JSON scalars, in a canonical order.

    >>> digest({"b": 1, "a": 2}) == digest({"a": 2, "b": 1})
    True
    """
    h = hashlib.sha256()
    _feed(h, ["ssm-cache", FORMAT, __version__, code_digest()])
    for p in parts:
        _feed(h, p)
    return h.hexdigest()


@dataclass
class InstanceProduct:
    """What a worker returns for one instance: import figures and the coating.

    Attributes
    ----------
    name : str
    frame : ObjectFrame
        The instance's object frame (paper 2).
    volume_mm3 : float
        Volume of the resampled mask, mm³.
    voxels : int
    findings : list of Finding
        The import gates that failed (components).
    coating : CoatingResult
        Object mm of the instance.
    from_cache : bool
        Read from the cache, not computed.
    """

    name: str
    frame: ObjectFrame
    volume_mm3: float
    voxels: int
    coating: CoatingResult
    findings: list = field(default_factory=list)
    from_cache: bool = False


class BuildCache:
    """Per-instance and template entries in ``folder`` (created at the first write).

    Every entry read is validated (a readable ``.npz`` with the keys and array shapes the
    build expects, finite points); a damaged one is moved aside (``<entry>.damaged``) and
    recomputed. A cache that cannot be written is used read-only for the rest of the build.
    Either is said once in :attr:`notes` (the build prints them); the cache never raises
    for its own files.

    Raises
    ------
    InputError
        ``folder`` exists, is not empty and is not a cache (no ``.ssm-cache`` marker):
        it is someone's folder, and the cache never writes into it.
    """

    def __init__(self, folder):
        self.folder = Path(folder).expanduser().resolve()
        self.hits = 0
        self.writes = 0
        self.read_only = False
        self.notes: list[str] = []
        if self.folder.exists():
            if not self.folder.is_dir():
                raise InputError(f"--cache {self.folder}: is a file, not a folder")
            if not (self.folder / MARKER).exists() and any(self.folder.iterdir()):
                raise InputError(f"--cache {self.folder}: the folder holds files and is not an SSM build cache (no "
                                 f"{MARKER}); choose another --cache folder")
        self._ready = False

    def take_notes(self) -> list[str]:
        """The notes since the last call (each said once)."""
        notes, self.notes = self.notes, []
        return notes

    def _unwritable(self, err: OSError, what: str) -> None:
        if not self.read_only:
            self.notes.append(f"cache: cannot write {what} in {self.folder} ({err.strerror or err}); the cache is used "
                              "read-only for this build (its entries are read, new ones are not kept)")
        self.read_only = True

    def _make(self) -> bool:
        """Create the folder and its marker at the first write (a build that fails first leaves nothing)."""
        if self._ready or self.read_only:
            return self._ready
        try:
            (self.folder / "instances").mkdir(parents=True, exist_ok=True)
            (self.folder / "templates").mkdir(exist_ok=True)
            marker = self.folder / MARKER
            if not marker.exists():
                marker.write_text(json.dumps({"format": FORMAT, "ssm_builder": __version__}) + "\n")
        except OSError as err:
            self._unwritable(err, "the cache's folders")
            return False
        self._ready = True
        return True

    # ------------------------------------------------------------------ files
    def _write(self, path: Path, arrays: dict) -> None:
        if not self._make():
            return
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            with open(tmp, "wb") as f:
                np.savez(f, **arrays)
            os.replace(tmp, path)
        except OSError as err:
            try:
                tmp.unlink(missing_ok=True)
            except OSError:
                pass
            self._unwritable(err, path.name)
            return
        self.writes += 1

    def _damaged(self, path: Path, what: str, reason: str) -> None:
        """Move a damaged entry aside (kept for a look, never read again) and say so."""
        aside = path.with_name(path.name + ".damaged")
        try:
            os.replace(path, aside)
            where = f"moved aside to {aside.name}"
        except OSError:
            where = "left in place (the cache is not writable)"
        self.notes.append(f"cache: the entry of {what} is damaged ({reason}); {where}; recomputing it")

    def _read(self, path: Path, what: str, shapes: dict | None = None) -> dict | None:
        """The entry's arrays, or None when there is none or it is damaged (then moved aside).

        ``shapes``: key -> expected shape (None for a free axis) of the arrays that must be there.
        """
        if not path.exists():
            return None
        try:
            with np.load(path, allow_pickle=False) as npz:
                arrays = {k: npz[k] for k in npz.files}
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as err:
            self._damaged(path, what, f"unreadable: {type(err).__name__}: {err}")
            return None
        for key, shape in (shapes or {}).items():
            a = arrays.get(key)
            if a is None:
                self._damaged(path, what, f"no {key!r}")
                return None
            if len(a.shape) != len(shape) or any(e is not None and e != g for e, g in zip(shape, a.shape)):
                self._damaged(path, what, f"{key} has shape {a.shape}, expected "
                                          f"{tuple('any' if e is None else e for e in shape)}")
                return None
            if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
                self._damaged(path, what, f"{key} holds NaN or infinite values")
                return None
        return arrays

    # ------------------------------------------------------------------ instances
    def instance_path(self, key: str) -> Path:
        return self.folder / "instances" / f"{key}.npz"

    def get_instance(self, key: str, name: str, n_points: int | None = None) -> InstanceProduct | None:
        """The product stored under ``key`` (renamed to ``name``), or None; ``n_points``: the
        template's point count its coating must have."""
        shape = {"points_object": (n_points, 3), "warped_points_object": (n_points, 3)}
        a = self._read(self.instance_path(key), f"instance {name!r}", shape)
        if a is None:
            return None
        try:
            findings = [Finding(**{k: (float("nan") if v is None and k in ("value", "threshold") else v)
                                   for k, v in {**f, "instance": name}.items()})
                        for f in json.loads(str(a["findings_json"]))]
            coating = CoatingResult(points_object=a["points_object"], warped_points_object=a["warped_points_object"],
                                    fit=FitFigures.from_json(str(a["fit_json"])), name=name)
            product = InstanceProduct(name=name, frame=frame_from_arrays("frame", a),
                                      volume_mm3=float(a["volume_mm3"]), voxels=int(a["voxels"]), coating=coating,
                                      findings=findings, from_cache=True)
        except (KeyError, ValueError, TypeError) as err:
            self._damaged(self.instance_path(key), f"instance {name!r}", f"{type(err).__name__}: {err}")
            return None
        self.hits += 1
        return product

    def put_instance(self, key: str, product: InstanceProduct) -> None:
        arrays = {"points_object": np.asarray(product.coating.points_object, float),
                  "warped_points_object": np.asarray(product.coating.warped_points_object, float),
                  "fit_json": np.asarray(product.coating.fit.to_json()),
                  "volume_mm3": np.asarray(float(product.volume_mm3)), "voxels": np.asarray(int(product.voxels)),
                  "findings_json": np.asarray(json.dumps([_finding_dict(f) for f in product.findings]))}
        frame_to_arrays("frame", product.frame, arrays)
        self._write(self.instance_path(key), arrays)

    # ------------------------------------------------------------------ template
    def template_path(self, key: str) -> Path:
        return self.folder / "templates" / f"{key}.npz"

    def get_template(self, key: str) -> Template | None:
        path = self.template_path(key)
        a = self._read(path, "the template", {"points_object": (None, 3), "faces": (None, 3), "curvature": (None,)})
        if a is None:
            return None
        n = len(a["points_object"])
        if len(a["curvature"]) != n or a["faces"].size == 0 or a["faces"].min() < 0 or a["faces"].max() >= n:
            self._damaged(path, "the template", "its faces or curvature do not match its points")
            return None
        try:
            t = Template.from_arrays(a, frame_from_arrays("frame", a))
        except (KeyError, ValueError, TypeError) as err:
            self._damaged(path, "the template", f"{type(err).__name__}: {err}")
            return None
        self.hits += 1
        return t

    def put_template(self, key: str, template: Template) -> None:
        arrays = {k: np.asarray(v) for k, v in template.to_arrays().items()}
        frame_to_arrays("frame", template.frame, arrays)
        self._write(self.template_path(key), arrays)


def _finding_dict(f: Finding) -> dict:
    d = f.to_dict()
    return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in d.items()}
