"""The project file, the headless build and the demo population.

Every project-file error names the file, the line (where TOML has one), the key or
instance and the problem; a failing or cancelled build leaves the output folder as it
was; the demo population consists of closed genus-1 solids whose landmarks lie on the
surface; ``jobs=2`` gives the same model as ``jobs=1``.
"""

from __future__ import annotations

import json
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest

from ssm_addon.__main__ import main
from ssm_addon.base.errors import Cancelled, InputError
from ssm_addon.cli import demo
from ssm_addon.formats.landmarks import LandmarkSet, read_landmarks, write_landmarks
from ssm_addon.pipeline.project import read_project, write_project
from ssm_addon.pipeline.project_build import build

NAMES = ("a", "b", "c", "d", "e")


def _landmarks(path: Path, names=NAMES, shift=0.0) -> Path:
    pts = np.arange(len(names) * 3, dtype=float).reshape(-1, 3) ** 1.5 + shift
    write_landmarks(path, LandmarkSet(tuple(names), pts, source=str(path)))
    return path


@pytest.fixture()
def files(tmp_path):
    """Two (dummy) volumes and matching landmark files in tmp/data."""
    data = tmp_path / "data"
    data.mkdir()
    for name in ("one", "two"):
        (data / f"{name}.nii.gz").write_bytes(b"placeholder: only existence is checked when reading the project")
        _landmarks(data / f"{name}.csv")
    return tmp_path


VALID = """\
[template]
instance = "two"
spacing = 1.5

[coating]
kernel = "biharmonic"

[model]
alignment = "rigid"

[[instances]]
name = "one"
volume = "data/one.nii.gz"
label = 20
landmarks = "data/one.csv"

[[instances]]
name = "two"
volume = "data/two.nii.gz"
landmarks = "data/two.csv"
"""


def _write(folder: Path, text: str, name="project.toml") -> Path:
    path = folder / name
    path.write_text(text)
    return path


def _error(folder: Path, text: str) -> str:
    with pytest.raises(InputError) as err:
        read_project(_write(folder, text))
    return str(err.value)


def _line_of(text: str, needle: str) -> int:
    return next(i for i, line in enumerate(text.splitlines(), 1) if needle in line)


def test_valid_project_resolves_paths_against_its_folder(files):
    proj = read_project(_write(files, VALID))
    assert proj.names == ("one", "two")
    assert proj.instances[0].volume_path == (files / "data" / "one.nii.gz").resolve()
    assert proj.instances[0].label == 20 and proj.instances[1].label is None
    assert proj.instances[1].landmarks_path == (files / "data" / "two.csv").resolve()
    assert proj.template_instance == "two" and proj.params.template.spacing_mm == 1.5
    assert proj.params.coating.kernel == "biharmonic"
    assert proj.params.model.alignment == "rigid"
    assert proj.landmark_names == NAMES


def test_paths_resolve_against_project_folder_not_cwd(files, monkeypatch):
    sub = files / "projects" / "deep"
    sub.mkdir(parents=True)
    text = VALID.replace('"data/', '"../../data/')
    monkeypatch.chdir(files / "data")
    proj = read_project(_write(sub, text))
    assert proj.instances[1].volume_path == (files / "data" / "two.nii.gz").resolve()


def test_unknown_key_names_line_and_suggests_closest(files):
    text = VALID.replace('kernel = "biharmonic"', 'kernal = "biharmonic"')
    msg = _error(files, text)
    assert f"project.toml:{_line_of(text, 'kernal')}:" in msg
    assert "unknown key 'kernal'" in msg and "did you mean 'kernel'" in msg


def test_unknown_instance_key_suggests_closest(files):
    text = VALID.replace('landmarks = "data/two.csv"', 'landmark = "data/two.csv"')
    msg = _error(files, text)
    assert f":{_line_of(text, 'landmark =')}:" in msg
    assert "unknown key 'landmark'" in msg and "did you mean 'landmarks'" in msg


def test_unknown_table_suggests_closest(files):
    msg = _error(files, VALID.replace("[coating]", "[coatings]"))
    assert "unknown table or key 'coatings'" in msg and "did you mean 'coating'" in msg


