"""A joint model in Blender: an empty whose custom property per mode drives one mesh per structure,
so one slider moves every structure's shape and their relative pose together."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import joint_model, joint_population, joint_project, write_foreign_statismo

pytestmark = pytest.mark.blender


def test_import_shape_model_opens_a_joint_model_as_an_empty_driving_one_mesh_per_structure(bpy_clean, tmp_path):
    """The model is an empty with one custom property per mode; each structure a mesh parented
    to it whose mode shape keys follow that property: one slider (and one animation channel)
    moves every structure, the evaluated meshes are the model's rows of mean + v √λ q (eq. 7)."""
    from ssm.operators import bridge
    from ssm.operators.model import mode_fcurves
    from ssm.operators.scene import find_model_object, mode_sliders, model_from_object, model_parts

    from ssm_addon.model.files import load_npz, save_npz

    bpy = bpy_clean
    a, b, fa, fb, _t = joint_population(n=10)
    model = joint_model(a, b, fa, fb)
    save_npz(model, tmp_path / "joint.npz")
    assert bpy.ops.ssm.import_model(filepath=str(tmp_path / "joint.npz")) == {"FINISHED"}
    empty = find_model_object(bpy.context)
    assert empty.type == "EMPTY" and empty.ssm.role == "MODEL"
    parts = model_parts(empty)
    assert [p.name for p in parts] == ["SSM Model a", "SSM Model b"]
    assert [len(p.data.vertices) for p in parts] == [a.shape[1], b.shape[1]]
    assert [len(p.data.polygons) for p in parts] == [len(fa), len(fb)]
    bpy.context.view_layer.objects.active = parts[1]  # a structure selected: its model is the empty
    assert find_model_object(bpy.context) == empty
    opened = model_from_object(empty)  # the scene keeps the structures (Save Model, Fit Model read it)
    assert opened.structure_names == ("a", "b")
    np.testing.assert_array_equal(opened.structure_offsets, model.structure_offsets)
    sliders = mode_sliders(empty)
    assert [s.name for s in sliders] == [f"Mode {k + 1}" for k in range(model.n_modes)]
    v = np.array([2.0, -1.0])
    for slider, val in zip(sliders, v):
        slider.value = val
    bpy.context.view_layer.update()
    expected = model.mean + np.tensordot(v * model.standard_deviations[:2], model.modes[:2], axes=1)
    for part, name in zip(parts, ("a", "b")):
        sl = model.structure_slice(name)
        got = np.asarray(part.matrix_world)[:3, :3] @ bridge.evaluated_vertices(bpy.context, part).T
        got = got.T + np.asarray(part.matrix_world)[:3, 3] - np.asarray(empty.matrix_world)[:3, 3]
        np.testing.assert_allclose(got, expected[sl], atol=1e-4 * np.abs(model.mean).max())
        assert np.abs(expected[sl] - model.mean[sl]).max() > 0.05  # the modes move this structure too
    assert bpy.ops.ssm.reset_modes() == {"FINISHED"}
    assert all(s.value == 0.0 for s in mode_sliders(empty))
    assert bpy.ops.ssm.animate_modes(n_modes=2, frames_per_mode=12, amplitude=2.0) == {"FINISHED"}
    assert sorted(mode_fcurves(empty)) == ["Mode 1", "Mode 2"]  # one channel per mode, on the empty
    bpy.context.scene.frame_set(1 + 6)  # half-way through mode 1's sweep: +2 SD
    bpy.context.view_layer.update()
    kb = parts[0].data.shape_keys.key_blocks["Mode 1"]
    assert kb.value == pytest.approx(2.0, abs=1e-5) and empty["Mode 1"] == pytest.approx(2.0, abs=1e-5)
    assert bpy.ops.ssm.reset_modes() == {"FINISHED"}
    out = tmp_path / "saved"
    assert bpy.ops.ssm.save_model(directory=str(out), metrics=False, plots=False) == {"FINISHED"}
    back = load_npz(out / "model.npz")
    assert back.structure_names == ("a", "b")
    np.testing.assert_allclose(back.modes, model.modes, atol=1e-6)
    # importing again replaces the model, its structures with it
    assert bpy.ops.ssm.import_model(filepath=str(tmp_path / "joint.npz")) == {"FINISHED"}
    assert sorted(o.name for o in bpy.data.objects if o.name.startswith("SSM Model")) == [
        "SSM Model", "SSM Model a", "SSM Model b"]
    # another tool's joined statismo file: its parts become the structures

    assert bpy.ops.ssm.import_model(filepath=str(write_foreign_statismo(model, tmp_path / "j.h5"))) == {"FINISHED"}
    assert [p.name for p in model_parts(find_model_object(bpy.context))] == ["SSM Model part 1", "SSM Model part 2"]


