"""Segmenting in Blender: the image as slice planes, Segment with Model from the 3D cursor, Save Segmentation;
the same numbers and files as ``ssm segment``."""

from __future__ import annotations

import dataclasses
import json

import nibabel as nib
import numpy as np
import pytest
from conftest import joint_model, joint_population
from test_segmentation import bumped_shapes, posed, synthetic_image

from ssm_addon.model.files import save_npz
from ssm_addon.model.pca import build_model
from ssm_addon.segmentation import learn_appearance, segment_files, volume_centroid

pytestmark = pytest.mark.blender


@pytest.fixture()
def files(tmp_path):
    shapes, faces = bumped_shapes()
    model = build_model(shapes[1:], faces, [f"s{i}" for i in range(1, len(shapes))], alignment="none")
    truth = posed(shapes[0], shift=(-30.0, 10.0, 5.0))
    image, mask = synthetic_image(truth, faces)
    nib.save(nib.Nifti1Image(image.data, image.affine), str(tmp_path / "ct.nii.gz"))
    train = [posed(s) for s in shapes[1:4]]
    app = learn_appearance(model.mean, faces, train, [synthetic_image(s, faces, seed=5 + i)[0]
                                                      for i, s in enumerate(train)], names=["a", "b", "c"])
    save_npz(model, tmp_path / "model.npz", extra=app.to_arrays())
    at = volume_centroid(truth, faces) + np.array([2.0, -3.0, 2.5])
    return tmp_path, at, image, mask


