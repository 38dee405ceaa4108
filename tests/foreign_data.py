"""Data as other tools write it, made from ``../shared/data``: the inputs users bring.

* 3D Slicer (since 4.11): surface meshes in LPS, saying so (``comment SPACE=LPS`` in a PLY
  after ``comment VTK generated PLY File``, ``solid 3D Slicer output. SPACE=LPS`` on an
  ASCII STL's first line, a comment in an OBJ), landmarks in ``.fcsv`` with
  ``CoordinateSystem = LPS``;
* Scalismo: meshes with no statement, landmarks as a JSON list ``{"id", "coordinates",
  "uncertainty"}`` in the frame of the mesh they were clicked on;
* scanner coordinates that differ per subject: every mesh moved by its own rigid transform.

Used by the tests of issue "data as users bring it" and by ``tools/eval_foreign.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

LPS = np.array([-1.0, -1.0, 1.0])


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    n = np.zeros_like(vertices)
    fn = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def slicer_ply(path: Path, vertices_ras: np.ndarray, faces: np.ndarray, space: str | None = "LPS") -> Path:
    """A binary PLY as 3D Slicer writes a model: float x y z and nx ny nz, in ``space`` (None:
    as given, with no statement, as Scalismo and ShapeWorks write)."""
    v = np.asarray(vertices_ras, float) * (LPS if space == "LPS" else 1.0)
    faces = np.asarray(faces)
    n = vertex_normals(v, faces)
    head = ["ply", "format binary_little_endian 1.0", "comment VTK generated PLY File"]
    if space:
        head.append(f"comment SPACE={space}")
    head += [f"element vertex {len(v)}", "property float x", "property float y", "property float z",
             "property float nx", "property float ny", "property float nz", f"element face {len(faces)}",
             "property list uchar int vertex_indices", "end_header"]
    rec = np.empty(len(v), dtype=[("p", "<f4", 3), ("n", "<f4", 3)])
    rec["p"], rec["n"] = v, n
    frec = np.empty(len(faces), dtype=[("k", "u1"), ("i", "<i4", 3)])
    frec["k"], frec["i"] = 3, faces
    path.write_bytes(("\n".join(head) + "\n").encode("ascii") + rec.tobytes() + frec.tobytes())
    return path


def slicer_stl(path: Path, vertices_ras: np.ndarray, faces: np.ndarray, space: str = "LPS") -> Path:
    """An ASCII STL as 3D Slicer writes one (``solid 3D Slicer output. SPACE=LPS``)."""
    v = np.asarray(vertices_ras, float) * (LPS if space == "LPS" else 1.0)
    lines = [f"solid 3D Slicer output. SPACE={space}"]
    for a, b, c in np.asarray(faces):
        nrm = np.cross(v[b] - v[a], v[c] - v[a])
        nrm /= max(np.linalg.norm(nrm), 1e-12)
        lines += [f" facet normal {nrm[0]:.9g} {nrm[1]:.9g} {nrm[2]:.9g}", "  outer loop"]
        lines += [f"   vertex {v[i][0]:.9g} {v[i][1]:.9g} {v[i][2]:.9g}" for i in (a, b, c)]
        lines += ["  endloop", " endfacet"]
    lines.append("endsolid")
    path.write_text("\n".join(lines) + "\n")
    return path


def slicer_obj(path: Path, vertices_ras: np.ndarray, faces: np.ndarray, space: str = "LPS") -> Path:
    """An OBJ with Slicer's statement of its coordinates as a comment."""
    v = np.asarray(vertices_ras, float) * (LPS if space == "LPS" else 1.0)
    lines = ["# wavefront obj file written by the visualization toolkit", f"# SPACE={space}"]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in v]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.asarray(faces)]
    path.write_text("\n".join(lines) + "\n")
    return path


def scalismo_landmarks(path: Path, names, points) -> Path:
    """Scalismo's landmark JSON: no coordinate system, the frame of the mesh clicked on."""
    doc = [{"id": str(n), "coordinates": [float(x) for x in p],
            "uncertainty": {"stddevs": [1.0, 1.0, 1.0], "pcvectors": [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]}}
           for n, p in zip(names, np.asarray(points, float))]
    path.write_text(json.dumps(doc, indent=1))
    return path


def random_rigid(rng: np.random.Generator, *, max_turn_deg: float = 180.0, shift_mm: float = 300.0):
    """A rotation (uniform axis, angle up to ``max_turn_deg``) and a shift (mm, per axis)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.radians(rng.uniform(0.0, max_turn_deg))
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
    return rot, rng.uniform(-shift_mm, shift_mm, size=3)


def label_surface(label_map: Path, label: int):
    """One label's surface as a segmentation tool exports it: marching cubes of the label map
    (world RAS mm, outward triangles), and the label's voxel centres (world mm)."""
    import nibabel as nib
    from skimage.measure import marching_cubes

    img = nib.load(str(label_map))
    mask = np.asarray(img.dataobj) == label
    verts, faces, _n, _v = marching_cubes(np.pad(mask, 1).astype(np.float32), 0.5)
    verts = (verts - 1.0) @ img.affine[:3, :3].T + img.affine[:3, 3]
    if np.linalg.det(img.affine[:3, :3]) < 0:
        faces = faces[:, ::-1]
    return verts, faces, np.argwhere(mask) @ img.affine[:3, :3].T + img.affine[:3, 3]


