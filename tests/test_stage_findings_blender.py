"""Each stage owns its findings: Blender shows exactly the quality findings the command line reports.

One project with a bad instance (its label map holds the neighbouring vertebra under the
same label: two components, which also makes it the model's outlier), built headless and through ``bpy.ops`` (Open Project, Build
Template, Coat Template, Build Model): the same findings (stage, gate, instance, figure)
in ``report.json`` and in the scene's record the panels draw, and the same model.
"""

from __future__ import annotations

import json

import nibabel as nib
import numpy as np
import pytest

from ssm_addon.cli import demo
from ssm_addon.pipeline.project import read_project
from ssm_addon.pipeline.project_build import build

pytestmark = [pytest.mark.blender, pytest.mark.slow]


@pytest.fixture(scope="module")
def flawed_project(tmp_path_factory):
    path = demo.make_demo_population(tmp_path_factory.mktemp("flawed"), n=6, seed=11)
    path.write_text(path.read_text().replace("spacing = 1.0", "spacing = 1.0\nr_min_mm = 4.0\nr_max_mm = 8.0")
                    .replace("[model]", "[model]\nspecificity_samples = 50"))
    project = read_project(path)
    two = project.instances[2]  # two components: the neighbour under the vertebra's label
    img = nib.load(two.volume_path)
    labels = np.asarray(img.dataobj).copy()
    labels[labels == demo.NEIGHBOUR_LABEL] = demo.VERTEBRA_LABEL
    nib.save(nib.Nifti1Image(labels, img.affine), str(two.volume_path))
    return path, two.name


def _key(f: dict) -> tuple:
    return f["stage"], f["gate"], f["instance"], round(f["value"], 6) if f["value"] is not None else None


def test_blender_and_headless_builds_report_the_same_findings(bpy_clean, flawed_project, tmp_path):
    from ssm.operators import scene as opscene

    path, two = flawed_project
    headless = build(read_project(path), tmp_path / "out", log=None)
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    expected = {_key(f) for f in report["quality"]["findings"]}
    gates = {(f[1], f[2]) for f in expected}
    assert ("components", two) in gates  # the import gate
    assert any(stage == "model" for stage, *_ in expected), expected  # the outlier gates of the model stage
    # the coating's gates (measured again on the optimised coatings: the optimisation's record replaces them)
    assert any(stage in ("coating", "optimisation") for stage, *_ in expected), expected

    bpy = bpy_clean
    assert bpy.ops.ssm.open_project(filepath=str(path)) == {"FINISHED"}
    assert bpy.ops.ssm.build_template() == {"FINISHED"}
    assert bpy.ops.ssm.coat_template() == {"FINISHED"}
    assert bpy.ops.ssm.build_model() == {"FINISHED"}
    shown = {_key(f.to_dict()) for f in opscene.scene_findings(bpy.context)}
    assert shown == expected
    blender_model = opscene.model_from_object(opscene.find_model_object(bpy.context))
    for key in ("mean", "modes", "variances", "instance_points"):
        assert np.array_equal(getattr(blender_model, key), getattr(headless.model, key)), key
