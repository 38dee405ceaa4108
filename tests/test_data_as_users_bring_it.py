"""Data as other tools write it: meshes in LPS or RAS saying so (3D Slicer), landmarks in the frame of
the mesh they were clicked on (Scalismo), scanner coordinates far from the origin, label maps whose
header another tool wrote, models with empty modes; the defaults must hold on them.

The inputs are made from ``../shared/data`` and synthetic shapes by ``tests/foreign_data.py``.
"""

from __future__ import annotations

import json

import nibabel as nib
import numpy as np
import pytest
from conftest import ellipsoid_mesh, spiked_project, synthetic_population
from foreign_data import (
    LPS,
    deformed_slicer_meshes,
    knee30_in_scanner_poses,
    scalismo_landmarks,
    slicer_obj,
    slicer_ply,
    slicer_stl,
    two_subject_level,
)

from ssm_addon.formats.label_maps import read_label_map
from ssm_addon.formats.meshes import mesh_space, read_mesh, write_ply
from ssm_addon.meshutil import MeshLocator
from ssm_addon.pipeline.project import read_project
from ssm_addon.pipeline.project_build import build

WRITERS = {"ply": slicer_ply, "stl": slicer_stl, "obj": slicer_obj}


@pytest.mark.parametrize("fmt", ["ply", "stl", "obj"])
def test_a_mesh_file_is_read_in_the_convention_it_states(tmp_path, fmt):
    """The same surface written in LPS and in RAS, each file saying which (as 3D Slicer writes
    them), reads as the same RAS coordinates; a file that states nothing is taken as given."""
    verts, faces = ellipsoid_mesh(centre=(120.0, -80.0, 900.0))
    lps = WRITERS[fmt](tmp_path / f"lps.{fmt}", verts, faces, space="LPS")
    ras = WRITERS[fmt](tmp_path / f"ras.{fmt}", verts, faces, space="RAS")
    assert mesh_space(lps) == "LPS" and mesh_space(ras) == "RAS"
    for path in (lps, ras):
        v, f = read_mesh(path)
        assert len(f) == len(faces)
        np.testing.assert_allclose(np.sort(v, axis=0), np.sort(verts, axis=0), atol=1e-4)
    plain = tmp_path / "plain.ply"
    write_ply(plain, verts * LPS, faces)  # LPS numbers, no statement
    assert mesh_space(plain) is None
    np.testing.assert_allclose(read_mesh(plain)[0], verts * LPS, atol=1e-4)  # taken as RAS: as written
    np.testing.assert_allclose(read_mesh(plain, space="LPS")[0], verts, atol=1e-4)  # given as LPS
    np.testing.assert_allclose(read_mesh(lps, space="RAS")[0], read_mesh(lps)[0])  # a statement wins


def _three_meshes(tmp_path, centre, space, fmt="ply"):
    lines = ["[template]", "spacing = 1.0", "r_min_mm = 4.0", "r_max_mm = 8.0", "", "[model]",
             "specificity_samples = 20", ""]
    shapes = {}
    for i, radii in enumerate(((30.0, 20.0, 14.0), (33.0, 19.0, 15.0), (28.0, 22.0, 13.0))):
        verts, faces = ellipsoid_mesh(radii, centre=centre)
        name = f"e{i}"
        (slicer_ply if fmt == "ply" else WRITERS[fmt])(tmp_path / f"{name}.{fmt}", verts, faces, space=space)
        tips = verts[[np.argmax(verts[:, 0]), np.argmin(verts[:, 0]), np.argmax(verts[:, 1]), np.argmin(verts[:, 1]),
                      np.argmax(verts[:, 2]), np.argmin(verts[:, 2])]]
        scalismo_landmarks(tmp_path / f"{name}.json", list("ABCDEF"), tips * (LPS if space == "LPS" else 1.0))
        lines += ["[[instances]]", f'name = "{name}"', f'mesh = "{name}.{fmt}"', f'landmarks = "{name}.json"', ""]
        shapes[name] = (verts, faces)
    (tmp_path / "project.toml").write_text("\n".join(lines))
    return tmp_path / "project.toml", shapes


