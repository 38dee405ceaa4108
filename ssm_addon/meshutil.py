"""Triangle-mesh utilities: edges, topology checks, volume, normals and PLY files.

Meshes are ``vertices (V, 3)`` float arrays (any frame; lengths in that frame's unit,
usually mm) and ``faces (F, 3)`` integer arrays of vertex indices. A face
``(a, b, c)`` is oriented counter-clockwise seen from outside, so its normal
``(b - a) × (c - a)`` points outward and a closed outward mesh has positive
:func:`signed_volume`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components as _cc

from .errors import InputError

__all__ = [
    "ManifoldReport",
    "connected_components",
    "edges",
    "euler_characteristic",
    "face_normals",
    "genus",
    "is_closed_manifold",
    "read_ply",
    "signed_volume",
    "vertex_normals",
    "write_ply",
]


def _faces(faces) -> np.ndarray:
    f = np.asarray(faces)
    if f.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3:
        raise InputError(f"faces: expected an (F, 3) array of vertex indices, got shape {f.shape}")
    return f.astype(np.int64, copy=False)


def edges(faces) -> np.ndarray:
    """Unique undirected edges of a triangle mesh.

    Parameters
    ----------
    faces : (F, 3) int array

    Returns
    -------
    (E, 2) int64 array
        Each edge once, as ``(min, max)`` vertex indices, sorted lexicographically.
    """
    f = _faces(faces)
    e = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return _unique_rows(e) if len(e) else np.zeros((0, 2), dtype=np.int64)


def _unique_rows(a: np.ndarray, return_inverse: bool = False, return_counts: bool = False):
    """``np.unique(a, axis=0)`` for small non-negative int rows via a scalar key (much faster)."""
    a = np.asarray(a, dtype=np.int64)
    k = a.shape[1]
    base = int(a.max()) + 1 if a.size else 1
    if base ** k >= 2**62:
        return np.unique(a, axis=0, return_inverse=return_inverse, return_counts=return_counts)
    key = np.zeros(len(a), dtype=np.int64)
    for j in range(k):
        key = key * base + a[:, j]
    res = np.unique(key, return_inverse=return_inverse, return_counts=return_counts)
    if not (return_inverse or return_counts):
        res = (res,)
    uk = res[0]
    rows = np.empty((len(uk), k), dtype=np.int64)
    for j in range(k - 1, -1, -1):
        rows[:, j] = uk % base
        uk = uk // base
    out = (rows, *res[1:])
    return out if len(out) > 1 else out[0]


def euler_characteristic(vertices_count: int, faces) -> int:
    """Euler characteristic χ = V − E + F.

    Parameters
    ----------
    vertices_count : int
        Number of vertices V counted (pass the number of vertices referenced by
        ``faces`` to ignore isolated vertices).
    faces : (F, 3) int array
    """
    f = _faces(faces)
    return int(vertices_count) - len(edges(f)) + len(f)


def connected_components(faces, n_vertices: int | None = None) -> tuple[int, np.ndarray]:
    """Connected components of the mesh's vertex graph.

    Parameters
    ----------
    faces : (F, 3) int array
    n_vertices : int, optional
        Number of vertices (default: ``faces.max() + 1``). Unreferenced vertices form
        components of their own.

    Returns
    -------
    n : int
        Number of components.
    labels : (V,) int array
        Component index per vertex.
    """
    f = _faces(faces)
    n = int(n_vertices) if n_vertices is not None else (int(f.max()) + 1 if len(f) else 0)
    e = edges(f)
    g = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    return _cc(g, directed=False)


def genus(vertices_count: int | None, faces) -> int | np.ndarray:
    """Genus of a closed orientable mesh, g = (2 − χ) / 2 per connected component.

    Parameters
    ----------
    vertices_count : int or None
        Number of vertices (None: ``faces.max() + 1``). Vertices not used by any face
        are ignored.
    faces : (F, 3) int array

    Returns
    -------
    int
        The genus if the mesh is one component, else an int array with the genus of
        each component (components ordered by their label in
        :func:`connected_components`). Meaningful only for closed orientable meshes
        (check :func:`is_closed_manifold`).
    """
    f = _faces(faces)
    n = int(vertices_count) if vertices_count is not None else (int(f.max()) + 1 if len(f) else 0)
    used = np.zeros(n, dtype=bool)
    used[f.ravel()] = True
    ncomp, lab = connected_components(f, n)
    comps = np.unique(lab[used])
    e = edges(f)
    v_per = np.bincount(lab[used], minlength=ncomp)
    e_per = np.bincount(lab[e[:, 0]], minlength=ncomp)
    f_per = np.bincount(lab[f[:, 0]], minlength=ncomp)
    chi = v_per - e_per + f_per
    g = (2 - chi[comps]) // 2
    return int(g[0]) if len(g) == 1 else g.astype(int)


@dataclass(frozen=True)
class ManifoldReport:
    """What :func:`is_closed_manifold` found.

    Attributes
    ----------
    boundary_edges : (B, 2) int array
        Edges used by exactly one face.
    nonmanifold_edges : (N, 2) int array
        Edges used by three or more faces.
    nonmanifold_vertices : (K,) int array
        Vertices whose ring of faces is not one fan (pinch points), among vertices
        whose edges are all manifold.
    inconsistent_edges : (I, 2) int array
        Interior edges whose two faces traverse them in the same direction
        (inconsistent orientation).
    duplicate_faces : int
        Faces with the same vertex set as another face.
    degenerate_faces : int
        Faces that repeat a vertex.
    """

    boundary_edges: np.ndarray
    nonmanifold_edges: np.ndarray
    nonmanifold_vertices: np.ndarray
    inconsistent_edges: np.ndarray
    duplicate_faces: int
    degenerate_faces: int

    @property
    def ok(self) -> bool:
        """True for a closed, edge- and vertex-manifold, consistently oriented mesh."""
        return (
            len(self.boundary_edges) == 0
            and len(self.nonmanifold_edges) == 0
            and len(self.nonmanifold_vertices) == 0
            and len(self.inconsistent_edges) == 0
            and self.duplicate_faces == 0
            and self.degenerate_faces == 0
        )

    def __bool__(self) -> bool:
        return self.ok

    def summary(self) -> str:
        """One line: the counts of every defect."""
        return (
            f"boundary edges {len(self.boundary_edges)}, non-manifold edges {len(self.nonmanifold_edges)}, "
            f"non-manifold vertices {len(self.nonmanifold_vertices)}, inconsistent edges "
            f"{len(self.inconsistent_edges)}, duplicate faces {self.duplicate_faces}, "
            f"degenerate faces {self.degenerate_faces}"
        )


def is_closed_manifold(faces) -> ManifoldReport:
    """Check that a triangle mesh is closed, 2-manifold and consistently oriented.

    Parameters
    ----------
    faces : (F, 3) int array

    Returns
    -------
    ManifoldReport
        Truthy when the mesh is closed and manifold with consistent orientation.
    """
    f = _faces(faces)
    empty = np.zeros((0, 2), dtype=np.int64)
    if len(f) == 0:
        return ManifoldReport(empty, empty, np.zeros(0, np.int64), empty, 0, 0)
    degenerate = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    _, counts_f = _unique_rows(np.sort(f, axis=1), return_counts=True)
    duplicates = int((counts_f[counts_f > 1]).sum())
    directed = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    und = np.sort(directed, axis=1)
    uniq, inv, cnt = _unique_rows(und, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    boundary = uniq[cnt == 1]
    nonmanifold = uniq[cnt >= 3]
    # orientation: on a 2-face edge one face goes a->b (forward = directed[0] < directed[1])
    forward = (directed[:, 0] < directed[:, 1]).astype(np.int64)
    fwd_count = np.bincount(inv, weights=forward, minlength=len(uniq)).astype(np.int64)
    inconsistent = uniq[(cnt == 2) & (fwd_count != 1)]
    # vertex manifoldness: the faces around v form one fan. For each face, the edge
    # opposite v links its two other vertices; the link of v is one cycle iff its
    # (link-vertex, link-edge) graph is connected. Count link components per vertex.
    nv = int(f.max()) + 1
    corner_v = f.ravel()
    # link edges: for face (a,b,c) the link of a is edge (b,c), of b (c,a), of c (a,b)
    opp = np.stack([f[:, [1, 2]], f[:, [2, 0]], f[:, [0, 1]]], axis=1).reshape(-1, 2)
    # nodes of the link graphs: pairs (v, w) with w adjacent to v
    key_a = corner_v * nv + opp[:, 0]
    key_b = corner_v * nv + opp[:, 1]
    keys, inv_k = np.unique(np.concatenate([key_a, key_b]), return_inverse=True)
    m = len(opp)
    g = sp.coo_matrix((np.ones(m), (inv_k[:m], inv_k[m:])), shape=(len(keys), len(keys)))
    ncomp, lab = _cc(g, directed=False)
    owner = keys // nv
    comp_owner = np.zeros(ncomp, dtype=np.int64)
    comp_owner[lab] = owner
    link_components = np.bincount(comp_owner, minlength=nv)
    bad_v = np.flatnonzero(link_components > 1)
    return ManifoldReport(
        boundary_edges=boundary if len(boundary) else empty,
        nonmanifold_edges=nonmanifold if len(nonmanifold) else empty,
        nonmanifold_vertices=bad_v.astype(np.int64),
        inconsistent_edges=inconsistent if len(inconsistent) else empty,
        duplicate_faces=duplicates,
        degenerate_faces=int(degenerate.sum()),
    )


def signed_volume(vertices, faces) -> float:
    """Enclosed volume by the divergence theorem, Σ a · (b × c) / 6.

    Positive for a closed mesh whose faces are oriented outward; in the cube of the
    vertices' unit (mm³ for mm).
    """
    v = np.asarray(vertices, dtype=float)
    f = _faces(faces)
    if len(f) == 0:
        return 0.0
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def face_normals(vertices, faces, normalize: bool = True) -> np.ndarray:
    """(F, 3) face normals ``(b − a) × (c − a)``, unit length unless ``normalize=False``
    (then their length is twice the face area)."""
    v = np.asarray(vertices, dtype=float)
    f = _faces(faces)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    if normalize:
        ln = np.linalg.norm(n, axis=1, keepdims=True)
        n = n / np.where(ln > 0, ln, 1.0)
    return n


def vertex_normals(vertices, faces) -> np.ndarray:
    """(V, 3) unit vertex normals: area-weighted sum of the adjacent face normals."""
    v = np.asarray(vertices, dtype=float)
    f = _faces(faces)
    fn = face_normals(v, f, normalize=False)
    corners = f.ravel()
    out = np.stack(
        [np.bincount(corners, np.repeat(fn[:, c], 3), minlength=len(v)) for c in range(3)], axis=1
    )
    ln = np.linalg.norm(out, axis=1, keepdims=True)
    return out / np.where(ln > 0, ln, 1.0)


# --------------------------------------------------------------------------- PLY I/O
def write_ply(path, vertices, faces, vertex_scalars: dict | None = None, binary: bool = True) -> None:
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
    """
    v = np.asarray(vertices, dtype=np.float32).reshape(-1, 3)
    f = _faces(faces).astype(np.int32)
    scalars = {k: np.asarray(s, dtype=np.float32).ravel() for k, s in (vertex_scalars or {}).items()}
    for k, s in scalars.items():
        if len(s) != len(v):
            raise InputError(f"{path}: vertex scalar '{k}' has {len(s)} values for {len(v)} vertices")
    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0", "comment SSM Builder",
              f"element vertex {len(v)}", "property float x", "property float y", "property float z"]
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
