"""The file formats the tool reads, in one table.

Each :class:`FileFormat` names a format, its extensions, what it holds (its kinds) and the
coordinates its files are read in. The readers dispatch on it (:mod:`.label_maps`,
:mod:`.meshes`, :mod:`.landmarks`), the command line's help and Blender's file filters list
from it, and the messages that name the formats a file may be take their names from it, so a
new format is one entry here and its reader in its module.

>>> extensions("mesh")
('.stl', '.ply', '.obj')
>>> format_names("mesh")
'STL/PLY/OBJ'
>>> file_glob("landmarks")
'*.fcsv;*.mrk.json;*.csv;*.json'
>>> format_of("L1.nii.gz", "image").name, format_of("points.mrk.json", "landmarks").name
('NIfTI', '3D Slicer markups JSON')
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

__all__ = ["FORMATS", "KINDS", "FileFormat", "extensions", "file_glob", "format_names", "format_of",
           "registered_extension"]

#: What a file may hold: a label map (integer labels on a voxel grid), a grey-value image (CT),
#: a closed surface mesh, landmark points, or a shape model.
KINDS = ("label map", "image", "mesh", "landmarks", "model")


@dataclass(frozen=True)
class FileFormat:
    """One file format.

    Attributes
    ----------
    name : str
        As messages name it (``"NIfTI"``, ``"STL"``).
    extensions : tuple of str
        Lower-case, with the dot; the longest (``".nii.gz"``, ``".mrk.json"``) matched first.
    kinds : tuple of str
        What its files hold (:data:`KINDS`).
    coordinates : str
        The world coordinates its files are read in (all become RAS mm).
    """

    name: str
    extensions: tuple
    kinds: tuple
    coordinates: str


#: Every format read, in the order the help lists them.
FORMATS = (
    FileFormat("NIfTI", (".nii", ".nii.gz"), ("label map", "image"), "its sform or qform (RAS)"),
    FileFormat("NRRD", (".nrrd", ".nhdr"), ("label map", "image"), "as its space field says (LPS or RAS)"),
    FileFormat("MetaImage", (".mha", ".mhd"), ("label map", "image"), "LPS (ITK's)"),
    FileFormat("NumPy", (".npy", ".npz"), ("label map",), "voxel indices times the spacing given (no affine in .npy)"),
    FileFormat("STL", (".stl",), ("mesh",), "as its header states (3D Slicer: LPS), else the project's space (RAS)"),
    FileFormat("PLY", (".ply",), ("mesh",), "as its comments state (3D Slicer: LPS), else the project's space (RAS)"),
    FileFormat("OBJ", (".obj",), ("mesh",), "as its comments state, else the project's space (RAS)"),
    FileFormat("3D Slicer markups CSV", (".fcsv",), ("landmarks",), "LPS or RAS as its header says"),
    FileFormat("3D Slicer markups JSON", (".mrk.json",), ("landmarks",), "LPS or RAS as its coordinateSystem says"),
    FileFormat("CSV", (".csv",), ("landmarks",), "name, x, y, z in the project's space (RAS)"),
    FileFormat("JSON", (".json",), ("landmarks",), "Scalismo's landmark list, in the project's space (RAS)"),
    FileFormat("model.npz", (".npz",), ("model",), "RAS mm (the build's contract)"),
    FileFormat("statismo HDF5", (".h5", ".hdf5"), ("model",), "its own world (Scalismo, ShapeWorks: LPS or RAS)"),
)


def _of_kind(kind: str) -> tuple:
    if kind not in KINDS:
        raise ValueError(f"unknown kind of file {kind!r} ({', '.join(KINDS)})")
    return tuple(f for f in FORMATS if kind in f.kinds)


def extensions(kind: str) -> tuple:
    """The extensions of every format holding ``kind``, in :data:`FORMATS` order."""
    return tuple(e for f in _of_kind(kind) for e in f.extensions)


def format_names(kind: str, sep: str = "/") -> str:
    """The names of the formats holding ``kind`` for a message (``"STL/PLY/OBJ"``)."""
    return sep.join(f.name for f in _of_kind(kind))


def file_glob(kind: str) -> str:
    """A file dialog's filter for ``kind`` (``"*.stl;*.ply;*.obj"``)."""
    return ";".join(f"*{e}" for e in extensions(kind))


#: Every registered extension, the longest first (so ``.nii.gz`` is met before ``.gz``).
_LONGEST_FIRST = tuple(sorted({e for f in FORMATS for e in f.extensions}, key=lambda e: (-len(e), e)))


def registered_extension(path) -> str:
    """The lower-case extension of ``path``: the longest registered one it ends with
    (``.nii.gz``, ``.mrk.json``), else its last suffix (``""`` for none)."""
    name = Path(path).name.lower()
    return next((e for e in _LONGEST_FIRST if name.endswith(e) and len(name) > len(e)), Path(name).suffix)


def format_of(path, kind: str) -> FileFormat | None:
    """The format of ``kind`` a file's extension names, or None."""
    ext = registered_extension(path)
    return next((f for f in _of_kind(kind) if ext in f.extensions), None)
