"""Instances in Blender: File > Import > Segmentation (SSM), meshes as instances, .blend round trip."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import VERSE_FILE, VERSE_LABELS, icosphere, write_stl_binary

from ssm_addon import meshutil as mu
from ssm_addon.formats import label_maps as IO
from ssm_addon.instances import frame as FR
from ssm_addon.instances import importing as INS
from ssm_addon.instances import volume as V

pytestmark = pytest.mark.blender


def _label_map(tmp_path, name="synth.nii.gz"):
    """Two labels on an oblique, anisotropic grid: an ellipsoid (20) and a ball (7)."""
    c, s = np.cos(0.3), np.sin(0.3)
    A = np.eye(4)
    A[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) * [0.9, 1.1, 1.6]
    A[:3, 3] = [-20.0, 14.0, 50.0]
    shape = (40, 36, 22)
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1).reshape(-1, 3)
    world = ijk @ A[:3, :3].T + A[:3, 3]
    centre = A[:3, :3] @ (np.array(shape) / 2) + A[:3, 3]
    ell = ((((world - centre) / [11.0, 7.0, 5.0]) ** 2).sum(axis=1) <= 1).reshape(shape)
    ball = (np.linalg.norm(world - (centre + [0, 0, 12.0]), axis=1) <= 3.5).reshape(shape)
    labels = np.zeros(shape, np.uint8)
    labels[ell] = 20
    labels[ball & ~ell] = 7
    return IO.write_label_map(tmp_path / name, labels, A)


def _world_vertices(obj):
    from ssm.operators import bridge

    return bridge.object_world_vertices(obj)


def _instances(bpy):
    return sorted(o.name for o in bpy.data.objects if o.ssm.role == "INSTANCE")


def test_import_creates_instance_at_its_world_position(bpy_clean, tmp_path):
    bpy = bpy_clean
    from ssm.operators import scene
    path = _label_map(tmp_path)
    assert bpy.ops.ssm.import_segmentation(filepath=str(path), label=20, spacing_mm=1.0) == {"FINISHED"}
    obj = bpy.data.objects["synth label 20"]
    assert obj.name in bpy.data.collections["SSM Instances"].objects
    assert bpy.context.scene.unit_settings.scale_length == pytest.approx(0.001)
    vol = IO.load_volume(path, 20)
    verts, _ = V.display_surface(vol)
    world = _world_vertices(obj)
    np.testing.assert_allclose(world.min(axis=0), verts.min(axis=0), atol=1e-3)
    np.testing.assert_allclose(world.max(axis=0), verts.max(axis=0), atol=1e-3)
    frame = FR.object_frame(vol)
    ssm = obj.ssm
    assert (ssm.role, ssm.source_kind, ssm.label) == ("INSTANCE", "VOLUME", 20)
    assert bpy.context.scene.ssm_template.spacing_mm == pytest.approx(1.0)
    stored = scene.stored_frame(obj)
    assert stored.method == "patient"
    # the frame is kept in double precision: exactly the core's
    np.testing.assert_array_equal(stored.origin_world, frame.origin_world)
    np.testing.assert_array_equal(stored.axes_world, frame.axes_world)
    np.testing.assert_allclose(scene.import_matrix(obj), np.array(obj.matrix_world), atol=1e-4)
    assert ssm.volume_mm3 == pytest.approx(vol.volume_mm3, rel=1e-6)
    assert obj["ssm_voxels"] == int(vol.mask.sum())
    assert bpy.path.abspath(ssm.source) == str(path)


def test_split_labels_creates_one_instance_per_label(bpy_clean, tmp_path):
    bpy = bpy_clean
    path = _label_map(tmp_path)
    bpy.ops.ssm.import_segmentation(filepath=str(path), split_labels=True, spacing_mm=1.5)
    assert _instances(bpy) == ["synth label 20", "synth label 7"]
    assert bpy.context.scene.ssm_template.spacing_mm == pytest.approx(1.5)  # one spacing for the study
    # importing the same file again replaces, it does not duplicate
    bpy.ops.ssm.import_segmentation(filepath=str(path), split_labels=True, spacing_mm=1.5)
    assert _instances(bpy) == ["synth label 20", "synth label 7"]


def test_blend_round_trip_keeps_metadata_and_reloads_the_volume(bpy_clean, tmp_path):
    bpy = bpy_clean
    from ssm.operators import instances as ops
    from ssm.operators import scene

    blend = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    path = _label_map(tmp_path)
    bpy.ops.ssm.import_segmentation(filepath=str(path), label=20, spacing_mm=1.0)
    obj = bpy.data.objects["synth label 20"]
    assert obj.ssm.source == "//synth.nii.gz"  # relative to the saved .blend
    before = {k: getattr(obj.ssm, k) for k in ("label", "volume_mm3", "source", "order")}
    frame_before, import_before = scene.stored_frame(obj), scene.import_matrix(obj)
    ov_before = ops.instance_object_volume(bpy.context, obj)
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.read_homefile(use_empty=True)
    assert "synth label 20" not in bpy.data.objects
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    obj = bpy.data.objects["synth label 20"]
    assert obj.ssm.role == "INSTANCE"
    for k, v in before.items():
        assert getattr(obj.ssm, k) == v, k
    np.testing.assert_array_equal(scene.stored_frame(obj).axes_world, frame_before.axes_world)
    np.testing.assert_array_equal(scene.stored_frame(obj).origin_world, frame_before.origin_world)
    np.testing.assert_array_equal(scene.import_matrix(obj), import_before)
    scene.clear_volume_cache()
    ov = ops.instance_object_volume(bpy.context, obj)
    np.testing.assert_array_equal(ov.mask, ov_before.mask)
    np.testing.assert_allclose(ov.origin_object, ov_before.origin_object)
    np.testing.assert_allclose(ov.frame.axes_world, ov_before.frame.axes_world, atol=1e-6)
    assert ops.instance_object_volume(bpy.context, obj) is ov  # cached
    ref = INS.load_object(path, label=20, spacing_mm=1.0)
    np.testing.assert_array_equal(ov.mask, ref.mask)


def test_moving_an_instance_keeps_file_world_coordinates(bpy_clean, tmp_path):
    bpy = bpy_clean
    from ssm.operators import scene as ops

    path = _label_map(tmp_path)
    bpy.ops.ssm.import_segmentation(filepath=str(path), label=7)
    obj = bpy.data.objects["synth label 7"]
    p_file = np.array([[1.0, 2.0, 3.0], [-4.0, 5.0, 60.0]])
    np.testing.assert_allclose(ops.blender_to_file_world(obj, p_file), p_file, atol=1e-4)
    world_before = _world_vertices(obj)
    obj.location = (obj.location[0] + 30.0, obj.location[1], obj.location[2] - 12.0)
    obj.rotation_euler = (0.2, 0.0, 0.5)
    bpy.context.view_layer.update()
    moved = _world_vertices(obj)
    assert np.abs(moved - world_before).max() > 10
    np.testing.assert_allclose(ops.blender_to_file_world(obj, moved), world_before, atol=1e-3)
    np.testing.assert_allclose(ops.file_to_blender_world(obj, world_before), moved, atol=1e-3)


def test_add_mesh_instances_voxelizes_a_uv_sphere(bpy_clean):
    bpy = bpy_clean
    from ssm.operators import bridge, scene
    from ssm.operators import instances as ops

    bpy.ops.mesh.primitive_uv_sphere_add(radius=12.0, segments=32, ring_count=16, location=(5.0, -3.0, 40.0))
    sphere = bpy.context.active_object
    sphere.scale = (1.0, 1.5, 0.8)
    bpy.context.view_layer.update()
    verts = bridge.object_world_vertices(sphere)
    faces = bridge.mesh_triangles(sphere.data)
    analytic = mu.signed_volume(verts, faces)
    assert bpy.ops.ssm.add_mesh_instances(spacing_mm=1.0) == {"FINISHED"}
    ssm = sphere.ssm
    assert (ssm.role, ssm.source_kind) == ("INSTANCE", "BLENDER_MESH")
    frame = scene.stored_frame(sphere)
    assert frame.method == "moments"  # "auto" for a mesh
    assert sphere.name in bpy.data.collections["SSM Instances"].objects
    assert ssm.volume_mm3 == pytest.approx(analytic, rel=0.02)
    np.testing.assert_allclose(frame.origin_world, [5.0, -3.0, 40.0], atol=0.05)
    axes = frame.axes_world
    assert abs(axes[1, 0]) > 0.999 and abs(axes[0, 1]) > 0.999  # longest axis along y, then x
    core_frame = INS.mesh_frame(verts, faces)  # the core's frame of the same closed mesh, as a build's
    np.testing.assert_allclose(frame.origin_world, core_frame.origin_world, atol=1e-4)
    np.testing.assert_allclose(frame.axes_world, core_frame.axes_world, atol=1e-5)
    ov = ops.instance_object_volume(bpy.context, sphere)
    assert ov.volume_mm3 == pytest.approx(analytic, rel=0.02)
    scene.clear_volume_cache()
    sphere.location = (100.0, 0.0, 0.0)  # moving it does not change its file world volume
    bpy.context.view_layer.update()
    ov2 = ops.instance_object_volume(bpy.context, sphere)
    np.testing.assert_array_equal(ov2.mask, ov.mask)


def test_open_mesh_is_refused_naming_the_object_and_scene_is_unchanged(bpy_clean):
    bpy = bpy_clean
    bpy.ops.mesh.primitive_grid_add(size=20.0)
    grid = bpy.context.active_object
    grid.name = "Open Grid"
    n_objects = len(bpy.data.objects)
    with pytest.raises(RuntimeError, match=r"Open Grid: the mesh is not closed and watertight \(\d+ boundary edges"):
        bpy.ops.ssm.add_mesh_instances(spacing_mm=1.0)
    assert grid.ssm.role == "NONE"
    assert len(bpy.data.objects) == n_objects
    assert "SSM Instances" not in bpy.data.collections


def test_failed_import_leaves_the_scene_unchanged(bpy_clean, tmp_path):
    bpy = bpy_clean
    path = _label_map(tmp_path)
    with pytest.raises(
        RuntimeError, match=r"synth\.nii\.gz: label 5 is not present; labels present: 7 \(\d+ voxels\), 20"
    ):
        bpy.ops.ssm.import_segmentation(filepath=str(path), label=5)
    with pytest.raises(RuntimeError, match=r"missing\.nrrd: file not found"):
        bpy.ops.ssm.import_segmentation(filepath=str(tmp_path / "missing.nrrd"))
    assert len(bpy.data.objects) == 0
    assert len(bpy.data.meshes) == 0
    assert "SSM Instances" not in bpy.data.collections


def test_import_mesh_file_and_multiple_files(bpy_clean, tmp_path):
    bpy = bpy_clean

    v, f = icosphere(15.0, 2)
    write_stl_binary(tmp_path / "ball.stl", v, f)
    _label_map(tmp_path, "other.nii.gz")
    bpy.ops.ssm.import_segmentation(
        directory=str(tmp_path), files=[{"name": "ball.stl"}, {"name": "other.nii.gz"}], label=7
    )
    assert _instances(bpy) == ["ball", "other label 7"]
    ball = bpy.data.objects["ball"]
    from ssm.operators import scene

    assert (ball.ssm.source_kind, scene.stored_frame(ball).method, ball.ssm.label) == ("MESH_FILE", "moments", -1)
    assert ball.ssm.volume_mm3 == pytest.approx(mu.signed_volume(v, f), rel=0.02)


def test_panel_and_menu_are_registered(bpy_clean):
    bpy = bpy_clean
    panel = bpy.types.SSM_PT_instances
    assert (panel.bl_category, panel.bl_order, panel.bl_region_type) == ("SSM", 0, "UI")
    from ssm.operators import instances as ops

    assert ops.menu_func_import in bpy.types.TOPBAR_MT_file_import._dyn_ui_initialize()


def test_import_verse_l1(bpy_clean, verse_dir):
    bpy = bpy_clean
    label = VERSE_LABELS["L1"]
    bpy.ops.ssm.import_segmentation(filepath=str(VERSE_FILE), label=label, spacing_mm=1.0)
    (name,) = _instances(bpy)
    obj = bpy.data.objects[name]
    vol = IO.load_volume(VERSE_FILE, label)
    assert obj.ssm.volume_mm3 == pytest.approx(vol.volume_mm3, rel=1e-6)
    verts, _ = V.display_surface(vol)
    world = _world_vertices(obj)
    np.testing.assert_allclose(world.min(axis=0), verts.min(axis=0), atol=1e-3)
    np.testing.assert_allclose(world.max(axis=0), verts.max(axis=0), atol=1e-3)


def test_import_a_directory_takes_every_supported_file(bpy_clean, tmp_path):
    bpy = bpy_clean
    folder = tmp_path / "cases"
    folder.mkdir()
    _label_map(folder, "a.nii.gz")
    _label_map(folder, "b.nrrd")
    (folder / "notes.txt").write_text("not an image")
    bpy.ops.ssm.import_segmentation(directory=str(folder), label=20)
    assert _instances(bpy) == ["a label 20", "b label 20"]
    a, b = bpy.data.objects["a label 20"], bpy.data.objects["b label 20"]
    np.testing.assert_allclose(np.array(a.matrix_world), np.array(b.matrix_world), atol=1e-4)
