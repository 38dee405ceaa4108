"""Landmarks in Blender: schema editing, placement by ray, snapping, files, proposal, .blend."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import VERSE_FILE, VERSE_LABELS, icosphere, object_frame_of

from ssm_addon.formats.landmarks import LANDMARK_PRESETS, LandmarkSet, read_landmarks, write_landmarks
from ssm_addon.instances import volume as vol

pytestmark = pytest.mark.blender


class _Ops:
    """The landmark operators' module and the scene helpers they use, under one name."""

    def __getattr__(self, name):
        import ssm.operators.landmarks as lmops
        import ssm.operators.scene as scene

        return getattr(lmops, name) if hasattr(lmops, name) else getattr(scene, name)


def _ops():
    return _Ops()


def _rotation(seed):
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _matrix(rotation, translation):
    m = np.eye(4)
    m[:3, :3] = rotation
    m[:3, 3] = translation
    return m


def _make_instance(bpy, name, vertices_local, faces, matrix_world, frame=None):
    """An instance as the import stage leaves it: mesh in local mm, matrix_world = import_matrix."""
    from ssm.operators import bridge

    obj = bridge.new_mesh_object(bpy.context, name, vertices_local, faces, collection_name=bridge.INSTANCES_COLLECTION, matrix_world=matrix_world)
    from ssm.operators import scene

    obj.ssm.role = "INSTANCE"
    m = np.asarray(matrix_world, dtype=float)
    scene.write_frame(obj, frame if frame is not None else vol.ObjectFrame(m[:3, 3], m[:3, :3]), m)
    bpy.context.view_layer.objects.active = obj
    return obj


def _distance_to_mesh(obj, point_world):
    from mathutils import Vector

    inv = obj.matrix_world.inverted()
    found, loc, _n, _i = obj.closest_point_on_mesh(inv @ Vector(point_world))
    assert found
    return ((obj.matrix_world @ loc) - Vector(point_world)).length


def _world(emp):
    return np.array(emp.matrix_world.translation, dtype=float)


@pytest.fixture()
def sphere(bpy_clean):
    bpy = bpy_clean
    v, f = icosphere(10.0, 4)
    m = _matrix(_rotation(4), [50.0, -20.0, 300.0])
    obj = _make_instance(bpy, "Ball", v, f, m, vol.ObjectFrame(m[:3, 3], m[:3, :3]))
    return bpy, obj


# ------------------------------------------------------------------------------ schema


def test_schema_operators_edit_the_ordered_names(sphere):
    bpy, inst = sphere
    lm = _ops()
    s = bpy.context.scene.ssm_landmarks
    assert bpy.ops.ssm.landmark_schema_preset(preset="extremal-14") == {"FINISHED"}
    assert lm.schema_names(bpy.context) == LANDMARK_PRESETS["extremal-14"]
    s.active_index = 0
    bpy.ops.ssm.landmark_schema_add(name="tip")
    assert lm.schema_names(bpy.context)[:3] == ("right", "tip", "left") and s.active_index == 1
    bpy.ops.ssm.landmark_schema_add()
    assert lm.schema_names(bpy.context)[2] == "landmark-16"
    bpy.ops.ssm.landmark_schema_move(direction="UP")
    assert lm.schema_names(bpy.context)[:3] == ("right", "landmark-16", "tip") and s.active_index == 1
    bpy.ops.ssm.landmark_schema_remove()
    assert "landmark-16" not in lm.schema_names(bpy.context) and len(s.names) == 15
    with pytest.raises(RuntimeError, match="already in the schema"):
        bpy.ops.ssm.landmark_schema_add(name="left")

    # renaming renames the placed landmarks, by operator and by editing the list entry
    bpy.ops.ssm.place_landmarks(landmark="tip", ray_origin=(50, -20, 400), ray_direction=(0, 0, -1))
    assert bpy.ops.ssm.landmark_schema_rename(index=1, new_name="spinous-tip") == {"FINISHED"}
    assert set(lm.landmark_empties(inst)) == {"spinous-tip"}
    assert bpy.data.objects.get("Ball spinous-tip") is not None
    s.names[1].landmark = "spinous-process-tip"  # what double-click renaming in the UIList does
    assert s.names[1].name == "spinous-process-tip"
    assert list(lm.landmark_empties(inst)) == ["spinous-process-tip"]
    s.names[1].landmark = "left"  # a duplicate is refused
    assert s.names[1].name == "spinous-process-tip" and s.names[1].landmark == "spinous-process-tip"
    with pytest.raises(RuntimeError, match="cannot rename"):
        bpy.ops.ssm.landmark_schema_rename(index=1, new_name="right")

    # schema from the instance's landmarks
    bpy.ops.ssm.landmark_schema_preset(preset="lumbar-vertebra")
    assert len(s.names) == 15
    assert bpy.ops.ssm.landmark_schema_from_instance() == {"FINISHED"}
    assert lm.schema_names(bpy.context) == ("spinous-process-tip",)


