"""A joint model in Blender: one mesh whose structures are vertex groups, one slider per mode
moving every structure's shape and their relative pose together."""

from __future__ import annotations

import numpy as np
import pytest
from test_joint import _joint, _population

pytestmark = pytest.mark.blender


def test_import_shape_model_opens_a_joint_model_with_a_vertex_group_per_structure(bpy_clean, tmp_path):
    from ssm.operators import bridge
    from ssm.operators.scene import find_model_object, model_from_object

    from ssm_addon.model.files import load_npz, save_npz

    bpy = bpy_clean
    a, b, fa, fb, _t = _population(n=10)
    model = _joint(a, b, fa, fb)
    save_npz(model, tmp_path / "joint.npz")
    assert bpy.ops.ssm.import_model(filepath=str(tmp_path / "joint.npz")) == {"FINISHED"}
    obj = find_model_object(bpy.context)
    assert [vg.name for vg in obj.vertex_groups] == ["a", "b"]
    for vg in obj.vertex_groups:
        members = [v.index for v in obj.data.vertices if any(g.group == vg.index and g.weight == 1.0 for g in v.groups)]
        sl = model.structure_slice(vg.name)
        assert members == list(range(sl.start, sl.stop))
    opened = model_from_object(obj)  # the scene keeps the structures (Save Model, Fit Model read it)
    assert opened.structure_names == ("a", "b")
    np.testing.assert_array_equal(opened.structure_offsets, model.structure_offsets)
    obj.data.shape_keys.key_blocks["Mode 1"].value = 2.0  # one slider: both structures move
    got = bridge.evaluated_vertices(bpy.context, obj)
    expected = model.mean + 2.0 * model.standard_deviations[0] * model.modes[0]
    np.testing.assert_allclose(got, expected, atol=1e-3 * np.abs(model.mean).max())
    for name in ("a", "b"):
        sl = model.structure_slice(name)
        assert np.abs(got[sl] - model.mean[sl]).max() > 0.05  # the mode moves this structure too
    obj.data.shape_keys.key_blocks["Mode 1"].value = 0.0
    out = tmp_path / "saved"
    assert bpy.ops.ssm.save_model(directory=str(out), metrics=False, plots=False) == {"FINISHED"}
    back = load_npz(out / "model.npz")
    assert back.structure_names == ("a", "b")
    np.testing.assert_allclose(back.modes, model.modes, atol=1e-6)


def test_open_project_of_a_joint_project_says_where_it_is_built_and_changes_nothing(bpy_clean, tmp_path):
    from foreign_data import scalismo_landmarks, slicer_ply

    bpy = bpy_clean
    a, b, fa, fb, _t = _population(n=3)
    lines = ["[template]", "spacing = 1.0", ""]
    for i in range(3):
        slicer_ply(tmp_path / f"S{i}_a.ply", a[i], fa, space=None)
        slicer_ply(tmp_path / f"S{i}_b.ply", b[i], fb, space=None)
        scalismo_landmarks(tmp_path / f"S{i}_a.json", list("ABCD"), a[i][:4])
        scalismo_landmarks(tmp_path / f"S{i}_b.json", list("ABCD"), b[i][:4])
        lines += ["[[instances]]", f'name = "S{i}"', f'meshes = {{ a = "S{i}_a.ply", b = "S{i}_b.ply" }}',
                  f'landmarks = {{ a = "S{i}_a.json", b = "S{i}_b.json" }}', ""]
    (tmp_path / "joint.toml").write_text("\n".join(lines))
    before = sorted(o.name for o in bpy.data.objects)
    with pytest.raises(RuntimeError, match=r"joint project \(a, b\).*ssm build.*Import > Shape Model"):
        bpy.ops.ssm.open_project(filepath=str(tmp_path / "joint.toml"))
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
    a, b, fa, fb, _t = _population(n=10)
    model = _joint(a, b, fa, fb)
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
    with pytest.raises(RuntimeError, match="no structure 'c'"):
        bpy.ops.ssm.fit_model(structures="c")


def _scene_fit_params(bpy):
    from ssm.operators.properties import scene_params

    return scene_params(bpy.context, "ssm_fit")
