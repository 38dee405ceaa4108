"""glTF 2.0 binary (``.glb``): a triangle mesh with morph targets, in metres.

glTF's unit is the metre (spec 3.4, "Coordinate System and Units"), so coordinates in mm
are written scaled by 0.001 and a viewer shows the model at its real size. Each morph
target is a displacement of every vertex (``POSITION`` of the target); its default weight
is 0, so the file opens on the mean shape and a viewer's morph sliders play the modes.

glTF's up axis is +Y (spec 3.4); the model's frames, like Blender's and the scanner's
patient frames, have +Z up (superior). The writer turns the model by -90° about X,
``(x, y, z) -> (x, z, -y)`` (what Blender's own glTF exporter does), so a viewer shows a
vertebra standing as it stands in the body; :func:`read_glb_mesh` turns it back.

References
----------
.. [1] Khronos Group, "glTF 2.0 Specification" (2021): GLB container (chapter 4), meshes
   and morph targets (3.7.2), accessors with ``min``/``max`` required for ``POSITION``.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["MM_TO_M", "Z_UP_TO_Y_UP", "read_glb", "read_glb_mesh", "write_glb"]

MM_TO_M = 0.001

Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""The rotation from the model's frame (+Z up) to glTF's (+Y up): ``p_gltf = Z_UP_TO_Y_UP @ p``."""

_FLOAT, _UINT32 = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


def write_glb(path, points_mm, faces, morph_targets_mm: dict | None = None, *, name: str = "SSM model",
              parts: dict | None = None, display_turn=None) -> Path:
    """Write a mesh and its morph targets as a binary glTF file, coordinates in metres.

    Parameters
    ----------
    path : path
        The ``.glb`` file.
    points_mm : (N, 3) array_like
        Vertex positions, mm, in a right-handed frame with +Z up (written in metres, turned
        by :data:`Z_UP_TO_Y_UP` into glTF's +Y up).
    faces : (F, 3) int array_like
        Triangles, counter-clockwise seen from outside.
    morph_targets_mm : dict name -> (N, 3) array_like, optional
        Displacements (mm) of every vertex, one morph target each (e.g. +1 SD of a mode).
    name : str
        Mesh and node name.
    parts : dict name -> slice, optional
        The structures of a joint model (their vertex ranges): each becomes one primitive of
        the mesh, with its own vertices, triangles (those wholly inside it) and morph targets
        and a material named after it, so the mesh's morph weights, one per target, move every
        structure together, and an importer keeps them apart (Blender: *Separate by Material*).
    display_turn : (3, 3) array_like, optional
        A rotation of the points' frame (``D @ p``) that shows the mesh upright, written as the
        node's ``rotation`` (the vertices stay in the points' frame); None or the identity: none.
    """
    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3) @ Z_UP_TO_Y_UP.T * MM_TO_M
    tris = np.asarray(faces, dtype=np.uint32).reshape(-1, 3)
    targets = {k: np.asarray(v, dtype=np.float64).reshape(-1, 3) @ Z_UP_TO_Y_UP.T * MM_TO_M
               for k, v in (morph_targets_mm or {}).items()}
    blobs, views, accessors = [], [], []

    def add(array: np.ndarray, component: int, kind: str, target=None, bounds=False) -> int:
        data = np.ascontiguousarray(array).tobytes()
        offset = sum(len(b) for b in blobs)
        blobs.append(data + b"\0" * (-len(data) % 4))
        view = {"buffer": 0, "byteOffset": offset, "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        views.append(view)
        acc = {"bufferView": len(views) - 1, "componentType": component, "count": int(array.shape[0]),
               "type": kind}
        if bounds:
            acc["min"] = [float(v) for v in array.min(axis=0)]
            acc["max"] = [float(v) for v in array.max(axis=0)]
        accessors.append(acc)
        return len(accessors) - 1

    ranges = {None: slice(0, len(pts))} if not parts else dict(parts)
    primitives, materials = [], []
    for part, sl in ranges.items():
        inside = (tris >= sl.start).all(axis=1) & (tris < sl.stop).all(axis=1) if part is not None else slice(None)
        position = add(pts[sl].astype(np.float32), _FLOAT, "VEC3", _ARRAY_BUFFER, bounds=True)
        these = tris[inside] - np.uint32(sl.start)
        indices = add(these.reshape(-1, 1), _UINT32, "SCALAR", _ELEMENT_ARRAY_BUFFER)
        accessors[indices]["count"] = int(these.size)
        primitive = {"attributes": {"POSITION": position}, "indices": indices, "mode": 4}
        if part is not None:
            primitive["material"] = len(materials)
            primitive["extras"] = {"structure": str(part)}
            materials.append({"name": str(part)})
        if targets:
            primitive["targets"] = [{"POSITION": add(t[sl].astype(np.float32), _FLOAT, "VEC3", _ARRAY_BUFFER,
                                                     bounds=True)} for t in targets.values()]
        primitives.append(primitive)
    mesh = {"name": name, "primitives": primitives}
    if targets:
        mesh["weights"] = [0.0] * len(targets)
        mesh["extras"] = {"targetNames": list(targets)}  # the names viewers show on the sliders
    binary = b"".join(blobs)
    doc = {"asset": {"version": "2.0", "generator": "SSM Builder"}, "scene": 0,
           "scenes": [{"nodes": [0]}], "nodes": [_node(name, display_turn)], "meshes": [mesh],
           "accessors": accessors, "bufferViews": views, "buffers": [{"byteLength": len(binary)}],
           "extras": {"unit": "metre (the model's mm times 0.001)",
                      "up": "+Y, glTF's (the model's +Z: (x, y, z) written as (x, z, -y))"}}
    if materials:
        doc["materials"] = materials
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    out = struct.pack("<III", 0x46546C67, 2, 12 + 8 + len(text) + 8 + len(binary))
    out += struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(binary), 0x004E4942) + binary
    path = Path(path)
    path.write_bytes(out)
    return path