# --------------------------------------------------------------------------- placement


def test_place_landmark_from_ray_lands_on_surface_and_advances(sphere):
    bpy, inst = sphere
    lm = _ops()
    _ops().set_schema(bpy.context.scene.ssm_landmarks, ("a", "b", "c"))
    centre = np.array([50.0, -20.0, 300.0])
    rays = {"a": (centre + [0, 0, 100], [0, 0, -1]), "b": (centre + [-80, 5, 3], [1, 0, 0]), "c": (centre + [30, 30, 30], [-1, -1, -1])}
    for expected in ("a", "b", "c"):
        assert lm.missing_names(bpy.context, inst)[0] == expected  # what the header shows next
        origin, direction = rays[expected]
        assert bpy.ops.ssm.place_landmarks(ray_origin=origin, ray_direction=direction) == {"FINISHED"}
        emp = bpy.data.objects[f"Ball {expected}"]
        assert emp[lm.LANDMARK_PROP] == expected
        assert emp.parent == inst and emp.ssm.instance == inst and emp.ssm.role == "LANDMARK"
        assert emp.empty_display_type == "SPHERE"
        p = _world(emp)
        assert _distance_to_mesh(inst, p) < 0.01
        # on the ray, on the near side of the ball (radius 10, faceted)
        d = np.asarray(direction, float) / np.linalg.norm(direction)
        off = p - origin
        assert np.linalg.norm(off - off.dot(d) * d) < 1e-3
        assert 9.8 < np.linalg.norm(p - centre) <= 10.0 + 1e-4 and (p - centre).dot(d) < 0
    assert lm.missing_names(bpy.context, inst) == []
    with pytest.raises(RuntimeError, match="every landmark of the schema is placed"):
        bpy.ops.ssm.place_landmarks(ray_origin=centre + [0, 0, 100], ray_direction=(0, 0, -1))
    # re-placing a named landmark moves it; the empty keeps its world place when the parent moves
    assert bpy.ops.ssm.place_landmarks(landmark="a", ray_origin=centre - [0, 0, 100], ray_direction=(0, 0, 1)) == {"FINISHED"}
    a = bpy.data.objects["Ball a"]
    assert _world(a)[2] < centre[2] - 9.8
    assert len(lm.landmark_empties(inst)) == 3
    # a ray that misses places nothing
    assert bpy.ops.ssm.place_landmarks(landmark="b", ray_origin=centre + [0, 50, 100], ray_direction=(0, 0, -1)) == {"CANCELLED"}
    # interactively it needs a 3D viewport (headless there is none); a given ray runs execute
    with pytest.raises(RuntimeError, match="3D viewport"):
        bpy.ops.ssm.place_landmarks("INVOKE_DEFAULT")
    assert bpy.ops.ssm.place_landmarks("INVOKE_DEFAULT", landmark="b", ray_origin=centre + [100, 0, 0], ray_direction=(-1, 0, 0)) == {"FINISHED"}
    # undo is available: the operator registers undo steps
    assert "UNDO" in bpy.types.SSM_OT_place_landmarks.bl_options