def deformed_slicer_meshes(folder: Path, label_map: Path, label: int, landmark_file: Path, n: int, prefix: str):
    """One label's surface and ``n - 1`` known smooth deformations of it (those of
    ``tools/eval_correspondence.py deformed``; the first is the identity), each as a 3D Slicer
    LPS PLY ``{prefix}_{k}.ply`` with Scalismo JSON landmarks (``landmark_file``'s, moved by the
    deformation). Returns the names and the project's instance lines."""
    import sys

    from ssm_addon.formats.landmarks import read_landmarks

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
    from eval_correspondence import deformations

    folder.mkdir(parents=True, exist_ok=True)
    verts, faces, voxels = label_surface(label_map, label)
    given = read_landmarks(landmark_file)
    names, lines = [], []
    for k, u in enumerate(deformations(n, 0, voxels)):
        name = f"{prefix}_{k}"
        names.append(name)
        slicer_ply(folder / f"{name}.ply", verts + u(verts), faces)
        scalismo_landmarks(folder / f"{name}.json", given.names, (given.points_world + u(given.points_world)) * LPS)
        lines += ["[[instances]]", f'name = "{name}"', f'mesh = "{name}.ply"', f'landmarks = "{name}.json"', ""]
    return names, lines


def two_subject_level(folder: Path, data_dir: Path, level: str, label: int) -> Path:
    """One lumbar level of two subjects as a 3D Slicer user brings it: verse004's and three known
    deformations of it (:func:`deformed_slicer_meshes`, ``v4_0`` … ``v4_3``, Scalismo landmarks) and
    verse005's (``v5``, no landmarks), the template from ``v4_0``. Returns ``project.toml``."""
    v4 = data_dir / "verse004"
    _names, lines = deformed_slicer_meshes(folder, v4 / "sub-verse004_seg-vert_msk.nii.gz", label,
                                           v4 / "landmarks" / f"{level}.fcsv", 4, "v4")
    verts, faces, _voxels = label_surface(data_dir / "verse005" / "sub-verse005_seg-vert_msk.nii.gz", label)
    slicer_ply(folder / "v5.ply", verts, faces)
    lines += ["[[instances]]", 'name = "v5"', 'mesh = "v5.ply"', ""]
    path = folder / "project.toml"
    path.write_text("\n".join(["[template]", 'instance = "v4_0"', ""] + lines))
    return path


def verse_slicer_meshes(folder: Path, verse_file: Path, labels: dict, landmark_dir: Path, *, fmt: str = "ply",
                        landmarks: str = "scalismo") -> Path:
    """VerSe vertebrae as 3D Slicer exports them: each label's surface (marching cubes in
    world RAS mm, written in LPS with the statement) and its landmarks (``"scalismo"``: a JSON
    list in the mesh's LPS frame; ``"slicer"``: the .fcsv as given). Returns ``project.toml``
    with ``mesh =`` and ``landmarks =`` and nothing else."""

    from ssm_addon.formats.landmarks import read_landmarks

    folder.mkdir(parents=True, exist_ok=True)
    writer = {"ply": slicer_ply, "stl": slicer_stl, "obj": slicer_obj}[fmt]
    lines = []
    for name, label in labels.items():
        verts, faces, _voxels = label_surface(verse_file, label)
        writer(folder / f"{name}.{fmt}", verts, faces)
        given = read_landmarks(landmark_dir / f"{name}.fcsv")  # RAS
        if landmarks == "scalismo":
            lm = scalismo_landmarks(folder / f"{name}.json", given.names, given.points_world * LPS)
        else:
            lm = folder / f"{name}.fcsv"
            lm.write_text((landmark_dir / f"{name}.fcsv").read_text())
        lines += ["[[instances]]", f'name = "{name}"', f'mesh = "{(folder / f"{name}.{fmt}").name}"',
                  f'landmarks = "{lm.name}"', ""]
    path = folder / "project.toml"
    path.write_text("\n".join(lines))
    return path


