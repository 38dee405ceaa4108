"""VTK polydata files: XML ``.vtp`` and legacy ``.vtk``, triangles with per-point fields.

Both are read by ParaView, 3D Slicer, ShapeWorks and SlicerSALT. Coordinates are written
as given (mm); scalar fields are one value per point, vector fields three.

References
----------
.. [1] Kitware, "VTK File Formats" (VTK User's Guide, ch. 19): the legacy format and the
   XML PolyData (``.vtp``) layout with ``Points``, ``Polys`` (``connectivity``,
   ``offsets``) and ``PointData``.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..base.errors import InputError

__all__ = ["write_vtk", "write_vtp"]


def _fields(points: np.ndarray, point_data: dict | None) -> dict[str, np.ndarray]:
    out = {}
    for name, values in (point_data or {}).items():
        a = np.asarray(values, dtype=float)
        if a.shape not in ((len(points),), (len(points), 3)):
            raise InputError(f"VTK field {name!r}: shape {a.shape}, expected ({len(points)},) or ({len(points)}, 3)")
        out[re.sub(r"[^A-Za-z0-9_.+-]+", "_", str(name)) or "field"] = a
    return out


def _numbers(a: np.ndarray, fmt: str = "%.9g") -> str:
    a = np.asarray(a)
    if a.ndim == 1:
        a = a[:, None]
    row = " ".join([fmt] * a.shape[1])  # one formatting call per row, the same text as per value
    return "\n".join(row % tuple(r) for r in a.tolist())


_CONNECTIVITY_TEXT: dict = {}


def _connectivity_text(faces: np.ndarray) -> tuple[str, str]:
    """The connectivity and offsets text of ``faces``; the last one is kept, since every coated
    instance of a study has the template's triangles."""
    key = faces.tobytes()
    text = _CONNECTIVITY_TEXT.get(key)
    if text is None:
        text = (_numbers(faces, "%d"), _numbers(np.arange(1, len(faces) + 1) * 3, "%d"))
        _CONNECTIVITY_TEXT.clear()
        _CONNECTIVITY_TEXT[key] = text
    return text


def write_vtp(path, points, faces, point_data: dict | None = None) -> Path:
    """Write a triangle mesh as VTK XML PolyData (ASCII ``.vtp``).

    Parameters
    ----------
    path : path
    points : (N, 3) array_like, mm
    faces : (F, 3) int array_like
    point_data : dict name -> (N,) or (N, 3) array_like, optional
        Per-point fields (e.g. a displacement in mm, a p-value).
    """
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    fields = _fields(points, point_data)
    parts = ['<?xml version="1.0"?>',
             '<VTKFile type="PolyData" version="1.0" byte_order="LittleEndian" header_type="UInt64">',
             "<PolyData>",
             f'<Piece NumberOfPoints="{len(points)}" NumberOfVerts="0" NumberOfLines="0" NumberOfStrips="0" '
             f'NumberOfPolys="{len(faces)}">']
    if fields:
        scalars = next((k for k, v in fields.items() if v.ndim == 1), None)
        vectors = next((k for k, v in fields.items() if v.ndim == 2), None)
        attrs = (f' Scalars="{scalars}"' if scalars else "") + (f' Vectors="{vectors}"' if vectors else "")
        parts.append(f"<PointData{attrs}>")
        for k, v in fields.items():
            comps = 3 if v.ndim == 2 else 1
            parts += [f'<DataArray type="Float64" Name="{k}" NumberOfComponents="{comps}" format="ascii">',
                      _numbers(v), "</DataArray>"]
        parts.append("</PointData>")
    connectivity, offsets = _connectivity_text(faces)
    parts += ["<Points>", '<DataArray type="Float64" NumberOfComponents="3" format="ascii">', _numbers(points),
              "</DataArray>", "</Points>", "<Polys>",
              '<DataArray type="Int64" Name="connectivity" format="ascii">', connectivity, "</DataArray>",
              '<DataArray type="Int64" Name="offsets" format="ascii">', offsets, "</DataArray>",
              "</Polys>", "</Piece>", "</PolyData>", "</VTKFile>", ""]
    path = Path(path)
    path.write_text("\n".join(parts), encoding="ascii")
    return path


def write_vtk(path, points, faces, point_data: dict | None = None, *, title: str = "SSM Builder mesh") -> Path:
    """Write a triangle mesh as a legacy ASCII VTK polydata file (``.vtk``), fields as ``POINT_DATA``."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    fields = _fields(points, point_data)
    parts = ["# vtk DataFile Version 4.2", title.replace("\n", " ")[:250], "ASCII", "DATASET POLYDATA",
             f"POINTS {len(points)} double", _numbers(points),
             f"POLYGONS {len(faces)} {4 * len(faces)}",
             _numbers(np.concatenate([np.full((len(faces), 1), 3), faces], axis=1), "%d")]
    if fields:
        parts.append(f"POINT_DATA {len(points)}")
        for k, v in fields.items():
            if v.ndim == 2:
                parts += [f"VECTORS {k} double", _numbers(v)]
            else:
                parts += [f"SCALARS {k} double 1", "LOOKUP_TABLE default", _numbers(v)]
    path = Path(path)
    path.write_text("\n".join(parts) + "\n", encoding="ascii")
    return path
