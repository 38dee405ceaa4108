"""The template refined across the population (``[template] refine_where_cut_off``): where the
coatings cut off parts of the instances' own meshes, the template is built again, denser there,
and every instance coated again."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import spiked_project

from ssm_addon.coating.coating import CoatingResult
from ssm_addon.instances.volume import ObjectFrame
from ssm_addon.pipeline.project import read_project
from ssm_addon.pipeline.project_build import build

#: the template instance s0's spike is 6 mm long, the others' 14 and 16 mm: longer than the template's
SHAPES = ((6.0, (24.0, 20.0, 16.0)), (14.0, (24.0, 20.0, 16.0)), (16.0, (24.0, 20.0, 16.0)))
HEADER = ["[model]", "specificity_samples = 20", "", "[template]", 'instance = "s0"']


def _cut_off(report) -> dict:
    return {f["instance"]: f["value"] for f in report["quality"]["findings"] if f["gate"] == "input_surface"}


def _far(report) -> dict:
    return {n: d["input_surface_mm"]["from_input"]["max_mm"] for n, d in report["instances"].items()}


@pytest.mark.slow
def test_a_process_longer_than_the_template_instances_is_kept_by_refining_the_template(tmp_path):
    """With the template refined off, the coatings cut off the longer spikes of s1 and s2 (their
    meshes lie more than 3 mm from the coatings at the tip: the ``input_surface`` finding). With
    the default, the template is built again denser where those tips lie on it: no finding, every
    mesh nearer its coating than before, the template's own tolerance still kept, and the report
    says where it was refined. (The model method, with landmarks on two of them, reaches these
    spikes by its rounds alone: no finding either way; its refinement is tested on the lumbar
    vertebrae, tests/test_data_as_users_bring_it.py.)"""
    off_project = spiked_project(tmp_path / "off", SHAPES, HEADER + ["refine_where_cut_off = false"])
    off = build(read_project(off_project), tmp_path / "off" / "out", log=None)
    lines = []
    on = build(read_project(spiked_project(tmp_path / "on", SHAPES, HEADER)), tmp_path / "on" / "out",
               log=lines.append)
    before, after = _cut_off(off.report), _cut_off(on.report)
    print("without / with the refinement, largest distance mm:", _far(off.report), _far(on.report))
    assert set(before) == {"s1", "s2"}, before
    assert not after, after
    assert all(_far(on.report)[n] < _far(off.report)[n] for n in ("s1", "s2"))
    assert all(v <= 3.0 for v in _far(on.report).values())
    refined = on.study.template.params["refined_at"]
    assert set(refined["instances"]) == {"s1", "s2"} and refined["places"] == sum(refined["instances"].values())
    assert refined["points"] == len(on.study.template.points_object) > refined["points_before"]
    assert refined["points_before"] == len(off.study.template.points_object)
    assert refined["input_surface_findings"] == [2, 0]
    assert on.report["template"]["refined_at"] == refined
    assert any(line.startswith("template: refined where 2 coating(s) cut off parts") and line.endswith("kept")
               for line in lines), lines
    assert on.study.template.params["largest_distance_mm"] <= 1.0 + 1e-9
    assert "refined_at" not in off.study.template.params


def test_cut_off_places_lie_on_the_template_where_the_mesh_is_far(tmp_path):
    """:func:`cut_off_places`: every far vertex of the mesh (beyond ``max_input_distance_mm``) is carried
    to the template through its nearest coated triangle: on a coating that is the template itself
    (in an object frame 50 mm off the world's origin), the places lie on the template's sphere
    under the mesh's bulge. The factor is 0.6 where the coating keeps the template's size and 1/2
    where its triangles are twice as long."""
    from conftest import icosphere

    from ssm_addon.formats.meshes import write_ply
    from ssm_addon.pipeline.stages import cut_off_places
    from ssm_addon.pipeline.study import Study
    from ssm_addon.template.template import Template

    v, f = icosphere(20.0, 3)
    mesh = v * np.where(v[:, [0]] > 19.0, 1.4, 1.0)  # a bulge at +x: 28 mm out where the sphere is 20
    write_ply(tmp_path / "a.ply", mesh, f, space="RAS")
    (tmp_path / "p.toml").write_text("".join(f'[[instances]]\nname = "{n}"\nmesh = "a.ply"\n' for n in "abc"))
    study = Study.from_project(read_project(tmp_path / "p.toml"))
    frame = ObjectFrame(np.array([50.0, 0.0, 0.0]), np.eye(3))
    template = Template(points_object=v, faces=f, curvature=np.zeros(len(v)), frame=frame)
    coated = {"a": CoatingResult(points_object=v - [50.0, 0.0, 0.0], warped_points_object=v, fit=None)}
    far = np.linalg.norm(mesh - v, axis=1) > study.params.quality.max_input_distance_mm
    places, factors, counts = cut_off_places(study, coated, template, ["a"], frames={"a": frame})
    assert counts == {"a": int(far.sum())} and len(places) == far.sum() > 0
    assert np.all(np.linalg.norm(places, axis=1) <= 20.0 + 1e-9) and np.all(places[:, 0] > 15.0)
    np.testing.assert_allclose(factors, 0.6)
    # the coating twice the template's size: the template points halved, the same coating
    half = Template(points_object=v / 2.0, faces=f, curvature=np.zeros(len(v)), frame=frame)
    _p, factors, _c = cut_off_places(study, coated, template, ["a"], coated_from=half, frames={"a": frame})
    np.testing.assert_allclose(factors, 0.5)