def knee30_in_scanner_poses(folder: Path, names, vertices, faces, *, landmarks: int = 12, seed: int = 0,
                            max_turn_deg: float = 180.0, template: int = 0, move: bool = True) -> tuple[Path, dict]:
    """knee30 bones, each moved by its own random rigid transform (scanner coordinates differ per
    subject), written as plain PLY (no statement) with Scalismo landmarks at the same vertices
    of every bone (farthest points of the template's vertices); ``move=False`` keeps the data
    set's own poses (the reference). Returns the project and ``{name: (rotation, shift)}``."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    v0 = np.asarray(vertices[template], float)
    chosen = [0]
    d = np.linalg.norm(v0 - v0[0], axis=1)
    for _ in range(landmarks - 1):
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(v0 - v0[i], axis=1))
    moves, lines = {}, []
    for name, v in zip(names, vertices):
        rot, shift = random_rigid(rng, max_turn_deg=max_turn_deg) if move else (np.eye(3), np.zeros(3))
        moved = np.asarray(v, float) @ rot.T + shift
        slicer_ply(folder / f"{name}.ply", moved, faces, space=None)
        scalismo_landmarks(folder / f"{name}.json", [f"P{k}" for k in range(landmarks)], moved[chosen])
        moves[name] = (rot, shift)
        lines += ["[[instances]]", f'name = "{name}"', f'mesh = "{name}.ply"', f'landmarks = "{name}.json"', ""]
    path = folder / "project.toml"
    path.write_text("\n".join(lines))
    return path, moves


def verse_spine_population(folder: Path, verse_file: Path, landmark_dir: Path, labels: dict, *, n: int = 8,
                           seed: int = 0, turn_sd_deg: float = 3.0, shift_sd_mm: float = 1.0) -> tuple[Path, dict]:
    """A lumbar spine population from one VerSe label map: in every subject but the first, each
    vertebra turned about its centroid (``turn_sd_deg`` per axis) and moved (``shift_sd_mm``), so
    the vertebrae's relative poses vary by known amounts. One label map per subject (``volume`` +
    ``labels = { L1 = 20, … }``), landmarks per vertebra as CSV (RAS mm) moved alike. Returns the
    project and ``{subject: {vertebra: (rotation, shift)}}``."""
    import nibabel as nib
    from scipy.ndimage import map_coordinates

    from ssm_addon.formats.landmarks import read_landmarks

    folder.mkdir(parents=True, exist_ok=True)
    img = nib.load(str(verse_file))
    data = np.asarray(img.dataobj).astype(np.int16)
    keep = np.isin(data, list(labels.values()))
    idx = np.argwhere(keep)
    lo = np.maximum(idx.min(axis=0) - 8, 0)
    hi = np.minimum(idx.max(axis=0) + 9, data.shape)
    sub = np.where(keep, data, 0)[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    affine = img.affine.copy()
    affine[:3, 3] = img.affine[:3, :3] @ lo + img.affine[:3, 3]
    inv = np.linalg.inv(affine)
    grid = np.stack(np.meshgrid(*[np.arange(s) for s in sub.shape], indexing="ij"), -1).reshape(-1, 3)
    world = grid @ affine[:3, :3].T + affine[:3, 3]
    given = {name: read_landmarks(landmark_dir / f"{name}.fcsv") for name in labels}
    rng = np.random.default_rng(seed)
    moves, lines = {}, []
    for k in range(n):
        subject = f"sub{k:02d}"
        out = np.zeros(sub.shape, np.int16)
        moves[subject] = {}
        lm_lines = {}
        for name, label in labels.items():
            mask = (sub == label).astype(np.float32)
            centre = (np.argwhere(sub == label) @ affine[:3, :3].T + affine[:3, 3]).mean(axis=0)
            if k == 0:
                rot, shift = np.eye(3), np.zeros(3)
            else:
                angles = np.radians(rng.normal(scale=turn_sd_deg, size=3))
                rot = np.eye(3)
                for axis, a in enumerate(angles):
                    c, s = np.cos(a), np.sin(a)
                    i, j = [(1, 2), (0, 2), (0, 1)][axis]
                    r = np.eye(3)
                    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
                    rot = r @ rot
                shift = rng.normal(scale=shift_sd_mm, size=3)
            moves[subject][name] = (rot, shift)
            src = (world - centre - shift) @ rot + centre  # the source point each target voxel shows
            ijk = src @ inv[:3, :3].T + inv[:3, 3]
            vals = map_coordinates(mask, ijk.T, order=1, mode="constant", cval=0.0).reshape(sub.shape)
            out[(vals >= 0.5) & (out == 0)] = label
            pts = (given[name].points_world - centre) @ rot.T + centre + shift
            lm_path = folder / f"{subject}_{name}.csv"
            lm_path.write_text("".join(f"{nm},{x!r},{y!r},{z!r}\n" for nm, (x, y, z) in zip(given[name].names, pts)))
            lm_lines[name] = lm_path.name
        path = folder / f"{subject}.nii.gz"
        nib.save(nib.Nifti1Image(out, affine), str(path))
        lines += ["[[instances]]", f'name = "{subject}"', f'volume = "{path.name}"',
                  "labels = { " + ", ".join(f"{nm} = {lab}" for nm, lab in labels.items()) + " }",
                  "landmarks = { " + ", ".join(f'{nm} = "{f}"' for nm, f in lm_lines.items()) + " }", ""]
    project = folder / "project.toml"
    project.write_text("\n".join(lines))
    return project, moves


def _log_rotation_for_tests(rot: np.ndarray) -> np.ndarray:
    """The rotation vector of a rotation matrix (small turns), for the truth of a test."""
    angle = float(np.arccos(np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0)))
    if angle < 1e-12:
        return np.zeros(3)
    w = np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    return w / (2.0 * np.sin(angle)) * angle