def test_segment_with_model_equals_ssm_segment_and_saves_the_same_files(bpy_clean, files, layout_recorder):
    bpy = bpy_clean
    folder, at, image, mask = files
    assert bpy.ops.ssm.import_model(filepath=str(folder / "model.npz")) == {"FINISHED"}
    assert bpy.ops.ssm.import_image(filepath=str(folder / "ct.nii.gz")) == {"FINISHED"}
    planes = [bpy.data.objects.get(f"SSM {p} slice") for p in ("sagittal", "coronal", "axial")]
    assert all(p is not None for p in planes)
    # the axial plane lies at the slider's z (world mm) and follows it; the window changes its pixels
    scene = bpy.context.scene
    axial = planes[2]
    z0 = scene.ssm_image.position_z
    assert np.allclose([v.co.z for v in axial.data.vertices], z0)
    scene.ssm_image.position_z = z0 + 7.0
    assert np.allclose([v.co.z for v in axial.data.vertices], z0 + 7.0)
    before = np.array(bpy.data.images["SSM axial slice"].pixels[:])
    scene.ssm_image.width = 300.0
    assert not np.allclose(before, np.array(bpy.data.images["SSM axial slice"].pixels[:]))
    # a cursor outside the image: refused with the reason, nothing added
    scene.cursor.location = (5000.0, 0.0, 0.0)
    n_objects = len(bpy.data.objects)
    with pytest.raises(RuntimeError, match="outside the image"):
        bpy.ops.ssm.segment_image()
    assert len(bpy.data.objects) == n_objects
    scene.cursor.location = tuple(at)
    assert bpy.ops.ssm.segment_image() == {"FINISHED"}
    (obj,) = [o for o in bpy.data.objects if "ssm_segment_json" in o]
    assert obj.name.startswith("ct ") and obj.name.endswith(" segmented")  # named by image and model
    doc = json.loads(obj["ssm_segment_json"])
    assert doc["evidence"] == "learned"  # the appearance came with the imported model.npz
    # as the command's: the model file and the start
    assert doc["model"] == str(folder / "model.npz") and doc["start_given"]["at"] == pytest.approx(list(at), abs=1e-4)
    # the slices moved to the result: each plane through its solid centroid
    seg_points = np.array([v.co for v in obj.data.vertices], float)
    centre = volume_centroid(seg_points, np.array([p.vertices[:] for p in obj.data.polygons]))
    got = (scene.ssm_image.position_x, scene.ssm_image.position_y, scene.ssm_image.position_z)
    assert np.allclose(got, centre, atol=1e-3), (got, centre)
    assert np.allclose([v.co.z for v in axial.data.vertices], centre[2], atol=1e-3)
    assert np.allclose([v.co.x for v in planes[0].data.vertices], centre[0], atol=1e-3)
    # the SD colours on the fixed scale, with a legend in mm beside the result (one per scene)
    from ssm.operators import bridge

    legend = bpy.data.objects["SSM SD legend"]
    texts = sorted(o.data.body for o in legend.children)
    assert texts == ["0 mm", "1.5 mm", "3 mm or more (posterior SD)"] and bridge.SD_SCALE_MM == 3.0
    assert np.array(legend.matrix_world)[0, 3] > seg_points[:, 0].max()
    sd = bridge.get_point_attribute(obj.data, "posterior_sd_mm")
    colours = np.array([c.color[:] for c in obj.data.color_attributes["posterior_sd"].data])
    loops = np.array([lp.vertex_index for lp in obj.data.loops])
    assert np.allclose(colours, bridge.sd_colours(sd)[loops], atol=1e-6)
    assert np.allclose(bridge.sd_colours(np.array([0.0, 3.0, 7.0]))[:, 0], [0.15, 0.95, 0.95])
    # a second segmentation (another structure, another start) is its own object: the first stays; the search
    # takes the sidebar's parameters (Scene.ssm_segment, as `ssm segment`'s options) and records them
    assert doc["parameters"]["noise_mm"] == 1.0 and doc["parameters"]["search_mm"] == [12.0, 6.0, 3.0]
    first = np.array([v.co for v in obj.data.vertices])
    scene.ssm_segment.noise_mm = 1.5
    assert bpy.ops.ssm.segment_image() == {"FINISHED"}
    scene.ssm_segment.noise_mm = 1.0
    segs = [o for o in bpy.data.objects if "ssm_segment_json" in o]
    assert len(segs) == 2 and np.array_equal(np.array([v.co for v in obj.data.vertices]), first)
    second = json.loads([o for o in segs if o != obj][0]["ssm_segment_json"])
    assert second["parameters"]["noise_mm"] == 1.5
    bpy.data.objects.remove([o for o in segs if o != obj][0])
    bpy.context.view_layer.objects.active = obj
    # the command line on the same files and the same point (the cursor holds float32 coordinates): the same surface
    cursor = np.array(scene.cursor.location, float)
    head = segment_files(folder / "model.npz", folder / "ct.nii.gz", folder / "cli", at=[",".join(map(repr, cursor))])
    verts = np.array([v.co for v in obj.data.vertices])
    ply = (folder / "cli" / "segmented.ply")
    from ssm_addon.formats.meshes import read_ply

    cli_points, _faces, _extra = read_ply(ply)
    assert np.abs(verts - cli_points).max() < 1e-4  # both stored as float32
    assert doc["mahalanobis"] == pytest.approx(head["mahalanobis"], abs=1e-9)
    assert obj.data.attributes.get("posterior_sd") is not None
    # Save Segmentation writes the command's files; the label maps are the same voxels
    assert bpy.ops.ssm.save_segmentation(directory=str(folder / "blender")) == {"FINISHED"}
    for name in ("segmentation.nii.gz", "segmented.ply", "segment.json", "segment.png"):
        assert (folder / "blender" / name).is_file(), name
    a = np.asarray(nib.load(str(folder / "blender" / "segmentation.nii.gz")).dataobj)
    b = np.asarray(nib.load(str(folder / "cli" / "segmentation.nii.gz")).dataobj)
    assert np.array_equal(a, b) and 2 * np.count_nonzero(a.astype(bool) & mask) / (a.sum() + mask.sum()) > 0.9
    # saving again into the same folder never overwrites: refused, said
    with pytest.raises(RuntimeError, match="never overwrites"):
        bpy.ops.ssm.save_segmentation(directory=str(folder / "blender"))
    log = []
    bpy.types.SSM_PT_segment.draw(type("P", (), {"layout": layout_recorder(log)})(), bpy.context)
    assert ("operator", "ssm.save_segmentation") in log and any("learned evidence" in t for k, t in log if k == "label")
    assert ("prop", "noise_mm") in log and ("prop", "evidence") in log  # the search's parameters in the panel


def _joint_scene(bpy, tmp_path, names=None):
    """A joint model of two structures (``names``, else a and b) as ``joint.npz`` and a synthetic CT of a
    held-out subject, both imported into the scene; returns (truth points, faces of each, the split)."""
    a, b, fa, fb, _turns = joint_population(n=14, seed=3)
    model = joint_model(a[1:], b[1:], fa, fb)
    if names:
        model = dataclasses.replace(model, structure_names=tuple(names))
    na = a.shape[1]
    truth = np.concatenate([a[0], b[0]]) + np.array([20.0, -10.0, 5.0])
    image, _mask = synthetic_image(truth, np.concatenate([fa, fb + na]))
    nib.save(nib.Nifti1Image(image.data, image.affine), str(tmp_path / "ct.nii.gz"))
    save_npz(model, tmp_path / "joint.npz")
    assert bpy.ops.ssm.import_model(filepath=str(tmp_path / "joint.npz")) == {"FINISHED"}
    assert bpy.ops.ssm.import_image(filepath=str(tmp_path / "ct.nii.gz")) == {"FINISHED"}
    return truth, fa, fb, na


