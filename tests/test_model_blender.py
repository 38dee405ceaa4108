"""The model in Blender: shape keys = eigenmodes (eq. 7), animation, sampling, files, glTF."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import N_INST, add_coated, coated_population, write_foreign_statismo

pytestmark = pytest.mark.blender


@pytest.fixture()
def built(bpy_clean, population):
    bpy = bpy_clean
    add_coated(bpy, population)
    instance = bpy.data.objects["V00"]
    bpy.context.view_layer.objects.active = instance
    assert bpy.ops.ssm.build_model() == {"FINISHED"}
    # the active instance stays active (Build Template right after still finds it)
    assert bpy.context.view_layer.objects.active == instance
    from ssm.operators import model as opmodel

    obj = bpy.data.objects["SSM Model"]
    return bpy, obj, opmodel.model_from_object(obj)


@pytest.fixture(scope="module")
def population():
    return coated_population()


def test_build_model_from_coated_instances(built, population):
    from ssm_addon.model.pca import build_model

    bpy, obj, model = built
    shapes, faces, frames = population
    ref = build_model(shapes, faces, [f"V{i:02d}" for i in range(N_INST)],
                      alignment=bpy.context.scene.ssm_model.alignment)  # the scene's parameters, as Build Model's
    assert obj.ssm.role == "MODEL"
    assert list(model.instance_names) == [f"V{i:02d}" for i in range(N_INST)]
    np.testing.assert_allclose(model.variances, ref.variances, rtol=1e-6)
    np.testing.assert_allclose(model.mean, ref.mean, atol=1e-5)
    # world points through each instance's object frame, in double precision (no float32 mesh on the way)
    np.testing.assert_allclose(model.instance_points, ref.instance_points, rtol=0, atol=1e-12)
    for i in (0, 6):
        origin, axes = frames[i]
        np.testing.assert_allclose(model.instance_points_world[i], shapes[i] @ axes.T + origin, rtol=0, atol=1e-9)
    kbs = obj.data.shape_keys.key_blocks
    assert [kb.name for kb in kbs] == ["Basis"] + [f"Mode {k + 1}" for k in range(model.n_modes)]
    assert all(kb.slider_min == -3 and kb.slider_max == 3 for kb in kbs[1:])
    from ssm.operators import bridge

    np.testing.assert_allclose(bridge.get_point_attribute(obj.data, "variance"), model.point_variance, rtol=1e-5)
    assert model.params["fit"]["V03"]["mean_distance_mm"] == pytest.approx(0.3)
    colours = obj.data.color_attributes.get("correspondence")
    assert colours is not None and colours.domain == "CORNER" and len(colours.data) == 3 * len(faces)
    rgba = np.empty(len(colours.data) * 4, dtype=np.float32)
    colours.data.foreach_get("color", rgba)
    rgba = rgba.reshape(len(faces), 3, 4)
    np.testing.assert_allclose(rgba, bridge.position_colors(shapes[0])[faces])  # the template's colours
    # beside the instances, not at the world origin
    xs = [np.array(o.matrix_world.translation)[0] for o in bpy.data.objects if o.ssm.role == "INSTANCE"]
    assert obj.matrix_world.translation[0] + model.mean[:, 0].min() > max(xs)


def test_evaluated_mesh_at_mode_values_obeys_eq7(built):
    from ssm.operators import bridge

    bpy, obj, model = built
    v = np.array([1.5, -2.0, 0.7, 3.0])
    for k, val in enumerate(v):
        obj.data.shape_keys.key_blocks[f"Mode {k + 1}"].value = val
    got = bridge.evaluated_vertices(bpy.context, obj)
    expected = model.mean + np.tensordot(v * model.standard_deviations[:4], model.modes[:4], axes=1)
    scale = np.abs(model.mean).max()
    np.testing.assert_allclose(got, expected, atol=4 * scale * np.finfo(np.float32).eps * len(v))
    # and the model says these are the mode weights b = v sqrt(lambda)
    np.testing.assert_allclose(model.project(got)[:4], v * model.standard_deviations[:4], atol=1e-3)


def test_gltf_export_has_one_morph_target_per_mode(built, tmp_path):
    bpy, obj, model = built
    path = tmp_path / "model.gltf"
    for o in bpy.context.view_layer.objects:
        o.select_set(o == obj)
    bpy.ops.export_scene.gltf(filepath=str(path), export_format="GLTF_SEPARATE", export_morph=True, use_selection=True)
    doc = json.loads(path.read_text())
    assert len(doc["meshes"]) == 1
    prim = doc["meshes"][0]["primitives"][0]
    assert len(prim["targets"]) == model.n_modes
    assert doc["meshes"][0]["extras"]["targetNames"] == [f"Mode {k + 1}" for k in range(model.n_modes)]


def test_animate_modes_sweeps_each_mode_and_loops(built):
    from ssm.operators import bridge

    bpy, obj, model = built
    assert bpy.ops.ssm.animate_modes(n_modes=2, frames_per_mode=48, amplitude=2.0, cyclic=True) == {"FINISHED"}
    scene = bpy.context.scene
    kbs = obj.data.shape_keys.key_blocks
    assert (scene.frame_start, scene.frame_end) == (1, 96)
    expect = {9: (-2, 0), 25: (2, 0), 41: (-2, 0), 49: (0, 0), 57: (0, -2), 73: (0, 2), 89: (0, -2)}
    for frame, (m1, m2) in expect.items():
        scene.frame_set(frame)
        assert kbs["Mode 1"].value == pytest.approx(m1, abs=1e-6), frame
        assert kbs["Mode 2"].value == pytest.approx(m2, abs=1e-6), frame
        assert kbs["Mode 3"].value == 0.0
    # loops: one period later the same pose
    scene.frame_set(96 + 25)
    assert kbs["Mode 1"].value == pytest.approx(2.0, abs=1e-6)
    got = bridge.evaluated_vertices(bpy.context, obj)
    np.testing.assert_allclose(got, model.generate_sd([2.0]), atol=1e-4)
    assert bpy.ops.ssm.reset_modes(clear_animation=True) == {"FINISHED"}
    assert obj.data.shape_keys.animation_data is None
    assert all(kb.value == 0 for kb in kbs[1:])


def test_random_shape_and_reset(built):
    from ssm.operators import bridge

    bpy, obj, model = built
    obj.data.shape_keys.key_blocks["Mode 2"].value = 1.0
    assert bpy.ops.ssm.reset_modes() == {"FINISHED"}
    assert all(kb.value == 0 for kb in obj.data.shape_keys.key_blocks[1:])
    assert bpy.ops.ssm.random_shape(seed=7, sd_limit=3.0) == {"FINISHED"}
    sample = bpy.data.objects["SSM Sample 7"]
    assert sample.ssm.role == "SAMPLE"
    expected = model.sample(1, seed=7, sd_limit=3.0)[0]
    np.testing.assert_allclose(bridge.mesh_vertices(sample.data), expected, atol=1e-4)
    z = np.asarray(sample["ssm_z"])
    assert z.shape == (model.n_modes,) and np.all(np.abs(z) <= 3.0 + 1e-6)


def test_save_model_writes_files_and_blend_reopen_keeps_model(built, tmp_path):
    from ssm.operators import model as opmodel

    from ssm_addon.model.files import load_npz, load_statismo

    bpy, obj, model = built
    out = tmp_path / "out"
    assert bpy.ops.ssm.save_model(directory=str(out), metrics=True, plots=False, n_samples=50) == {"FINISHED"}
    back = load_npz(out / "model.npz")
    np.testing.assert_array_equal(back.modes, model.modes)
    np.testing.assert_array_equal(back.instance_points_world, model.instance_points_world)
    assert load_statismo(out / "model.h5").n_modes == model.n_modes
    report = json.loads((out / "report.json").read_text())
    assert report["metrics"]["generalization"]["method"] == "leave-one-out"
    assert report["fit_summary"]["mean_distance_mm"]["n"] == N_INST
    blend = tmp_path / "model.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    obj2 = bpy.data.objects["SSM Model"]
    again = opmodel.model_from_object(obj2)
    for key in ("mean", "modes", "variances", "instance_points", "instance_points_world"):
        np.testing.assert_array_equal(getattr(again, key), getattr(model, key))
    assert again.params == model.params
    assert bpy.ops.ssm.random_shape(seed=1) == {"FINISHED"}


def test_create_model_object_from_a_shape_model(bpy_clean, population):
    from ssm.operators import model as opmodel

    from ssm_addon.model.pca import build_model

    bpy = bpy_clean
    shapes, faces, _ = population
    model = build_model(shapes, faces, [f"s{i}" for i in range(N_INST)], n_modes=4)
    obj = opmodel.create_model_object(bpy.context, model, name="Direct")
    assert obj.name == "Direct" and obj.ssm.role == "MODEL"
    assert len(opmodel.mode_sliders(obj)) == 4
    # calling it again replaces, not duplicates
    opmodel.create_model_object(bpy.context, model, name="Direct")
    assert sum(1 for ob in bpy.data.objects if ob.name.startswith("Direct")) == 1


def test_build_model_needs_two_coated_instances(bpy_clean, population):
    bpy = bpy_clean
    add_coated(bpy, population, n=1)
    assert not bpy.ops.ssm.build_model.poll()
    with pytest.raises(RuntimeError, match="at least 2 instances first"):
        bpy.ops.ssm.build_model()
    with pytest.raises(RuntimeError, match="Build the model first"):
        bpy.ops.ssm.random_shape()


class _Layout:
    """Records panel drawing calls (no UI headless)."""

    def __init__(self, log):
        self.log = log
        self.enabled = True

    def __getattr__(self, name):
        def call(*args, **kwargs):
            self.log.append((name, args, kwargs))
            if name == "operator":
                from types import SimpleNamespace

                return SimpleNamespace()
            return self

        return call


def test_model_panel_draws_variance_bars_and_sliders(built):
    from types import SimpleNamespace

    from ssm.operators import model as opmodel

    bpy, obj, model = built
    log = []
    panel = SimpleNamespace(layout=_Layout(log))
    opmodel.SSM_PT_model.draw(panel, bpy.context)
    bars = [kw for name, _, kw in log if name == "progress"]
    shown = min(bpy.context.scene.ssm_model.show_modes, model.n_modes)
    assert len(bars) == shown
    frac = model.variances / model.total_variance
    np.testing.assert_allclose([b["factor"] for b in bars], frac[:shown], rtol=1e-6)
    assert bars[0]["text"].startswith(f"1: {100 * frac[0]:.1f} %")
    sliders = [args for name, args, _ in log if name == "prop" and args[1] == "value"]
    assert [a[0].name for a in sliders] == [f"Mode {k + 1}" for k in range(shown)]
    ops = [args[0] for name, args, _ in log if name == "operator"]
    assert {"ssm.build_model", "ssm.animate_modes", "ssm.random_shape", "ssm.reset_modes", "ssm.save_model"} <= set(ops)


def test_import_shape_model_opens_our_npz_and_a_foreign_statismo_file(bpy_clean, population, tmp_path):
    """File › Import › Shape Model: our model.npz and a statismo 0.9 file as another tool
    writes it give the mean mesh with one shape key per mode, whose evaluated shape at
    mode values v is mean + Σ v_k √λ_k q_k (float32 meshes), and the Model panel's object."""
    from ssm.operators import bridge
    from ssm.operators.scene import find_model_object, model_from_object

    from ssm_addon.model.files import save_npz
    from ssm_addon.model.pca import build_model

    bpy = bpy_clean
    shapes, faces, _frames = population
    model = build_model(shapes, faces, [f"s{i}" for i in range(len(shapes))])
    save_npz(model, tmp_path / "model.npz")
    other = write_foreign_statismo(model, tmp_path / "other.h5")  # another tool's statismo 0.9 layout
    v = np.array([1.5, -2.0, 0.7])
    for path in (tmp_path / "model.npz", other):
        assert bpy.ops.ssm.import_model(filepath=str(path)) == {"FINISHED"}
        obj = find_model_object(bpy.context)
        opened = model_from_object(obj)
        assert obj.ssm.role == "MODEL" and len(obj.data.shape_keys.key_blocks) == 1 + opened.n_modes
        for k, val in enumerate(v):
            obj.data.shape_keys.key_blocks[f"Mode {k + 1}"].value = val
        got = bridge.evaluated_vertices(bpy.context, obj)
        expected = opened.mean + np.tensordot(v * opened.standard_deviations[:3], opened.modes[:3], axes=1)
        np.testing.assert_allclose(got, expected, atol=1e-4 * max(1.0, np.abs(expected).max() / 100))
        np.testing.assert_allclose(opened.mean, model.mean, atol=1e-4)
        bpy.data.objects.remove(obj)
    (tmp_path / "bad.npz").write_bytes(b"not a model")
    n_objects = len(bpy.data.objects)
    with pytest.raises(RuntimeError, match="bad.npz"):
        bpy.ops.ssm.import_model(filepath=str(tmp_path / "bad.npz"))
    assert len(bpy.data.objects) == n_objects