def test_landmarks_follow_a_moved_instance_and_snap_to_its_surface(sphere):
    bpy, inst = sphere
    lm = _ops()
    lm.set_schema(bpy.context.scene.ssm_landmarks, ("a", "b"))
    centre = np.array([50.0, -20.0, 300.0])
    bpy.ops.ssm.place_landmarks(ray_origin=centre + [0, 0, 100], ray_direction=(0, 0, -1))
    bpy.ops.ssm.place_landmarks(ray_origin=centre + [100, 0, 0], ray_direction=(-1, 0, 0))
    a, b = bpy.data.objects["Ball a"], bpy.data.objects["Ball b"]
    # move the instance: landmarks move with it and stay on its surface
    from mathutils import Matrix

    inst.matrix_world = Matrix.Translation((5, 6, 7)) @ inst.matrix_world
    bpy.context.view_layer.update()
    assert _distance_to_mesh(inst, _world(a)) < 0.01
    # knock both off the surface, snap only the selected one, then all
    for emp, shift in ((a, [0, 0, 3.0]), (b, [2.5, 0, 0])):
        emp.matrix_world.translation = emp.matrix_world.translation + __import__("mathutils").Vector(shift)
    bpy.context.view_layer.update()
    assert _distance_to_mesh(inst, _world(a)) > 2.0
    for o in bpy.context.selected_objects:
        o.select_set(False)
    a.select_set(True)
    bpy.context.view_layer.objects.active = inst
    assert bpy.ops.ssm.snap_landmarks(selected_only=True) == {"FINISHED"}
    bpy.context.view_layer.update()
    assert _distance_to_mesh(inst, _world(a)) < 1e-3
    assert _distance_to_mesh(inst, _world(b)) > 2.0
    assert bpy.ops.ssm.snap_landmarks() == {"FINISHED"}
    bpy.context.view_layer.update()
    assert _distance_to_mesh(inst, _world(b)) < 1e-3


# ------------------------------------------------------------------------- real data


@pytest.fixture(scope="module")
def verse_meshes(verse_dir):
    """L1 and L2 as the import stage would make them: marching cubes, object frame, world mm."""
    import nibabel as nib
    from skimage.measure import marching_cubes

    img = nib.load(str(VERSE_FILE))
    labels, affine = np.asarray(img.dataobj), img.affine
    out = {}
    for name in ("L1", "L2"):
        mask = labels == VERSE_LABELS[name]
        verts, faces, _, _ = marching_cubes(np.pad(mask, 1).astype(np.float32), 0.5)
        world = (verts - 1.0) @ affine[:3, :3].T + affine[:3, 3]
        frame = object_frame_of(mask, affine)
        out[name] = (frame.to_object(world), faces[:, ::-1], frame)
    return out


def _verse_instance(bpy, verse_meshes, name):
    local, faces, frame = verse_meshes[name]
    return _make_instance(bpy, name, local, faces, frame.matrix_world, frame)