def test_mesh_instances_one_metre_from_the_origin_give_instance_points_world_on_their_meshes(tmp_path):
    """Scanner coordinates (about 1 m from the origin, as femur10's), LPS meshes saying so and
    Scalismo landmarks in the meshes' frame: every coated point in ``instance_points_world`` lies
    on its mesh (RAS world mm), and the landmarks were read in the meshes' convention."""
    project, shapes = _three_meshes(tmp_path, centre=(250.0, -400.0, 950.0), space="LPS")
    spec = read_project(project).instances[0]
    assert "its mesh e0.ply states LPS" in spec.landmarks.coordinates
    np.testing.assert_allclose(spec.landmarks.points_world[0], shapes["e0"][0][np.argmax(shapes["e0"][0][:, 0])])
    result = build(read_project(project), tmp_path / "out", log=None)
    model = result.model
    for name, world in zip(model.instance_names, model.instance_points_world):
        verts, faces = shapes[str(name)]
        _c, d, _t, _b = MeshLocator(verts, faces).query(world, k=12)
        assert d.max() < 1.0 and d.mean() < 0.35, (name, d.mean(), d.max())  # mm: on the mesh, a voxel at most
        assert result.report["inputs"][str(name)]["coordinates"] == "LPS, stated in the file"
        fig = result.report["instances"][str(name)]["input_surface_mm"]
        assert fig["to_input"]["mean_mm"] < 0.35 and fig["from_input"]["max_mm"] < 3.0
    assert not [f for f in result.report["quality"]["findings"] if f["gate"] in ("frame", "input_surface")]


@pytest.mark.parametrize("fmt", ["ply", "stl", "obj"])
def test_the_same_surfaces_in_ras_and_in_lps_give_the_same_model(tmp_path, fmt):
    """Each file says which convention it is in: the two builds give the same model in the same
    RAS world frame, for each mesh format."""
    (tmp_path / "lps").mkdir()
    (tmp_path / "ras").mkdir()
    a, _ = _three_meshes(tmp_path / "lps", centre=(0.0, 100.0, -300.0), space="LPS", fmt=fmt)
    b, _ = _three_meshes(tmp_path / "ras", centre=(0.0, 100.0, -300.0), space="RAS", fmt=fmt)
    ma = build(read_project(a), tmp_path / "out_lps", log=None).model
    mb = build(read_project(b), tmp_path / "out_ras", log=None).model
    np.testing.assert_allclose(ma.instance_points_world, mb.instance_points_world, atol=1e-6)
    np.testing.assert_allclose(ma.variances, mb.variances, rtol=1e-9)


def test_an_lps_nrrd_written_as_3d_slicer_writes_it_lands_where_slicer_shows_it(tmp_path):
    """A label map in 3D Slicer's own NRRD form (its header text, LPS, an oblique grid): the world
    RAS point of a voxel is where Slicer shows it (x and y of the LPS header negated)."""
    labels = np.zeros((20, 30, 40), np.uint8)
    labels[5:9, 10:14, 20:30] = 3
    dirs = np.array([[0.8, 0.1, 0.0], [-0.1, 0.8, 0.0], [0.0, 0.0, 1.5]])  # rows: the i, j, k steps (LPS mm)
    origin = np.array([-10.0, 20.5, -330.0])
    header = ("NRRD0004\n# Complete NRRD file format specification at:\n# http://teem.sourceforge.net/nrrd/format.html\n"
              "type: unsigned char\ndimension: 3\nspace: left-posterior-superior\nsizes: 20 30 40\n"
              "space directions: " + " ".join("(" + ",".join(f"{x:g}" for x in row) + ")" for row in dirs) + "\n"
              "kinds: domain domain domain\nendian: little\nencoding: raw\n"
              f"space origin: ({origin[0]:g},{origin[1]:g},{origin[2]:g})\n\n")
    path = tmp_path / "Segmentation-label.nrrd"
    path.write_bytes(header.encode("ascii") + np.asfortranarray(labels).tobytes(order="F"))
    lm = read_label_map(path)
    assert lm.labels[6, 11, 25] == 3
    ijk = np.array([6.0, 11.0, 25.0])
    slicer_ras = (origin + ijk @ dirs) * LPS
    np.testing.assert_allclose(lm.affine[:3, :3] @ ijk + lm.affine[:3, 3], slicer_ras, atol=1e-9)


