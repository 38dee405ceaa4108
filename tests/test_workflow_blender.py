"""The interactive workflow end to end in Blender, every step through ``bpy.ops``.

Import label maps -> import landmark files -> Build Template -> Coat Template -> Build
Model -> Animate/Random/Reset, on a small synthetic population (the demo generator), and
every SSM sidebar panel drawn against a stand-in layout that checks each property and
operator the panel asks for exists.
"""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = pytest.mark.blender


def _ssm_panels(bpy):
    panels = [getattr(bpy.types, name) for name in dir(bpy.types) if name.startswith("SSM_PT_")]
    return sorted(panels, key=lambda p: getattr(p, "bl_order", 0))


def _draw_all_panels(bpy, layout_recorder):
    log = []
    for panel in _ssm_panels(bpy):
        assert panel.bl_category == "SSM" and panel.bl_space_type == "VIEW_3D"
        if hasattr(panel, "poll") and not panel.poll(bpy.context):
            continue
        panel.draw(type("P", (), {"layout": layout_recorder(log)})(), bpy.context)
    return log


@pytest.fixture(scope="module")
def population(tmp_path_factory):
    from ssm_addon.cli.demo import make_demo_population

    folder = tmp_path_factory.mktemp("population")
    make_demo_population(folder, n=4, seed=3)
    return folder


@pytest.mark.slow
def test_workflow_from_import_to_model_through_bpy_ops(bpy_clean, population, layout_recorder):
    from ssm_addon import meshutil

    bpy = bpy_clean
    assert len(_ssm_panels(bpy)) >= 6
    _draw_all_panels(bpy, layout_recorder)  # an empty scene draws too

    volumes = sorted(population.glob("demo_*.nii.gz"))
    instances = []
    for path in volumes:
        before = set(bpy.data.objects)
        assert bpy.ops.ssm.import_segmentation(filepath=str(path), label=20, spacing_mm=1.0) == {"FINISHED"}
        (obj,) = [o for o in bpy.data.objects if o not in before and o.ssm.role == "INSTANCE"]
        instances.append(obj)
        stem = path.name.removesuffix(".nii.gz")
        (lm_file,) = [p for p in population.glob(f"{stem}.*") if not p.name.endswith(".nii.gz")]
        for o in bpy.context.view_layer.objects:
            o.select_set(o == obj)
        bpy.context.view_layer.objects.active = obj
        assert bpy.ops.ssm.import_landmarks(filepath=str(lm_file), add_to_schema=True) == {"FINISHED"}
    names = [n.landmark for n in bpy.context.scene.ssm_landmarks.names]
    assert len(names) == 13

    bpy.context.view_layer.objects.active = instances[0]
    assert bpy.ops.ssm.build_template() == {"FINISHED"}
    template = bpy.data.objects["SSM Template"]
    assert template.ssm.role == "TEMPLATE" and template.ssm.instance == instances[0]
    from ssm.operators import bridge

    faces = bridge.mesh_triangles(template.data)
    assert meshutil.is_closed_manifold(faces).ok
    assert meshutil.genus(len(template.data.vertices), faces) == 1

    assert bpy.ops.ssm.coat_template() == {"FINISHED"}
    coated = [o for o in bpy.data.objects if o.ssm.role == "COATED"]
    assert {o.ssm.instance for o in coated} == set(instances)
    from ssm_addon.coating.coating import FitFigures

    for obj in coated:
        fit = FitFigures.from_json(obj.ssm.fit_json)
        assert fit.folded_after == 0 and fit.max_distance_mm <= 1.0, (obj.name, fit)
        np.testing.assert_array_equal(bridge.mesh_triangles(obj.data), faces)

    assert bpy.ops.ssm.build_model() == {"FINISHED"}
    model = next(o for o in bpy.data.objects if o.ssm.role == "MODEL")
    keys = model.data.shape_keys.key_blocks
    assert [k.name for k in keys] == ["Basis", "Mode 1", "Mode 2", "Mode 3"]  # n - 1 modes for n = 4

    bpy.context.view_layer.objects.active = model
    assert bpy.ops.ssm.animate_modes() == {"FINISHED"}
    assert bpy.ops.ssm.random_shape(seed=1) == {"FINISHED"}
    bpy.context.view_layer.objects.active = model
    keys[1].value = 1.5
    assert bpy.ops.ssm.reset_modes() == {"FINISHED"}
    assert all(k.value == 0.0 for k in keys[1:])

    log = _draw_all_panels(bpy, layout_recorder)  # the model active
    bpy.context.view_layer.objects.active = instances[1]
    log += _draw_all_panels(bpy, layout_recorder)  # an instance active
    ops = {x[1] for x in log if x[0] == "operator"}
    assert {"ssm.import_segmentation", "ssm.place_landmarks", "ssm.build_template", "ssm.coat_template",
            "ssm.build_model", "ssm.animate_modes", "ssm.save_project"} <= ops  # fmt: skip
