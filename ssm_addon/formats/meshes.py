"""Triangle mesh files: PLY (ASCII and binary), STL (ASCII and binary) and OBJ.

Coordinates are mm. The world frame of the core is RAS (as for label maps); a file that
states its convention is read in it: 3D Slicer (since 4.11) writes ``SPACE=LPS`` (or
``SPACE=RAS``) as a comment in PLY and OBJ and in the STL header (``solid 3D Slicer output.
SPACE=LPS``), and LPS coordinates are turned into RAS (x and y negated, a half turn about
z, so triangles keep their orientation). A file that states nothing is taken in the
convention the caller gives (a project's ``space``), else as RAS. The mesh type and its
geometry are :mod:`ssm_addon.meshutil`.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..base.errors import InputError
from ..meshutil import as_faces
from .registry import extensions, format_names, format_of, registered_extension

__all__ = ["MESH_EXTENSIONS", "SPACES", "mesh_space", "read_mesh", "read_ply", "to_ras", "write_ply"]

#: Coordinate conventions a file can state (world mm): right-anterior-superior, left-posterior-superior.
SPACES = ("RAS", "LPS")
_LPS_TO_RAS = np.array([-1.0, -1.0, 1.0])
_SPACE = re.compile(rb"SPACE\s*=\s*(LPS|RAS)\b", re.IGNORECASE)


def to_ras(points, space: str | None):
    """(..., 3) points in ``space`` ("LPS" or "RAS"; None is RAS) as RAS mm.

    >>> to_ras(np.array([1.0, 2.0, 3.0]), "LPS").tolist()
    [-1.0, -2.0, 3.0]
    """
    pts = np.asarray(points, dtype=float)
    return pts * _LPS_TO_RAS if (space or "RAS").upper() == "LPS" else pts


def _stated_space(head: bytes) -> str | None:
    found = _SPACE.search(head)
    return found.group(1).decode("ascii").upper() if found else None


def mesh_space(path) -> str | None:
    """The coordinate convention a mesh file states (``"LPS"`` or ``"RAS"``), or None.

    Read where the tools write it: the header comments of a PLY, the 80-byte header (binary)
    or the ``solid`` line (ASCII) of an STL, the comment lines of an OBJ.
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(65536)
    except OSError as err:
        raise InputError(f"{path}: cannot read ({err.strerror})") from None
    ext = path.suffix.lower()
    if ext == ".ply":
        end = head.find(b"end_header")
        return _stated_space(head[: end if end >= 0 else len(head)])
    if ext == ".stl":
        first = head[:80] if not head.lstrip().lower().startswith(b"solid") else head.split(b"\n", 1)[0]
        return _stated_space(first)
    if ext == ".obj":
        return _stated_space(b"\n".join(line for line in head.splitlines() if line.lstrip().startswith(b"#")))
    return None