def test_a_joint_project_does_not_mix_into_a_scene_of_one_structure(bpy_clean, tmp_path):
    """Open Project of a joint project into a scene holding a one-structure study refuses, says
    why, and changes nothing."""

    bpy = bpy_clean
    joint = joint_project(tmp_path, 3, ["[template]", "spacing = 1.0", ""], name="joint.toml")
    single = tmp_path / "single.toml"
    single.write_text("\n".join(["[template]", "spacing = 1.0", ""] + [
        line for i in range(2) for line in ("[[instances]]", f'name = "S{i}"', f'mesh = "S{i}_a.ply"',
                                            f'landmarks = "S{i}_a.json"', "")]))
    assert bpy.ops.ssm.open_project(filepath=str(single)) == {"FINISHED"}
    before = sorted(o.name for o in bpy.data.objects)
    with pytest.raises(RuntimeError, match=r"holds a study of one structure.*new"):
        bpy.ops.ssm.open_project(filepath=str(joint))
    assert sorted(o.name for o in bpy.data.objects) == before


def test_fit_as_one_structure_predicts_the_others_as_ssm_fit_does(bpy_clean, tmp_path):
    """Fit Model with Structures = "b" on a mesh of structure b alone: the model is matched to b's
    surface, a is predicted; the coefficients are those of ``ssm fit --mesh b=FILE``."""
    import json

    from ssm.operators import bridge

    from ssm_addon.fitting.batch import FitTarget, fit_structures_to_folder
    from ssm_addon.formats.meshes import write_ply
    from ssm_addon.model.files import save_npz

    bpy = bpy_clean
    a, b, fa, fb, _t = joint_population(n=10)
    model = joint_model(a, b, fa, fb)
    save_npz(model, tmp_path / "joint.npz")
    assert bpy.ops.ssm.import_model(filepath=str(tmp_path / "joint.npz")) == {"FINISHED"}
    bpy.context.scene.ssm_fit.noise_mm = 0.05  # the target is an exact model shape
    z = np.array([1.0, -0.8])
    shape = model.generate(z * model.standard_deviations[:2])
    sa, sb = model.structure_slice("a"), model.structure_slice("b")
    obj = bridge.new_mesh_object(bpy.context, "Subject b", shape[sb], fb, matrix_world=np.eye(4))
    bridge.select_only(bpy.context, [obj], active=obj)
    assert bpy.ops.ssm.fit_model(structures="b") == {"FINISHED"}
    fitted = bpy.data.objects["Subject b fitted"]
    from ssm.operators.scene import find_model_object, mode_sliders

    z_fit = [sl.value for sl in mode_sliders(find_model_object(bpy.context))]
    got = bridge.mesh_vertices(fitted.data)
    scale = np.abs(model.mean).max()
    assert np.abs(got[sb] - shape[sb]).max() < 0.01 * scale
    # a, never seen, is the model's prediction from b: b's turn and the subject's pose trade off
    # (a sits 32 mm away), and the posterior SD says so honestly
    sd = bridge.get_point_attribute(fitted.data, "posterior_sd_mm")
    assert sd[sa].mean() > 3 * sd[sb].mean()
    err = np.linalg.norm(got[sa] - shape[sa], axis=1)
    assert np.mean(err <= 2 * sd[sa]) >= 0.9
    write_ply(tmp_path / "b.ply", shape[sb], fb)
    doc = fit_structures_to_folder(model, {"b": FitTarget(name="b", mesh=tmp_path / "b.ply")}, tmp_path / "fit",
                                   params=_scene_fit_params(bpy))
    blender = json.loads(fitted["ssm_fit_json"])
    np.testing.assert_allclose(blender["coefficients"], doc["coefficients"], atol=1e-3)
    np.testing.assert_allclose(z_fit, blender["coefficients"], atol=1e-6)  # the sliders show the fit
    with pytest.raises(RuntimeError, match="no structure 'c'"):
        bpy.ops.ssm.fit_model(structures="c")