def test_a_joint_segmentation_saved_in_blender_has_the_commands_labels(bpy_clean, tmp_path):
    """A joint model (two touching structures, named L1 and L2) imported into Blender and segmented from
    the 3D cursor: *Save Segmentation* writes the label map the command writes from the same point,
    voxel for voxel, each structure under its VerSe number (20, 21), none in both, or under the numbers
    given (its ``labels``, the command's ``--labels``)."""
    bpy = bpy_clean
    truth, fa, fb, na = _joint_scene(bpy, tmp_path, names=("L1", "L2"))
    bpy.context.scene.cursor.location = tuple(volume_centroid(truth, np.concatenate([fa, fb + na])) + [1.0, 1.0, 0.0])
    assert bpy.ops.ssm.segment_image() == {"FINISHED"}
    (obj,) = [o for o in bpy.data.objects if "ssm_segment_json" in o]
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.ssm.save_segmentation(directory=str(tmp_path / "blender")) == {"FINISHED"}
    cursor = np.array(bpy.context.scene.cursor.location, float)
    segment_files(tmp_path / "joint.npz", tmp_path / "ct.nii.gz", tmp_path / "cli", at=[",".join(map(repr, cursor))])
    blender = np.asarray(nib.load(str(tmp_path / "blender" / "segmentation.nii.gz")).dataobj)
    cli = np.asarray(nib.load(str(tmp_path / "cli" / "segmentation.nii.gz")).dataobj)
    assert set(np.unique(cli)) == {0, 20, 21} and np.array_equal(blender, cli)
    saved = json.loads((tmp_path / "blender" / "segment.json").read_text())
    assert saved["segmentation"]["structures"]["L2"]["label"] == 21
    # numbers of one's own, as `ssm segment --labels L1=3,L2=7`: the same voxels under them; a bad one refused
    assert bpy.ops.ssm.save_segmentation(directory=str(tmp_path / "own"), labels="L1=3, L2=7") == {"FINISHED"}
    own = np.asarray(nib.load(str(tmp_path / "own" / "segmentation.nii.gz")).dataobj)
    assert np.array_equal(own == 3, cli == 20) and np.array_equal(own == 7, cli == 21)
    with pytest.raises(RuntimeError, match="no structure 'L9'"):
        bpy.ops.ssm.save_segmentation(directory=str(tmp_path / "bad"), labels="L9=4")
    assert not (tmp_path / "bad" / "segmentation.nii.gz").exists()


def test_a_joint_models_starts_placed_per_structure_segment_as_the_command_does(bpy_clean, tmp_path, layout_recorder):
    """*Place Start* marks the 3D cursor as one structure's start (an empty per structure); *Segment with
    Model* then starts each at its own point, as ``ssm segment --at a=… --at b=…``: the same label map,
    and ``segment.json`` records the points."""
    bpy = bpy_clean
    truth, fa, fb, na = _joint_scene(bpy, tmp_path)
    log = []
    bpy.types.SSM_PT_segment.draw(type("P", (), {"layout": layout_recorder(log)})(), bpy.context)
    assert log.count(("operator", "ssm.place_start")) == 2  # a button per structure
    with pytest.raises(RuntimeError, match="no structure 'c'"):
        bpy.ops.ssm.place_start(structure="c")
    starts = {"a": volume_centroid(truth[:na], fa) + [2.0, 2.0, 0.0],
              "b": volume_centroid(truth[na:], fb) + [-2.0, 1.0, 1.0]}
    for name, point in starts.items():
        bpy.context.scene.cursor.location = tuple(point)
        assert bpy.ops.ssm.place_start(structure=name) == {"FINISHED"}
    bpy.context.scene.cursor.location = (0.0, 0.0, 0.0)  # not the start any more
    assert bpy.ops.ssm.segment_image() == {"FINISHED"}
    (obj,) = [o for o in bpy.data.objects if "ssm_segment_json" in o]
    placed = {n: np.array(bpy.data.objects[f"SSM start {n}"].location, float) for n in starts}
    assert json.loads(obj["ssm_segment_json"])["start_given"]["points"]["b"] == pytest.approx(list(placed["b"]))
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.ssm.save_segmentation(directory=str(tmp_path / "blender")) == {"FINISHED"}
    segment_files(tmp_path / "joint.npz", tmp_path / "ct.nii.gz", tmp_path / "cli",
                  at=[f"{n}={','.join(map(repr, p))}" for n, p in placed.items()])
    blender = np.asarray(nib.load(str(tmp_path / "blender" / "segmentation.nii.gz")).dataobj)
    cli = np.asarray(nib.load(str(tmp_path / "cli" / "segmentation.nii.gz")).dataobj)
    assert set(np.unique(cli)) == {0, 1, 2} and np.array_equal(blender, cli)