def _node(name: str, display_turn) -> dict:
    """The mesh's node, with ``display_turn`` (model frame) as its rotation in glTF's frame."""
    node = {"mesh": 0, "name": name}
    if display_turn is not None and not np.allclose(display_turn, np.eye(3)):
        turn = Z_UP_TO_Y_UP @ np.asarray(display_turn, float) @ Z_UP_TO_Y_UP.T
        node["rotation"] = [float(round(v, 12)) + 0.0 for v in Rotation.from_matrix(turn).as_quat()]  # x, y, z, w
    return node


def read_glb(path) -> tuple[dict, bytes]:
    """The JSON document and the binary chunk of a ``.glb`` file (for checks and tests)."""
    raw = Path(path).read_bytes()
    magic, version, length = struct.unpack_from("<III", raw, 0)
    if magic != 0x46546C67 or version != 2 or length != len(raw):
        raise ValueError(f"{path}: not a glTF 2.0 binary file")
    n, kind = struct.unpack_from("<II", raw, 12)
    doc = json.loads(raw[20:20 + n])
    m, _ = struct.unpack_from("<II", raw, 20 + n)
    return doc, raw[28 + n:28 + n + m]


def read_glb_mesh(path) -> tuple[np.ndarray, np.ndarray, dict]:
    """A ``.glb`` written by :func:`write_glb` back in the model's frame and unit.

    Returns
    -------
    points_mm : (N, 3) float ndarray
        Vertices, mm, +Z up (every primitive's, in order).
    faces : (F, 3) int ndarray
        Triangles, indexing ``points_mm``.
    morph_targets_mm : dict name -> (N, 3) float ndarray
        Displacements, mm, +Z up, by the names of ``extras.targetNames``.
    """
    doc, binary = read_glb(path)

    def array(index: int, width: int, dtype) -> np.ndarray:
        acc = doc["accessors"][index]
        view = doc["bufferViews"][acc["bufferView"]]
        start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        return np.frombuffer(binary, dtype, acc["count"] * width, start).reshape(-1, width) if width > 1 else \
            np.frombuffer(binary, dtype, acc["count"], start)

    mesh = doc["meshes"][0]
    names = mesh.get("extras", {}).get("targetNames", [])
    to_model = Z_UP_TO_Y_UP / MM_TO_M  # p_model = p_gltf @ (Z_UP_TO_Y_UP / 0.001), the transpose of the inverse
    points, faces, targets, offset = [], [], {n: [] for n in names}, 0
    for prim in mesh["primitives"]:
        pos = array(prim["attributes"]["POSITION"], 3, "<f4").astype(np.float64)
        points.append(pos @ to_model)
        faces.append(array(prim["indices"], 1, "<u4").astype(np.int64).reshape(-1, 3) + offset)
        for name, t in zip(names, prim.get("targets", [])):
            targets[name].append(array(t["POSITION"], 3, "<f4").astype(np.float64) @ to_model)
        offset += len(pos)
    return np.concatenate(points), np.concatenate(faces), {n: np.concatenate(v) for n, v in targets.items() if v}