def _scene_fit_params(bpy):
    from ssm.operators.properties import scene_params

    return scene_params(bpy.context, "ssm_fit")


def test_blenders_gltf_importer_opens_a_joint_model_glb_with_shared_mode_keys(bpy_clean, tmp_path):
    """Blender's own glTF importer: one object whose shape keys (the modes) move both structures,
    a material per structure (Separate by Material gives one object each)."""
    from ssm_addon.model.files import write_exchange_meshes

    bpy = bpy_clean
    a, b, fa, fb, _t = joint_population(n=8)
    model = joint_model(a, b, fa, fb)
    written = write_exchange_meshes(model, tmp_path, modes=3, vtk=False)
    assert bpy.ops.import_scene.gltf(filepath=written["gltf"]) == {"FINISHED"}
    obj = next(o for o in bpy.data.objects if o.type == "MESH")
    assert len(obj.data.vertices) == model.n_points and [m.name for m in obj.data.materials] == ["a", "b"]
    assert [k.name for k in obj.data.shape_keys.key_blocks][1:] == [f"Mode {i} (+1 SD)" for i in (1, 2, 3)]
    by_material = np.array([p.material_index for p in obj.data.polygons])
    assert np.bincount(by_material).tolist() == [len(fa), len(fb)]
    # Blender's importer turns glTF's +Y up back to its +Z up: the model stands as it was built (m)
    m = np.array(obj.matrix_world)
    got = np.array([v.co for v in obj.data.vertices]) @ m[:3, :3].T + m[:3, 3]
    np.testing.assert_allclose(got.min(axis=0), model.mean.min(axis=0) / 1000, atol=1e-6)
    np.testing.assert_allclose(got.max(axis=0), model.mean.max(axis=0) / 1000, atol=1e-6)