@pytest.mark.parametrize("sform_code, used", [(2, "qform"), (1, "sform")])
def test_a_nifti_whose_qform_and_sform_differ_is_read_as_3d_slicer_reads_it(tmp_path, sform_code, used):
    """3D Slicer (ITK) takes the sform only when it is the scanner's (code 1) or equals the qform;
    an sform coded 'aligned' (2) maps to another space and the qform stands (nibabel would take
    the sform): the voxel lands where Slicer shows it, and the report says which form."""
    from ssm_addon.formats.label_maps import label_map_coordinates

    labels = np.zeros((10, 10, 10), np.uint8)
    labels[3:6, 3:6, 3:6] = 1
    qform = np.diag([1.0, 1.0, 2.0, 1.0])
    qform[:3, 3] = [10.0, -20.0, 30.0]
    sform = qform.copy()
    sform[:3, 3] += [5.0, 0.0, 0.0]  # another space, 5 mm along x
    img = nib.Nifti1Image(labels, qform)
    img.set_qform(qform, code=1)
    img.set_sform(sform, code=sform_code)
    path = tmp_path / "seg.nii.gz"
    nib.save(img, str(path))
    expected = qform if used == "qform" else sform
    np.testing.assert_allclose(read_label_map(path).affine, expected)
    note = label_map_coordinates(path)
    assert used in note and ("differs by up to 5" in note)


def test_a_foreign_statismo_model_loses_its_empty_modes(tmp_path):
    """A statismo file with modes of zero variance appended (as a Scalismo model of n shapes keeps
    n - 1 modes, many of them empty): they are dropped on load, with one line saying how many, and
    a fit counts only the real modes."""
    import h5py

    from ssm_addon.fitting.fit import Target, fit_any_pose
    from ssm_addon.model.files import load_model, save_statismo
    from ssm_addon.model.pca import build_model

    shapes, mean, _f, _l = synthetic_population(n=8, n_points=80, noise_mm=0.0, seed=2)  # three real modes
    from scipy.spatial import ConvexHull

    model = build_model(shapes, ConvexHull(mean).simplices, [f"s{i}" for i in range(8)])
    path = save_statismo(model, tmp_path / "foreign.h5")
    with h5py.File(path, "r+") as f:  # another tool's file: 20 more modes, of zero variance, no /ssm group
        basis = np.asarray(f["model/pcaBasis"][()])
        extra = np.linalg.qr(np.random.default_rng(0).normal(size=(basis.shape[0], basis.shape[1] + 20)))[0]
        del f["model/pcaBasis"], f["model/pcaVariance"]
        f["model/pcaBasis"] = np.hstack([basis, extra[:, basis.shape[1]:]]).astype(np.float32)
        f["model/pcaVariance"] = np.concatenate([model.variances, np.zeros(20)]).astype(np.float32)
        if "ssm" in f:
            del f["ssm"]
    said = []
    loaded = load_model(path, say=said.append)
    real = int((model.variances > 1e-6 * model.variances[0]).sum())
    assert loaded.n_modes == real and len(said) == 1 and f"{model.n_modes + 20 - real} of" in said[0]
    result, _ = fit_any_pose(loaded, Target.from_mesh(shapes[3], model.faces))
    assert result.n_modes == real and np.isfinite(result.mahalanobis)


