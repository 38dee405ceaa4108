"""Import stage (paper section 2): readers, object frame, resampling, mesh voxelization."""

from __future__ import annotations

import gzip
import json
import re
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT, VERSE_FILE, VERSE_LABELS, icosphere, write_stl_binary

from ssm_addon import meshutil as mu
from ssm_addon.base.errors import InputError
from ssm_addon.formats import label_maps as IO
from ssm_addon.formats import meshes
from ssm_addon.instances import frame as FR
from ssm_addon.instances import importing as INS
from ssm_addon.instances import resampling as RS
from ssm_addon.instances import volume as V
from ssm_addon.instances import voxelize as VX

# ----------------------------------------------------------------------------- fixtures


def rotation(rx_deg: float, ry_deg: float, rz_deg: float) -> np.ndarray:
    """Rotation Rz @ Ry @ Rx (degrees)."""
    x, y, z = np.radians([rx_deg, ry_deg, rz_deg])
    Rx = np.array([[1, 0, 0], [0, np.cos(x), -np.sin(x)], [0, np.sin(x), np.cos(x)]])
    Ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    Rz = np.array([[np.cos(z), -np.sin(z), 0], [np.sin(z), np.cos(z), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


SEMI_AXES = np.array([13.0, 9.0, 6.0])  # along R, A, S before rotation, mm
OBJ_ROT = rotation(12.0, -9.0, 17.0)  # object axes in world (columns)
GRID_ROT = rotation(-8.0, 5.0, 25.0)  # oblique voxel grid directions
SPACING = np.array([0.8, 1.1, 1.5])
CENTRE = np.array([-31.3, 12.7, 101.9])


def ellipsoid_affine(shape=(46, 42, 30)) -> np.ndarray:
    """Oblique, anisotropic affine whose grid centre sits near CENTRE."""
    A = np.eye(4)
    A[:3, :3] = GRID_ROT * SPACING
    A[:3, 3] = CENTRE - A[:3, :3] @ ((np.array(shape) - 1) / 2) + np.array([0.37, -0.21, 0.13])
    return A


def ellipsoid_mask(affine, shape=(46, 42, 30), rot=OBJ_ROT, semi=SEMI_AXES, centre=CENTRE, egg=False):
    """Voxel centres inside the ellipsoid (egg: the +x half is 1.3x longer)."""
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1).reshape(-1, 3)
    world = ijk @ affine[:3, :3].T + affine[:3, 3]
    local = (world - centre) @ rot
    semi = np.broadcast_to(semi, local.shape).copy()
    if egg:
        semi[local[:, 0] > 0, 0] *= 1.3
    return ((local / semi) ** 2).sum(axis=1).reshape(shape) <= 1.0


@pytest.fixture(scope="module")
def ellipsoid():
    A = ellipsoid_affine()
    return V.Volume(mask=ellipsoid_mask(A), affine=A, source="ellipsoid")


def write_stl_ascii(path, v, f):
    lines = ["solid ico"]
    for t in f:
        lines += ["facet normal 0 0 0", " outer loop"]
        lines += [f"  vertex {x:.9g} {y:.9g} {z:.9g}" for x, y, z in v[t]]
        lines += [" endloop", "endfacet"]
    lines.append("endsolid ico")
    path.write_text("\n".join(lines) + "\n")


def write_ply(path, v, f, binary):
    head = [
        "ply",
        f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
        f"element vertex {len(v)}",
        "property float x",
        "property float y",
        "property float z",
        f"element face {len(f)}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    if binary:
        vert = v.astype("<f4").tobytes()
        rec = np.zeros(len(f), dtype=[("n", "u1"), ("i", "<i4", 3)])
        rec["n"], rec["i"] = 3, f
        path.write_bytes(("\n".join(head) + "\n").encode() + vert + rec.tobytes())
    else:
        body = [f"{x:.9g} {y:.9g} {z:.9g}" for x, y, z in v] + [f"3 {a} {b} {c}" for a, b, c in f]
        path.write_text("\n".join(head + body) + "\n")


def write_obj_quads_negative(path, v, f):
    """OBJ whose faces use negative (relative) indices and some quads (pairs of triangles)."""
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in v]
    n = len(v)
    lines += ["f " + " ".join(f"{i - n}/1/1" for i in t) for t in f]
    path.write_text("\n".join(lines) + "\n")


# ----------------------------------------------------------------------------- packaging


def test_core_imports_without_bpy():
    code = "import sys; sys.modules['bpy'] = None; import ssm_addon, ssm_addon.instances.volume; print('ok')"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


# ----------------------------------------------------------------------------- readers


@pytest.mark.parametrize("ext", [".nii.gz", ".nii", ".nrrd", ".nhdr", ".mha", ".mhd", ".npz"])
def test_every_reader_round_trips_oblique_anisotropic_affine(tmp_path, ellipsoid, ext):
    labels = ellipsoid.mask.astype(np.uint8) * 7
    labels[0, 0, 0] = 3  # a second label at the corner: orientation of the array matters
    path = IO.write_label_map(tmp_path / f"ell{ext}", labels, ellipsoid.affine)
    lm = IO.read_label_map(path)
    assert lm.labels.shape == labels.shape
    np.testing.assert_array_equal(lm.labels, labels)
    np.testing.assert_allclose(lm.affine, ellipsoid.affine, atol=1e-5)
    assert IO.label_counts(lm) == {3: 1, 7: int(ellipsoid.mask.sum())}


def test_npy_takes_spacing_from_caller_or_sidecar(tmp_path):
    labels = np.zeros((5, 6, 7), np.int16)
    labels[1:3, 2:4, 3:6] = 2
    np.save(tmp_path / "a.npy", labels)
    lm = IO.read_label_map(tmp_path / "a.npy", spacing_mm=(0.5, 0.7, 2.0))
    np.testing.assert_allclose(lm.affine, np.diag([0.5, 0.7, 2.0, 1.0]))
    with pytest.raises(InputError, match=r"a\.npy: .*no voxel size"):
        IO.read_label_map(tmp_path / "a.npy")
    (tmp_path / "a.json").write_text(json.dumps({"spacing_mm": [1.5, 1.5, 3.0]}))
    lm = IO.read_label_map(tmp_path / "a.npy")
    np.testing.assert_allclose(lm.affine, np.diag([1.5, 1.5, 3.0, 1.0]))
    assert IO.label_counts(lm) == {2: 12}


def test_npz_with_spacing_and_float_labels_are_rounded(tmp_path):
    labels = np.zeros((4, 4, 4))
    labels[1:3, 1:3, 1:3] = 19.0000001
    np.savez(tmp_path / "f.npz", labels=labels, spacing=np.array([1.0, 2.0, 3.0]))
    lm = IO.read_label_map(tmp_path / "f.npz")
    assert lm.labels.dtype.kind in "iu"
    assert IO.label_counts(lm) == {19: 8}
    np.testing.assert_allclose(lm.affine, np.diag([1.0, 2.0, 3.0, 1.0]))


def test_nrrd_in_ras_space_is_not_flipped(tmp_path):
    import nrrd

    labels = np.zeros((4, 5, 6), np.uint8)
    labels[1, 2, 3] = 1
    nrrd.write(
        str(tmp_path / "r.nrrd"),
        labels,
        {"space": "right-anterior-superior", "space directions": np.diag([0.5, 0.6, 0.7]), "space origin": [1, 2, 3]},
    )
    lm = IO.read_label_map(tmp_path / "r.nrrd")
    expected = np.diag([0.5, 0.6, 0.7, 1.0])
    expected[:3, 3] = [1, 2, 3]
    np.testing.assert_allclose(lm.affine, expected)


def test_metaimage_lps_header_written_by_hand_is_converted_to_ras(tmp_path):
    """A MetaImage as ITK writes it: LPS world, TransformMatrix rows = axis directions."""
    labels = np.zeros((3, 4, 5), np.int16)
    labels[2, 1, 4] = 5
    header = (
        "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = True\n"
        "CompressedData = False\nTransformMatrix = 0 1 0 -1 0 0 0 0 1\nOffset = 10 20 30\n"
        "AnatomicalOrientation = RAI\nElementSpacing = 2 3 4\nDimSize = 3 4 5\n"
        "ElementType = MET_SHORT\nElementDataFile = LOCAL\n"
    )
    (tmp_path / "h.mha").write_bytes(header.encode() + labels.astype(">i2").ravel(order="F").tobytes())
    lm = IO.read_label_map(tmp_path / "h.mha")
    np.testing.assert_array_equal(lm.labels, labels)
    # voxel (2, 1, 4): LPS = offset + 2*2*(0,1,0) + 1*3*(-1,0,0) + 4*4*(0,0,1) = (7, 24, 46)
    world = lm.affine @ np.array([2, 1, 4, 1.0])
    np.testing.assert_allclose(world[:3], [-7.0, -24.0, 46.0])


# ----------------------------------------------------------------------------- object frame


def test_ellipsoid_frame_recovers_centre_and_axes(ellipsoid):
    frame = FR.object_frame(ellipsoid)
    assert frame.method == "patient"
    assert np.linalg.norm(frame.origin_world - CENTRE) < 0.5 * SPACING.min()
    cos = np.abs(np.sum(frame.axes_world * OBJ_ROT, axis=0))
    assert np.all(cos > 0.999), cos
    assert np.linalg.det(frame.axes_world) == pytest.approx(1.0)
    np.testing.assert_allclose(frame.axes_world.T @ frame.axes_world, np.eye(3), atol=1e-12)
    # second moments of a solid ellipsoid: a²/5
    np.testing.assert_allclose(frame.second_moments_mm2, SEMI_AXES**2 / 5, rtol=0.03)


def test_moments_frame_orders_by_eigenvalue_and_is_right_handed(ellipsoid):
    frame = FR.object_frame(ellipsoid, "moments")
    assert frame.method == "moments"
    assert np.all(np.diff(frame.second_moments_mm2) < 0)
    assert np.linalg.det(frame.axes_world) == pytest.approx(1.0)
    cos = np.abs(np.sum(frame.axes_world * OBJ_ROT, axis=0))  # semi-axes are already descending
    assert np.all(cos > 0.999)


def _perturbed(volume, rng, n=15):
    from scipy import ndimage

    mask = volume.mask.copy()
    surface = np.argwhere(mask & ~ndimage.binary_erosion(mask))
    outside = np.argwhere(ndimage.binary_dilation(mask) & ~mask)
    for pts, value in ((surface, False), (outside, True)):
        pick = pts[rng.choice(len(pts), n, replace=False)]
        mask[tuple(pick.T)] = value
    return V.Volume(mask=mask, affine=volume.affine, source="perturbed")


@pytest.mark.parametrize("method,egg", [("patient", False), ("moments", True)])
def test_frames_do_not_flip_under_small_perturbations(method, egg):
    A = ellipsoid_affine()
    base = V.Volume(mask=ellipsoid_mask(A, egg=egg), affine=A, source="egg" if egg else "ellipsoid")
    ref = FR.object_frame(base, method).axes_world
    rng = np.random.default_rng(4)
    variants = [_perturbed(base, rng) for _ in range(3)]
    for angles in ((2, 0, 0), (0, -2, 0), (0, 0, 2)):
        rot = rotation(*angles) @ OBJ_ROT
        variants.append(V.Volume(mask=ellipsoid_mask(A, rot=rot, egg=egg), affine=A, source="rotated"))
    for var in variants:
        axes = FR.object_frame(var, method).axes_world
        dots = np.sum(axes * ref, axis=0)
        assert np.all(dots > 0.99), (var.source, dots)


def test_patient_frame_pairs_axes_with_r_a_s_even_when_eigenvalues_reorder():
    """Eigenvalue order changes (a long S axis) but object x, y, z stay with R, A, S."""
    A = np.diag([1.0, 1.0, 1.0, 1.0])
    shape = (40, 40, 40)
    A[:3, 3] = -19.5
    for semi in ((15.0, 9.0, 6.0), (6.0, 9.0, 15.0), (9.0, 15.0, 6.0)):
        rot = rotation(5, -4, 6)
        vol = V.Volume(mask=ellipsoid_mask(A, shape, rot=rot, semi=np.array(semi), centre=np.zeros(3)), affine=A)
        axes = FR.object_frame(vol, "patient").axes_world
        assert np.all(np.sum(axes * rot, axis=0) > 0.999), (semi, axes)


def _egg_mesh():
    """A closed egg (an icosphere stretched to semi-axes 13, 9, 6 mm, longer towards +x, +y and +z: skewed
    along every axis), turned by ``OBJ_ROT`` about ``CENTRE``: outward triangles, vertices world mm."""
    v, f = icosphere(1.0, 4)
    v = v * SEMI_AXES * np.where(v > 0, [1.5, 1.35, 1.2], 1.0)
    return v @ OBJ_ROT.T + CENTRE, f


def test_a_closed_meshs_frame_is_its_solids_exact_moments_and_moves_with_it():
    """The frame of a closed mesh is its solid's (exact integrals over the triangles, not a
    voxelization): a cube's centre and moments (a²/12) to rounding; the same whichever way its
    triangles turn; the frame of a moved mesh is the moved frame (to 1e-9), so its object
    grid is the same voxels in any scanner pose; and it agrees with the voxelized solid's frame
    (centre within 0.05 mm, axes within 0.5°, moments 1 %)."""
    from scipy.spatial import ConvexHull

    corners = np.array([[x, y, z] for x in (-1, 5) for y in (2, 4) for z in (0, 3)], float)
    hull = ConvexHull(corners).simplices  # qhull's triangles turn either way: outwards
    tri = corners[hull]
    inward = np.einsum("ij,ij->i", np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), tri.mean(axis=1) - corners.mean(axis=0)) < 0
    hull[inward] = hull[inward][:, ::-1]
    box = FR.mesh_solid_frame(corners, hull)
    np.testing.assert_allclose(box.origin_world, [2.0, 3.0, 1.5], atol=1e-12)
    np.testing.assert_allclose(box.second_moments_mm2, [36 / 12, 9 / 12, 4 / 12], atol=1e-9)  # rounded to 1e-9 mm²
    np.testing.assert_allclose(np.abs(box.axes_world), [[1, 0, 0], [0, 0, 1], [0, 1, 0]], atol=1e-12)
    v, f = _egg_mesh()
    frame = FR.mesh_solid_frame(v, f)
    inward = FR.mesh_solid_frame(v, f[:, ::-1])
    np.testing.assert_allclose(inward.axes_world, frame.axes_world, atol=1e-12)
    rot, shift = rotation(130.0, -40.0, 75.0), np.array([180.0, -250.0, 40.0])
    moved = FR.mesh_solid_frame(v @ rot.T + shift, f)
    np.testing.assert_allclose(moved.origin_world, rot @ frame.origin_world + shift, atol=1e-9)
    np.testing.assert_allclose(moved.axes_world, rot @ frame.axes_world, atol=1e-9)
    a = INS.object_from_mesh(v, f, spacing_mm=0.5)
    b = INS.object_from_mesh(v @ rot.T + shift, f, spacing_mm=0.5)
    np.testing.assert_array_equal(a.mask, b.mask)
    np.testing.assert_allclose(a.origin_object, b.origin_object)
    voxels = FR.object_frame(VX.voxelize_mesh(v, f, 0.25), "moments")
    assert np.linalg.norm(voxels.origin_world - frame.origin_world) < 0.05
    assert np.all(np.sum(voxels.axes_world * frame.axes_world, axis=0) > np.cos(np.radians(0.5)))
    np.testing.assert_allclose(voxels.second_moments_mm2, frame.second_moments_mm2, rtol=0.01)


def test_a_mesh_that_bounds_no_solid_is_refused_by_name():
    """The exact moments need a closed mesh: an open one is refused as the voxelization refused it
    (naming the file and its boundary edges), and so is a closed one that bounds no volume."""
    v, f = _egg_mesh()
    with pytest.raises(InputError, match=r"egg\.ply: the mesh is not closed and watertight \(3 boundary edges"):
        INS.mesh_frame(v, f[1:], spacing_mm=0.5, source="egg.ply")
    flat = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    faces = np.array([[0, 1, 2], [1, 3, 2], [0, 2, 1], [1, 2, 3]])
    with pytest.raises(InputError, match="no volume"):
        FR.mesh_solid_frame(flat, faces)
    with pytest.raises(InputError, match="flat.ply"):
        INS.mesh_frame(flat, faces, spacing_mm=0.5, source="flat.ply")


# ----------------------------------------------------------------------------- resampling


def test_resampling_preserves_volume_and_leaves_background_border(ellipsoid):
    frame = FR.object_frame(ellipsoid)
    for spacing in (1.0, 0.7):
        ov = RS.resample(ellipsoid, frame, spacing)
        assert ov.volume_mm3 == pytest.approx(ellipsoid.volume_mm3, rel=0.01)
        assert ov.volume_mm3 == pytest.approx(4 / 3 * np.pi * np.prod(SEMI_AXES), rel=0.02)
        m = ov.mask
        for axis in range(3):
            assert not m.take([0, 1, -2, -1], axis=axis).any()
        # the object is centred on its frame origin, axes along the grid
        ijk = np.argwhere(m)
        centre_object = ov.voxel_to_object(ijk).mean(axis=0)
        assert np.linalg.norm(centre_object) < 0.5 * spacing
        extent = ov.voxel_to_object(ijk).max(axis=0)
        np.testing.assert_allclose(extent, SEMI_AXES, atol=1.5 * spacing)


def test_mask_touching_the_volume_border_still_resamples():
    A = np.diag([1.0, 1.0, 2.0, 1.0])
    ijk = np.stack(np.meshgrid(np.arange(20), np.arange(20), np.arange(8), indexing="ij"), axis=-1)
    world = ijk @ A[:3, :3].T
    mask = np.linalg.norm(world - [3.3, 9.6, 7.3], axis=-1) <= 9.0  # cut by three faces of the volume
    assert mask[0].any() and mask[:, :, 0].any() and mask[:, :, -1].any()
    vol = V.Volume(mask=mask, affine=A, source="border")
    ov = RS.resample(vol, FR.object_frame(vol), 1.0)
    assert ov.volume_mm3 == pytest.approx(vol.volume_mm3, rel=0.01)
    assert not ov.mask[[0, -1]].any() and not ov.mask[:, [0, -1]].any() and not ov.mask[:, :, [0, -1]].any()
    verts, faces = V.display_surface(vol)
    assert VX.mesh_edge_defects(faces) == (0, 0, 0)
    assert mu.signed_volume(verts, faces) == pytest.approx(vol.volume_mm3, rel=0.05)


def test_display_surface_is_outward_in_world_and_object_mm(ellipsoid):
    verts, faces = V.display_surface(ellipsoid)
    assert mu.signed_volume(verts, faces) == pytest.approx(ellipsoid.volume_mm3, rel=0.03)
    np.testing.assert_allclose(verts.mean(axis=0), CENTRE, atol=0.5)
    ov = RS.resample(ellipsoid, FR.object_frame(ellipsoid), 1.0)
    vo, fo = V.display_surface(ov)
    assert mu.signed_volume(vo, fo) > 0
    assert np.linalg.norm(vo.mean(axis=0)) < 0.5
    vw, _ = V.display_surface(ov, to_world=True)
    np.testing.assert_allclose(vw, ov.frame.to_world(vo))


def test_summary_reports_voxels_volume_and_bbox(ellipsoid):
    s = V.summary(ellipsoid)
    assert s["voxels"] == int(ellipsoid.mask.sum())
    assert s["volume_mm3"] == pytest.approx(ellipsoid.volume_mm3)
    np.testing.assert_allclose(s["spacing_mm"], SPACING)
    assert np.all(np.array(s["bbox_min"]) < CENTRE) and np.all(np.array(s["bbox_max"]) > CENTRE)


# ----------------------------------------------------------------------------- meshes


@pytest.mark.parametrize("fmt", ["stl-binary", "stl-ascii", "ply-ascii", "ply-binary", "obj"])
def test_voxelized_icosphere_has_the_analytic_mesh_volume(tmp_path, fmt):
    v, f = icosphere(20.0, 3)
    v = v + np.array([3.3, -7.1, 12.4])
    analytic = mu.signed_volume(v, f)
    path = tmp_path / ("ico." + fmt.split("-")[0])
    {
        "stl-binary": write_stl_binary,
        "stl-ascii": write_stl_ascii,
        "ply-ascii": lambda p, v, f: write_ply(p, v, f, False),
        "ply-binary": lambda p, v, f: write_ply(p, v, f, True),
        "obj": write_obj_quads_negative,
    }[fmt](path, v, f)
    rv, rf = meshes.read_mesh(path)
    assert len(rv) == len(v) and len(rf) == len(f)
    assert mu.signed_volume(rv, rf) == pytest.approx(analytic, rel=1e-5)
    vol = VX.load_mesh_volume(path, 1.0)
    assert not vol.patient_oriented
    assert vol.volume_mm3 == pytest.approx(analytic, rel=0.02)
    ov = INS.load_object(path, spacing_mm=1.0)
    assert ov.frame.method == "moments"
    assert ov.volume_mm3 == pytest.approx(analytic, rel=0.02)


def test_obj_polygons_are_triangulated(tmp_path):
    cube = "\n".join(
        ["v 0 0 0", "v 1 0 0", "v 1 1 0", "v 0 1 0", "v 0 0 1", "v 1 0 1", "v 1 1 1", "v 0 1 1"]
        + ["f 1 4 3 2", "f 5 6 7 8", "f 1 2 6 5", "f 2 3 7 6", "f 3 4 8 7", "f 4 1 5 8"]
    )
    (tmp_path / "c.obj").write_text(cube + "\n")
    v, f = meshes.read_mesh(tmp_path / "c.obj")
    assert f.shape == (12, 3)
    assert VX.mesh_edge_defects(f) == (0, 0, 0)
    assert mu.signed_volume(v * 10, f) == pytest.approx(1000.0)


def test_voxelizing_a_cube_whose_edges_and_vertices_hit_voxel_centres_is_exact():
    """Vertices on voxel centres, faces through centre rows: ties must be counted once."""
    v = np.array([[x, y, z] for x in (0, 10) for y in (0, 10) for z in (0, 10)], float)
    f = np.array(
        [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    )  # fmt: skip
    assert mu.signed_volume(v, f) == pytest.approx(1000.0)
    for spacing in (1.0, 0.5, 2.0, 2.5):
        vol = VX.voxelize_mesh(v, f, spacing)
        assert vol.volume_mm3 == pytest.approx(1000.0), spacing
    # a diagonal split through centres of the z faces (the triangles' shared edge) too
    vol = VX.voxelize_mesh(v + 0.0, f[:, ::-1], 1.0)  # inward faces: parity does not care
    assert vol.volume_mm3 == pytest.approx(1000.0)


SPUR_DIRECTION = np.array([1.0, 0.8, 0.5]) / np.linalg.norm([1.0, 0.8, 0.5])  # oblique to the ellipsoid's axes


def ellipsoid_with_spur(radius_mm: float, length_mm: float = 16.0, step_mm: float = 0.25, *, pit: bool = False):
    """A closed mesh (mm): an ellipsoid of semi-axes 12, 8, 6 mm and a rod of ``radius_mm``
    from its centre along SPUR_DIRECTION to ``length_mm`` (about 6 mm beyond its surface), the
    zero set of the union's distance field traced at ``step_mm``. ``pit``: the rod runs from
    ``length_mm`` outward and is cut out of the ellipsoid, a hole from its surface to
    ``length_mm`` from its centre."""
    from skimage.measure import marching_cubes

    semi_axes = np.array([12.0, 8.0, 6.0])
    p = np.stack(np.meshgrid(*[np.arange(-20.0, 20.0, step_mm)] * 3, indexing="ij"), axis=-1)
    ellipsoid = (np.linalg.norm(p / semi_axes, axis=-1) - 1.0) * semi_axes.min()
    along = np.clip(p @ SPUR_DIRECTION, *((length_mm, 40.0) if pit else (0.0, length_mm)))
    rod = np.linalg.norm(p - along[..., None] * SPUR_DIRECTION, axis=-1) - radius_mm
    field = np.maximum(ellipsoid, -rod) if pit else np.minimum(ellipsoid, rod)
    v, f, _n, _v = marching_cubes(field.astype(np.float32), 0.0, spacing=(step_mm,) * 3)
    return v - 20.0, f[:, ::-1]


def _tip_from_voxel_surface(mask, voxel_to_object, tip_object):
    """Distance (mm) from ``tip_object`` to the marching-cubes surface of the mask's largest part
    (its cavities filled), and the mask's count of face-connected parts."""
    from scipy import ndimage

    labels, parts = ndimage.label(mask)
    body = ndimage.binary_fill_holes(labels == 1 + np.argmax(np.bincount(labels.ravel())[1:]))
    gv, gf = mu.marching_cubes(body)
    return mu.MeshLocator(voxel_to_object(gv), gf).query(tip_object[None], k=12)[1][0], parts


def _import_against_plain(v, f, end_mm, along_mm):
    """The import of mesh ``(v, f)`` at 1 mm and the plain voxelization on its object grid: the
    distances (mm) of the rod's end, ``end_mm`` along SPUR_DIRECTION, from both voxel surfaces,
    the import's count of face-connected parts, and the voxels that changed side, as (added,
    taken away, their largest distance (mm) from the rod's axis between ``along_mm``)."""
    ov = INS.object_from_mesh(v, f, spacing_mm=1.0, frame_method="moments")
    end = ov.frame.to_object(end_mm * SPUR_DIRECTION)
    plain = VX.voxelize_mesh(ov.frame.to_object(v), f, 1.0)
    before_mm, _ = _tip_from_voxel_surface(plain.mask, lambda g: g + plain.affine[:3, 3], end)
    now_mm, parts = _tip_from_voxel_surface(ov.mask, ov.voxel_to_object, end)
    # the same grid (both start at multiples of the spacing)
    offset = np.rint(ov.origin_object - plain.affine[:3, 3]).astype(int)
    before = plain.mask[tuple(slice(o, o + n) for o, n in zip(offset, ov.mask.shape))]
    changed = ov.voxel_to_object(np.argwhere(before != ov.mask))
    centre = ov.frame.to_object(np.zeros((1, 3)))[0]
    axis = ov.frame.to_object(SPUR_DIRECTION[None])[0] - centre
    along = np.clip((changed - centre) @ axis, *along_mm)
    off_axis = np.linalg.norm(changed - centre - along[:, None] * axis, axis=1)
    to_mesh = mu.MeshLocator(ov.frame.to_object(v), f).query(changed, k=12)[1]
    added, taken = int((ov.mask & ~before).sum()), int((before & ~ov.mask).sum())
    return before_mm, now_mm, parts, added, taken, off_axis.max(initial=0.0), to_mesh.max(initial=0.0)


@pytest.mark.parametrize("radius", [0.25, 0.35])
def test_a_spur_thinner_than_a_voxel_is_kept_by_the_mesh_import(radius):
    """A rod 0.5-0.7 mm across encloses almost no voxel centre at 1 mm: voxelized plainly, its
    6 mm beyond the ellipsoid are lost (a few centres, apart from the object); the import puts it
    back, joined to the object, its tip within 1/sqrt(3) voxel of the voxel surface, and adds
    voxels nowhere else (on the rod, and at its root on the ellipsoid's skin)."""
    lost, kept, parts, added, taken, off_axis, to_mesh = _import_against_plain(*ellipsoid_with_spur(radius), 16.0,
                                                                               (0.0, 16.0))
    assert lost > 5.0 and kept < 0.6 and parts == 1
    assert added >= 6 and taken == 0
    assert off_axis < 3.0  # the rod, and at its root a few voxels of the ellipsoid's skin
    assert to_mesh <= np.sqrt(3.0) / 2  # voxels the mesh passes through


def test_a_pit_narrower_than_a_voxel_is_opened_by_the_mesh_import():
    """A hole 0.6 mm across, 6 mm deep (its floor 3 mm from the ellipsoid's centre), holds no
    voxel centre of the outside at 1 mm (or one, apart): voxelized plainly it is filled, its
    floor more than 3 mm under the voxel surface; the import opens it to within 1/sqrt(3) voxel
    of its floor, and takes voxels away only along it."""
    filled, opened, parts, added, taken, off_axis, to_mesh = _import_against_plain(
        *ellipsoid_with_spur(0.3, 3.0, pit=True), 3.0, (3.0, 40.0))
    assert filled > 3.0 and opened < 0.6 and parts == 1
    assert taken >= 3 and added == 0
    assert off_axis < 3.0 and to_mesh <= np.sqrt(3.0) / 2


def test_the_import_adds_no_voxel_where_every_part_is_thicker_than_a_voxel():
    """A rod 3 mm across and a smooth sphere: the mask is the plain voxelization's, the same array."""
    v, f = ellipsoid_with_spur(1.5)
    grid = VX.voxelize_mesh(v, f, 1.0)
    kept, added, opened = VX.keep_thin_parts(grid.mask, v - grid.affine[:3, 3], f)
    assert added == opened == 0 and kept is grid.mask
    v, f = icosphere(20.0, 4)
    grid = VX.voxelize_mesh(v + np.array([0.31, -0.47, 0.12]), f, 1.0)
    assert VX.keep_thin_parts(grid.mask, v + np.array([0.31, -0.47, 0.12]) - grid.affine[:3, 3], f)[1:] == (0, 0)


# ----------------------------------------------------------------------------- VerSe


@pytest.fixture(scope="module")
def verse_frames(verse_dir):
    lm = IO.read_label_map(VERSE_FILE)
    out = {}
    for name, label in VERSE_LABELS.items():
        vol = IO.select_label(lm, label)
        frame = FR.object_frame(vol)
        out[name] = (vol, frame, RS.resample(vol, frame, 1.0))
    return lm, out


def test_verse_label_counts_list_all_nine_vertebrae(verse_frames):
    lm, _ = verse_frames
    counts = IO.label_counts(lm)
    assert sorted(counts) == sorted(VERSE_LABELS.values())
    values, ref = np.unique(lm.labels[lm.labels != 0], return_counts=True)
    assert counts == dict(zip(values.tolist(), ref.tolist()))
    np.testing.assert_allclose(sorted(np.linalg.norm(lm.affine[:3, :3], axis=0)), [1, 1, 2], atol=1e-3)


def test_each_verse_vertebra_keeps_its_volume_when_resampled(verse_frames):
    _, items = verse_frames
    for name, (vol, _, ov) in items.items():
        expected = np.count_nonzero(vol.mask) * abs(np.linalg.det(vol.affine[:3, :3]))
        assert ov.volume_mm3 == pytest.approx(expected, rel=0.01), name


@pytest.mark.parametrize("names", [("L1", "L2", "L3", "L4", "L5"), ("T9", "T10", "T11", "T12", "L1")])
def test_verse_neighbouring_vertebrae_get_corresponding_axes(verse_frames, names):
    """Adjacent vertebrae: each axis agrees (dot > 0.8, same sign); all pairs: same sign.

    L1 vs L5 differ by the lumbar lordosis (their A and S axes are ~42 degrees apart),
    so the > 0.8 bound is checked between neighbours.
    """
    _, items = verse_frames
    axes = {n: items[n][1].axes_world for n in names}
    for a, b in zip(names, names[1:]):
        dots = np.sum(axes[a] * axes[b], axis=0)
        assert np.all(dots > 0.8), (a, b, dots)
    for a in names:
        for b in names:
            assert np.all(np.sum(axes[a] * axes[b], axis=0) > 0.5), (a, b)


# ----------------------------------------------------------------------------- bad input


def test_missing_file_is_named(tmp_path):
    with pytest.raises(InputError, match=r"nothere\.nii\.gz: file not found"):
        IO.read_label_map(tmp_path / "nothere.nii.gz")


def test_unknown_extension_lists_supported(tmp_path):
    p = tmp_path / "scan.dcm"
    p.write_bytes(b"x")
    with pytest.raises(InputError, match=r"scan\.dcm: unknown file extension '\.dcm'; supported: .*\.nii\.gz.*\.nrrd"):
        IO.read_label_map(p)
    with pytest.raises(InputError, match=r"scan\.dcm: unknown file extension.*\.stl"):
        meshes.read_mesh(p)


@pytest.mark.parametrize("ext", [".nii.gz", ".nrrd", ".mha"])
def test_truncated_file_is_reported(tmp_path, ext):
    labels = np.zeros((30, 30, 30), np.int16)
    labels[5:20, 5:20, 5:20] = 1
    labels[8:12] = np.arange(30 * 30).reshape(1, 30, 30) % 7  # poorly compressible
    p = IO.write_label_map(tmp_path / f"t{ext}", labels, np.eye(4))
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=re.escape(p.name) + r": .*(corrupt|truncated)"):
        IO.read_label_map(p)


def test_garbage_nifti_is_reported(tmp_path):
    p = tmp_path / "g.nii.gz"
    p.write_bytes(gzip.compress(b"not a nifti header" * 3))
    with pytest.raises(InputError, match=r"g\.nii\.gz: cannot read NIfTI file"):
        IO.read_label_map(p)


def test_absent_label_lists_the_labels_present(tmp_path):
    labels = np.zeros((6, 6, 6), np.uint8)
    labels[1:3, 1:3, 1:3] = 4
    labels[3:5, 3:5, 3:4] = 9
    p = IO.write_label_map(tmp_path / "l.nii.gz", labels, np.eye(4))
    with pytest.raises(
        InputError, match=r"l\.nii\.gz: label 5 is not present; labels present: 4 \(8 voxels\), 9 \(4 voxels\)"
    ):
        IO.load_volume(p, 5)
    with pytest.raises(InputError, match=r"l\.nii\.gz: label 0 is the background; pick a label from 4 \(8 voxels\)"):
        IO.load_volume(p, 0)


def test_empty_label_map_is_reported(tmp_path):
    p = IO.write_label_map(tmp_path / "e.nrrd", np.zeros((5, 5, 5), np.uint8), np.eye(4))
    with pytest.raises(InputError, match=r"e\.nrrd: empty mask"):
        IO.load_volume(p)
    with pytest.raises(InputError, match=r"empty mask"):
        FR.object_frame(V.Volume(mask=np.zeros((3, 3, 3), bool), affine=np.eye(4), source="e"))


def test_4d_image_is_rejected_but_singleton_4th_axis_is_squeezed(tmp_path):
    import nibabel as nib

    data = np.zeros((5, 5, 5, 3), np.uint8)
    data[2, 2, 2] = 1
    nib.save(nib.Nifti1Image(data, np.eye(4)), str(tmp_path / "four.nii.gz"))
    with pytest.raises(InputError, match=r"four\.nii\.gz: 4-D image of shape \(5, 5, 5, 3\)"):
        IO.read_label_map(tmp_path / "four.nii.gz")
    nib.save(nib.Nifti1Image(data[..., :1], np.eye(4)), str(tmp_path / "one.nii.gz"))
    assert IO.read_label_map(tmp_path / "one.nii.gz").labels.shape == (5, 5, 5)


def test_open_mesh_is_rejected_with_edge_counts(tmp_path):
    v, f = icosphere(10.0, 1)
    write_stl_binary(tmp_path / "open.stl", v, f[1:])
    with pytest.raises(InputError, match=r"open\.stl: the mesh is not closed and watertight \(3 boundary edges"):
        VX.load_mesh_volume(tmp_path / "open.stl", 1.0)
    f2 = f.copy()
    f2[0] = f2[0, ::-1]  # one flipped face
    with pytest.raises(InputError, match=r"flipped: .*3 inconsistently oriented edges"):
        VX.voxelize_mesh(v, f2, 1.0, source="flipped")
    with pytest.raises(InputError, match=r"nonmanifold: .*non-manifold"):
        VX.voxelize_mesh(v, np.vstack([f, f[:1], f[:1, ::-1]]), 1.0, source="nonmanifold")


def test_voxelizing_a_vertebra_surface_gives_back_its_volume(verse_frames):
    """A marching-cubes surface of L1 (genus > 0, oblique world) voxelizes to its own volume."""
    _, items = verse_frames
    vol = items["L1"][0]
    verts, faces = V.display_surface(vol)
    assert VX.mesh_edge_defects(faces) == (0, 0, 0)
    enclosed = mu.signed_volume(verts, faces)
    assert enclosed == pytest.approx(vol.volume_mm3, rel=0.02)
    assert VX.voxelize_mesh(verts, faces, 1.0, source="L1").volume_mm3 == pytest.approx(enclosed, rel=0.01)


def test_moment_signs_flip_between_verse_neighbours_where_patient_pairing_does_not(verse_frames):
    """Why "patient" is the default for images (design notes): on VerSe the third-moment
    signs flip between neighbours (e.g. L1/L2) and L5 swaps its two largest axes."""
    lm, items = verse_frames
    names = list(VERSE_LABELS)
    moments = {n: FR.object_frame(items[n][0], "moments").axes_world for n in names}
    flips = [(a, b) for a, b in zip(names, names[1:]) if np.any(np.sum(moments[a] * moments[b], axis=0) < 0)]
    assert ("L1", "L2") in flips
    assert np.sum(moments["L4"] * moments["L5"], axis=0)[0] < 0.5  # L5's first two axes swapped
    patient = {n: items[n][1].axes_world for n in names}
    assert all(np.all(np.sum(patient[a] * patient[b], axis=0) > 0.8) for a, b in zip(names, names[1:]))
