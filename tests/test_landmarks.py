"""Landmark sets: file formats, LPS/RAS, matching to a schema, errors, and the proposal."""

from __future__ import annotations

import json
import re
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import VERSE_FILE, VERSE_LABELS, icosphere, knee30_bone, object_frame_of
from scipy import ndimage
from scipy.spatial import cKDTree

from ssm_addon.base.errors import InputError
from ssm_addon.correspondence.proposal import (
    propose_from_meshes,
    propose_landmarks,
    surface_points_object,
    transfer_landmarks,
)
from ssm_addon.formats.landmarks import (
    LANDMARK_PRESETS,
    LandmarkSet,
    landmark_format,
    match_landmarks,
    order_by_schema,
    read_landmarks,
    write_landmarks,
)
from ssm_addon.instances import volume as vol


def _example_set() -> LandmarkSet:
    rng = np.random.default_rng(3)
    names = ("spinous-process-tip", "pedicle, left", 'odd "quoted" name', "body-anterior-superior", "x")
    return LandmarkSet(names, rng.normal(scale=300.0, size=(5, 3)), "example")


# ---------------------------------------------------------------------------- formats


@pytest.mark.parametrize(
    ("fmt", "system"), [("fcsv", "LPS"), ("fcsv", "RAS"), ("mrk.json", "LPS"), ("mrk.json", "RAS"), ("csv", None), ("json", None)]
)
def test_write_read_round_trip_is_exact(tmp_path, fmt, system):
    lm = _example_set()
    path = write_landmarks(tmp_path / f"a.{fmt}", lm, coordinate_system=system)
    back = read_landmarks(path)
    assert back.names == lm.names
    np.testing.assert_allclose(back.points_world, lm.points_world, atol=1e-6, rtol=0)
    assert back.source == str(path)


def test_slicer_formats_are_written_in_lps_by_default(tmp_path):
    lm = LandmarkSet(("a",), [[1.5, -2.0, 3.0]])
    fcsv = write_landmarks(tmp_path / "a.fcsv", lm).read_text()
    assert "# CoordinateSystem = LPS" in fcsv
    row = [line for line in fcsv.splitlines() if not line.startswith("#")][0].split(",")
    assert [float(v) for v in row[1:4]] == [-1.5, 2.0, 3.0]
    doc = json.loads(write_landmarks(tmp_path / "a.mrk.json", lm).read_text())
    assert doc["markups"][0]["coordinateSystem"] == "LPS"
    assert doc["markups"][0]["controlPoints"][0]["position"] == [-1.5, 2.0, 3.0]
    ras = json.loads(write_landmarks(tmp_path / "b.mrk.json", lm, coordinate_system="RAS").read_text())
    assert ras["markups"][0]["controlPoints"][0]["position"] == [1.5, -2.0, 3.0]


@pytest.mark.parametrize(
    ("header", "sign"),
    [("# CoordinateSystem = LPS", -1), ("# CoordinateSystem = 1", -1), ("# CoordinateSystem = RAS", 1), ("# CoordinateSystem = 0", 1), ("", 1)],
)
def test_fcsv_coordinate_system_header_is_honoured(tmp_path, header, sign):
    path = tmp_path / "p.fcsv"
    path.write_text(
        "# Markups fiducial file version = 4.11\n"
        + (header + "\n" if header else "")
        + "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
        + "n0,10.5,-20.25,30,0,0,0,1,1,1,0,tip,,\n"
        + 'n1,1,2,3,0,0,0,1,1,1,0,"with, comma",desc,\n'
    )
    lm = read_landmarks(path)
    assert lm.names == ("tip", "with, comma")
    np.testing.assert_array_equal(lm.points_world, [[sign * 10.5, sign * -20.25, 30.0], [sign * 1, sign * 2, 3.0]])


def test_fcsv_columns_line_reorders_fields(tmp_path):
    path = tmp_path / "p.fcsv"
    path.write_text("# CoordinateSystem = RAS\n# columns = label,z,y,x,id\nA,3,2,1,id0\n")
    lm = read_landmarks(path)
    assert lm.names == ("A",)
    np.testing.assert_array_equal(lm.points_world, [[1.0, 2.0, 3.0]])


