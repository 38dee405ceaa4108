"""The model's floor: the best it can do for a target (closest points within its span, no prior)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import axis_rotation
from test_segmentation import bumped_shapes

from ssm_addon.cli.command import main
from ssm_addon.fitting import Target, fit_any_pose, fit_floor
from ssm_addon.formats.meshes import write_ply
from ssm_addon.model.files import save_npz
from ssm_addon.model.pca import build_model


@pytest.fixture(scope="module")
def model_and_faces():
    shapes, faces = bumped_shapes(n=16, seed=4)
    return build_model(shapes[1:], faces, [f"s{i}" for i in range(15)], alignment="rigid"), faces, shapes[0]


def _posed(points):
    return points @ axis_rotation([1.0, 2.0, 0.5], 70.0).T + [30.0, -60.0, 200.0]


def test_a_shape_inside_the_span_has_a_floor_of_zero_and_the_fit_is_never_below_the_floor(model_and_faces):
    model, faces, held_out = model_and_faces
    inside = _posed(model.generate(np.array([2.0, -1.5]) * model.standard_deviations[:2]))
    target = Target.from_mesh(inside, faces)
    fit, _ = fit_any_pose(model, target)
    floor = fit_floor(model, target, fit.pose)
    assert floor["floor_mm"] < 0.02 and floor["starts"] == 13
    assert fit.mean_distance_mm >= floor["floor_mm"] - 1e-9
    # a shape outside the span (a bump the model never saw): the floor is what is left, the fit above it
    outside = held_out.copy()
    outside[np.argmax(outside[:, 2])] += [0.0, 0.0, 4.0]
    target = Target.from_mesh(_posed(outside), faces)
    fit, _ = fit_any_pose(model, target)
    floor = fit_floor(model, target, fit.pose)
    assert 0.0 < floor["floor_mm"] <= fit.mean_distance_mm + 1e-9


def test_ssm_fit_floor_reports_it_beside_the_fit(model_and_faces, tmp_path, capsys):
    model, faces, held_out = model_and_faces
    save_npz(model, tmp_path / "model.npz")
    write_ply(tmp_path / "t.ply", _posed(held_out), faces)
    code = main(["fit", str(tmp_path / "model.npz"), "--mesh", str(tmp_path / "t.ply"), "--floor",
                 "--out", str(tmp_path / "o")])
    out = capsys.readouterr().out
    assert code == 0 and "floor: the model reaches" in out
    doc = json.loads((tmp_path / "o" / "fit.json").read_text())
    assert doc["floor_mm"] <= doc["mean_distance_mm"] + 1e-9 and "without the prior" in doc["floor"]["method"]
    assert doc["above_floor_mm"] == pytest.approx(doc["mean_distance_mm"] - doc["floor_mm"])
    code = main(["fit", str(tmp_path / "model.npz"), "--glob", str(tmp_path / "*.ply"), "--floor",
                 "--out", str(tmp_path / "o2")])
    assert code == 2 and "computed for one target" in capsys.readouterr().err
