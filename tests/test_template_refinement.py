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
    """:func:`cut_off_places`: every far vertex of the mesh (beyond ``max_input_distance_mm``, as the
    coating stage's :func:`input_distances` finds them) is carried to the template through its
    nearest coated triangle: on a coating that is the template itself
    (in an object frame 50 mm off the world's origin), the places lie on the template's sphere
    under the mesh's bulge. The factor is 0.6 where the coating keeps the template's size and 1/2
    where its triangles are twice as long."""
    from conftest import icosphere

    from ssm_addon.formats.meshes import write_ply
    from ssm_addon.pipeline.stages import cut_off_places, input_distances
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
    _figures, cut_off = input_distances(study, coated, template, {"a": frame})  # the coating stage's measure
    places, factors, counts = cut_off_places(coated, cut_off, template, ["a"])
    assert counts == {"a": int(far.sum())} and len(places) == far.sum() > 0
    assert np.all(np.linalg.norm(places, axis=1) <= 20.0 + 1e-9) and np.all(places[:, 0] > 15.0)
    np.testing.assert_allclose(factors, 0.6)
    # the coating twice the template's size: the template points halved, the same coating
    half = Template(points_object=v / 2.0, faces=f, curvature=np.zeros(len(v)), frame=frame)
    _p, factors, _c = cut_off_places(coated, cut_off, template, ["a"], coated_from=half)
    np.testing.assert_allclose(factors, 0.5)


def _result(findings, distances, **product):
    from ssm_addon.pipeline.study import StageResult

    return StageResult("coating", {"coatings": {}, "input_distances": distances, **product}, tuple(findings))


def _cut(name, far_mm, count, share, lost=0):
    from ssm_addon.model.quality import Finding

    beyond = {"mm": 3.0, "count": count, "share": share, "voxels": {"count": lost, "spacing_mm": 1.0}}
    return (Finding(name, "input_surface", f"{name} cut off", far_mm, 3.0),
            {"from_input": {"max_mm": far_mm, "mean_mm": 0.5, "beyond": beyond}})


def test_only_parts_the_coating_cut_off_ask_for_a_denser_template():
    """A few far vertices the coating lost: refine. All of them lost by the import's voxels (a
    finer spacing mends that), or a tenth of the mesh and more (a wrong coating or a gate set too
    tight): not."""
    from ssm_addon.pipeline.template_refinement import CUT_OFF_SHARE, cut_off_instances

    cases = {"tip": _cut("tip", 3.6, 13, 0.0004), "voxels": _cut("voxels", 3.4, 5, 0.0002, lost=5),
             "most": _cut("most", 9.0, 6000, CUT_OFF_SHARE + 0.01), "near": _cut("near", 3.1, 3, 0.0001, lost=1)}
    result = _result([f for f, _d in cases.values()], {n: d for n, (_f, d) in cases.items()})
    assert cut_off_instances(result) == ["tip", "near"]


@pytest.mark.parametrize("second", ["better", "worse", "other-finding", "farther", "cancelled"])
def test_the_second_coating_is_kept_only_when_fewer_meshes_are_cut_off(monkeypatch, second):
    """The coatings with the refined template replace the first only with fewer ``input_surface``
    findings, no more findings of other gates and no mesh farther from its coating anywhere (its
    finding gone on one instance but another's mesh 0.7 mm farther: the first kept, and said where);
    Esc during them keeps the first."""
    import dataclasses

    from ssm_addon.base.errors import Cancelled
    from ssm_addon.model.quality import Finding
    from ssm_addon.pipeline import template_refinement as R
    from ssm_addon.pipeline.study import Study
    from ssm_addon.template.template import Template

    frame = ObjectFrame(np.zeros(3), np.eye(3))
    built = Template(points_object=np.eye(3), faces=np.array([[0, 1, 2]]), curvature=np.zeros(3), frame=frame,
                     params={})
    refined = dataclasses.replace(built, points_object=2 * np.eye(3))
    monkeypatch.setattr(R, "cut_off_places", lambda *a, **k: (np.ones((2, 3)), np.full(2, 0.6), {"a": 2}))
    monkeypatch.setattr(R, "make_template", lambda study, **k: refined)
    study = Study(instances=[], template_instance="t", template=built, volumes={"t": None})
    finding, distance = _cut("a", 3.6, 2, 0.001)
    b_first, b_farther = ({"from_input": {"max_mm": mm, "mean_mm": 0.4}} for mm in (1.6, 2.3))
    first = _result([finding], {"a": distance, "b": b_first})
    near = {"from_input": {"max_mm": 2.5, "mean_mm": 0.5}}
    seconds = {"better": _result([], {"a": near, "b": b_first}), "worse": _result([finding], {"a": distance, "b": b_first}),
               "other-finding": _result([Finding("a", "folds", "folded", 2.0, 0.0)], {"a": near, "b": b_first}),
               "farther": _result([], {"a": near, "b": b_farther})}
    seen = []

    def coat(s):
        seen.append(s.template)
        if second == "cancelled":
            raise Cancelled("Esc")
        return seconds[second]

    lines = []
    out = R.with_template_refined(study, first, coat, log=lines.append)
    assert seen == [refined]  # the second coating had the refined template
    if second == "better":
        assert out.product["template"].params["refined_at"]["input_surface_findings"] == [1, 0]
        assert out.product["template"].points_object is not None and not out.findings
        assert out.summary[-1].endswith("kept") and "1 → 0" in out.summary[-1]
    else:
        assert out.findings == first.findings and "template" not in out.product
        assert out.summary[-1].endswith("the first coatings kept")
        assert ("cancelled" in out.summary[-1]) == (second == "cancelled")
        assert ("(farther from its coating on b 1.60 → 2.30 mm)" in out.summary[-1]) == (second == "farther")