def test_a_headless_joint_builds_blend_holds_every_structure_and_saves_the_build_when_reopened(bpy_clean, tmp_path):
    """``ssm build`` of a joint project inside Blender: ``model.blend`` holds every structure's instances
    (with their landmarks) and coated meshes as Open Project + Build Joint Model leave the scene, the
    joint model's sliders drive every structure, and *Save Model* of the reopened file writes the build's
    files (each structure's template and coated meshes, the same report), refusing the inputs' folder."""
    import json
    import sys

    from ssm.operators import bridge
    from ssm.operators.scene import (
        COATING_KEY,
        find_model_object,
        mode_sliders,
        model_parts,
        scene_instances,
        scene_structures,
    )

    from ssm_addon.model.files import load_npz

    bpy = bpy_clean
    path = joint_project(tmp_path, 4, ["[template]", "spacing = 1.0", ""])
    cli = sys.modules["ssm.operators.cli"]
    assert cli.command(["build", str(path), "--out", str(tmp_path / "out")]) == 0
    model = load_npz(tmp_path / "out" / "model.npz")
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "out" / "model.blend"))
    assert scene_structures(bpy.context) == ["a", "b"]
    objs = scene_instances(bpy.context)
    assert sorted(o.name for o in objs) == sorted(f"S{i} {s}" for i in range(4) for s in "ab")
    assert all(len([c for c in o.children if c.ssm.role == "LANDMARK"]) == 4 for o in objs)
    coated = [o for o in bpy.data.objects if o.ssm.role == "COATED"]
    assert len(coated) == 8
    for o in coated:  # each coated mesh is the build's: its world points are the model's rows of that subject
        inst = o.ssm.instance
        i = list(model.instance_names).index(inst.ssm.subject)
        pts = bridge.load_arrays(o, COATING_KEY)["points_object"]
        sl = model.structure_slice(inst.ssm.structure)
        assert pts.shape == (sl.stop - sl.start, 3)
        ply = (tmp_path / "out" / "structures" / inst.ssm.structure / "coated" / f"{inst.ssm.subject}.ply")
        assert ply.is_file()
        np.testing.assert_allclose(model.instance_points_world[i][sl].mean(axis=0), np.asarray(
            inst.matrix_world)[:3, :3] @ pts.mean(axis=0) + np.asarray(inst.matrix_world)[:3, 3], atol=2.0)
    empty = find_model_object(bpy.context)
    parts = model_parts(empty)
    assert [p.name for p in parts] == ["SSM Model a", "SSM Model b"]
    mode_sliders(empty)[0].value = 1.5
    bpy.context.view_layer.update()
    for part, name in zip(parts, ("a", "b")):
        sl = model.structure_slice(name)
        got = bridge.evaluated_vertices(bpy.context, part)
        np.testing.assert_allclose(got, model.mean[sl] + 1.5 * model.standard_deviations[0] * model.modes[0][sl],
                                   atol=1e-4 * np.abs(model.mean).max())
    mode_sliders(empty)[0].value = 0.0
    # Save Model of the reopened file: the build's writer, from what the .blend keeps
    assert bpy.ops.ssm.save_model(directory=str(tmp_path / "saved")) == {"FINISHED"}
    saved = json.loads((tmp_path / "saved" / "report.json").read_text())
    built = json.loads((tmp_path / "out" / "report.json").read_text())
    assert saved["joint"]["structures"] == built["joint"]["structures"]
    assert saved["joint"]["shape_pose"] == built["joint"]["shape_pose"]
    assert saved["metrics"] == built["metrics"] and saved["instances"] == built["instances"]
    assert sorted((f["instance"], f["gate"]) for f in saved["quality"]["findings"]) == sorted(
        (f["instance"], f["gate"]) for f in built["quality"]["findings"])
    for name in "ab":
        assert (tmp_path / "saved" / "structures" / name / "template.ply").read_bytes() == (
            tmp_path / "out" / "structures" / name / "template.ply").read_bytes()
        for i in range(4):
            assert (tmp_path / "saved" / "structures" / name / "coated" / f"S{i}.ply").read_bytes() == (
                tmp_path / "out" / "structures" / name / "coated" / f"S{i}.ply").read_bytes()
    resaved = load_npz(tmp_path / "saved" / "model.npz")
    for key in ("mean", "modes", "variances", "instance_points_world"):
        np.testing.assert_array_equal(getattr(resaved, key), getattr(model, key), err_msg=key)
    # the build's rule: never into the folder of an input (the subjects' meshes are in tmp_path)
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(RuntimeError, match="input"):
        bpy.ops.ssm.save_model(directory=str(tmp_path))
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_a_joint_project_opened_and_built_in_blender_gives_the_headless_model(bpy_clean, tmp_path, layout_recorder):
    """Open Project of a joint project makes one object per structure per subject with its
    landmarks; Build Joint Model runs the build's computation on what the scene holds: the same
    joint model as ``ssm build`` of the project, and each structure's coated meshes in the scene.
    The single-structure operators step aside."""
    from ssm.operators.scene import find_model_object, model_from_object, scene_instances, scene_structures

    from ssm_addon.model.files import load_npz
    from ssm_addon.pipeline.project import read_project
    from ssm_addon.pipeline.project_build import build

    bpy = bpy_clean
    path = joint_project(tmp_path, 4, ["[template]", "spacing = 1.0", "", "[[structures]]", 'name = "b"',
                                       "template = { r_min_mm = 3.0 }", ""])
    assert bpy.ops.ssm.open_project(filepath=str(path)) == {"FINISHED"}
    assert scene_structures(bpy.context) == list(read_project(path).structures) == ["b", "a"]  # the project's order
    objs = scene_instances(bpy.context)
    assert sorted(o.name for o in objs) == sorted(f"S{i} {s}" for i in range(4) for s in "ab")
    assert all(len([c for c in o.children if c.ssm.role == "LANDMARK"]) == 4 for o in objs)
    assert not bpy.ops.ssm.build_template.poll() and not bpy.ops.ssm.build_model.poll()
    assert bpy.ops.ssm.build_joint_model() == {"FINISHED"}
    blender = model_from_object(find_model_object(bpy.context))
    build(read_project(path), tmp_path / "out", jobs=2, log=None, blender_hook=None)
    headless = load_npz(tmp_path / "out" / "model.npz")
    assert blender.structure_names == headless.structure_names == ("b", "a")
    np.testing.assert_array_equal(blender.structure_offsets, headless.structure_offsets)
    for key in ("mean", "modes", "variances", "instance_points_world"):
        np.testing.assert_array_equal(getattr(blender, key), getattr(headless, key), err_msg=key)
    coated = [o for o in bpy.data.objects if o.ssm.role == "COATED"]
    assert len(coated) == 8
    sl = headless.structure_slice("b")
    b_coated = next(o for o in coated if o.ssm.instance.ssm.structure == "b")
    assert len(b_coated.data.vertices) == sl.stop - sl.start
    # Save Model of the joint model built in this session: the joint build's writer and report
    import json

    assert bpy.ops.ssm.save_model(directory=str(tmp_path / "saved")) == {"FINISHED"}
    saved = json.loads((tmp_path / "saved" / "report.json").read_text())
    built = json.loads((tmp_path / "out" / "report.json").read_text())
    assert saved["joint"]["structures"].keys() == built["joint"]["structures"].keys()
    assert saved["joint"]["shape_pose"] == built["joint"]["shape_pose"]
    assert sorted((f["instance"], f["gate"]) for f in saved["quality"]["findings"]) == sorted(
        (f["instance"], f["gate"]) for f in built["quality"]["findings"])
    assert (tmp_path / "saved" / "structures" / "b" / "template.ply").is_file()
    # the Model panel of a joint scene: its one build, the joint model's sliders and the build's findings
    log = []
    from ssm.operators.model import SSM_PT_model

    SSM_PT_model.draw(type("P", (), {"layout": layout_recorder(log)})(), bpy.context)
    ops = [x[1] for x in log if x[0] == "operator"]
    assert "ssm.build_joint_model" in ops and "ssm.build_model" not in ops
    assert ("prop", '["Mode 1"]') in log
    assert any(x[0] == "label" and x[1].startswith("joint model: b, a") for x in log)
    # the build reads the scene, not the file: a landmark moved in the viewport changes the model
    inst = bpy.data.objects["S1 a"]
    emp = next(c for c in inst.children if c.ssm.role == "LANDMARK")
    emp.location.x += 3.0
    bpy.context.view_layer.update()
    assert bpy.ops.ssm.build_joint_model() == {"FINISHED"}
    moved = model_from_object(find_model_object(bpy.context))
    assert not np.array_equal(moved.mean, headless.mean)


