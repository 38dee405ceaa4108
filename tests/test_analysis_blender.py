"""The Analysis panel in Blender: its shape keys are the core's effect shapes; maps on the mean mesh."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import analysis_population

from ssm_addon.analysis import analyze, write_attributes
from ssm_addon.model.files import save_npz

pytestmark = pytest.mark.blender


@pytest.fixture()
def scene_with_model(bpy_clean, tmp_path):
    bpy = bpy_clean
    model, attrs, truth = analysis_population(n=20, seed=2)
    save_npz(model, tmp_path / "model.npz")
    write_attributes(attrs, tmp_path / "subjects.csv")
    assert bpy.ops.ssm.import_model(filepath=str(tmp_path / "model.npz")) == {"FINISHED"}
    return bpy, model, attrs, tmp_path


def test_analysis_shape_keys_reproduce_the_core_effects(scene_with_model, layout_recorder):
    bpy, model, attrs, tmp_path = scene_with_model
    s = bpy.context.scene.ssm_analysis
    s.attributes, s.group, s.covariates, s.permutations = str(tmp_path / "subjects.csv"), "group", "age", 199
    out = tmp_path / "analysis"
    assert bpy.ops.ssm.run_analysis(out_dir=str(out)) == {"FINISHED"}
    core = analyze(model, attrs, group="group", covariates=["age"], permutations=199)
    from ssm.operators import bridge
    from ssm.operators.scene import find_model_object

    obj = find_model_object(bpy.context)
    blocks = obj.data.shape_keys.key_blocks
    base = bridge.mesh_vertices(obj.data)
    def offset(kb):
        co = np.empty(3 * len(base), np.float32)
        kb.data.foreach_get("co", co)
        return co.reshape(-1, 3) - base

    group, age = core.effect("group: patient"), core.effect("age")
    np.testing.assert_allclose(offset(blocks["Effect: group: patient (patient − control)"]), group.displacement,
                               atol=1e-4)
    # age spans ±3 SD = ±30.6 years: the key is 10 years (Blender's sliders stop at ±10), slider ±3.06
    key = blocks["Effect: age (per 10 of age)"]
    np.testing.assert_allclose(offset(key), 10 * age.displacement, atol=1e-4)
    assert key.slider_max == pytest.approx(3 * np.std(core.attributes["age"]) / 10, rel=1e-5)
    assert "Discriminant (per within-group SD)" in blocks and "Group mean: patient" in blocks
    # the map: the group effect's normal component and its FDR on the points, colours made active
    normal = bridge.get_point_attribute(obj.data, "analysis_normal_mm")
    np.testing.assert_allclose(normal, core.effects[0].normal, atol=1e-4)
    assert "analysis_map" in obj.data.color_attributes
    # the same numbers as the core, and the files of `ssm analyze`
    doc = json.loads((out / "analysis.json").read_text())
    assert doc["group_test"]["p_value"] == core.group_test.p_value
    assert (out / "effects" / "group_patient.vtp").is_file()
    # the panel shows the tests and a slider per key
    log = []
    bpy.types.SSM_PT_analysis.draw(type("P", (), {"layout": layout_recorder(log)})(), bpy.context)
    labels = [x[1] for x in log if x[0] == "label"]
    assert ("operator", "ssm.run_analysis") in log and any(t.startswith("group: p ") for t in labels)
    assert sum(1 for x in log if x == ("prop", "value")) == len(core.effects) + 1 + 2  # effects, LDA, 2 means


def test_analysis_errors_leave_the_scene_as_it_was(scene_with_model):
    bpy, model, attrs, tmp_path = scene_with_model
    s = bpy.context.scene.ssm_analysis
    s.attributes, s.group = str(tmp_path / "subjects.csv"), "gruop"
    from ssm.operators.scene import find_model_object

    obj = find_model_object(bpy.context)
    before = [kb.name for kb in obj.data.shape_keys.key_blocks]
    with pytest.raises(RuntimeError, match="no attribute column 'gruop' .did you mean 'group'"):
        bpy.ops.ssm.run_analysis()
    assert [kb.name for kb in obj.data.shape_keys.key_blocks] == before
    assert "ssm_analysis_record" not in bpy.context.scene