def test_import_verse_fcsv_lands_on_l1_and_exports_every_format(bpy_clean, verse_dir, verse_meshes, tmp_path):
    bpy = bpy_clean
    lm = _ops()
    l1 = _verse_instance(bpy, verse_meshes, "L1")
    path = verse_dir / "landmarks" / "L1.fcsv"
    assert bpy.ops.ssm.import_landmarks(filepath=str(path)) == {"FINISHED"}
    truth = read_landmarks(path)
    assert lm.schema_names(bpy.context) == truth.names  # empty schema: taken from the file
    empties = lm.landmark_empties(l1)
    assert len(empties) == 14
    dist = [_distance_to_mesh(l1, _world(empties[n])) for n in truth.names]
    print(f"\nimported L1.fcsv (LPS): max distance to the L1 surface mesh {max(dist):.3f} mm")
    assert max(dist) <= 2.0  # within one voxel (1 x 1 x 2 mm) of the surface

    # move the instance: import and export still speak the file's world coordinates
    from mathutils import Matrix

    l1.matrix_world = Matrix.Translation((30, -10, 5)) @ Matrix.Rotation(0.4, 4, "Z") @ l1.matrix_world
    bpy.context.view_layer.update()
    got = lm.landmark_sets_by_instance(bpy.context)["L1"]
    assert got.names == truth.names
    np.testing.assert_allclose(got.points_world, truth.points_world, atol=1e-3)
    for ext in ("fcsv", "mrk.json", "csv", "json"):
        out = tmp_path / f"L1.{ext}"
        assert bpy.ops.ssm.export_landmarks(filepath=str(out), coordinate_system="LPS") == {"FINISHED"}
        back = read_landmarks(out)
        assert back.names == truth.names
        np.testing.assert_allclose(back.points_world, truth.points_world, atol=1e-3)
    assert "CoordinateSystem = LPS" in (tmp_path / "L1.fcsv").read_text()

    # re-import onto the moved instance: the landmarks land at the moved surface
    moved = LandmarkSet(truth.names[:3], truth.points_world[:3], "x")
    write_landmarks(tmp_path / "three.csv", moved)
    for emp in list(empties.values()):
        bpy.data.objects.remove(emp)
    assert bpy.ops.ssm.import_landmarks(filepath=str(tmp_path / "three.csv")) == {"FINISHED"}
    assert lm.missing_names(bpy.context, l1) == list(truth.names[3:])
    for n in truth.names[:3]:
        assert _distance_to_mesh(l1, _world(lm.landmark_empties(l1)[n])) <= 2.0


def test_import_errors_are_clear(sphere, tmp_path):
    bpy, inst = sphere
    _ops().set_schema(bpy.context.scene.ssm_landmarks, ("a", "b", "c"))
    (tmp_path / "unknown.csv").write_text("a,1,2,3\ntip,4,5,6\nwing,7,8,9\n")
    with pytest.raises(RuntimeError, match=r"unknown\.csv: not in the schema tip, wing"):
        bpy.ops.ssm.import_landmarks(filepath=str(tmp_path / "unknown.csv"))
    (tmp_path / "dup.fcsv").write_text("# CoordinateSystem = LPS\nn0,1,2,3,0,0,0,1,1,1,0,a,,\nn1,1,2,3,0,0,0,1,1,1,0,a,,\n")
    with pytest.raises(RuntimeError, match=r"dup\.fcsv: duplicate landmark name\(s\) 'a'"):
        bpy.ops.ssm.import_landmarks(filepath=str(tmp_path / "dup.fcsv"))
    (tmp_path / "bad.csv").write_text("a,1,2,3\nb,1,two,3\n")
    with pytest.raises(RuntimeError, match=r"bad\.csv, line 2: y 'two' is not a number"):
        bpy.ops.ssm.import_landmarks(filepath=str(tmp_path / "bad.csv"))
    (tmp_path / "empty.json").write_text("[]")
    with pytest.raises(RuntimeError, match=r"empty\.json: the file holds no landmark points"):
        bpy.ops.ssm.import_landmarks(filepath=str(tmp_path / "empty.json"))
    assert _ops().landmark_empties(inst) == {}
    # unknown names may be added to the schema on request
    assert bpy.ops.ssm.import_landmarks(filepath=str(tmp_path / "unknown.csv"), add_to_schema=True) == {"FINISHED"}
    assert _ops().schema_names(bpy.context) == ("a", "b", "c", "tip", "wing")
    with pytest.raises(RuntimeError, match="no landmarks to export|unknown landmark file extension"):
        bpy.ops.ssm.export_landmarks(filepath=str(tmp_path / "x.txt"))