# --------------------------------------------------------------------------- PLY I/O
def write_ply(path, vertices, faces, vertex_scalars: dict | None = None, binary: bool = True,
              space: str | None = None) -> None:
    """Write a triangle mesh as PLY.

    Parameters
    ----------
    path : str or Path
    vertices : (V, 3) float array
        Written as float32 ``x y z`` (frame and unit are the caller's; mm by convention).
    faces : (F, 3) int array
    vertex_scalars : dict of name -> (V,) array, optional
        Extra float32 vertex properties (e.g. ``{"curvature": c}``).
    binary : bool
        Binary little-endian (default) or ASCII.
    space : {"RAS", "LPS"}, optional
        The convention of world coordinates, stated as 3D Slicer does (``comment SPACE=RAS``)
        so Slicer and this reader place the mesh right; None for other frames.
    """
    v = np.asarray(vertices, dtype=np.float32).reshape(-1, 3)
    f = as_faces(faces).astype(np.int32)
    scalars = {k: np.asarray(s, dtype=np.float32).ravel() for k, s in (vertex_scalars or {}).items()}
    for k, s in scalars.items():
        if len(s) != len(v):
            raise InputError(f"{path}: vertex scalar '{k}' has {len(s)} values for {len(v)} vertices")
    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0", "comment SSM Builder",
              *([f"comment SPACE={space.upper()}"] if space else []), f"element vertex {len(v)}", "property float x", "property float y", "property float z"]
    header += [f"property float {k}" for k in scalars]
    header += [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    vdtype = np.dtype([(n, "<f4") for n in ("x", "y", "z", *scalars)])
    vrec = np.empty(len(v), dtype=vdtype)
    vrec["x"], vrec["y"], vrec["z"] = v[:, 0], v[:, 1], v[:, 2]
    for k, s in scalars.items():
        vrec[k] = s
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        if binary:
            fh.write(vrec.tobytes())
            frec = np.empty(len(f), dtype=np.dtype([("n", "u1"), ("i", "<i4", (3,))]))
            frec["n"] = 3
            frec["i"] = f
            fh.write(frec.tobytes())
        else:
            cols = np.column_stack([vrec[n] for n in vdtype.names]) if len(v) else np.zeros((0, len(vdtype.names)))
            np.savetxt(fh, cols, fmt="%.7g")
            np.savetxt(fh, np.column_stack([np.full(len(f), 3), f]), fmt="%d")


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _parse_ply(path: Path, raw: bytes) -> dict:
    """Elements of a PLY file: {element: {property: values}} (ASCII or binary, either endian)."""
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise InputError(f"{path}: not a PLY file (no 'ply' magic or 'end_header')")
    body_start = raw.find(b"\n", end) + 1
    fmt = None
    elements: list[tuple[str, int, list]] = []
    for line in raw[:end].decode("latin-1").splitlines():
        words = line.split()
        if not words:
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if words[1] == "list":
                elements[-1][2].append((words[4], "list", _PLY_TYPES[words[2]], _PLY_TYPES[words[3]]))
            else:
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(f"{path}: unsupported PLY format {fmt!r}")
    result: dict[str, dict[str, object]] = {}
    if fmt == "ascii":
        tokens = raw[body_start:].split()
        pos = 0
        for name, count, props in elements:
            if all(len(p) == 2 for p in props):
                n = count * len(props)
                if pos + n > len(tokens):
                    raise InputError(f"{path}: truncated PLY: element {name!r} incomplete")
                arr = np.array(tokens[pos : pos + n], dtype=np.float64).reshape(count, len(props))
                pos += n
                result[name] = {p[0]: arr[:, i] for i, p in enumerate(props)}
            else:
                values = {p[0]: [] for p in props}
                for _ in range(count):
                    for p in props:
                        if pos >= len(tokens):
                            raise InputError(f"{path}: truncated PLY: element {name!r} incomplete")
                        if len(p) == 2:
                            values[p[0]].append(float(tokens[pos]))
                            pos += 1
                        else:
                            k = int(tokens[pos])
                            values[p[0]].append([int(t) for t in tokens[pos + 1 : pos + 1 + k]])
                            pos += 1 + k
                result[name] = values
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        buf = memoryview(raw)
        pos = body_start
        for name, count, props in elements:
            if all(len(p) == 2 for p in props):
                dt = np.dtype([(p[0], order + p[1]) for p in props])
                if pos + dt.itemsize * count > len(raw):
                    raise InputError(f"{path}: truncated PLY: element {name!r} incomplete")
                arr = np.frombuffer(buf, dtype=dt, count=count, offset=pos)
                pos += dt.itemsize * count
                result[name] = {p[0]: arr[p[0]] for p in props}
                continue
            if count == 0:  # an empty element has no bytes to probe
                result[name] = {p[0]: np.zeros((0, 3) if len(p) != 2 else 0) for p in props}
                continue
            # Fast path: every list has the length of the first one.
            fields, first_len = [], None
            probe = pos
            for p in props:
                if len(p) == 2:
                    fields.append((p[0], order + p[1]))
                    probe += np.dtype(p[1]).itemsize
                else:
                    if probe + np.dtype(p[2]).itemsize > len(raw):
                        raise InputError(f"{path}: truncated PLY: element {name!r} incomplete")
                    k = int(np.frombuffer(buf, dtype=order + p[2], count=1, offset=probe)[0])
                    first_len = k if first_len is None else first_len
                    fields.append((p[0] + "#n", order + p[2]))
                    fields.append((p[0], order + p[3], (k,)))
                    probe += np.dtype(p[2]).itemsize + k * np.dtype(p[3]).itemsize
            dt = np.dtype(fields)
            ok = pos + dt.itemsize * count <= len(raw)
            if ok:
                arr = np.frombuffer(buf, dtype=dt, count=count, offset=pos)
                ok = all(np.all(arr[f[0]] == arr[f[0]][0]) for f in fields if f[0].endswith("#n")) if count else True
                ok = ok and all(np.all(arr[f[0] + "#n"] == arr[f[0]].shape[1]) for f in fields if len(f) == 3)
            if ok:
                pos += dt.itemsize * count
                result[name] = {f[0]: arr[f[0]] for f in fields if not f[0].endswith("#n")}
                continue
            values = {p[0]: [] for p in props}
            for _ in range(count):
                for p in props:
                    if len(p) == 2:
                        size = np.dtype(p[1]).itemsize
                        if pos + size > len(raw):
                            raise InputError(f"{path}: truncated PLY: element {name!r} incomplete")
                        values[p[0]].append(float(np.frombuffer(buf, order + p[1], 1, pos)[0]))
                        pos += size
                    else:
                        size = np.dtype(p[2]).itemsize
                        if pos + size > len(raw):
                            raise InputError(f"{path}: truncated PLY: element {name!r} incomplete")
                        k = int(np.frombuffer(buf, order + p[2], 1, pos)[0])
                        pos += size
                        isize = np.dtype(p[3]).itemsize
                        if pos + k * isize > len(raw):
                            raise InputError(f"{path}: truncated PLY: element {name!r} incomplete")
                        values[p[0]].append(np.frombuffer(buf, order + p[3], k, pos).tolist())
                        pos += k * isize
            result[name] = values
    return result


def read_ply(path) -> tuple[np.ndarray, np.ndarray, dict]:
    """Read a triangle mesh from PLY (ASCII or binary, little or big endian).

    Returns
    -------
    vertices : (V, 3) float64 array
    faces : (F, 3) int64 array
        Polygons with more than three corners are fan-triangulated.
    vertex_scalars : dict of name -> (V,) float64 array
        Every other scalar vertex property.

    Raises
    ------
    InputError
        Unreadable, not PLY, unsupported format, truncated, or no vertex/face elements;
        the message names the file.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise InputError(f"{path}: cannot read PLY file ({err})") from err
    result = _parse_ply(path, raw)
    vert = result.get("vertex")
    face = result.get("face")
    if vert is None or face is None or not all(c in vert for c in "xyz"):
        raise InputError(f"{path}: PLY file needs 'vertex' (x, y, z) and 'face' elements")
    vertices, scalars = _vertex_cols(path, vert)
    key = "vertex_indices" if "vertex_indices" in face else ("vertex_index" if "vertex_index" in face else None)
    if key is None:
        raise InputError(f"{path}: PLY 'face' element has no vertex_indices list")
    polys = face[key]
    if isinstance(polys, np.ndarray) and polys.ndim == 2:
        if polys.shape[1] == 3:
            faces = polys.astype(np.int64)
        else:
            faces = _fan(polys.tolist())
    else:
        faces = _fan([list(p) for p in polys])
    return vertices, faces, scalars


def _vertex_cols(path, cols: dict) -> tuple[np.ndarray, dict]:
    if not {"x", "y", "z"} <= set(cols):
        raise InputError(f"{path}: vertex element lacks x, y, z properties")
    v = np.column_stack([cols["x"], cols["y"], cols["z"]]).astype(np.float64)
    rest = {
        k: np.asarray(c, dtype=np.float64)
        for k, c in cols.items()
        if k not in ("x", "y", "z") and np.ndim(c) == 1
    }
    return v, rest


def _fan(polys) -> np.ndarray:
    if isinstance(polys, np.ndarray):
        if polys.shape[1] == 3:
            return polys
        polys = polys.tolist()
    tris = [(p[0], p[i], p[i + 1]) for p in polys for i in range(1, len(p) - 1)]
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


# --------------------------------------------------------------------------- mesh files
MESH_EXTENSIONS = extensions("mesh")


def _merge_vertices(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(3F, 3) triangle corners -> unique vertices and (F, 3) faces (exact duplicates merged)."""
    vertices, inverse = np.unique(corners, axis=0, return_inverse=True)
    return vertices.astype(np.float64), inverse.reshape(-1, 3).astype(np.int64)


def _read_stl(path: Path):
    raw = path.read_bytes()
    if len(raw) >= 84:
        n = int(np.frombuffer(raw, dtype="<u4", count=1, offset=80)[0])
        if len(raw) == 84 + 50 * n:
            rec = np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
            tri = np.frombuffer(raw, dtype=rec, count=n, offset=84)["v"]
            return _merge_vertices(tri.reshape(-1, 3))
    head = raw[:512].lstrip().lower()
    if not head.startswith(b"solid"):
        raise InputError(f"{path}: not an STL file (binary size mismatch and no ASCII 'solid' header); truncated?")
    text = raw.decode("latin-1")
    num = r"([-+0-9.eEinfINFnaN]+)"
    coords = re.findall(rf"vertex\s+{num}\s+{num}\s+{num}", text)
    if len(coords) == 0 or len(coords) % 3:
        raise InputError(f"{path}: corrupt ASCII STL: {len(coords)} vertices is not a multiple of 3")
    if text.count("endfacet") * 3 != len(coords):
        raise InputError(f"{path}: corrupt or truncated ASCII STL (facet/vertex count mismatch)")
    return _merge_vertices(np.array(coords, dtype=np.float64))


def _read_ply(path: Path):
    vertices, faces, _ = read_ply(path)
    return vertices, faces


def _read_obj(path: Path):
    vertices: list[list[float]] = []
    polys: list[list[int]] = []
    with open(path, encoding="latin-1") as fh:
        for lineno, line in enumerate(fh, 1):
            if line.startswith("v "):
                parts = line.split()
                if len(parts) < 4:
                    raise InputError(f"{path}: line {lineno}: a vertex needs three coordinates")
                vertices.append([float(parts[1]), float(parts[2]), float(parts[3])])
            elif line.startswith("f "):
                poly = []
                for tok in line.split()[1:]:
                    idx = int(tok.split("/")[0])
                    poly.append(len(vertices) + idx if idx < 0 else idx - 1)
                polys.append(poly)
    if not vertices or not polys:
        raise InputError(f"{path}: OBJ file has no vertices or no faces")
    return np.array(vertices, dtype=np.float64), _fan(polys)


#: The reader of each mesh format of :mod:`.registry`.
_MESH_READERS = {"STL": _read_stl, "PLY": _read_ply, "OBJ": _read_obj}


def read_mesh(path, *, space: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle surface mesh (STL binary/ASCII, PLY ascii/binary, OBJ) in RAS world mm.

    Polygons are fan-triangulated, OBJ negative indices resolved, STL duplicate vertices
    merged; faces that repeat a vertex are dropped. Coordinates are taken as mm, in the
    convention the file states (:func:`mesh_space`), else in ``space``, else RAS; LPS
    coordinates are turned into RAS.

    Parameters
    ----------
    space : {"RAS", "LPS"}, optional
        The convention of a file that states none.

    Returns
    -------
    vertices_world : (V, 3) float ndarray, mm (RAS)
    faces : (F, 3) int ndarray
    """
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a mesh file ({format_names('mesh', ', ')})")
    fmt = format_of(path, "mesh")
    if fmt is None:
        ext = registered_extension(path)
        raise InputError(f"{path}: unknown file extension {ext or '(none)'!r}; supported: {', '.join(MESH_EXTENSIONS)}")
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    try:
        vertices, faces = _MESH_READERS[fmt.name](path)
    except InputError:
        raise
    except Exception as err:  # noqa: BLE001 - every parser failure becomes a named InputError
        raise InputError(
            f"{path}: cannot read {fmt.name} mesh, corrupt or truncated? ({type(err).__name__}: {err})"
        ) from err
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        raise InputError(f"{path}: the mesh has no faces")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InputError(f"{path}: face indices out of range (0..{len(vertices) - 1})")
    if not np.all(np.isfinite(vertices)):
        raise InputError(f"{path}: the mesh has NaN or infinite vertex coordinates")
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])
    stated = mesh_space(path)
    if space is not None and str(space).upper() not in SPACES:
        raise InputError(f"{path}: unknown coordinate convention {space!r} (RAS or LPS)")
    return to_ras(vertices, stated or space), faces[keep]