def test_template_keys_follow_template_params(files):
    from ssm_addon.base.params import TemplateParams, specs

    spec = specs(TemplateParams)[2]
    key = spec.key
    value = {"bool": "true", "int": "3", "float": "2.5", "choice": '"x"', "floats": "[1, 2]"}[spec.kind]
    text = VALID.replace("spacing = 1.5", f"spacing = 1.5\n{key}_typo = {value}")
    msg = _error(files, text)
    assert f"unknown key '{key}_typo'" in msg and f"did you mean '{key}'" in msg


@pytest.mark.parametrize("table, expected", [
    ("", 1.0),                                          # the default: one tolerance, 1 mm
    ("max_distance_mm = 0.5", 0.5),
    ('max_distance_mm = "off"', None),                  # eq. 1
    ('max_distance_mm = "OFF"', None),
    ("r_min_mm = 3.0\nr_max_mm = 8.0", None),           # a project written before the tolerance: eq. 1
    ("p = 3.0", None),
    ("r_max_mm = 8.0\nmax_distance_mm = 1.5", 1.5),     # both stated: the tolerance, capped by r_max
    ("normal_radius_mm = 4.0", 1.0),                    # not one of eq. 1's keys
])
def test_the_template_tolerance_is_the_default_and_old_projects_keep_eq_1(files, tmp_path, table, expected):
    """The template's density follows from max_distance_mm (1 mm) unless the table says "off" or
    states eq. 1's radii or exponent without a tolerance; a saved project reads back the same."""
    text = VALID.replace("spacing = 1.5", f"spacing = 1.5\n{table}")
    proj = read_project(_write(files, text))
    assert proj.params.template.max_distance_mm == expected
    again = read_project(write_project(tmp_path / "copy.toml", proj))
    assert again.params.template == proj.params.template
    if expected is None:
        assert 'max_distance_mm = "off"' in (tmp_path / "copy.toml").read_text()


def test_a_table_of_the_changed_keys_reads_back_the_same_template():
    """Writing only the changed keys must not turn a tolerance into eq. 1: r_min_mm changed with the
    default tolerance writes the tolerance too."""
    from ssm_addon.base.params import TemplateParams, from_table, to_table

    for params in (TemplateParams(r_min_mm=3.0), TemplateParams(r_min_mm=3.0, max_distance_mm=None),
                   TemplateParams(max_distance_mm=None), TemplateParams()):
        table = to_table(params, only_changed=True)
        assert from_table(TemplateParams, table) == params, table
    assert to_table(TemplateParams(r_min_mm=3.0), only_changed=True) == {"r_min_mm": 3.0, "max_distance_mm": 1.0}


def test_a_bad_template_tolerance_names_the_off_word(files):
    msg = _error(files, VALID.replace("spacing = 1.5", 'spacing = 1.5\nmax_distance_mm = "none"'))
    assert "max_distance_mm must be a number > 0 mm and <= 100 mm (or 'off': the radii of eq. 1" in msg
    assert "got string 'none'" in msg


def test_the_command_line_takes_off_for_the_template_tolerance():
    import argparse

    from ssm_addon.base.params import TemplateParams, add_arguments, from_arguments

    ap = argparse.ArgumentParser()
    add_arguments(ap, TemplateParams, prefix="template")
    assert from_arguments(ap.parse_args(["--template-max-distance-mm", "off"]), TemplateParams,
                          prefix="template").max_distance_mm is None
    assert from_arguments(ap.parse_args(["--template-max-distance-mm", "0.75"]), TemplateParams,
                          prefix="template").max_distance_mm == 0.75
    base = TemplateParams(max_distance_mm=None)  # a project with eq. 1, an option that does not touch it
    assert from_arguments(ap.parse_args(["--template-seed", "3"]), TemplateParams, prefix="template",
                          base=base).max_distance_mm is None
    with pytest.raises(SystemExit):
        ap.parse_args(["--template-max-distance-mm", "of"])
    assert "default 1.0 ('off': the radii of eq. 1 (r_min, r_max, p))" in " ".join(ap.format_help().split())


def test_the_panel_greys_out_what_the_tolerance_leaves_unused():
    from ssm_addon.base.params import TemplateParams

    on, off = TemplateParams(), TemplateParams(max_distance_mm=None)
    assert TemplateParams.inactive(lambda k: getattr(on, k)) == {"p", "radius", "curvature_percentiles"}
    assert TemplateParams.inactive(lambda k: getattr(off, k)) == frozenset()


