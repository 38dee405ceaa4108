"""Model-guided correspondence in Blender: Coat Template with the model method equals the
headless build's coating, Refine Correspondence adds rounds and Esc keeps the scene,
and Propose Landmarks fits the scene's model."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import project_variant, template_of

from ssm_addon.cli import demo
from ssm_addon.formats.landmarks import read_landmarks
from ssm_addon.pipeline.project import read_project
from ssm_addon.pipeline.project_build import build

pytestmark = pytest.mark.blender


@pytest.fixture(scope="module")
def light_project(tmp_path_factory):
    """Five demo vertebrae, landmarks on the template instance only, method = "model"."""
    folder = tmp_path_factory.mktemp("corr_blender")
    path = demo.make_demo_population(folder / "population", n=5, seed=9)
    path.write_text(path.read_text().replace("spacing = 1.0", "spacing = 1.0\nr_min_mm = 4.0\nr_max_mm = 8.0")
                    .replace("[model]", "[model]\nspecificity_samples = 50"))
    tpl = template_of(path)
    return project_variant(path, "light.toml", correspondence='[correspondence]\nmethod = "model"\niterations = 2\noptimise = true',
                    keep_landmarks={tpl})


def _coatings(bpy):
    from ssm.operators import bridge

    return {o.ssm.instance.name: bridge.load_arrays(o, "ssm_coating")["points_object"]
            for o in bpy.data.objects if o.ssm.role == "COATED"}


def _select(bpy, obj):
    for o in bpy.context.view_layer.objects:
        o.select_set(o == obj)
    bpy.context.view_layer.objects.active = obj


@pytest.mark.slow
def test_model_method_in_blender_equals_the_headless_build(bpy_clean, light_project, tmp_path):
    bpy = bpy_clean
    from ssm.operators.coating import correspondence_rounds

    headless = build(read_project(light_project), tmp_path / "out", log=None)
    assert bpy.ops.ssm.open_project(filepath=str(light_project)) == {"FINISHED"}
    assert bpy.context.scene.ssm_correspondence.method == "model"
    assert bpy.ops.ssm.build_template() == {"FINISHED"}
    assert bpy.ops.ssm.coat_template() == {"FINISHED"}  # the model method: starts + rounds, as the build
    # Esc before the optimisation's first iteration ends: the coatings stay as they were
    before = _coatings(bpy)
    assert bpy.ops.ssm.optimise_correspondence(cancel_after=0) == {"FINISHED"}
    assert all(np.array_equal(_coatings(bpy)[n], before[n]) for n in before)
    from ssm.operators.coating import scene_optimisation

    assert scene_optimisation(bpy.context)["stop"] == "cancelled"
    assert bpy.ops.ssm.optimise_correspondence() == {"FINISHED"}  # the build's step after the coating
    assert scene_optimisation(bpy.context)["steps"] == headless.report["correspondence"]["optimisation"]["steps"]
    coated = _coatings(bpy)
    assert set(coated) == set(headless.study.names)
    for name, pts in coated.items():
        np.testing.assert_allclose(pts, headless.study.coatings[name].points_object, atol=1e-9, err_msg=name)
    rounds = correspondence_rounds(bpy.context)
    assert [r["mean_change_mm"] for r in rounds] == pytest.approx(
        [r["mean_change_mm"] for r in headless.report["correspondence"]["rounds"]], abs=1e-9)
    starts = {o.ssm.instance.name: o["ssm_coating_start"] for o in bpy.data.objects if o.ssm.role == "COATED"}
    assert starts == headless.report["correspondence"]["start"]
    # the same self-check and stop in the panel's record as in report.json
    from ssm.operators.coating import correspondence_check

    check = correspondence_check(bpy.context)
    assert check["stop"] == headless.report["correspondence"]["stop"]
    assert check["instance_mm"] == pytest.approx(headless.report["correspondence"]["self_check"]["instance_mm"],
                                                 abs=1e-9)

    # Esc during a further refinement: nothing changes
    assert bpy.ops.ssm.refine_correspondence(cancel_after=2) == {"CANCELLED"}
    after = _coatings(bpy)
    assert all(np.array_equal(after[n], coated[n]) for n in coated)
    assert correspondence_rounds(bpy.context) == rounds

    # a further round: appended to the panel's figures, coatings replaced (not duplicated)
    n_objects = len(bpy.data.objects)
    bpy.context.scene.ssm_correspondence.iterations = 1
    assert bpy.ops.ssm.refine_correspondence() == {"FINISHED"}
    assert len(correspondence_rounds(bpy.context)) == len(rounds) + 1
    assert len(bpy.data.objects) == n_objects
    moved = [np.linalg.norm(_coatings(bpy)[n] - coated[n], axis=1).max() for n in coated]
    # a kept round moves the coatings; one the self-check drops leaves them as they were
    last = correspondence_rounds(bpy.context)[-1]
    assert (max(moved) > 0.0) == last["kept"], (last, moved)
    from ssm.operators.coating import correspondence_check

    check = correspondence_check(bpy.context)
    assert check["stop"] in ("converged", "criterion", "limit") and check["study_mm"] > 0.0


@pytest.mark.slow
def test_propose_landmarks_fits_the_scene_model(bpy_clean, light_project):
    bpy = bpy_clean
    from ssm.operators.scene import landmark_empties, scene_instances

    assert bpy.ops.ssm.open_project(filepath=str(light_project)) == {"FINISHED"}
    assert bpy.ops.ssm.build_template() == {"FINISHED"}
    assert bpy.ops.ssm.coat_template() == {"FINISHED"}
    assert bpy.ops.ssm.build_model() == {"FINISHED"}
    tpl = template_of(light_project)
    others = [o for o in scene_instances(bpy.context) if o.name != tpl]
    errors = []
    for obj in others:
        assert not landmark_empties(obj)
        _select(bpy, obj)
        assert bpy.ops.ssm.propose_landmarks() == {"FINISHED"}  # automatic: the model
        placed = landmark_empties(obj)
        truth_file = next(p for p in light_project.parent.iterdir()
                          if p.name.split(".")[0] == obj.name and not p.name.endswith(".nii.gz"))
        truth = read_landmarks(truth_file).as_dict()
        from ssm.operators.scene import landmark_point

        errors += [np.linalg.norm(landmark_point(obj, emp) - truth[name]) for name, emp in placed.items()]
        assert set(placed) == set(truth)
    assert np.median(errors) < 2.5 and np.max(errors) < 8.0, np.round(errors, 2)
    # a second proposal has nothing left to place: said, not silently done
    with pytest.raises(RuntimeError, match="already has every landmark the model knows"):
        bpy.ops.ssm.propose_landmarks(method="model")


@pytest.mark.slow
def test_coat_template_without_landmarks_takes_the_medoid_template_as_the_build_does(bpy_clean, tmp_path):
    """No landmarks on any instance: the build coats from the given template, builds the template
    again from the instance whose coating is nearest the mean shape and coats every instance from it;
    Coat Template in Blender does the same (the template object moves to that instance, the same
    coatings to 1e-9 mm, the same record)."""
    bpy = bpy_clean
    from ssm.operators.scene import find_template, scene_records

    path = demo.make_demo_population(tmp_path / "population", n=6, seed=9)
    path.write_text(path.read_text().replace("spacing = 1.0", "spacing = 1.0\nr_min_mm = 4.0\nr_max_mm = 8.0")
                    .replace("[model]", "[model]\nspecificity_samples = 50"))
    bare = project_variant(path, "bare.toml", keep_landmarks=set())
    headless = build(read_project(bare), tmp_path / "out", log=None)
    choice = headless.report["correspondence"]["template_choice"]
    assert choice["by"] == "coatings" and choice["kept"] and choice["medoid"] != choice["given"], choice
    assert bpy.ops.ssm.open_project(filepath=str(bare)) == {"FINISHED"}
    assert bpy.ops.ssm.build_template() == {"FINISHED"}
    assert find_template(bpy.context).ssm.instance.name == choice["given"]
    assert bpy.ops.ssm.coat_template() == {"FINISHED"}
    assert find_template(bpy.context).ssm.instance.name == choice["medoid"]
    assert bpy.context.scene.ssm_display.template_instance.name == choice["medoid"]
    assert scene_records(bpy.context)["template_choice"]["medoid"] == choice["medoid"]
    for name, pts in _coatings(bpy).items():
        np.testing.assert_allclose(pts, headless.study.coatings[name].points_object, atol=1e-9, err_msg=name)


@pytest.mark.slow
@pytest.mark.parametrize("template_choice", ["landmark-medoid", "medoid"])
def test_the_medoid_template_of_the_model_method_reaches_the_scene(bpy_clean, tmp_path, template_choice):
    """Landmarks on every instance: the model method builds the template from the instance whose
    landmarks are nearest their mean ("landmark-medoid", before the first coating) or again from
    the population's medoid when that lowers the self-check ("medoid"); Coat Template in Blender
    does what the headless build does: the same template instance (the template object follows
    it), the same coatings, the same record of the choice."""

    bpy = bpy_clean
    from ssm.operators.scene import find_template

    path = demo.make_demo_population(tmp_path / "population", n=6, seed=9)
    path.write_text(path.read_text().replace("spacing = 1.0", "spacing = 1.0\nr_min_mm = 4.0\nr_max_mm = 8.0")
                    .replace("[model]", "[model]\nspecificity_samples = 50")
                    .replace("[coating]", '[correspondence]\nmethod = "model"\niterations = 2\n'
                                                f'template_choice = "{template_choice}"\n\n[coating]'))
    headless = build(read_project(path), tmp_path / "out", log=None)
    choice = headless.report["correspondence"]["template_choice"]
    assert choice["kept"] and choice["medoid"] != choice["given"], choice  # the fixture exercises the choice
    assert headless.study.template_instance == choice["medoid"]
    assert bpy.ops.ssm.open_project(filepath=str(path)) == {"FINISHED"}
    assert bpy.ops.ssm.build_template() == {"FINISHED"}
    assert find_template(bpy.context).ssm.instance.name == choice["given"]
    assert bpy.ops.ssm.coat_template() == {"FINISHED"}  # the build's coatings (its optimisation is off by default)
    assert find_template(bpy.context).ssm.instance.name == choice["medoid"]
    assert bpy.context.scene.ssm_display.template_instance.name == choice["medoid"]
    from ssm.operators.scene import scene_records  # the scene's record of the stages, as a build's report

    assert scene_records(bpy.context)["template_choice"]["medoid"] == choice["medoid"]
    for name, pts in _coatings(bpy).items():
        np.testing.assert_allclose(pts, headless.study.coatings[name].points_object, atol=1e-9, err_msg=name)
    assert bpy.ops.ssm.build_model() == {"FINISHED"}  # the model is built on the medoid's template
