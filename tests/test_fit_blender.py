"""Fit Model in Blender: the model's sliders show the fit; Edit Mode selection completes a shape."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import add_coated, coated_population, random_rotation, synthetic_population

pytestmark = pytest.mark.blender


@pytest.fixture()
def scene_with_model(bpy_clean):
    bpy = bpy_clean
    population = coated_population()
    add_coated(bpy, population)
    assert bpy.ops.ssm.build_model() == {"FINISHED"}
    bpy.context.scene.ssm_fit.noise_mm = 0.05  # the targets below are exact model shapes
    from ssm.operators import model as opmodel

    model_obj = opmodel.find_model_object(bpy.context)
    return bpy, model_obj, opmodel.model_from_object(model_obj)


def _target(bpy, model, z):
    from ssm.operators import bridge

    shape = model.generate(np.asarray(z) * model.standard_deviations[: len(z)])
    obj = bridge.new_mesh_object(bpy.context, "New bone", shape, model.faces, matrix_world=np.eye(4))
    for o in bpy.context.view_layer.objects:
        o.select_set(o == obj)
    bpy.context.view_layer.objects.active = obj
    return obj, shape


def test_fit_model_sets_the_sliders_to_the_fitted_coefficients(scene_with_model):
    bpy, model_obj, model = scene_with_model
    z = [1.2, -0.6, 0.3]
    target, shape = _target(bpy, model, z)
    assert bpy.ops.ssm.fit_model() == {"FINISHED"}
    from ssm.operators.scene import mode_keys

    values = [kb.value for kb in mode_keys(model_obj)[:3]]
    np.testing.assert_allclose(values, z, atol=0.1)
    fitted = bpy.data.objects["New bone fitted"]
    from ssm.operators import bridge

    np.testing.assert_allclose(bridge.mesh_vertices(fitted.data), shape, atol=0.3)
    sd = bridge.get_point_attribute(fitted.data, "posterior_sd_mm")
    assert sd is not None and len(sd) == model.n_points and "posterior_sd" in fitted.data.color_attributes


def test_edit_mode_selection_completes_the_shape_with_its_uncertainty(scene_with_model):
    bpy, model_obj, model = scene_with_model
    target, shape = _target(bpy, model, [0.8, 0.4])
    keep = shape[:, 0] > np.quantile(shape[:, 0], 0.8)  # one end: 20 % of the vertices
    _select_vertices(bpy, target, keep)  # exactly these (a new mesh's faces are all selected)
    assert bpy.ops.ssm.fit_model() == {"FINISHED"}
    bpy.ops.object.mode_set(mode="OBJECT")
    from ssm.operators import bridge

    fitted = bpy.data.objects["New bone fitted"]
    sd = bridge.get_point_attribute(fitted.data, "posterior_sd_mm")
    assert np.all(np.isfinite(sd)) and sd.min() > 0
    err = np.linalg.norm(bridge.mesh_vertices(fitted.data) - shape, axis=1)
    assert err[~keep].mean() < 0.5  # the unselected 80 % predicted from one end (mm)


def test_a_failed_fit_leaves_the_scene_as_it_was(scene_with_model):
    bpy, model_obj, model = scene_with_model
    target, _ = _target(bpy, model, [0.5])
    target.data.vertices.foreach_set("select", np.zeros(len(target.data.vertices), bool))
    target.data.vertices[0].select = True
    names = sorted(o.name for o in bpy.data.objects)
    with pytest.raises(RuntimeError, match="select at least 10 vertices"):
        bpy.ops.ssm.fit_model(partial=True)
    assert sorted(o.name for o in bpy.data.objects) == names


def test_a_fitted_value_beyond_three_sd_is_shown_not_clamped(scene_with_model):
    """A target 4.5 SD along mode 1: the slider shows 4.5 (its range widened past ±3, not
    set to ±10), and the others keep ±3."""
    bpy, model_obj, model = scene_with_model
    _target(bpy, model, [4.5, 0.0, 0.0])
    assert bpy.ops.ssm.fit_model() == {"FINISHED"}
    from ssm.operators.scene import mode_keys

    keys = mode_keys(model_obj)
    assert abs(keys[0].value - 4.5) < 0.2 and keys[0].slider_max >= keys[0].value and keys[0].slider_max < 10
    assert all(kb.slider_min == -3.0 and kb.slider_max == 3.0 for kb in keys[1:] if abs(kb.value) < 2.5)


@pytest.mark.parametrize("pose_step", ["joint", "alternating"])
def test_fit_model_gives_the_apis_fit_for_each_pose_step(scene_with_model, pose_step):
    # Blender and ssm fit are one computation: the operator's fitted mesh is fit_any_pose's
    # with the scene's fit parameters (a model shape turned and moved, not an instance)
    from ssm.operators import bridge
    from ssm.operators.properties import scene_params

    from ssm_addon.fitting.fit import Target, fit_any_pose

    bpy, model_obj, model = scene_with_model
    bpy.context.scene.ssm_fit.pose_step = pose_step
    target, _shape = _target(bpy, model, [0.8, 0.4])
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    target.matrix_world = [[*turn[0], 5.0], [*turn[1], -3.0], [*turn[2], 2.0], [0.0, 0.0, 0.0, 1.0]]
    bpy.context.view_layer.update()
    params = scene_params(bpy.context, "ssm_fit")
    assert params.pose_step == pose_step
    expected, _search = fit_any_pose(model, Target.from_mesh(bridge.object_world_vertices(target), model.faces),
                                     params=params)
    assert bpy.ops.ssm.fit_model() == {"FINISHED"}
    fitted = bpy.data.objects[f"{target.name} fitted"]
    np.testing.assert_allclose(bridge.mesh_vertices(fitted.data), expected.points, atol=1e-6)


def _select_vertices(bpy, obj, keep):
    """Edit Mode on ``obj`` with exactly the vertices ``keep`` selected."""
    import bmesh

    bpy.ops.object.mode_set(mode="EDIT")
    bm = bmesh.from_edit_mesh(obj.data)
    bm.verts.ensure_lookup_table()
    for f in bm.faces:
        f.select_set(False)
    for v in bm.verts:
        v.select_set(bool(keep[v.index]))
    bm.select_flush_mode()
    bmesh.update_edit_mesh(obj.data)


def _fit_json(bpy, name):
    import json

    return json.loads(bpy.data.objects[f"{name} fitted"]["ssm_fit_json"])


def test_fit_model_says_the_warnings_of_ssm_fit(bpy_clean, tmp_path):
    """One owner of a fit's verdicts (ssm_addon.fitting.verdict): Blender's Fit Model and ``ssm fit``
    give the same warnings on the same target, a whole shape in metres and a partial one that
    covers under a tenth of the model."""
    from scipy.spatial import ConvexHull
    from ssm.operators import bridge
    from ssm.operators import model as opmodel
    from ssm.operators.properties import scene_params

    from ssm_addon.fitting.batch import FitTarget, fit_to_folder
    from ssm_addon.formats.meshes import write_ply

    bpy = bpy_clean
    shapes, mean, _fields, _lam = synthetic_population(n=10, n_points=300, noise_mm=0.2, seed=3)
    rng = np.random.default_rng(0)
    add_coated(bpy, (shapes, ConvexHull(mean).simplices,
                     [(rng.normal(scale=50, size=3), random_rotation(rng)) for _ in range(10)]), n=10)
    assert bpy.ops.ssm.build_model() == {"FINISHED"}
    bpy.context.scene.ssm_fit.noise_mm = 0.05
    model = opmodel.model_from_object(opmodel.find_model_object(bpy.context))
    params = scene_params(bpy.context, "ssm_fit")
    # a whole shape given in metres: fitted from the pose search, and said to be another unit
    shape = model.generate(np.array([0.8, 0.4]) * model.standard_deviations[:2])
    target = bridge.new_mesh_object(bpy.context, "In metres", shape / 1000.0, model.faces, matrix_world=np.eye(4))
    for o in bpy.context.view_layer.objects:
        o.select_set(o == target)
    bpy.context.view_layer.objects.active = target
    write_ply(tmp_path / "metres.ply", shape / 1000.0, model.faces)
    headless = fit_to_folder(model, FitTarget("metres", mesh=tmp_path / "metres.ply"), tmp_path / "m", params=params)
    assert bpy.ops.ssm.fit_model() == {"FINISHED"}
    blender = _fit_json(bpy, target.name)
    assert "unit" in headless["warning_kinds"] and "metres" not in headless["warnings"][0]
    assert blender["warning_kinds"] == headless["warning_kinds"]
    assert blender["warnings"] == headless["warnings"]
    # a partial shape: ten vertices at one end, a thirtieth of the model's points
    target, shape = _target(bpy, model, [0.5, -0.3])
    target.name = "partial"
    keep = np.zeros(len(shape), bool)
    keep[np.argsort(shape[:, 0])[-10:]] = True
    _select_vertices(bpy, target, keep)
    assert bpy.ops.ssm.fit_model() == {"FINISHED"}
    bpy.ops.object.mode_set(mode="OBJECT")
    (tmp_path / "partial.csv").write_text("".join(f"{x},{y},{z}\n" for x, y, z in shape[keep]))
    headless = fit_to_folder(model, FitTarget("partial", points=tmp_path / "partial.csv"), tmp_path / "p",
                             params=params, partial=True)
    blender = _fit_json(bpy, "partial")
    assert "coverage" in headless["warning_kinds"]
    assert blender["warning_kinds"] == headless["warning_kinds"]
    assert blender["coverage"] == pytest.approx(headless["coverage"], abs=0.05)