def test_propose_l2_from_l1_puts_every_landmark_on_l2(bpy_clean, verse_dir, verse_meshes):
    bpy = bpy_clean
    lm = _ops()
    l1 = _verse_instance(bpy, verse_meshes, "L1")
    bpy.ops.ssm.import_landmarks(filepath=str(verse_dir / "landmarks" / "L1.fcsv"))
    l2 = _verse_instance(bpy, verse_meshes, "L2")
    with pytest.raises(RuntimeError, match="choose another, landmarked instance"):
        bpy.ops.ssm.propose_landmarks()
    bpy.context.scene.ssm_landmarks.proposal_source = l1
    assert bpy.ops.ssm.propose_landmarks() == {"FINISHED"}
    empties = lm.landmark_empties(l2)
    truth = read_landmarks(verse_dir / "landmarks" / "L2.fcsv")
    assert set(empties) == set(truth.names)
    assert all(e.parent == l2 for e in empties.values())
    assert max(_distance_to_mesh(l2, _world(e)) for e in empties.values()) < 0.01
    got = lm.landmark_sets_by_instance(bpy.context)["L2"]
    dist = np.linalg.norm(got.points_world - truth.subset(got.names).points_world, axis=1)
    print(f"\nBlender proposal L1 -> L2: mean distance to the given L2 landmarks {dist.mean():.2f} mm (max {dist.max():.2f})")
    assert dist.mean() < 15.0
    with pytest.raises(RuntimeError, match="none of L2's missing landmarks"):
        bpy.ops.ssm.propose_landmarks(source="L1")


def test_landmarks_on_instances_made_by_the_import_operator(bpy_clean, verse_dir, tmp_path):
    """End to end with ssm.import_segmentation: import L1.fcsv, propose L2, export L2."""
    bpy = bpy_clean
    lm = _ops()
    made = {}
    for name in ("L1", "L2"):
        assert bpy.ops.ssm.import_segmentation(filepath=str(VERSE_FILE), label=VERSE_LABELS[name]) == {"FINISHED"}
        made[name] = next(o for o in lm.scene_instances(bpy.context) if o.ssm.label == VERSE_LABELS[name])
    bpy.context.view_layer.objects.active = made["L1"]
    assert bpy.ops.ssm.import_landmarks(filepath=str(verse_dir / "landmarks" / "L1.fcsv")) == {"FINISHED"}
    assert max(_distance_to_mesh(made["L1"], _world(e)) for e in lm.landmark_empties(made["L1"]).values()) <= 2.0
    bpy.context.view_layer.objects.active = made["L2"]
    assert bpy.ops.ssm.propose_landmarks(source=made["L1"].name) == {"FINISHED"}
    assert max(_distance_to_mesh(made["L2"], _world(e)) for e in lm.landmark_empties(made["L2"]).values()) < 0.01
    assert bpy.ops.ssm.export_landmarks(filepath=str(tmp_path / "L2.mrk.json")) == {"FINISHED"}
    proposed, truth = read_landmarks(tmp_path / "L2.mrk.json"), read_landmarks(verse_dir / "landmarks" / "L2.fcsv")
    dist = np.linalg.norm(proposed.points_world - truth.subset(proposed.names).points_world, axis=1)
    print(f"\nimport operator + proposal L1 -> L2: mean distance to the given L2 landmarks {dist.mean():.2f} mm")
    assert set(lm.landmark_sets_by_instance(bpy.context)) == {made["L1"].name, made["L2"].name}
    assert dist.mean() < 15.0


def test_save_and_reopen_keeps_schema_and_landmarks(sphere, tmp_path):
    bpy, inst = sphere
    lm = _ops()
    bpy.ops.ssm.landmark_schema_preset(preset="lumbar-vertebra")
    centre = np.array([50.0, -20.0, 300.0])
    bpy.ops.ssm.place_landmarks(ray_origin=centre + [0, 0, 100], ray_direction=(0, 0, -1))
    bpy.ops.ssm.place_landmarks(ray_origin=centre + [0, 100, 0], ray_direction=(0, -1, 0))
    before = {n: _world(e) for n, e in lm.landmark_empties(inst).items()}
    path = tmp_path / "landmarks.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.read_homefile(use_empty=True)
    assert len(bpy.context.scene.ssm_landmarks.names) == 0
    bpy.ops.wm.open_mainfile(filepath=str(path))
    assert lm.schema_names(bpy.context) == LANDMARK_PRESETS["lumbar-vertebra"]
    inst = bpy.data.objects["Ball"]
    after = lm.landmark_empties(inst)
    assert set(after) == set(before) == set(LANDMARK_PRESETS["lumbar-vertebra"][:2])
    for n, e in after.items():
        assert e.parent == inst
        np.testing.assert_allclose(_world(e), before[n], atol=1e-5)
    assert lm.missing_names(bpy.context, inst) == list(LANDMARK_PRESETS["lumbar-vertebra"][2:])