def test_mrk_json_reads_ras_and_lps_and_skips_unplaced(tmp_path):
    def doc(system):
        return {
            "markups": [
                {
                    "type": "Fiducial",
                    "coordinateSystem": system,
                    "controlPoints": [
                        {"label": "a", "position": [1.0, 2.0, 3.0], "positionStatus": "defined"},
                        {"label": "b", "position": [0.0, 0.0, 0.0], "positionStatus": "undefined"},
                        {"label": "c", "position": [-4, 5, 6.5]},
                    ],
                }
            ]
        }

    for system, sign in (("LPS", -1), ("RAS", 1)):
        path = tmp_path / f"{system}.mrk.json"
        path.write_text(json.dumps(doc(system)))
        lm = read_landmarks(path)
        assert lm.names == ("a", "c")
        np.testing.assert_array_equal(lm.points_world, [[sign * 1, sign * 2, 3], [sign * -4, sign * 5, 6.5]])


def test_csv_with_and_without_header(tmp_path):
    (tmp_path / "plain.csv").write_text("a,1,2,3\nb,4,5,6\n")
    (tmp_path / "head.csv").write_text("# comment\nz,label,y,x\n3,a,2,1\n6,b,5,4\n")
    for name in ("plain.csv", "head.csv"):
        lm = read_landmarks(tmp_path / name)
        assert lm.names == ("a", "b")
        np.testing.assert_array_equal(lm.points_world, [[1, 2, 3], [4, 5, 6]])


def test_scalismo_json(tmp_path):
    path = tmp_path / "s.json"
    path.write_text(json.dumps([{"id": "a", "coordinates": [1, 2, 3.5], "uncertainty": {}}, {"id": "b", "coordinates": [0, 0, -1]}]))
    lm = read_landmarks(path)
    assert lm.names == ("a", "b")
    np.testing.assert_array_equal(lm.points_world, [[1, 2, 3.5], [0, 0, -1]])


def test_landmark_format_by_extension():
    assert [landmark_format(f"x/y.{e}") for e in ("FCSV", "mrk.json", "Mrk.Json", "csv", "json")] == ["fcsv", "mrk.json", "mrk.json", "csv", "json"]


# ---------------------------------------------------------------------------- errors


def test_duplicate_names_are_an_error_naming_file_and_name(tmp_path):
    path = tmp_path / "dup.csv"
    path.write_text("a,1,2,3\nb,1,2,3\na,4,5,6\n")
    with pytest.raises(InputError, match=r"dup\.csv.*duplicate.*'a'"):
        read_landmarks(path)