def test_a_template_too_coarse_for_a_thin_process_is_named(tmp_path):
    """The user's mesh far from its coating (a thin spike the template's points do not reach) is
    a finding naming the instance and the remedy, not a silence (the template not refined where
    the coatings cut off parts: tests/test_template_refinement.py)."""
    spiked_project(tmp_path, ((26.0, (24.0, 20.0, 16.0)), (28.0, (25.0, 19.0, 16.0)), (25.0, (23.0, 21.0, 15.0))),
                   ["[template]", "spacing = 1.0", "r_min_mm = 6.0", "r_max_mm = 12.0", "refine_where_cut_off = false",
                    "", "[model]",
                    "specificity_samples = 20"])
    result = build(read_project(tmp_path / "project.toml"), tmp_path / "out", log=None)
    named = [f for f in result.report["quality"]["findings"] if f["gate"] == "input_surface"]
    assert named, json.dumps(result.report["instances"]["s0"].get("input_surface_mm"))
    assert "thin process" in named[0]["message"] and "r_min_mm" in named[0]["message"]
    assert "max_distance_mm = 1" in named[0]["message"]  # the one number first
    beyond = result.report["instances"][named[0]["instance"]]["input_surface_mm"]["from_input"]["beyond"]
    x, y, z = beyond["centre_offset_mm"]  # where: out along the spike (+x), not around the body
    assert beyond["count"] > 0 and x > 15.0 and abs(y) < 5.0 and abs(z) < 5.0, beyond
    assert f"{beyond['count']:,} of its vertices" in named[0]["message"]
    # the spike (3.2 mm thick) is in the 1 mm voxels: the coating, not the import, lost it
    assert beyond["voxels"]["count"] == 0 and beyond["voxels"]["spacing_mm"] == 1.0, beyond
    assert beyond["voxels"]["max_mm"] < 1.0, beyond
    assert all(result.report["instances"][f["instance"]]["input_surface_mm"]["from_input"]["max_mm"] > 3.0
               for f in named)


def _hollow_ellipsoids(folder, radii, cavities):
    """Ellipsoids as a segmentation tool exports them (marching cubes of a 0.5 mm mask, RAS PLY,
    with the 6 extreme points as CSV landmarks); ``cavities``: per instance, balls (centre and
    radius, mm) left out of the mask, which the tool writes as closed surfaces inside."""
    from ssm_addon.meshutil import marching_cubes

    h = 0.5
    lines = []
    for i, (r, holes) in enumerate(zip(radii, cavities)):
        axes = [np.arange(-rk - 2.0, rk + 2.0 + h / 2, h) for rk in r]
        x, y, z = np.meshgrid(*axes, indexing="ij")
        mask = (x / r[0]) ** 2 + (y / r[1]) ** 2 + (z / r[2]) ** 2 <= 1.0
        for centre, radius in holes:
            mask &= (x - centre[0]) ** 2 + (y - centre[1]) ** 2 + (z - centre[2]) ** 2 > radius**2
        v, f = marching_cubes(mask)
        v = v * h + np.array([a[0] for a in axes])
        name = f"e{i}"
        write_ply(folder / f"{name}.ply", v, f, space="RAS")
        tips = v[[np.argmax(v[:, 0]), np.argmin(v[:, 0]), np.argmax(v[:, 1]), np.argmin(v[:, 1]),
                  np.argmax(v[:, 2]), np.argmin(v[:, 2])]]
        (folder / f"{name}.csv").write_text("".join(f"{n},{a},{b},{c}\n" for n, (a, b, c) in zip("ABCDEF", tips)))
        lines += ["[[instances]]", f'name = "{name}"', f'mesh = "{name}.ply"', f'landmarks = "{name}.csv"', ""]
    (folder / "project.toml").write_text("\n".join(["[model]", "specificity_samples = 20", "", *lines]))
    return folder / "project.toml"