def test_save_project_of_a_joint_scene_reads_back_as_the_same_joint_project(bpy_clean, tmp_path):
    """Save Project of a joint scene: each structure's instances, landmarks (full precision) and
    own tables as the project had them; saving, opening and saving again gives the same bytes."""

    from ssm_addon.pipeline.project import read_project

    bpy = bpy_clean
    path = joint_project(tmp_path, 3, ["[template]", "spacing = 1.0", "", "[[structures]]", 'name = "b"',
                                       "template = { r_min_mm = 3.0 }", ""])
    assert bpy.ops.ssm.open_project(filepath=str(path)) == {"FINISHED"}
    saved = tmp_path / "saved" / "joint.toml"
    assert bpy.ops.ssm.save_project(filepath=str(saved)) == {"FINISHED"}
    before, after = read_project(path), read_project(saved)
    assert list(after.structures) == list(before.structures) == ["b", "a"]
    for name in before.structures:
        a, b = before.structures[name], after.structures[name]
        assert b.params == a.params and b.template_instance == a.template_instance
        for x, y in zip(a.instances, b.instances):
            assert (x.name, x.mesh_path) == (y.name, y.mesh_path)
            np.testing.assert_array_equal(x.landmarks.points_world, y.landmarks.points_world)
    text = saved.read_text()
    bpy.ops.wm.read_homefile(use_empty=True)
    assert bpy.ops.ssm.open_project(filepath=str(saved)) == {"FINISHED"}
    assert bpy.ops.ssm.save_project(filepath=str(saved)) == {"FINISHED"}
    assert saved.read_text() == text


