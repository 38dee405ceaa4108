"""The pipeline's stages return their products: one coating route, results applied once, reports written once."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from ssm_addon.base.compute import Executor
from ssm_addon.cli import demo
from ssm_addon.pipeline.cache import BuildCache
from ssm_addon.pipeline.model_method import refine_correspondence
from ssm_addon.pipeline.project import read_project
from ssm_addon.pipeline.project_build import build
from ssm_addon.pipeline.runner import run
from ssm_addon.pipeline.stages import import_stage, template_stage
from ssm_addon.pipeline.study import Study, apply_stage

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    path = demo.make_demo_population(tmp_path_factory.mktemp("pipeline") / "population", n=5, seed=13)
    path.write_text(path.read_text().replace("spacing = 1.0", "spacing = 1.0\nr_min_mm = 4.0\nr_max_mm = 8.0")
                    .replace("[model]", "[model]\nspecificity_samples = 50"))
    return path


def _arrays(study: Study) -> dict:
    m = study.model
    return {"mean": m.mean, "modes": m.modes, "variances": m.variances, "points": m.instance_points,
            "world": m.instance_points_world, "faces": m.faces}


def test_streamed_cached_and_in_memory_builds_give_identical_arrays(project, tmp_path):
    stages = ("import", "template", "coating", "model")
    in_memory = run(Study.from_project(read_project(project)), stages=stages)
    cache = BuildCache(tmp_path / "cache")
    with Executor("serial", 1) as executor:
        streamed = run(Study.from_project(read_project(project)), stages=stages, executor=executor, cache=cache)
        cached = run(Study.from_project(read_project(project)), stages=stages, executor=executor, cache=cache)
    assert streamed.streamed == {"cached": 0, "computed": 5} and cached.streamed == {"cached": 5, "computed": 0}
    for other in (streamed, cached):
        for key, value in _arrays(in_memory).items():
            assert np.array_equal(value, _arrays(other)[key]), key
        assert [(f.stage, f.gate, f.instance) for f in other.findings] == [
            (f.stage, f.gate, f.instance) for f in in_memory.findings]


def test_model_method_rounds_leave_the_given_study_unchanged(project):
    text = project.read_text().replace("[coating]", '[correspondence]\nmethod = "model"\niterations = 1\n'
                                       'round_template = "mean"\n\n[coating]')
    variant = project.with_name("model_method.toml")
    variant.write_text(text)
    study = Study.from_project(read_project(variant))
    apply_stage(study, import_stage(study))
    apply_stage(study, template_stage(study))
    template = study.template
    result = refine_correspondence(study)
    assert study.coatings == {} and study.coating_start == {} and study.correspondence_rounds == []
    assert study.template is template
    assert set(result.product["coatings"]) == set(study.names) and result.product["correspondence_rounds"]
    kept = result.product["correspondence_check"].kept_round
    medoid = result.product.get("template_instance", study.template_instance) != study.template_instance
    # the mean shape when a round was kept, the medoid's template when the medoid gave it
    assert (result.product["template"] is not template) == (kept > 0 or medoid), result.product.get("template_choice")
    apply_stage(study, result)
    assert set(study.coatings) == set(study.names) and len(study.correspondence_rounds) == 1


def test_a_build_writes_report_json_once_from_its_in_memory_report(project, tmp_path, monkeypatch):
    writes = []
    original = Path.write_text

    def counting(self, *args, **kwargs):
        if self.name == "report.json":
            writes.append(self)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", counting)
    result = build(read_project(project), tmp_path / "out", log=None)
    assert len(writes) == 1
    assert json.loads((tmp_path / "out" / "report.json").read_text()) == result.report


def test_import_on_worker_processes_gives_the_volumes_of_the_import_here(project, tmp_path):
    """The model method's import runs on the build's workers (each reads a label map shared by
    several instances once); the volumes are those of the import in this process."""
    import nibabel as nib

    from ssm_addon.base.compute import Executor
    from ssm_addon.pipeline.stages import import_instances

    folder = project.parent
    first, second = (nib.load(folder / f"demo_0{i}.nii.gz") for i in (0, 1))
    a, b = np.asarray(first.dataobj), np.asarray(second.dataobj)
    shape = np.maximum(a.shape, b.shape)
    both = np.zeros((2 * shape[0], shape[1], shape[2]), a.dtype)
    both[: a.shape[0], : a.shape[1], : a.shape[2]] = a
    both[shape[0]: shape[0] + b.shape[0], : b.shape[1], : b.shape[2]] = np.where(b > 0, b + 1, 0)
    nib.save(nib.Nifti1Image(both, first.affine), tmp_path / "both.nii.gz")
    text = re.sub(r"\n(group|covariates) = [^\n]*", "", project.read_text().split("[[instances]]")[0])
    for name, volume, label in (("demo_00", folder / "demo_00.nii.gz", 20), ("left", tmp_path / "both.nii.gz", 20),
                                ("right", tmp_path / "both.nii.gz", 21), ("demo_02", folder / "demo_02.nii.gz", 20)):
        text += f'[[instances]]\nname = "{name}"\nvolume = "{volume.as_posix()}"\nlabel = {label}\n'
        text += f'landmarks = "{next(folder.glob("demo_00.*csv")).as_posix()}"\n\n' if name == "demo_00" else "\n"
    text = re.sub(r'instance = "[^"]+"', 'instance = "demo_00"', text).replace(
        "[coating]", '[correspondence]\nmethod = "model"\n\n[coating]')
    variant = tmp_path / "shared.toml"
    variant.write_text(text)
    study = Study.from_project(read_project(variant))
    here = import_instances(study)
    with Executor("processes", 2) as executor:
        there = import_instances(study, executor=executor)
    assert list(there) == list(here) == ["demo_00", "left", "right", "demo_02"]
    for n in here:
        assert np.array_equal(here[n].mask, there[n].mask) and here[n].spacing_mm == there[n].spacing_mm
        assert np.array_equal(here[n].origin_object, there[n].origin_object)
        assert np.array_equal(here[n].frame.matrix_world, there[n].frame.matrix_world)
    assert not np.array_equal(here["left"].frame.matrix_world, here["right"].frame.matrix_world)


@pytest.mark.parametrize("thickness_mm, spacing_mm, import_keeps_thin_parts, lost",
                         [(0.4, 1.0, False, True), (0.4, 1.0, True, False), (3.0, 1.0, True, False),
                          (0.4, 0.25, True, False)])
def test_a_fin_finer_than_a_voxel_is_said_lost_at_the_import_not_by_the_coating(tmp_path, monkeypatch, thickness_mm,
                                                                                spacing_mm, import_keeps_thin_parts,
                                                                                lost):
    """The input-surface finding's cause. A mesh's fin 0.4 mm thick holds no voxel centre at 1 mm:
    an import that loses it (the plain voxelization) makes its tip far from the coating because of
    the import (each far vertex farther from the voxels than those voxels from the coating). The
    import keeps it (:func:`~ssm_addon.instances.voxelize.keep_thin_parts`), so a coating that stops
    at the body cut it off, as it cuts off a 3 mm fin, which is in the voxels; at the finer spacing
    the finding names (0.25 mm) the thin fin is in the voxels too."""
    from ssm_addon.formats.meshes import write_ply
    from ssm_addon.instances import importing
    from ssm_addon.instances.importing import InstanceSpec
    from ssm_addon.meshutil import MeshLocator, marching_cubes
    from ssm_addon.pipeline.stages import beyond_the_voxels

    if not import_keeps_thin_parts:
        monkeypatch.setattr(importing, "keep_thin_parts", lambda mask, *_a, **_k: (mask, 0, 0))
    h = 0.25
    x, y, z = np.meshgrid(np.arange(-14, 25, h), np.arange(-12, 12, h), np.arange(-10, 10, h), indexing="ij")
    body = (x / 12) ** 2 + (y / 10) ** 2 + (z / 8) ** 2 <= 1
    fin = (x >= 6) & (x <= 22) & (np.abs(y) < 3) & (np.abs(z - 0.37) < thickness_mm / 2)
    origin = np.array([-14.0, -12.0, -10.0])
    verts, faces = marching_cubes(body | fin)
    verts = verts * h + origin
    coat_v, coat_f = marching_cubes(body)  # a coating that stops at the body
    coat_v = coat_v * h + origin
    write_ply(tmp_path / "finned.ply", verts, faces, space="RAS")
    spec = InstanceSpec("finned", mesh_path=tmp_path / "finned.ply")
    far = verts[MeshLocator(coat_v, coat_f).query(verts)[1] > 3.0]
    assert len(far) > 20 and far[:, 0].min() > 14.0  # the fin's tip, out along x
    found = beyond_the_voxels(far, coat_v, coat_f, spec, {"spacing_mm": spacing_mm, "frame_method": "auto",
                                                          "space": "RAS"})
    assert found["spacing_mm"] == spacing_mm
    if lost:
        assert found["count"] == len(far) and found["max_mm"] > 3.0, found
    else:
        assert found["count"] == 0 and found["max_mm"] < 1.0, found


def test_the_coating_stretch_is_the_ratio_of_the_triangles_where_the_mesh_lies_far():
    """:func:`~ssm_addon.pipeline.stages.coating_stretch`: the coating's longest edges over the
    template's on the triangles around the far points: 1 where the coating keeps the template's
    spacing, 2 on a coating twice the template's size, and only the triangles near the far points
    count (a coating stretched along x on its +x half: points far on its -x side 1, on its +x side
    more, and at most 2)."""
    from conftest import icosphere

    from ssm_addon.meshutil import MeshLocator
    from ssm_addon.pipeline.stages import coating_stretch

    def stretch(far, coating):  # the far points' nearest triangles, as the input-surface measure finds them
        return coating_stretch(MeshLocator(coating, faces).query(far, k=12)[2], coating, faces, template)

    template, faces = icosphere(10.0, 2)
    far = np.array([[-16.0, 0.0, 0.0], [-12.0, 5.0, 3.0]])
    assert stretch(far, template) == pytest.approx(1.0, abs=1e-12)
    assert stretch(2 * far, 2 * template) == pytest.approx(2.0, abs=1e-12)
    half = template * np.where(template[:, :1] > 0, [2.0, 1.0, 1.0], 1.0)
    assert stretch(far, half) == pytest.approx(1.0, abs=1e-12)
    assert 1.2 < stretch(-2 * far, half) <= 2.0  # a doubling along x: at most twice


def test_the_appearance_is_a_stage_of_its_own_run_by_the_runner_and_reported(project, tmp_path):
    """Instances naming a CT (``image``): the appearance stage (in STAGES, after the model) learns their
    boundary profiles when ``run`` runs it, its time and record are the study's, the writer stores what it
    learned and report.html says so; an image that does not hold its instance fails in the stage, by
    instance and file, before any output is written."""
    import nibabel as nib

    from ssm_addon.base.errors import InputError
    from ssm_addon.formats.label_maps import read_label_map
    from ssm_addon.pipeline.study import STAGES

    assert STAGES.index("model") < STAGES.index("appearance") < STAGES.index("metrics")
    folder = project.parent
    text = project.read_text()
    rng = np.random.default_rng(0)
    for block in re.findall(r'volume = "([^"]+)"', text):
        labels = read_label_map(folder / block)
        ct = np.where(labels.labels == 20, 400.0, 0.0) + rng.normal(scale=20.0, size=labels.labels.shape)
        nib.save(nib.Nifti1Image(ct.astype(np.float32), labels.affine), str(tmp_path / f"ct_{block}"))
    with_images = re.sub(r'volume = "([^"]+)"', lambda m: f'volume = "{m.group(1)}"\nimage = "{tmp_path / ("ct_" + m.group(1))}"',
                         text)
    (folder / "with_images.toml").write_text(with_images)
    pr = read_project(folder / "with_images.toml")
    study = Study(instances=pr.instances, template_instance=pr.template_instance, params=pr.params)
    said = []
    run(study, stages=("import", "template", "coating", "model", "appearance"), jobs=2, log=said.append)
    assert study.appearance is not None and study.appearance_record["images"] == list(study.names)
    assert "appearance" in study.timings_s and any(line.startswith("appearance: boundary profiles") for line in said)
    result = build(pr, tmp_path / "out", jobs=2, blend=False, log=None, cache="off")
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["appearance"]["images"] == list(study.names) and "appearance" in report["timings_s"]
    assert "Appearance: boundary profiles learned from the images of 5 instance(s)" in (
        tmp_path / "out" / "report.html").read_text()
    assert result.study.appearance is not None
    # an image beside its instance, not around it: refused in the stage, nothing written
    name = re.findall(r'volume = "([^"]+)"', text)[1]
    ct = nib.load(str(tmp_path / f"ct_{name}"))
    moved = ct.affine.copy()
    moved[:3, 3] += 500.0
    nib.save(nib.Nifti1Image(np.asarray(ct.dataobj), moved), str(tmp_path / f"ct_{name}"))
    with pytest.raises(InputError, match=r"instance '[^']+': its image .*ct_.* covers 0 % of the instance's surface"):
        build(read_project(folder / "with_images.toml"), tmp_path / "refused", jobs=2, blend=False, log=None,
              cache="off")
    assert not (tmp_path / "refused").exists()
