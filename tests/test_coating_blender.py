"""Coating in Blender: ssm.coat_template on synthetic instances, overlay, colours, fit, Esc."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import ellipsoid_landmarks, icosphere

from ssm_addon.coating import distance_map as DM
from ssm_addon.formats import label_maps as IO

pytestmark = pytest.mark.blender

AXES = {1: np.array([16.0, 11.0, 8.0]), 2: np.array([18.0, 10.0, 9.0]), 3: np.array([15.0, 12.0, 8.5])}
CENTRES = {1: np.array([22.0, 20.0, 16.0]), 2: np.array([62.0, 20.0, 16.0]), 3: np.array([22.0, 52.0, 16.0])}


def _label_map(tmp_path):
    shape = (86, 72, 34)
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1).reshape(-1, 3).astype(float)
    labels = np.zeros(shape, np.uint8)
    for k, axes in AXES.items():
        labels[((((ijk - CENTRES[k]) / axes) ** 2).sum(1) <= 1).reshape(shape)] = k
    return IO.write_label_map(tmp_path / "ellipsoids.nii.gz", labels, np.eye(4))


def _scene(bpy, tmp_path):
    """Three ellipsoid instances with landmarks (true map: axis scaling) and a template on instance 1."""
    from ssm.operators.instances import instance_object_volume
    from ssm.operators.scene import set_landmark, stored_frame
    from ssm.operators.template import write_template_object

    from ssm_addon.template.template import Template

    path = _label_map(tmp_path)
    assert bpy.ops.ssm.import_segmentation(filepath=str(path), split_labels=True, spacing_mm=1.0) == {"FINISHED"}
    inst = {k: next(o for o in bpy.data.objects if o.ssm.role == "INSTANCE" and o.ssm.label == k) for k in AXES}
    base = ellipsoid_landmarks(AXES[1])
    names = [f"lm{i}" for i in range(len(base))]
    for k, obj in inst.items():
        world = stored_frame(obj).to_world(base * AXES[k] / AXES[1])
        for name, p in zip(names, world):
            set_landmark(bpy.context, obj, name, file_world=p)
    ov = instance_object_volume(bpy.context, inst[1])
    v, f = icosphere(subdivisions=3)
    pts = DM.DistanceMap.from_object_volume(ov).project(v * AXES[1], 3)
    template = Template(points_object=pts, faces=f, curvature=np.zeros(len(pts)), frame=ov.frame)
    tpl = write_template_object(bpy.context, inst[1], template)
    return inst, tpl


def test_coat_template_creates_overlaying_coloured_meshes(bpy_clean, tmp_path):
    bpy = bpy_clean
    from ssm.operators import bridge

    inst, tpl = _scene(bpy, tmp_path)
    assert bpy.ops.ssm.coat_template() == {"FINISHED"}
    n_faces = len(tpl.data.polygons)
    for k, obj in inst.items():
        coated = bpy.data.objects[f"{obj.name} coated"]
        assert coated.ssm.role == "COATED" and coated.ssm.instance == obj
        assert len(coated.data.vertices) == len(tpl.data.vertices)
        np.testing.assert_array_equal(bridge.mesh_triangles(coated.data), bridge.mesh_triangles(tpl.data))
        # the same correspondence colours as the template, corner by corner
        colours = coated.data.attributes["correspondence"]
        rgba = np.empty(len(colours.data) * 4, np.float32)
        colours.data.foreach_get("color", rgba)
        tpl_rgba = np.empty_like(rgba)
        tpl.data.attributes["correspondence"].data.foreach_get("color", tpl_rgba)
        np.testing.assert_array_equal(rgba, tpl_rgba)
        assert rgba.reshape(n_faces, 3, 4)[:, :, :3].std() > 0.1
        # float64 points kept with the object; the mesh is their float32 view
        stored = bridge.load_arrays(coated, "ssm_coating")["points_object"]
        np.testing.assert_allclose(bridge.mesh_vertices(coated.data), stored, atol=1e-4)
        # the coated mesh overlays the instance: Blender-world vertices on the ellipsoid
        world = bridge.object_world_vertices(coated)
        r = np.sqrt((((world - CENTRES[k]) / AXES[k]) ** 2).sum(1))
        assert np.abs(r - 1).max() * AXES[k].min() < 1.0
        fit = json.loads(coated.ssm.fit_json)
        assert fit["folded_after"] == 0 and fit["max_distance_mm"] < 1.0
    # correspondence: instance 2's coated points follow the axis scaling of the template
    coated2 = bridge.mesh_vertices(bpy.data.objects[f"{inst[2].name} coated"].data)
    truth = bridge.mesh_vertices(tpl.data) * AXES[2] / AXES[1]
    assert np.linalg.norm(coated2 - truth, axis=1).mean() < 0.5


def test_cancel_keeps_finished_instances(bpy_clean, tmp_path):
    bpy = bpy_clean
    inst, _ = _scene(bpy, tmp_path)
    assert bpy.ops.ssm.coat_template(cancel_after=1) == {"FINISHED"}
    coated = sorted(o.name for o in bpy.data.objects if o.ssm.role == "COATED")
    assert coated == [f"{inst[1].name} coated"]


def test_selected_only_and_missing_template(bpy_clean, tmp_path):
    bpy = bpy_clean
    inst, tpl = _scene(bpy, tmp_path)
    for o in bpy.data.objects:
        o.select_set(False)
    inst[3].select_set(True)
    assert bpy.ops.ssm.coat_template(selected_only=True) == {"FINISHED"}
    assert sorted(o.name for o in bpy.data.objects if o.ssm.role == "COATED") == [f"{inst[3].name} coated"]
    tpl.ssm.role = "NONE"
    assert not bpy.ops.ssm.coat_template.poll()


def test_panel_registered(bpy_clean):
    bpy = bpy_clean
    assert hasattr(bpy.types, "SSM_PT_coating")
    settings = bpy.context.scene.ssm_coating
    assert settings.rest_lengths == "projected"
    # the sidebar's defaults are the core's defaults (the same coating headless and in Blender)
    import dataclasses

    from ssm.operators.properties import params_from_group

    from ssm_addon.coating.coating import CoatingParams

    ui, core = params_from_group(CoatingParams, settings), CoatingParams()
    for field in ("kernel", "k1", "k2", "k3", "mass", "damping", "dt", "max_iterations", "velocity_tol_mm",
                  "fold_angle_deg", "rest_lengths", "regularization", "fold_free_warp", "fold_smoothing",
                  "registration_sigmas_mm", "carry_sigmas_mm", "hardy_s_mm"):  # fmt: skip
        assert getattr(ui, field) == pytest.approx(getattr(core, field)), field
    assert {f.name for f in dataclasses.fields(core)} >= {"registration_sigmas_mm", "k1", "k2"}
    settings.registration_sigmas_mm = ""  # the paper's scheme: no registration
    assert params_from_group(CoatingParams, settings).registration_sigmas_mm == ()
    settings.k1 = 0.35  # typed in the sidebar: the same number as 0.35 in a project file
    assert params_from_group(CoatingParams, settings).k1 == 0.35


def test_a_render_in_the_default_shading_shows_the_correspondence_colours(bpy_clean, tmp_path):
    """After coating, the scene's Solid shading shows colour attributes: a Workbench render of a
    coated instance (its instance hidden) is not one flat grey."""
    bpy = bpy_clean
    inst, _ = _scene(bpy, tmp_path)
    assert bpy.ops.ssm.coat_template() == {"FINISHED"}
    scene = bpy.context.scene
    assert scene.display.shading.color_type == "VERTEX"
    coated = bpy.data.objects[f"{inst[2].name} coated"]
    for obj in scene.objects:
        obj.hide_render = obj != coated
    cam_data = bpy.data.cameras.new("cam")
    cam_data.type = "ORTHO"
    cam_data.ortho_scale = 80.0
    cam = bpy.data.objects.new("cam", cam_data)
    scene.collection.objects.link(cam)
    centre = np.asarray(coated.matrix_world.translation) + bridge_centre(coated)
    cam.location = (centre[0], centre[1], centre[2] + 200.0)
    scene.camera = cam
    cam_data.clip_end = 1000.0
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.render.resolution_x = scene.render.resolution_y = 96
    scene.render.filepath = str(tmp_path / "coated.png")
    scene.render.image_settings.file_format = "PNG"
    bpy.ops.render.render(write_still=True)
    import matplotlib.image as mpimg

    img = mpimg.imread(str(tmp_path / "coated.png"))[:, :, :3].reshape(-1, 3)
    fg = img[np.abs(img - img[0]).sum(axis=1) > 0.05]  # pixels unlike the corner (background)
    assert len(fg) > 500
    chroma = fg.max(axis=1) - fg.min(axis=1)  # 0 for any grey
    assert np.percentile(chroma, 75) > 0.1 and fg.std(axis=0).max() > 0.05


def bridge_centre(obj) -> np.ndarray:
    from ssm.operators import bridge

    return bridge.mesh_vertices(obj.data).mean(axis=0)


def _coatings_equal(bpy, study):
    """The scene's coated points are the headless study's, to 1e-9 mm, instance by instance."""
    from ssm.operators import bridge

    coated = {o.ssm.instance.name: bridge.load_arrays(o, "ssm_coating")["points_object"]
              for o in bpy.data.objects if o.ssm.role == "COATED"}
    assert set(coated) == set(study.names)
    for name, points in coated.items():
        np.testing.assert_allclose(points, study.coatings[name].points_object, atol=1e-9, err_msg=name)

@pytest.mark.slow
def test_coat_template_refines_the_template_where_the_build_does(bpy_clean, tmp_path):
    """Spiked ellipsoids whose spikes are longer than the template instance's (as meshes): Coat
    Template builds the template again denser where the coatings cut off the spikes, as the
    headless build of the same project does; the scene's template and coatings equal the build's,
    and no ``input_surface`` finding is left in either."""
    from conftest import spiked_project
    from ssm.operators.scene import find_template, scene_findings, template_from_object
    from test_template_refinement import HEADER, SHAPES

    from ssm_addon.pipeline.project import read_project
    from ssm_addon.pipeline.project_build import build

    bpy = bpy_clean
    project = spiked_project(tmp_path / "spikes", SHAPES, HEADER)
    headless = build(read_project(project), tmp_path / "out", log=None)
    refined = headless.study.template.params["refined_at"]
    assert bpy.ops.ssm.open_project(filepath=str(project)) == {"FINISHED"}
    assert bpy.ops.ssm.build_template() == {"FINISHED"}
    assert len(template_from_object(find_template(bpy.context)).points_object) == refined["points_before"]
    assert bpy.ops.ssm.coat_template() == {"FINISHED"}
    template = template_from_object(find_template(bpy.context))
    assert template.params["refined_at"] == refined
    np.testing.assert_allclose(template.points_object, headless.study.template.points_object, atol=1e-9)
    np.testing.assert_array_equal(template.faces, headless.study.template.faces)
    _coatings_equal(bpy, headless.study)  # the build's coatings (its optimisation is off by default)
    assert not [f for f in scene_findings(bpy.context) if f.gate == "input_surface"]
    assert not [f for f in headless.study.findings if f.gate == "input_surface"]


@pytest.mark.slow
def test_coat_template_refines_the_model_methods_template_as_the_build_does(bpy_clean, tmp_path, verse_dir):
    """L2 of two subjects as 3D Slicer meshes, verse005's without landmarks (the model method supplies
    its correspondence) and with six cavities inside (closed surfaces its label map's holes give):
    Coat Template leaves the cavities out and refines the template where verse005's outer surface
    was cut off, as the headless build does; the scene's template and coatings equal the build's,
    and neither has an ``input_surface`` finding."""
    if not (verse_dir.parent / "verse005").is_dir():
        pytest.skip(f"verse005 not found in {verse_dir.parent}")
    from conftest import VERSE_LABELS
    from foreign_data import two_subject_level
    from ssm.operators.scene import find_template, scene_findings, template_from_object

    from ssm_addon.pipeline.project import read_project
    from ssm_addon.pipeline.project_build import build

    bpy = bpy_clean
    project = two_subject_level(tmp_path / "L2", verse_dir.parent, "L2", VERSE_LABELS["L2"])
    headless = build(read_project(project), tmp_path / "out", log=None)
    assert "v5" in headless.study.template.params["refined_at"]["instances"]
    assert headless.study.input_distances["v5"]["cavities"]["components"] == 6
    assert not [f for f in headless.study.findings if f.gate == "input_surface"]
    assert bpy.ops.ssm.open_project(filepath=str(project)) == {"FINISHED"}
    assert bpy.ops.ssm.build_template() == {"FINISHED"}
    assert bpy.ops.ssm.coat_template() == {"FINISHED"}
    template = template_from_object(find_template(bpy.context))
    assert template.params["refined_at"] == headless.study.template.params["refined_at"]
    np.testing.assert_array_equal(template.faces, headless.study.template.faces)
    _coatings_equal(bpy, headless.study)
    assert not [f for f in scene_findings(bpy.context) if f.gate == "input_surface"]


def test_coat_template_mirrors_a_right_instance_as_the_build_does(bpy_clean, tmp_path):
    """Four knobbed ellipsoids as meshes, two of them mirror images (no side given, no landmarks):
    Coat Template finds the two by their surface and mirrors them into the template's side as the
    headless build does: the same coatings (1e-9 mm), the instances marked mirrored, and each coated
    object shown on its own instance in Blender's world (not on its mirror image)."""
    from ssm.operators import bridge
    from ssm.operators.scene import MIRROR_PROP, scene_instances
    from test_sides import _chiral

    from ssm_addon.formats.meshes import write_ply
    from ssm_addon.instances.volume import display_surface
    from ssm_addon.meshutil import MeshLocator
    from ssm_addon.pipeline.project import read_project
    from ssm_addon.pipeline.project_build import build

    bpy = bpy_clean
    lines = ['[template]\ninstance = "k0"\n', "[correspondence]\noptimise = false\n",
             "[model]\nspecificity_samples = 20\n"]
    meshes = {}
    for i, (scale, mirror) in enumerate(((1.0, False), (1.06, True), (0.95, False), (1.1, True))):
        v, f = display_surface(_chiral(), to_world=True)
        v = v * scale
        if mirror:
            v, f = v * np.array([-1.0, 1.0, 1.0]), f[:, ::-1]
        write_ply(tmp_path / f"k{i}.ply", v, f, space="RAS")
        meshes[f"k{i}"] = (v, f)
        lines.append(f'[[instances]]\nname = "k{i}"\nmesh = "k{i}.ply"\n')
    project = tmp_path / "p.toml"
    project.write_text("\n".join(lines))
    headless = build(read_project(project), tmp_path / "out", log=None)
    assert {n for n, d in headless.study.sides.items() if d.mirror} == {"k1", "k3"}
    assert bpy.ops.ssm.open_project(filepath=str(project)) == {"FINISHED"}
    assert bpy.ops.ssm.build_template() == {"FINISHED"}
    assert bpy.ops.ssm.coat_template() == {"FINISHED"}
    _coatings_equal(bpy, headless.study)
    marked = {o.name: o.get(MIRROR_PROP) for o in scene_instances(bpy.context)}
    assert marked == {"k0": 0, "k1": 1, "k2": 0, "k3": 1}, marked  # the template instance: its own side
    for obj in bpy.data.objects:
        if obj.ssm.role == "COATED":
            m = bridge.matrix_to_numpy(obj.matrix_world)
            pts = bridge.load_arrays(obj, "ssm_coating")["points_object"] @ m[:3, :3].T + m[:3, 3]
            name = obj.ssm.instance.name
            assert MeshLocator(*meshes[name]).query(pts)[1].mean() < 1.0, name