def test_a_joint_project_of_either_side_is_mirrored_per_subject_in_blender_as_headless(bpy_clean, tmp_path):
    """A joint project whose subjects S1 and S3 are mirror images (both structures and their landmarks
    through world x): Build Joint Model mirrors each of them with all its structures (the instance
    objects say so), shows every coating on its own instance's mesh, and gives the model ``ssm build``
    gives."""
    from foreign_data import scalismo_landmarks, slicer_ply
    from ssm.operators.scene import MIRROR_PROP, find_model_object, model_from_object

    from ssm_addon.model.files import load_npz
    from ssm_addon.pipeline.project import read_project
    from ssm_addon.pipeline.project_build import build

    bpy = bpy_clean
    path = joint_project(tmp_path, 4, ["[template]", "spacing = 1.0", ""])
    a, b, fa, fb, _t = joint_population(n=4)
    flip = np.array([-1.0, 1.0, 1.0])
    for i in (1, 3):  # as joint_project writes them, mirrored
        slicer_ply(tmp_path / f"S{i}_a.ply", a[i] * flip, fa[:, ::-1], space=None)
        slicer_ply(tmp_path / f"S{i}_b.ply", b[i] * flip, fb[:, ::-1], space=None)
        scalismo_landmarks(tmp_path / f"S{i}_a.json", list("ABCD"), (a[i] * flip)[[0, 5, 40, 100]])
        scalismo_landmarks(tmp_path / f"S{i}_b.json", list("ABCD"), (b[i] * flip)[[0, 5, 30, 50]])
    assert bpy.ops.ssm.open_project(filepath=str(path)) == {"FINISHED"}
    assert bpy.ops.ssm.build_joint_model() == {"FINISHED"}
    for i in range(4):
        for s in "ab":
            assert bpy.data.objects[f"S{i} {s}"].get(MIRROR_PROP, 0) == int(i in (1, 3)), (i, s)
    for coated in (o for o in bpy.data.objects if o.ssm.role == "COATED"):  # each on its own instance
        inst = coated.ssm.instance
        cw = np.array([coated.matrix_world @ v.co for v in coated.data.vertices])
        iw = np.array([inst.matrix_world @ v.co for v in inst.data.vertices])
        assert np.linalg.norm(cw.mean(0) - iw.mean(0)) < 1.0, inst.name
    blender = model_from_object(find_model_object(bpy.context))
    result = build(read_project(path), tmp_path / "out", jobs=2, log=None, blender_hook=None)
    headless = load_npz(tmp_path / "out" / "model.npz")
    assert result.joint.model.params["mirrored"] == ["S1", "S3"]
    for key in ("mean", "modes", "variances", "instance_points_world"):
        np.testing.assert_array_equal(getattr(blender, key), getattr(headless, key), err_msg=key)