def test_panel_and_list_draw_the_status(sphere, layout_recorder):
    bpy, inst = sphere
    bpy.ops.ssm.landmark_schema_preset(preset="extremal-14")
    bpy.ops.ssm.place_landmarks(ray_origin=(50, -20, 400), ray_direction=(0, 0, -1))
    panel = bpy.types.SSM_PT_landmarks
    assert panel.bl_category == "SSM" and panel.bl_order == 10 and panel.bl_space_type == "VIEW_3D"
    log = []
    panel.draw(type("P", (), {"layout": layout_recorder(log)})(), bpy.context)
    labels = [x[1] for x in log if x[0] == "label"]
    ops = {x[1] for x in log if x[0] == "operator"}
    assert {"ssm.place_landmarks", "ssm.snap_landmarks", "ssm.import_landmarks", "ssm.export_landmarks", "ssm.propose_landmarks",
            "ssm.landmark_schema_add", "ssm.landmark_schema_remove", "ssm.landmark_schema_move", "ssm.landmark_schema_preset"} <= ops
    assert "Ball: 1/14 placed" in labels
    assert "  missing: left" in labels and "  … and 5 more" in labels
    assert "Ball: 1 placed, 13 missing" in labels
    lst = bpy.types.SSM_UL_landmark_schema
    s = bpy.context.scene.ssm_landmarks
    lst.draw_item(None, bpy.context, layout_recorder(log), s, s.names[0], 0, s, "active_index", 0)
    assert ("prop", "landmark") in log


def test_propose_by_coating_in_blender(bpy_clean):
    bpy = bpy_clean
    lm = _ops()
    v, f = icosphere(10.0, 3)
    semi = np.array([8.0, 11.0, 9.0])
    m_src = _matrix(_rotation(1), [5.0, -3.0, 2.0])
    m_tgt = _matrix(_rotation(2), [100.0, 40.0, -70.0])
    src = _make_instance(bpy, "Sphere", v, f, m_src, vol.ObjectFrame(m_src[:3, 3], m_src[:3, :3]))
    tgt = _make_instance(bpy, "Ellipsoid", v / 10.0 * semi, f, m_tgt, vol.ObjectFrame(m_tgt[:3, 3], m_tgt[:3, :3]))
    lm.set_schema(bpy.context.scene.ssm_landmarks, ("x", "y"))
    for name, p in zip(("x", "y"), (m_src[:3, :3] @ [10.0, 0, 0] + m_src[:3, 3], m_src[:3, :3] @ [0, 10.0, 0] + m_src[:3, 3])):
        lm.set_landmark(bpy.context, src, name, blender_world=p)
    bpy.context.view_layer.objects.active = tgt
    assert bpy.ops.ssm.propose_landmarks(source="Sphere", method="coating") == {"FINISHED"}
    got = {n: m_tgt[:3, :3].T @ (_world(e) - m_tgt[:3, 3]) for n, e in lm.landmark_empties(tgt).items()}
    # signed: the +x and +y poles, never the opposite pole (the end-for-end flip)
    np.testing.assert_allclose(got["x"], [8.0, 0, 0], atol=0.8)
    np.testing.assert_allclose(got["y"], [0, 11.0, 0], atol=0.8)


def test_click_near_a_landmark_picks_it_for_replacement(bpy_module):
    pick = _ops().pick_on_screen
    screen = {"a": (100.0, 100.0), "b": (108.0, 100.0), "behind": None}
    assert pick(screen, (105.0, 101.0)) == "b"
    assert pick(screen, (101.0, 99.0)) == "a"
    assert pick(screen, (100.0, 130.0)) == ""  # far from every landmark: place instead