def test_the_cavities_a_segmentation_leaves_inside_a_mesh_are_not_its_surface(tmp_path):
    """A segmentation's holes inside the object (voxels left out of a vertebral body) come out of
    its marching cubes as small closed surfaces inside the mesh. The template fills cavities, so
    the model holds the outer surface: the coating neither reaches for those walls (the surface it
    follows is the outer one) nor is gated on them (the mesh is measured by its outer surface,
    its cavities counted and said). The coatings are the same as those of the meshes without
    the cavities, whose walls lie 4.5-7.5 mm under the coating."""
    radii = ((24.0, 18.0, 14.0), (26.0, 17.0, 13.0), (23.0, 19.0, 15.0))
    holes = ((), (((0.0, 0.0, 6.0), 1.5), ((8.0, 0.0, -5.0), 1.0)), (((-10.0, 4.0, 0.0), 1.5),))
    results = {}
    for label, cavities in (("hollow", holes), ("solid", ((), (), ()))):
        (tmp_path / label).mkdir()
        log = []
        result = build(read_project(_hollow_ellipsoids(tmp_path / label, radii, cavities)), tmp_path / label / "out",
                       log=log.append)
        results[label] = (result, log)
    hollow, log = results["hollow"]
    solid, _ = results["solid"]
    assert not [f for f in hollow.report["quality"]["findings"] if f["gate"] == "input_surface"]
    measured = {n: hollow.report["instances"][n]["input_surface_mm"] for n in ("e0", "e1", "e2")}
    assert "cavities" not in measured["e0"]
    assert measured["e1"]["cavities"]["components"] == 2 and measured["e2"]["cavities"]["components"] == 1
    assert measured["e1"]["cavities"]["vertices"] > 50, measured["e1"]
    said = [line for line in log if "hold internal cavities" in line]
    assert said and "e1 2" in said[0] and "e2 1" in said[0], log
    for n in ("e1", "e2"):
        assert measured[n]["from_input"]["max_mm"] < 1.5, measured[n]
        alone = solid.report["instances"][n]["input_surface_mm"]["from_input"]
        assert measured[n]["from_input"]["max_mm"] == pytest.approx(alone["max_mm"], abs=0.1)
        # the same coating in the world, up to the object frame the cavity moves a little (0.006 and 0.02 mm)
        a = hollow.study.frame(n).to_world(hollow.study.coatings[n].points_object)
        b = solid.study.frame(n).to_world(solid.study.coatings[n].points_object)
        assert np.abs(a - b).max() < 0.1, np.abs(a - b).max()  # 0.32 mm when the coating followed the walls
    html = (tmp_path / "hollow" / "out" / "report.html").read_text()
    assert "hold internal cavities" in html and "e1: 2" in html


@pytest.mark.slow
def test_knee30_bones_in_scanner_poses_build_the_model_of_the_data_set_poses(tmp_path):
    """Every tibia moved by its own random rigid transform (turns up to 180°, shifts up to 300 mm),
    plain PLY and Scalismo landmarks: with the defaults no frame enters the model, and mode 1's
    share and the generalization equal the build in the data set's own poses within 2 %. (The
    voxels differ with the pose, and so the template: eq. 1 gave 791 / 783 points and figures
    within 0.9 %; the default tolerance 912 / 928 points, one refinement round in one pose and
    none in the other, share 0.303 / 0.299, generalization within 1.4 %.)"""
    from conftest import knee30_bone

    names, vertices, faces = knee30_bone("Tibia")
    names, vertices = names[:12], vertices[:12]
    ref, _ = knee30_in_scanner_poses(tmp_path / "ref", names, vertices, faces, move=False)
    moved, _ = knee30_in_scanner_poses(tmp_path / "moved", names, vertices, faces, seed=4)
    a = build(read_project(ref), tmp_path / "out_ref", log=None).report
    b = build(read_project(moved), tmp_path / "out_moved", log=None).report
    assert not [f for f in b["quality"]["findings"] if f["gate"] == "frame"]
    share = [r["model"]["variances_mm2"][0] / r["model"]["total_variance_mm2"] for r in (a, b)]
    assert share[1] == pytest.approx(share[0], rel=0.02)
    gen = [np.array(r["metrics"]["generalization"]["mean_mm"][:3]) for r in (a, b)]
    np.testing.assert_allclose(gen[1], gen[0], rtol=0.02)