def test_the_exact_landmarks_key_of_earlier_versions_is_read_as_the_landmark_error(files):
    """``exact_landmarks = true`` (earlier versions) is ``landmark_noise_mm = 0``; ``false`` the estimate."""
    for old, new in (("true", 0.0), ("false", None)):
        proj = read_project(_write(files, VALID + f"\n[correspondence]\nexact_landmarks = {old}\n"))
        assert proj.params.correspondence.landmark_noise_mm == new
    assert "true or false" in _error(files, VALID + "\n[correspondence]\nexact_landmarks = 1\n")
    assert "same setting" in _error(files, VALID + "\n[correspondence]\nexact_landmarks = true\n"
                                           "landmark_noise_mm = 1.0\n")


def test_missing_file_names_key_instance_and_line(files):
    text = VALID.replace("data/two.nii.gz", "data/missing.nii.gz")
    msg = _error(files, text)
    assert f":{_line_of(text, 'missing.nii.gz')}:" in msg
    assert "instance 'two'" in msg and "volume file not found" in msg and "missing.nii.gz" in msg


def test_missing_landmark_file(files):
    msg = _error(files, VALID.replace("data/one.csv", "data/nope.fcsv"))
    assert "instance 'one'" in msg and "landmarks file not found" in msg and "nope.fcsv" in msg


def test_mismatched_landmark_names_list_what_differs(files):
    _landmarks(files / "data" / "two.csv", names=("a", "b", "c", "d", "f"))
    msg = _error(files, VALID)
    assert "landmark names differ" in msg
    assert "instance 'two' (two.csv)" in msg and "missing e" in msg and "not in the schema f" in msg


def test_wrong_type_says_expected_and_got(files):
    text = VALID.replace("label = 20", 'label = "20"')
    msg = _error(files, text)
    assert f":{_line_of(text, 'label =')}:" in msg
    assert "label must be an integer, got string '20'" in msg


def test_wrong_type_of_parameter(files):
    text = VALID.replace("spacing = 1.5", 'spacing = "fine"')
    msg = _error(files, text)
    assert "[template] spacing must be a number > 0 mm and <= 50 mm, got string 'fine'" in msg


def test_bad_parameter_value(files):
    msg = _error(files, VALID.replace('kernel = "biharmonic"', 'kernel = "gaussian"'))
    assert "[coating] kernel must be one of 'biharmonic', 'thin-plate', 'hardy', got 'gaussian'" in msg


def test_toml_syntax_error_has_line_and_column(files):
    text = VALID.replace('name = "one"', 'name = "one')
    msg = _error(files, text)
    assert "TOML syntax error" in msg and f"line {_line_of(text, 'name = ' + chr(34) + 'one')}" in msg
    assert "column" in msg


def test_duplicate_instance_names(files):
    text = VALID.replace('name = "two"', 'name = "one"')
    msg = _error(files, text)
    assert "duplicate instance name 'one' (instances #1 and #2)" in msg
    assert f":{_line_of(text, 'volume = ' + chr(34) + 'data/two')-1}:" in msg


def test_no_instances(files):
    msg = _error(files, VALID.split("[[instances]]")[0])
    assert "no [[instances]]" in msg


def test_single_instance_is_not_a_population(files):
    msg = _error(files, VALID.rsplit("[[instances]]", 1)[0].replace('instance = "two"', 'instance = "one"'))
    assert "a build needs at least 3" in msg


def test_volume_and_mesh_are_exclusive(files):
    text = VALID.replace('volume = "data/two.nii.gz"', 'volume = "data/two.nii.gz"\nmesh = "data/two.nii.gz"')
    assert "exactly one of 'volume' (label map) or 'mesh'" in _error(files, text)


def test_unknown_template_instance(files):
    msg = _error(files, VALID.replace('instance = "two"', 'instance = "tow"'))
    assert "[template] instance 'tow' is not an instance name" in msg and "did you mean 'two'" in msg