def test_import_shape_model_drops_a_foreign_models_empty_modes(bpy_clean, population, tmp_path, capfd):
    """A statismo model as another tool writes it, with 12 modes of zero variance after its real
    ones: Import Shape Model makes shape keys of the real modes only and says how many it dropped."""
    import dataclasses

    from ssm.operators.scene import find_model_object, model_from_object

    from ssm_addon.model.pca import build_model

    bpy = bpy_clean
    shapes, faces, _frames = population
    model = build_model(shapes, faces, [f"s{i}" for i in range(len(shapes))])
    flat = model.modes.reshape(model.n_modes, -1).T
    basis = np.linalg.qr(np.hstack([flat, np.random.default_rng(1).normal(size=(flat.shape[0], 12))]))[0]
    padded = dataclasses.replace(model, modes=np.vstack([model.modes, basis[:, model.n_modes:].T.reshape(12, -1, 3)]),
                                 variances=np.concatenate([model.variances, np.zeros(12)]))
    path = write_foreign_statismo(padded, tmp_path / "padded.h5")
    assert bpy.ops.ssm.import_model(filepath=str(path)) == {"FINISHED"}
    obj = find_model_object(bpy.context)
    assert model_from_object(obj).n_modes == model.n_modes
    assert len(obj.data.shape_keys.key_blocks) == 1 + model.n_modes
    assert f"12 of {model.n_modes + 12} modes have zero variance" in capfd.readouterr().out