@pytest.mark.slow
def test_verse_vertebrae_as_slicer_meshes_build_the_label_map_model(verse_dir, tmp_path):
    """The nine vertebrae as 3D Slicer exports them (LPS PLY saying so, Scalismo landmark JSON in the
    meshes' frame), built with the defaults: no frame enters the model (a flip modelled as shape
    gave mode 1 97 % of the variance), the meshes and landmarks are read in LPS, and the model is
    the label map's within the method's own noise. That noise: the label-map build with its
    spacing moved by 0.01 % changes mode 1's share by 2 % and the generalization by up to 3.5 %
    (docs/history.md, "Data as users bring it"); mesh and label map are not the same
    sampling of the surface, so the bounds are 5 % and 8 %."""
    from conftest import VERSE_FILE, VERSE_LABELS
    from foreign_data import verse_slicer_meshes

    lines = ['[template]', 'instance = "L1"', ""]
    for name, label in VERSE_LABELS.items():
        lines += ["[[instances]]", f'name = "{name}"', f'volume = "{VERSE_FILE.as_posix()}"', f"label = {label}",
                  f'landmarks = "{(verse_dir / "landmarks" / f"{name}.fcsv").as_posix()}"', ""]
    (tmp_path / "labelmap.toml").write_text("\n".join(lines))
    slicer = verse_slicer_meshes(tmp_path / "slicer", VERSE_FILE, VERSE_LABELS, verse_dir / "landmarks")
    slicer.write_text('[template]\ninstance = "L1"\n\n' + slicer.read_text())
    a = build(read_project(tmp_path / "labelmap.toml"), tmp_path / "out_a", log=None).report
    b = build(read_project(slicer), tmp_path / "out_b", log=None).report
    assert not [f for f in b["quality"]["findings"] if f["gate"] == "frame"]
    assert all(d["coordinates"] == "LPS, stated in the file" for d in b["inputs"].values())
    assert all("states LPS" in d["landmark_coordinates"] for d in b["inputs"].values())
    share = [r["model"]["variances_mm2"][0] / r["model"]["total_variance_mm2"] for r in (a, b)]
    assert share[1] == pytest.approx(share[0], rel=0.05), share
    gen = [r["metrics"]["generalization"]["mean_mm"][0] for r in (a, b)]
    assert gen[1] == pytest.approx(gen[0], rel=0.08), gen


#: per level: the truth the correspondence keeps (mean, worst mm) and the cavities of verse005's mesh
LUMBAR_LEVELS = {"L2": (0.46, 3.0, 6), "L4": (0.44, 3.0, 1)}