def test_write_project_round_trip(files, tmp_path):
    proj = read_project(_write(files, VALID))
    out = write_project(tmp_path / "elsewhere" / "copy.toml", proj)
    text = out.read_text()
    assert '"../data/one.nii.gz"' in text  # relative to the new file
    again = read_project(out)
    assert [i.volume_path for i in again.instances] == [i.volume_path for i in proj.instances]
    assert [i.label for i in again.instances] == [i.label for i in proj.instances]
    assert again.template_instance == proj.template_instance and again.params.template.spacing_mm == proj.params.template.spacing_mm
    assert again.params.coating == proj.params.coating and again.params.model == proj.params.model and again.params.template == proj.params.template
    assert write_project(tmp_path / "elsewhere" / "copy.toml", again).read_text() == text  # byte-identical


ATTRIBUTES = VALID.replace('landmarks = "data/one.csv"\n',
                           'landmarks = "data/one.csv"\nattributes = { group = "patient", age = 63 }\n') + """
[analysis]
attributes = "subjects.csv"
group = "group"
covariates = ["age", "centroid_size"]
permutations = 500
"""


def test_attributes_come_from_the_instances_and_a_csv_and_round_trip(files, tmp_path):
    (files / "subjects.csv").write_text("name,group,age,height\none,control,70,1.8\ntwo,control,51,1.7\n"
                                        "three,control,40,1.6\n")
    proj = read_project(_write(files, ATTRIBUTES))
    t = proj.attributes
    assert t.kinds == {"group": "category", "age": "number", "height": "number"}
    got = t.aligned(["one", "two"])[0]
    # the instance's own table wins over the CSV; the CSV fills the rest
    assert got.values["group"] == ("patient", "control") and got.values["age"] == (63.0, 51.0)
    assert got.values["height"] == (1.8, 1.7)
    assert proj.params.analysis.covariates == ("age", "centroid_size") and proj.params.analysis.permutations == 500
    assert proj.params.analysis.attributes == str(files / "subjects.csv")
    out = write_project(tmp_path / "elsewhere" / "copy.toml", proj)
    text = out.read_text()
    assert 'attributes = { group = "patient", age = 63 }' in text and 'attributes = "../subjects.csv"' in text
    again = read_project(out)
    assert again.params.analysis == proj.params.analysis and again.instance_attributes == proj.instance_attributes
    assert write_project(tmp_path / "elsewhere" / "copy.toml", again).read_text() == text


@pytest.mark.parametrize("change, message", [
    (("group = \"group\"", "group = \"gruop\""), "no attribute column 'gruop' (did you mean 'group'?)"),
    (("attributes = \"subjects.csv\"", "attributes = \"missing.csv\""), "attributes file not found"),
    (("permutations = 500", "permutations = 5"), "permutations must be an integer >= 99"),
    (("attributes = { group = \"patient\", age = 63 }", "attributes = { group = [1, 2] }"),
     "attribute 'group' must be a number or a string"),
    (("attributes = { group = \"patient\", age = 63 }", "attributes = \"patient\""),
     "attributes must be a table of attributes"),
    (("[analysis]", "[study]\nattributes = \"subjects.csv\"\n[analysis]"),
     "attributes given in both [study] and [analysis]"),
])
def test_bad_attributes_in_a_project_name_the_line(files, change, message):
    (files / "subjects.csv").write_text("name,group,age\none,control,70\ntwo,control,51\n")
    text = ATTRIBUTES.replace(*change)
    assert message in _error(files, text)


def test_study_table_gives_the_attribute_file_too(files):
    (files / "subjects.csv").write_text("name,group\none,a\ntwo,b\n")
    text = VALID + '\n[study]\nattributes = "subjects.csv"\n'
    proj = read_project(_write(files, text))
    assert proj.attributes.values["group"] == ("a", "b") and not proj.params.analysis.requested
    assert "[analysis] needs attributes" in _error(files, VALID + '\n[analysis]\ngroup = "group"\n')


def test_cli_prints_input_error_and_exits_2(files, capsys):
    path = _write(files, VALID.replace("label = 20", "label = 2.5"))
    assert main(["build", str(path), "--out", str(files / "out")]) == 2
    err = capsys.readouterr().err
    assert "label must be an integer, got float 2.5" in err and "Traceback" not in err
    assert not (files / "out").exists()


# ---------------------------------------------------------------------------------------
# demo population


@pytest.fixture(scope="module")
def demo_population(tmp_path_factory):
    folder = tmp_path_factory.mktemp("demo")
    return demo.make_demo_population(folder, n=6, seed=3)