@pytest.mark.parametrize(
    ("name", "text"),
    [
        ("empty.fcsv", "# Markups fiducial file version = 4.11\n# CoordinateSystem = LPS\n"),
        ("empty.csv", "name,x,y,z\n"),
        ("empty.json", "[]"),
        ("empty.mrk.json", json.dumps({"markups": [{"coordinateSystem": "LPS", "controlPoints": []}]})),
    ],
)
def test_file_with_no_points_is_an_error(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(InputError, match=re.escape(name) + ".*no landmark points"):
        read_landmarks(path)


def test_malformed_number_reports_line(tmp_path):
    path = tmp_path / "bad.fcsv"
    path.write_text(
        "# CoordinateSystem = LPS\n# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
        "n0,1,2,3,0,0,0,1,1,1,0,a,,\nn1,1,2.x,3,0,0,0,1,1,1,0,b,,\n"
    )
    with pytest.raises(InputError, match=r"bad\.fcsv, line 4: y '2\.x' is not a number"):
        read_landmarks(path)
    csvp = tmp_path / "bad.csv"
    csvp.write_text("name,x,y,z\na,1,2,3\n\nb,1,2,nan\n")
    with pytest.raises(InputError, match=r"bad\.csv, line 4: z 'nan' is not a finite number"):
        read_landmarks(csvp)
    js = tmp_path / "bad.json"
    js.write_text('[{"id": "a", "coordinates": [1, 2, 3]},\n {"id": "b", "coordinates": [1, "2", 3]}]')
    with pytest.raises(InputError, match=r"bad\.json, entry 1: y '2' is not a finite number"):
        read_landmarks(js)
    broken = tmp_path / "broken.json"
    broken.write_text('[\n{"id": "a",\n "coordinates": [1, 2 3]}]')
    with pytest.raises(InputError, match=r"broken\.json, line 3: invalid JSON"):
        read_landmarks(broken)


def test_unknown_extension_and_missing_file(tmp_path):
    with pytest.raises(InputError, match=r"pts\.txt: unknown landmark file extension"):
        read_landmarks(tmp_path / "pts.txt")
    with pytest.raises(InputError, match=r"nope\.fcsv: landmark file not found"):
        read_landmarks(tmp_path / "nope.fcsv")
    with pytest.raises(InputError, match=r"\.csv landmark files are world RAS"):
        write_landmarks(tmp_path / "a.csv", _example_set(), coordinate_system="LPS")


# ---------------------------------------------------------------------------- matching


def test_match_reorders_to_schema():
    a = LandmarkSet(("x", "y", "z"), np.eye(3), "a.fcsv")
    b = LandmarkSet(("z", "x", "y"), np.eye(3)[[2, 0, 1]] * 2, "b.fcsv")
    ma, mb = match_landmarks([a, b], names=("y", "z", "x"))
    assert ma.names == mb.names == ("y", "z", "x")
    np.testing.assert_array_equal(ma.points_world, np.eye(3)[[1, 2, 0]])
    np.testing.assert_array_equal(mb.points_world, 2 * np.eye(3)[[1, 2, 0]])
    # default schema: the first set's order
    assert match_landmarks([b, a])[1].names == ("z", "x", "y")


def test_match_lists_missing_and_unknown_names_per_file():
    a = LandmarkSet(("x", "y", "z"), np.eye(3), "a.fcsv")
    b = LandmarkSet(("x", "tip", "w"), np.eye(3), "b.csv")
    with pytest.raises(InputError) as err:
        match_landmarks([a, b], names=("x", "y", "z"))
    msg = str(err.value)
    assert "b.csv: missing y, z; not in the schema tip, w" in msg
    assert "a.fcsv" not in msg
    with pytest.raises(InputError, match=r"b\.csv: missing y, z$"):
        match_landmarks([a, b], names=("x", "y", "z"), allow_extra=True)


def test_presets():
    assert len(LANDMARK_PRESETS["extremal-14"]) == 14
    assert len(set(LANDMARK_PRESETS["lumbar-vertebra"])) == len(LANDMARK_PRESETS["lumbar-vertebra"]) == 15


# ---------------------------------------------------------------------------- proposal


def _rotation(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_frame_proposal_maps_each_landmark_to_nearest_target_surface_point():
    # source: landmarks on a sphere of radius 12 around its centre; target: a sphere of
    # radius 10, translated and rotated in world; the object frames align the two, so the
    # proposal of landmark p is the target's surface point along p's direction.
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(15, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    src_frame = vol.ObjectFrame(np.array([5.0, -3.0, 2.0]), _rotation(1))
    tgt_frame = vol.ObjectFrame(np.array([100.0, 40.0, -700.0]), _rotation(2))
    lm = LandmarkSet(tuple(f"l{i}" for i in range(15)), src_frame.to_world(12.0 * dirs), "src")
    extra = rng.normal(size=(3000, 3))
    surface_object = 10.0 * np.vstack([dirs, extra / np.linalg.norm(extra, axis=1, keepdims=True)])
    out = transfer_landmarks(lm, src_frame, tgt_frame, tgt_frame.to_world(surface_object), source="tgt")
    assert out.names == lm.names and out.source == "tgt"
    np.testing.assert_allclose(out.points_world, tgt_frame.to_world(10.0 * dirs), atol=1e-9)


def test_proposal_onto_object_volume_lands_on_its_surface():
    r = 8.0
    ijk = np.indices((21, 21, 21)).reshape(3, -1).T
    mask = (np.linalg.norm(ijk - 10, axis=1) <= r).reshape(21, 21, 21)
    ov = vol.ObjectVolume(mask, 1.0, np.array([-10.0, -10.0, -10.0]), vol.ObjectFrame(np.zeros(3), np.eye(3)), "ball")
    src = np.array([[30.0, 0, 0], [0, -30.0, 0], [0, 0, 30.0], [17.0, 17.0, 0]])
    out = propose_landmarks(src, ov)
    radii = np.linalg.norm(out, axis=1)
    assert np.all(np.abs(radii - (r + 0.5)) < 0.6)  # the 0.5 iso-surface of a voxel ball
    cos = np.sum(out / radii[:, None] * src / np.linalg.norm(src, axis=1)[:, None], axis=1)
    assert np.all(cos > 0.99)
    pts = surface_points_object(ov)
    assert cKDTree(pts).query(out)[0].max() == 0.0


def test_coating_proposal_hook_lands_on_an_ellipsoid_target():
    # source: a sphere of radius 10 (the template's surface); target: a voxel ellipsoid
    # with semi-axes 8, 11, 9 mm; landmarks at the sphere's poles go to the ellipsoid's
    v, f = icosphere(10.0, 2)
    template = SimpleNamespace(points_object=v, faces=f)
    ijk = np.indices((31, 31, 31)).reshape(3, -1).T
    semi = np.array([8.0, 11.0, 9.0])
    mask = (np.sum(((ijk - 15) / semi) ** 2, axis=1) <= 1).reshape(31, 31, 31)
    ov = vol.ObjectVolume(mask, 1.0, np.full(3, -15.0), vol.ObjectFrame(np.zeros(3), np.eye(3)), "ellipsoid")
    src = np.array([[10.0, 0, 0], [0, 10.0, 0], [0, 0, -10.0]])
    out = propose_landmarks(src, ov, method="coating", source_template=template)
    assert out.shape == (3, 3)
    np.testing.assert_allclose(np.abs(out[[0, 1, 2], [0, 1, 2]]), semi + 0.5, atol=1.0)
    assert np.abs(out[[0, 0, 1, 1, 2, 2], [1, 2, 0, 2, 0, 1]]).max() < 1.0
    with pytest.raises(InputError, match="needs source_template"):
        propose_landmarks(src, ov, method="coating")
    with pytest.raises(InputError, match="needs the target's ObjectVolume"):
        propose_landmarks(src, np.zeros((4, 3)), method="coating", source_template=template)


def test_proposal_method_hook():
    with pytest.raises(InputError, match="unknown method 'magic'"):
        propose_landmarks(np.zeros((1, 3)), np.zeros((1, 3)), method="magic")
    with pytest.raises(InputError, match="no landmarks"):
        propose_landmarks(np.zeros((0, 3)), np.zeros((1, 3)))


# ---------------------------------------------------------------------------- real data


@pytest.fixture(scope="module")
def verse_labels(verse_dir):
    import nibabel as nib

    img = nib.load(str(VERSE_FILE))
    return np.asarray(img.dataobj), img.affine


def _surface_voxel_centres_world(mask, affine):
    surf = mask & ~ndimage.binary_erosion(mask, np.ones((3, 3, 3), bool), border_value=0)
    return np.argwhere(surf) @ affine[:3, :3].T + affine[:3, 3]


def test_verse_lps_landmarks_land_on_the_l1_surface(verse_dir, verse_labels):
    labels, affine = verse_labels
    surface = cKDTree(_surface_voxel_centres_world(labels == VERSE_LABELS["L1"], affine))
    lm = read_landmarks(verse_dir / "landmarks" / "L1.fcsv")
    assert lm.names == LANDMARK_PRESETS["extremal-14"]
    dist, _ = surface.query(lm.points_world)
    print(f"\nL1 landmarks (LPS file, read as RAS) to the nearest L1 surface voxel centre: max {dist.max():.4f} mm")
    assert dist.max() <= 2.0  # one voxel (1 x 1 x 2 mm)
    # without the LPS -> RAS conversion they would be far off the vertebra
    assert surface.query(lm.points_world * [-1, -1, 1])[0].min() > 50.0


def test_verse_proposal_of_l2_from_l1_lies_on_l2_surface(verse_dir, verse_labels):
    from skimage.measure import marching_cubes

    labels, affine = verse_labels
    m1, m2 = labels == VERSE_LABELS["L1"], labels == VERSE_LABELS["L2"]
    lm1 = read_landmarks(verse_dir / "landmarks" / "L1.fcsv")
    lm2 = read_landmarks(verse_dir / "landmarks" / "L2.fcsv")
    f2 = np.pad(m2, 1).astype(np.float32)
    verts, _, _, _ = marching_cubes(f2, 0.5)
    surface_world = (verts - 1.0) @ affine[:3, :3].T + affine[:3, 3]
    out = transfer_landmarks(lm1, object_frame_of(m1, affine), object_frame_of(m2, affine), surface_world, source="L2")
    assert out.names == lm2.names
    # on L2's surface: the linearly interpolated L2 mask is 0.5 at each proposed point
    inv = np.linalg.inv(affine)
    ijk = out.points_world @ inv[:3, :3].T + inv[:3, 3]
    level = ndimage.map_coordinates(m2.astype(float), ijk.T, order=1)
    np.testing.assert_allclose(level, 0.5, atol=1e-6)
    dist = np.linalg.norm(out.points_world - lm2.points_world, axis=1)
    print(f"\nproposal L1 -> L2 (frame): mean distance to the given L2 landmarks {dist.mean():.2f} mm, max {dist.max():.2f} mm")
    # the object frames align L1 and L2 far better than their world positions do
    assert dist.mean() < 0.5 * np.linalg.norm(lm1.points_world - lm2.points_world, axis=1).mean()


def test_order_by_schema_keeps_a_partial_set_and_lists_unknown_names():
    lm = LandmarkSet(("c", "a", "tip"), np.arange(9.0).reshape(3, 3), "part.csv")
    out = order_by_schema(lm.subset(("c", "a")), ("a", "b", "c"))
    assert out.names == ("a", "c")
    np.testing.assert_array_equal(out.points_world, [[3, 4, 5], [0, 1, 2]])
    with pytest.raises(InputError, match=r"part\.csv: not in the schema tip$"):
        order_by_schema(lm, ("a", "b", "c"))
    with pytest.raises(InputError, match=r"part\.csv: missing b; not in the schema tip$"):
        order_by_schema(lm, ("a", "b", "c"), allow_missing=False)
    assert order_by_schema(lm, ("a", "b", "c"), allow_extra=True).names == ("a", "c", "tip")


@pytest.mark.parametrize("method", ["frame", "coating"])
def test_proposal_from_meshes_puts_landmarks_on_the_target_mesh(method):
    # a sphere (radius 10) at one place and an ellipsoid (semi-axes 8, 11, 9 mm) rotated
    # and translated elsewhere: pole landmarks of the sphere go to the ellipsoid's poles
    v, f = icosphere(10.0, 3)
    semi = np.array([8.0, 11.0, 9.0])
    src_frame = vol.ObjectFrame(np.array([5.0, -3.0, 2.0]), _rotation(1))
    tgt_frame = vol.ObjectFrame(np.array([100.0, 40.0, -700.0]), _rotation(2))
    lm = LandmarkSet(("x", "y", "-z"), src_frame.to_world([[10.0, 0, 0], [0, 10.0, 0], [0, 0, -10.0]]), "sphere")
    target_world = tgt_frame.to_world(v / 10.0 * semi)
    out = propose_from_meshes(lm, src_frame, (src_frame.to_world(v), f), tgt_frame, (target_world, f), method=method, source="ellipsoid")
    assert out.names == lm.names and out.source == "ellipsoid"
    got = tgt_frame.to_object(out.points_world)
    # signed: the +x, +y and -z poles, never the opposite pole (the end-for-end flip)
    np.testing.assert_allclose(got, [[8.0, 0, 0], [0, 11.0, 0], [0, 0, -9.0]], atol=1.0)
    np.testing.assert_allclose(got[[0, 1, 2], [0, 1, 2]], semi * [1, 1, -1], atol=0.8)
    if method == "frame":
        assert cKDTree(target_world).query(out.points_world)[0].max() == 0.0


def test_model_proposal_finds_a_target_whose_frame_is_turned_end_for_end():
    # knee30 patellas: the model of 29 (their true correspondence, rigidly aligned) proposes the
    # landmarks of the held-out one given turned 180° in its frame, as a moments frame of a
    # near-symmetric bone may be resolved: the pose search finds it (from the frame alone the
    # proposals landed about 23 mm off)
    from ssm_addon.correspondence.proposal import propose_by_model
    from ssm_addon.meshutil import LandmarkLocations, locate_on_mesh
    from ssm_addon.model.pca import build_model

    names_all, points, faces = knee30_bone("Patella")
    held = 11
    train = np.delete(points, held, axis=0)
    picked = np.linspace(0, len(faces) - 1, 8).astype(int)
    corners = train[0][faces[picked]].mean(axis=1)  # triangle centroids: on the surface
    at = locate_on_mesh(train[0], faces, corners)
    names = tuple(f"L{j}" for j in range(len(picked)))
    located = LandmarkLocations(names, at.triangles, at.bary)
    model = build_model(train, faces, [n for i, n in enumerate(names_all) if i != held], alignment="rigid",
                        params={"landmark_locations": located.to_dict()})
    centre = points[held].mean(axis=0)
    turn = np.diag([-1.0, -1.0, 1.0])  # 180° about z through the centroid
    target = (points[held] - centre) @ turn.T + centre
    truth = located.evaluate(target, faces)
    frame = vol.ObjectFrame(origin_world=np.zeros(3), axes_world=np.eye(3))
    proposed = propose_by_model(model, frame, (target, faces), source=names_all[held])
    assert proposed.names == names
    error = np.linalg.norm(proposed.points_world - truth, axis=1)
    assert error.mean() < 1.5, error