@pytest.mark.slow
@pytest.mark.parametrize("level", sorted(LUMBAR_LEVELS))
def test_lumbar_vertebrae_of_two_subjects_as_slicer_meshes_keep_their_surface_at_the_defaults(tmp_path, verse_dir,
                                                                                             level):
    """A lumbar level as a 3D Slicer user brings it: verse004's and three known deformations of it
    as LPS PLY with Scalismo landmarks, and verse005's (another subject) without landmarks, so
    the model method supplies its correspondence. With the defaults no mesh lies beyond the 3 mm
    gate from its coating and none is folded.

    L4: verse005's transverse processes are longer than the template instance's; the coatings of
    verse005 and of one deformation cut off process tips (3.58 and 3.43 mm), so the template is
    built again denser there (1,416 -> 1,471 points) and every instance coated again (2.93 and
    2.51 mm). Against the known deformations the correspondence gets no worse (mean 0.434 ->
    0.423 mm, worst 4.74 -> 2.34 mm, measured from verse004's own coating).

    L2: verse005's label map has six holes inside the body (1-9 voxels), which its marching cubes
    writes as six closed surfaces 3-4 mm under the body's wall (3.81 mm from the coating when
    they counted); they are not the surface (the template fills cavities) and are said, not
    gated. One vertex of the outer surface lay 3.27 mm from its coating: the template is refined
    there (1,418 -> 1,434 points, 2.59 mm), the truth the same (mean 0.4551 -> 0.4552 mm, worst
    2.22 mm both)."""
    if not (verse_dir.parent / "verse005").is_dir():
        pytest.skip(f"verse005 not found in {verse_dir.parent}")
    from conftest import VERSE_LABELS

    mean_mm, worst_mm, cavities = LUMBAR_LEVELS[level]
    two_subject_level(tmp_path, verse_dir.parent, level, VERSE_LABELS[level])
    names = ["v4_0", "v4_1", "v4_2", "v4_3"]
    out = []
    result = build(read_project(tmp_path / "project.toml"), tmp_path / "out", log=out.append)
    findings = result.report["quality"]["findings"]
    measured = {n: result.report["instances"][n]["input_surface_mm"] for n in [*names, "v5"]}
    far = {n: m["from_input"]["max_mm"] for n, m in measured.items()}
    print("largest distance of each mesh from its coating, mm:", far)
    assert max(far.values()) < 3.0, far
    assert not [f for f in findings if f["gate"] in ("input_surface", "folds", "frame")], findings
    assert measured["v5"].get("cavities", {}).get("components") == cavities, measured["v5"]
    refined = result.report["template"]["refined_at"]
    assert "v5" in refined["instances"] and refined["points"] > refined["points_before"], refined
    assert any(line.startswith("template: refined where") and line.endswith("kept") for line in out), out
    # where the points land: verse004's own coating carried by each known deformation
    import sys
    from pathlib import Path

    from conftest import VERSE_FILE

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
    from eval_correspondence import deformations
    from foreign_data import label_surface

    study = result.study
    world = {n: study.frame(n).to_world(study.coatings[n].points_object) for n in names}
    moves = deformations(4, 0, label_surface(VERSE_FILE, VERSE_LABELS[level])[2])
    errors = np.concatenate([np.linalg.norm(world[f"v4_{k}"] - (world["v4_0"] + moves[k](world["v4_0"])), axis=1)
                             for k in (1, 2, 3)])
    print(f"against the truth: mean {errors.mean():.3f}, worst {errors.max():.2f} mm")
    assert errors.mean() < mean_mm and errors.max() < worst_mm


@pytest.mark.slow
def test_l1_vertebrae_as_slicer_meshes_keep_their_surface_at_the_defaults(tmp_path, verse_dir):
    """Six L1 vertebrae as a 3D Slicer user brings them: verse004's L1 surface (marching cubes of
    its label map in world RAS) and five known smooth deformations of it (those of
    ``tools/eval_correspondence.py deformed``), each written as an LPS PLY with Scalismo landmarks
    (its 14, moved by the deformation). With the defaults the coatings keep the users' surfaces:
    no mesh lies beyond the 3 mm gate from its coating (2.41-2.74 mm at most) and none is folded.
    Before the template kept its instance's shape (its topology cleaning filled the notches and
    cut the spurs) 4 of the 6 lay beyond it (3.09-3.74 mm) and one coating was folded."""
    from conftest import VERSE_FILE, VERSE_LABELS

    names, lines = deformed_slicer_meshes(tmp_path, VERSE_FILE, VERSE_LABELS["L1"], verse_dir / "landmarks" / "L1.fcsv",
                                          6, "L1")
    (tmp_path / "project.toml").write_text("\n".join(lines))
    result = build(read_project(tmp_path / "project.toml"), tmp_path / "out", log=None)
    findings = result.report["quality"]["findings"]
    far = {n: result.report["instances"][n]["input_surface_mm"]["from_input"]["max_mm"] for n in names}
    assert max(far.values()) < 3.0, far
    assert not [f for f in findings if f["gate"] in ("input_surface", "folds", "frame")], findings
    assert result.report["template"]["surface_largest_distance_mm"] < 3.5