@pytest.fixture(scope="module")
def demo_surfaces(demo_population):
    """Per instance: (Euler characteristic, components, marching-cubes vertices in world mm, image)."""
    from scipy import ndimage
    from skimage.measure import marching_cubes

    out = {}
    for inst in read_project(demo_population).instances:
        img = nib.load(inst.volume_path)
        mask = np.asarray(img.dataobj) == demo.VERTEBRA_LABEL
        box = ndimage.find_objects(mask.astype(np.uint8))[0]
        verts, faces, _, _ = marching_cubes(np.pad(mask[box], 1).astype(np.float32), 0.5)
        e = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1), axis=0)
        ijk = verts - 1 + [s.start for s in box]
        world = ijk @ img.affine[:3, :3].T + img.affine[:3, 3]
        out[inst.name] = (len(verts) - len(e) + len(faces), ndimage.label(mask)[1], world, img)
    return out


def _euler(mask: np.ndarray) -> int:
    from skimage.measure import marching_cubes

    verts, faces, _, _ = marching_cubes(np.pad(mask, 1).astype(np.float32), 0.5)
    e = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1), axis=0)
    return len(verts) - len(e) + len(faces)


@pytest.mark.slow
def test_demo_shapes_are_closed_genus_one_solids(demo_population, demo_surfaces):
    """The implicit shapes are genus 1 (sampled finely); the label maps are one oblique, anisotropic solid each."""
    from scipy import ndimage

    proj = read_project(demo_population)
    truth = json.loads((demo_population.parent / "truth.json").read_text())
    assert len(proj.instances) == 6 and len(proj.landmark_names) == 13
    for inst, t in zip(proj.instances, truth["instances"]):
        shape = demo.ShapeParams(**t["shape"])
        h = 0.7
        lo, hi = demo.canonical_box(shape)
        dims = tuple(int(d) for d in np.ceil((hi - lo) / h) + 1)
        to_canon = np.diag([h, h, h, 1.0])
        to_canon[:3, 3] = lo
        fine = demo.rasterize(lambda q, s=shape: demo.vertebra_sdf(q, s), dims, to_canon)
        assert not fine[0].any() and not fine[-1].any() and not fine[:, :, 0].any() and not fine[:, :, -1].any()
        assert ndimage.label(fine)[1] == 1 and _euler(fine) == 0, inst.name  # genus (2 - chi) / 2 = 1
        _, components, _, img = demo_surfaces[inst.name]
        assert np.allclose(img.header.get_zooms(), (0.8, 0.8, 1.5))
        assert not np.allclose(img.affine[:3, :3] / np.array([0.8, 0.8, 1.5]), np.diag([-1, -1, 1]))  # oblique
        assert components == 1, inst.name
        assert (np.asarray(img.dataobj) == demo.NEIGHBOUR_LABEL).any()


def test_demo_landmarks_lie_on_the_surface(demo_population, demo_surfaces):
    from scipy.spatial import cKDTree

    proj = read_project(demo_population)
    formats = {Path(i.landmarks_path).name.split(".", 1)[1] for i in proj.instances}
    assert formats == {"fcsv", "mrk.json", "csv", "json"}
    for inst in proj.instances:
        world = demo_surfaces[inst.name][2]
        d, _ = cKDTree(world).query(read_landmarks(inst.landmarks_path).points_world)
        assert d.max() < 1.5 and np.median(d) < 0.6, (inst.name, d.round(2))


def test_demo_landmarks_match_the_generator(demo_population):
    truth = json.loads((demo_population.parent / "truth.json").read_text())
    proj = read_project(demo_population)
    for inst, t in zip(proj.instances, truth["instances"]):
        shape = demo.ShapeParams(**t["shape"])
        canon = demo.landmarks_canonical(shape)
        pose = np.array(t["canonical_to_world"])
        expected = np.array([canon[n] for n in proj.landmark_names]) @ pose[:3, :3].T + pose[:3, 3]
        assert np.allclose(inst.landmarks.points_world, expected, atol=1e-3)
        sdf = demo.vertebra_sdf(np.array(list(canon.values())), shape)
        assert np.abs(sdf).max() < 1e-9  # analytic surface points


# ---------------------------------------------------------------------------------------
# the build


