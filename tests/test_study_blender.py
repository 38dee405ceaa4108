"""One study, two front ends: Blender and the command line give the same numbers.

The interactive workflow through ``bpy.ops`` (import, landmark files, template, coating,
model), Save Project, then the headless build of that project file: the same mean,
modes and variances to 1e-6. Plus: every parameter is a Blender property derived from
its one definition, Save -> Open -> Save gives the same bytes, a saved and re-opened
.blend continues exactly, renaming and re-coating replace rather than duplicate.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import VERSE_FILE, VERSE_LABELS, add_coated, coated_population

from ssm_addon.base import params as P
from ssm_addon.pipeline.project import read_project
from ssm_addon.pipeline.project_build import build

pytestmark = pytest.mark.blender


def _select(bpy, obj):
    for o in bpy.context.view_layer.objects:
        o.select_set(o == obj)
    bpy.context.view_layer.objects.active = obj


def _verse_workflow(bpy, verse_dir, names=("L1", "L2", "L3")):
    """Import, landmarks, template, coating, model, all through bpy.ops; returns the instances."""
    insts = {}
    for name in names:
        before = set(bpy.data.objects)
        assert bpy.ops.ssm.import_segmentation(filepath=str(VERSE_FILE), label=VERSE_LABELS[name]) == {"FINISHED"}
        (obj,) = [o for o in bpy.data.objects if o not in before and o.ssm.role == "INSTANCE"]
        assert obj.name == f"sub-verse004_seg-vert_msk label {VERSE_LABELS[name]}"  # the default name pattern
        obj.name = name  # what a user does: rename it to the vertebra
        insts[name] = obj
        _select(bpy, obj)
        assert bpy.ops.ssm.import_landmarks(filepath=str(verse_dir / "landmarks" / f"{name}.fcsv")) == {"FINISHED"}
    _select(bpy, insts[names[0]])
    assert bpy.ops.ssm.build_template() == {"FINISHED"}
    assert bpy.ops.ssm.coat_template() == {"FINISHED"}
    assert bpy.ops.ssm.build_model() == {"FINISHED"}
    return insts


@pytest.mark.slow
def test_blender_workflow_and_headless_build_of_its_project_give_the_same_model(bpy_clean, verse_dir, tmp_path):
    from ssm.operators import model as opmodel

    bpy = bpy_clean
    _verse_workflow(bpy, verse_dir)
    blender_model = opmodel.model_from_object(opmodel.find_model_object(bpy.context))
    project_file = tmp_path / "study" / "project.toml"
    assert bpy.ops.ssm.save_project(filepath=str(project_file)) == {"FINISHED"}
    project = read_project(project_file)
    assert project.names == ("L1", "L2", "L3") and project.template_instance == "L1"
    result = build(project, tmp_path / "out", log=None)
    headless = result.model
    assert list(headless.instance_names) == list(blender_model.instance_names)
    for key in ("mean", "modes", "variances", "instance_points", "instance_points_world"):
        a, b = getattr(blender_model, key), getattr(headless, key)
        diff = float(np.abs(a - b).max())
        print(f"{key}: largest difference {diff:.3g}")
        assert diff <= 1e-6, key


@pytest.mark.slow
def test_saved_and_reopened_blend_continues_exactly(bpy_clean, verse_dir, tmp_path):
    from ssm.operators import model as opmodel
    from ssm.operators import scene

    bpy = bpy_clean
    _verse_workflow(bpy, verse_dir, names=("L2", "L3"))
    before = opmodel.model_from_object(opmodel.find_model_object(bpy.context))
    blend = tmp_path / "study.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    assert all(o.ssm.source.startswith("//") for o in scene.scene_instances(bpy.context))  # relative on save
    bpy.ops.wm.read_homefile(use_empty=True)
    scene.clear_volume_cache()
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    model_obj = opmodel.find_model_object(bpy.context)
    bpy.data.objects.remove(model_obj)
    _select(bpy, bpy.data.objects["L2"])
    assert bpy.ops.ssm.coat_template() == {"FINISHED"}  # volumes reloaded from the sources
    assert bpy.ops.ssm.build_model() == {"FINISHED"}
    after = opmodel.model_from_object(opmodel.find_model_object(bpy.context))
    for key in ("mean", "modes", "variances", "instance_points_world"):
        np.testing.assert_array_equal(getattr(after, key), getattr(before, key), err_msg=key)


@pytest.mark.slow
def test_renaming_and_coating_again_replaces_the_coated_instance(bpy_clean, verse_dir):
    bpy = bpy_clean
    insts = _verse_workflow(bpy, verse_dir, names=("L2", "L3"))
    insts["L3"].name = "third lumbar"
    assert bpy.ops.ssm.coat_template() == {"FINISHED"}
    coated = sorted(o.name for o in bpy.data.objects if o.ssm.role == "COATED")
    assert coated == ["L2 coated", "third lumbar coated"]
    assert bpy.ops.ssm.build_model() == {"FINISHED"}
    model = next(o for o in bpy.data.objects if o.ssm.role == "MODEL")
    from ssm.operators import model as opmodel

    assert list(opmodel.model_from_object(model).instance_names) == ["L2", "third lumbar"]


# ------------------------------------------------------------------------------ parameters
def test_every_parameter_is_a_blender_property_with_the_core_definition(bpy_clean):
    from ssm.operators.properties import SCENE_GROUPS, params_from_group

    bpy = bpy_clean
    scene = bpy.context.scene
    for key, (_group_cls, cls) in SCENE_GROUPS.items():
        group = getattr(scene, key)
        rna = group.bl_rna.properties
        for s in P.specs(cls):
            assert s.name in rna, (key, s.name)
            prop = rna[s.name]
            if s.kind == "choice":
                assert {i.identifier for i in prop.enum_items} == set(s.choices)
            if s.kind in ("float", "int") and s.minimum is not None:
                assert prop.hard_min == pytest.approx(s.minimum)
            if s.optional:
                assert f"{s.name}_auto" in rna
            assert s.help[:20].lower() in prop.description.lower()
        assert params_from_group(cls, group) == cls()  # the sidebar's defaults are the core's
    group = scene.ssm_coating
    group.k1, group.dt = 0.35, 0.3  # typed in the sidebar
    got = params_from_group(P.CoatingParams, group)
    assert (got.k1, got.dt) == (0.35, 0.3)  # as typed, not 0.3499999940395355
    group.k2 = 0.2  # k2 must exceed k1: the sidebar's values are checked like a project file's
    with pytest.raises(Exception, match="must exceed k1"):
        params_from_group(P.CoatingParams, group)


@pytest.mark.slow
def test_save_open_save_project_is_byte_identical(bpy_clean, tmp_path):
    from ssm_addon.cli import demo

    bpy = bpy_clean
    source = demo.make_demo_population(tmp_path / "pop", n=3, seed=5)
    assert bpy.ops.ssm.open_project(filepath=str(source)) == {"FINISHED"}
    s = bpy.context.scene
    s.ssm_coating.k1, s.ssm_template.r_min_mm, s.ssm_model.n_modes_auto = 0.35, 3.5, False
    s.ssm_model.n_modes = 2
    s.ssm_coating.registration_sigmas_mm = "12, 6, 3"
    first = tmp_path / "saved" / "project.toml"
    assert bpy.ops.ssm.save_project(filepath=str(first)) == {"FINISHED"}
    text = first.read_text()
    assert "k1 = 0.35\n" in text and "r_min_mm = 3.5\n" in text and "registration_sigmas_mm = [12.0, 6.0, 3.0]" in text
    landmark_bytes = {p.name: p.read_bytes() for p in (first.parent / "landmarks").iterdir()}
    bpy.ops.wm.read_homefile(use_empty=True)
    assert bpy.ops.ssm.open_project(filepath=str(first)) == {"FINISHED"}
    assert bpy.ops.ssm.save_project(filepath=str(first)) == {"FINISHED"}
    assert first.read_text() == text
    assert {p.name: p.read_bytes() for p in (first.parent / "landmarks").iterdir()} == landmark_bytes
    # and the headless reader sees exactly the scene's parameters
    project = read_project(first)
    assert project.params.coating.k1 == 0.35 and project.params.model.n_modes == 2
    assert project.params.coating.registration_sigmas_mm == (12.0, 6.0, 3.0)


# ------------------------------------------------------------------------------ usability
def test_disabled_buttons_say_why(bpy_clean):
    bpy = bpy_clean
    for op, why in ((bpy.ops.ssm.build_template, "Make the instance"), (bpy.ops.ssm.coat_template, "Build the template"),
                    (bpy.ops.ssm.build_model, "Coat the template"), (bpy.ops.ssm.animate_modes, "Build the model")):
        assert not op.poll()
        with pytest.raises(RuntimeError, match=why):
            op()


def test_reset_clears_the_animation_and_script_calls_use_the_panel_settings(bpy_clean):

    bpy = bpy_clean
    add_coated(bpy, coated_population())
    assert bpy.ops.ssm.build_model() == {"FINISHED"}
    model = next(o for o in bpy.data.objects if o.ssm.role == "MODEL")
    settings = bpy.context.scene.ssm_model
    settings.anim_modes, settings.anim_frames = 2, 12
    bpy.context.view_layer.objects.active = model
    assert bpy.ops.ssm.animate_modes() == {"FINISHED"}  # no arguments: the panel's settings
    from ssm.operators.model import mode_fcurves

    assert sorted(mode_fcurves(model)) == ["Mode 1", "Mode 2"]
    assert bpy.context.scene.frame_end == 1 + 2 * 12 - 1
    assert bpy.ops.ssm.reset_modes() == {"FINISHED"}
    assert mode_fcurves(model) == {}
    bpy.context.scene.frame_set(7)
    assert all(k.value == 0.0 for k in model.data.shape_keys.key_blocks[1:])
    settings.sample_seed = 11
    assert bpy.ops.ssm.random_shape() == {"FINISHED"}
    assert "SSM Sample 11" in bpy.data.objects


def test_the_wrong_vertebras_landmark_file_is_refused_in_blender(bpy_clean, verse_dir):
    bpy = bpy_clean
    insts = {}
    for name, file in (("L1", "L1"), ("L2", "L4")):  # L2 gets L4's landmark file
        before = set(bpy.data.objects)
        bpy.ops.ssm.import_segmentation(filepath=str(VERSE_FILE), label=VERSE_LABELS[name])
        (obj,) = [o for o in bpy.data.objects if o not in before and o.ssm.role == "INSTANCE"]
        obj.name = name
        insts[name] = obj
        _select(bpy, obj)
        bpy.ops.ssm.import_landmarks(filepath=str(verse_dir / "landmarks" / f"{file}.fcsv"))
    _select(bpy, insts["L1"])
    assert bpy.ops.ssm.build_template() == {"FINISHED"}
    with pytest.raises(RuntimeError, match=r"instance 'L2': landmark .* mm from the instance's surface"):
        bpy.ops.ssm.coat_template()
    assert not [o for o in bpy.data.objects if o.ssm.role == "COATED"]  # nothing shown as a fit
