"""Template in Blender: ssm.build_template on an imported instance (synthetic torus, VerSe L1)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import VERSE_FILE, VERSE_LABELS
from scipy.spatial import cKDTree

from ssm_addon import meshutil as mu
from ssm_addon.formats import label_maps as IO

pytestmark = pytest.mark.blender


def _torus_label_map(tmp_path):
    """A torus (label 3; R = 12 mm, r = 5 mm) on an oblique 1 x 1 x 1.5 mm grid."""
    c, s = np.cos(0.4), np.sin(0.4)
    A = np.eye(4)
    A[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) * [1.0, 1.0, 1.5]
    A[:3, 3] = [30.0, -12.0, 40.0]
    shape = (44, 44, 20)
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1).reshape(-1, 3)
    world = ijk @ A[:3, :3].T + A[:3, 3]
    centre = A[:3, :3] @ ((np.array(shape) - 1) / 2) + A[:3, 3]
    x, y, z = (world - centre).T
    tor = ((np.hypot(x, y) - 12.0) ** 2 + z**2 <= 25.0).reshape(shape)
    labels = np.zeros(shape, np.uint8)
    labels[tor] = 3
    return IO.write_label_map(tmp_path / "torus.nii.gz", labels, A)


def _import(bpy, path, label):
    assert bpy.ops.ssm.import_segmentation(filepath=str(path), label=label, spacing_mm=1.0) == {"FINISHED"}
    inst = next(o for o in bpy.data.objects if o.ssm.role == "INSTANCE")
    bpy.context.view_layer.objects.active = inst
    return inst


def test_build_template_creates_coloured_template_overlaying_the_instance(bpy_clean, tmp_path):
    from ssm.operators import bridge

    bpy = bpy_clean
    inst = _import(bpy, _torus_label_map(tmp_path), 3)
    s = bpy.context.scene.ssm_template
    s.max_distance_mm_auto = True  # "Off": eq. 1's radii
    s.r_min_mm, s.r_max_mm = 2.0, 4.0
    assert bpy.ops.ssm.build_template() == {"FINISHED"}
    tpl = bpy.data.objects["SSM Template"]
    assert tpl.ssm.role == "TEMPLATE" and tpl.ssm.instance == inst
    faces = bridge.mesh_triangles(tpl.data)
    n = len(tpl.data.vertices)
    assert mu.is_closed_manifold(faces).ok and mu.genus(n, faces) == 1 and len(faces) == 2 * n
    # overlays the instance: template vertices (Blender world) lie on the instance surface
    tw = bridge.object_world_vertices(tpl)
    iw = bridge.object_world_vertices(inst)
    d, _ = cKDTree(iw).query(tw)
    assert np.percentile(d, 95) < 1.0
    # an inscribed coarse template of a thin torus: 8.3 % less volume than its voxels (7.4 % with the
    # tie order of scipy 1.17's own search, which no longer decides the triangulation)
    assert mu.signed_volume(tw, faces) == pytest.approx(inst.ssm.volume_mm3, rel=0.09)
    # correspondence colours: smooth by position on the template (default), on face corners
    stored = bridge.load_arrays(tpl, "ssm_template")
    col = tpl.data.color_attributes["correspondence"]
    assert col.domain == "CORNER" and len(col.data) == 3 * len(faces)
    rgba = np.empty(len(col.data) * 4, np.float32)
    col.data.foreach_get("color", rgba)
    np.testing.assert_allclose(rgba.reshape(-1, 3, 4), bridge.position_colors(stored["points_object"])[faces],
                               atol=1e-6)
    bpy.context.scene.ssm_display.colouring = "TRIANGLES"  # the paper's per-triangle colours (figs. 6-7)
    col.data.foreach_get("color", rgba)
    np.testing.assert_allclose(rgba.reshape(-1, 3, 4), np.repeat(bridge.triangle_index_colors(len(faces))[:, None], 3, 1),
                               atol=1e-6)
    # curvature (1/mm; a torus of r = 5 mm has |k| up to 1/5 + ...)
    curv = bridge.get_point_attribute(tpl.data, "curvature")
    assert len(curv) == n and 0.1 < np.median(curv) < 0.4
    assert tpl.data.materials[0].name == bridge.color_material().name
    params = json.loads(stored["params_json"])
    assert params["r_min_mm"] == 2.0 and params["genus"] == 1
    # the mesh is a float32 view of the float64 template
    np.testing.assert_allclose(bridge.mesh_vertices(tpl.data), stored["points_object"], atol=1e-4)
    # a second build replaces the template (one object), with the new parameters
    s.r_max_mm = 3.0
    bpy.context.view_layer.objects.active = inst
    assert bpy.ops.ssm.build_template() == {"FINISHED"}
    assert [o.name for o in bpy.data.objects if o.ssm.role == "TEMPLATE"] == ["SSM Template"]
    assert len(bpy.data.objects["SSM Template"].data.vertices) > n


def test_build_template_at_another_spacing_than_the_instance(bpy_clean, tmp_path):
    bpy = bpy_clean
    _import(bpy, _torus_label_map(tmp_path), 3)
    s = bpy.context.scene.ssm_template
    s.r_min_mm, s.r_max_mm, s.spacing_mm = 2.0, 4.0, 0.75
    assert bpy.ops.ssm.build_template() == {"FINISHED"}
    from ssm.operators import bridge

    tpl = bpy.data.objects["SSM Template"]
    assert json.loads(bridge.load_arrays(tpl, "ssm_template")["params_json"])["object_spacing_mm"] == 0.75


def test_build_template_needs_an_active_instance(bpy_clean):
    bpy = bpy_clean
    bpy.ops.mesh.primitive_cube_add()
    with pytest.raises(RuntimeError, match="context is incorrect|poll"):
        bpy.ops.ssm.build_template()
    assert "SSM Template" not in bpy.data.objects


def test_template_panel_is_registered_in_the_ssm_tab(bpy_clean):
    bpy = bpy_clean
    panel = bpy.types.SSM_PT_template
    assert panel.bl_category == "SSM" and panel.bl_order == 20
    assert hasattr(bpy.context.scene, "ssm_template")


def test_the_template_panel_offers_the_tolerance_first_and_greys_out_what_it_leaves_unused(bpy_clean,
                                                                                          layout_recorder):
    """The Template panel's first field is the one number (Max distance, with its "Off" toggle);
    under the tolerance eq. 1's exponent and radius rule are greyed out, with "Off" they are not;
    the toggle gives the core eq. 1."""
    from ssm.operators.properties import params_from_group

    from ssm_addon.base.params import TemplateParams

    bpy = bpy_clean
    scene = bpy.context.scene
    log = []
    bpy.types.SSM_PT_template.draw(type("P", (), {"layout": layout_recorder(log)})(), bpy.context)
    props = [x[1] for x in log if x[0] == "prop"]
    assert props[:2] == ["max_distance_mm_auto", "max_distance_mm"]
    assert {x[1] for x in log if x[0] == "inactive"} == {"p", "radius"}  # curvature percentiles: advanced
    assert params_from_group(TemplateParams, scene.ssm_template).max_distance_mm == pytest.approx(1.0)
    scene.ssm_template.max_distance_mm_auto = True
    log.clear()
    bpy.types.SSM_PT_template.draw(type("P", (), {"layout": layout_recorder(log)})(), bpy.context)
    assert not [x for x in log if x[0] == "inactive"]
    assert params_from_group(TemplateParams, scene.ssm_template).max_distance_mm is None
    assert TemplateParams.__dataclass_fields__["max_distance_mm"].default == 1.0


def test_a_scene_saved_before_the_tolerance_keeps_eq_1_and_one_saved_now_keeps_its_tolerance(bpy_clean, tmp_path):
    """A .blend whose [template] radii were set before the tolerance existed (no tolerance
    setting stored) builds eq. 1 when opened, as its project file would, and its panel shows
    "Off"; in this version setting a radius marks the tolerance as chosen, so a scene saved now
    keeps its tolerance; a scene that set no radius takes the default tolerance."""
    from ssm.operators.properties import params_from_group

    from ssm_addon.base.params import TemplateParams

    bpy = bpy_clean
    blend = tmp_path / "older.blend"
    group = bpy.context.scene.ssm_template
    group.r_min_mm, group.r_max_mm = 3.0, 9.0
    assert group.is_property_set("max_distance_mm_auto")  # marked as chosen by setting a radius
    assert params_from_group(TemplateParams, group).max_distance_mm == pytest.approx(1.0)
    for name in ("max_distance_mm", "max_distance_mm_auto"):  # as an older version stored it
        group.property_unset(name)
    assert params_from_group(TemplateParams, group).max_distance_mm is None
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    group = bpy.context.scene.ssm_template
    assert group.max_distance_mm_auto and group.r_min_mm == pytest.approx(3.0)  # the panel shows "Off"
    older = params_from_group(TemplateParams, group)
    assert older.max_distance_mm is None and older.r_min_mm == pytest.approx(3.0)

    bpy.ops.wm.read_homefile(use_empty=True)
    group = bpy.context.scene.ssm_template
    assert params_from_group(TemplateParams, group).max_distance_mm == pytest.approx(1.0)  # nothing set
    group.r_min_mm = 3.0
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "now.blend"))
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "now.blend"))
    group = bpy.context.scene.ssm_template
    now = params_from_group(TemplateParams, group)
    assert not group.max_distance_mm_auto and now.max_distance_mm == pytest.approx(1.0)
    assert now.r_min_mm == pytest.approx(3.0)


def test_build_template_of_verse_l1_has_genus_one(bpy_clean, verse_dir):
    from ssm.operators import bridge

    bpy = bpy_clean
    _import(bpy, VERSE_FILE, VERSE_LABELS["L1"])
    assert bpy.ops.ssm.build_template() == {"FINISHED"}
    tpl = bpy.data.objects["SSM Template"]
    faces = bridge.mesh_triangles(tpl.data)
    n = len(tpl.data.vertices)
    assert mu.is_closed_manifold(faces).ok and mu.genus(n, faces) == 1
    assert 800 < n < 2000  # the default tolerance, 1 mm (eq. 1: about 630)