def test_failing_build_leaves_output_folder_untouched(demo_population, tmp_path):
    text = demo_population.read_text().replace("label = 20", "label = 99", 1)
    bad = demo_population.with_name("bad_label.toml")
    bad.write_text(text)
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("earlier content")
    with pytest.raises(InputError, match="label 99 is not present"):
        build(read_project(bad), out, log=None, force=True)
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]
    # no temporary folder left (the cache keeps what was finished before the error, if anything)
    assert sorted(p.name for p in tmp_path.iterdir()) in (["out"], ["out", "out.cache"])


def test_cancelled_build_writes_nothing(demo_population, tmp_path):
    messages = []

    def cancelled():
        return any(m.startswith("coated") for m in messages)

    out = tmp_path / "never"
    with pytest.raises(Cancelled):
        build(read_project(demo_population), out, progress=lambda f, m: messages.append(m), cancelled=cancelled,
              log=None)
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == ["never.cache"]  # finished ones, to resume
    assert any(m.startswith("template") for m in messages)


@pytest.mark.slow
def test_parallel_build_equals_serial(demo_population, tmp_path):
    quick = demo_population.with_name("quick.toml")  # a coarser, shorter build: equality is the point here
    quick.write_text(demo_population.read_text().replace("spacing = 1.0", "spacing = 1.0\nr_min_mm = 4.0\nr_max_mm = 8.0")
                     .replace("[coating]", "[coating]\nmax_iterations = 60"))
    proj = read_project(quick)
    lines: list[str] = []
    r1 = build(proj, tmp_path / "serial", jobs=1, log=lines.append)
    r2 = build(proj, tmp_path / "parallel", jobs=2, log=None)
    m1 = np.load(tmp_path / "serial" / "model.npz", allow_pickle=False)
    m2 = np.load(tmp_path / "parallel" / "model.npz", allow_pickle=False)
    for key in ("mean", "faces", "modes", "variances", "instance_points", "instance_points_world"):
        assert np.allclose(m1[key], m2[key], rtol=0, atol=1e-9), key
    assert list(m1["instance_names"]) == list(proj.names)
    assert r1.report["metrics"].keys() == r2.report["metrics"].keys()
    for name in proj.names:
        assert (tmp_path / "serial" / "coated" / f"{name}.ply").is_file()
    assert (tmp_path / "serial" / "template.ply").is_file()
    stages = list(dict.fromkeys(line.split(":")[0] for line in lines))  # one or more lines per stage, in order
    assert stages[:5] == ["import", "template", "coating", "model", "metrics"]  # no optimisation: off by default


# ---------------------------------------------------------------------------------------
# the other subcommands


def test_info_lists_labels_with_voxel_counts(demo_population, capsys):
    inst = read_project(demo_population).instances[0]
    labels = np.asarray(nib.load(inst.volume_path).dataobj)
    assert main(["info", str(inst.volume_path)]) == 0
    out = capsys.readouterr().out
    assert "spacing: 0.8 x 0.8 x 1.5 mm" in out
    for label in (demo.VERTEBRA_LABEL, demo.NEIGHBOUR_LABEL):
        assert f"{label:6d}: {int((labels == label).sum()):9d} voxels" in out


def test_template_command_reports_genus_one_for_a_demo_vertebra(demo_population, tmp_path, capsys):
    from ssm_addon.formats.meshes import read_ply
    from ssm_addon.meshutil import genus

    inst = read_project(demo_population).instances[0]
    out = tmp_path / "template.ply"
    assert main(["template", str(inst.volume_path), "--label", "20", "--spacing", "1.0", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    verts, faces, _ = read_ply(out)
    assert f"vertices: {len(verts)}" in text and f"faces:    {len(faces)}" in text
    assert "genus:    1" in text and genus(len(verts), faces) == 1
    assert "Euler characteristic: 0" in text
    assert "density:  within " in text and "; tolerance 1 mm)" in text  # the default, and what it reached
    reached = float(text.split("density:  within ")[1].split(" mm")[0])
    assert 0.0 < reached <= 1.0
    assert main(["template", str(inst.volume_path), "--label", "20", "--max-distance-mm", "off", "--out",
                 str(tmp_path / "eq1.ply")]) == 0
    assert "density:  radii of eq. 1 (4-10 mm)" in capsys.readouterr().out
