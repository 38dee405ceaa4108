"""The correspondence self-check (landmark transfer error) and its gates, on analytic shapes.

Ellipsoids in exact correspondence (vertex i of the unit icosphere scaled by each
instance's axes) form a linear population: the model of the others represents any of
them, so each instance's landmarks are predicted where they are. Sliding one instance's
points along its own surface (the same surface, a wrong correspondence) corrupts the
others' model, and the study's transfer error rises.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import icosphere

from ssm_addon.base.params import FitParams, QualityParams
from ssm_addon.correspondence.rounds import CorrespondenceCheck, RoundFigures, check_correspondence
from ssm_addon.meshutil import LandmarkLocations
from ssm_addon.model.quality import check_correspondence_rounds, check_frames, check_landmark_transfer

LANDMARKS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11)  # the icosahedron's corners


def _population(n=7, seed=3):
    v, f = icosphere(subdivisions=3)
    rng = np.random.default_rng(seed)
    axes = np.array([40.0, 25.0, 15.0]) * (1 + 0.15 * rng.standard_normal((n, 3)))
    points = {f"e{k}": v * axes[k] for k in range(n)}
    # the template's landmarks: mesh points at the corners (first vertex of a triangle using it)
    tri = np.array([int(np.flatnonzero((f == i).any(axis=1))[0]) for i in LANDMARKS])
    bary = np.array([(f[t] == i).astype(float) for t, i in zip(tri, LANDMARKS)])
    locations = LandmarkLocations(tuple(f"L{i}" for i in LANDMARKS), tri, bary)
    given = {n: {f"L{i}": p[i] for i in LANDMARKS} for n, p in points.items()}
    return v, f, axes, points, locations, given


def _slid(v, axes, degrees):
    """The same ellipsoid, its points rotated about z on the unit sphere first: a wrong
    correspondence on the right surface."""
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return (v @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T) * axes


def test_exact_correspondence_transfers_landmarks_within_the_fit_noise():
    v, f, _axes, points, locations, given = _population()
    check = check_correspondence(points, f, locations, given, fit=FitParams(noise_mm=0.5, tolerance_mm=0.001))
    assert set(check.instance_mm) == set(points)
    assert set(check.landmark_mm["e0"]) == {f"L{i}" for i in LANDMARKS}
    # a linear population: the model of the others reaches every instance's landmarks
    assert check.study_mm < 0.5, check.instance_mm
    assert check.study_mm == np.mean(list(check.instance_mm.values()))


@pytest.mark.slow
def test_a_slid_correspondence_raises_the_transfer_error():
    v, f, axes, points, locations, given = _population()
    fit = FitParams(noise_mm=0.5, tolerance_mm=0.001)
    exact = check_correspondence(points, f, locations, given, fit=fit)
    slid = dict(points, e3=_slid(v, axes[3], 25.0))
    # the slid instance's landmarks are still its given ones (the landmark warp pins them in
    # a coating); here they are simply where the rotated points put the corners
    worse = check_correspondence(slid, f, locations, given, fit=fit)
    print(f"exact {exact.study_mm:.3f} mm, slid 25 deg {worse.study_mm:.3f} mm")
    assert worse.study_mm > 0.5 and worse.study_mm > 50 * exact.study_mm, (exact.study_mm, worse.study_mm)
    # ... and the more it slides, the larger the error
    more = check_correspondence(dict(points, e3=_slid(v, axes[3], 50.0)), f, locations, given, fit=fit)
    assert more.study_mm > worse.study_mm


def test_instances_without_landmarks_are_not_checked():
    v, f, _axes, points, locations, given = _population()
    given = {n: (d if n in ("e0", "e1") else {}) for n, d in given.items()}
    check = check_correspondence(points, f, locations, given, fit=FitParams(noise_mm=0.5))
    assert set(check.instance_mm) == {"e0", "e1"}
    none = check_correspondence(points, f, locations, {n: {} for n in points}, fit=FitParams())
    assert none.instance_mm == {} and not np.isfinite(none.study_mm)
    assert json.loads(json.dumps(none.to_dict()))["study_mm"] is None


def test_the_transfer_gate_names_the_instance_and_the_landmark():
    check = CorrespondenceCheck.from_landmarks({"a": {"tip": 3.0, "base": 1.0}, "b": {"tip": 22.5, "base": 2.0}})
    assert check.instance_mm == {"a": 2.0, "b": 12.25} and check.study_mm == 7.125
    found = check_landmark_transfer(check, QualityParams(max_landmark_transfer_mm=15.0))
    assert [(f.instance, f.gate) for f in found] == [("b", "landmark_transfer")]
    assert "'tip' is 22.5 mm" in found[0].message and found[0].threshold == 15.0
    assert check_landmark_transfer(check, QualityParams(max_landmark_transfer_mm=25.0)) == []


def test_rounds_at_their_limit_are_a_finding_converged_ones_are_not():
    rounds = [RoundFigures(round=1, mean_change_mm=0.4), RoundFigures(round=2, mean_change_mm=0.25)]
    found = check_correspondence_rounds(rounds, CorrespondenceCheck(stop="limit", kept_round=2), 0.1)
    assert [(f.instance, f.gate) for f in found] == [("", "rounds")]
    assert "limit of 2" in found[0].message and "0.250 mm" in found[0].message
    for stop in ("converged", "criterion", ""):
        assert check_correspondence_rounds(rounds, CorrespondenceCheck(stop=stop), 0.1) == []


def test_landmark_locations_read_the_corners():
    v, f, _axes, points, locations, _given = _population(n=3)
    assert np.allclose(locations.evaluate(points["e1"], f), points["e1"][list(LANDMARKS)])
    assert np.allclose(locations.location.evaluate(points["e1"], f), points["e1"][list(LANDMARKS)])
    again = LandmarkLocations.from_dict(locations.to_dict())
    assert again.names == locations.names and np.array_equal(again.triangles, locations.triangles)
    assert np.array_equal(again.bary, locations.bary) and len(LandmarkLocations.from_dict(None)) == 0


def test_a_coating_turned_end_for_end_is_named_by_the_frame_gate():
    """A near-symmetric shape's moments frame can flip: its coating, in correspondence,
    turned 180° about an axis against the template instance's."""
    v, f, _axes, points, _locations, _given = _population(n=4)
    turned = dict(points, e2=points["e2"] * np.array([-1.0, -1.0, 1.0]))  # 180° about z
    names = list(turned)
    stack = np.stack([turned[n] for n in names])
    found = check_frames(names, stack, "e0", "none")
    assert [(x.instance, x.gate) for x in found] == [("e2", "frame")] and round(found[0].value) == 180
    assert 'alignment = "rigid"' in found[0].message
    assert check_frames(names, stack, "e0", "rigid") == []
    assert check_frames(names, np.stack([points[n] for n in names]), "e0", "none") == []


def test_aligned_to_undoes_a_turn_and_the_transfer_sees_through_it():
    """The self-check puts the others onto the checked coating by their correspondence:
    an instance stored turned end for end changes nothing."""
    from ssm_addon.correspondence.rounds import aligned_to

    v, f, _axes, points, locations, given = _population()
    flip = np.array([-1.0, 1.0, -1.0])  # 180° about y
    back = aligned_to((points["e1"] * flip)[None], points["e1"])[0]
    assert np.allclose(back, points["e1"], atol=1e-9)
    turned = dict(points, e4=points["e4"] * flip)
    given_turned = dict(given, e4={k: p * flip for k, p in given["e4"].items()})
    fit = FitParams(noise_mm=0.5, tolerance_mm=0.001)
    a = check_correspondence(points, f, locations, given, fit=fit)
    b = check_correspondence(turned, f, locations, given_turned, fit=fit)
    assert abs(a.study_mm - b.study_mm) < 0.05, (a.study_mm, b.study_mm)


def test_landmark_noise_separates_the_click_error_from_the_model_error():
    """The template instance's transfer differences are the model's error alone; the others' add
    the click error: the estimate recovers both (per axis, mm) and the least-squares share.
    The other instances' predictions against their own coatings bound the model error below."""
    from ssm_addon.correspondence.rounds import landmark_noise

    rng = np.random.default_rng(5)
    for model_sd, click_sd in ((0.5, 1.5), (1.0, 0.0), (0.3, 0.6)):
        d = {f"i{k}": rng.normal(scale=model_sd, size=(15, 3))
             + (rng.normal(scale=click_sd, size=(15, 3)) if k else 0.0) for k in range(40)}
        found = landmark_noise(d, "i0")
        assert found.estimated
        # sigma_m^2 comes from one instance's 45 coordinates: standard error ~0.2 sigma_m^2
        assert found.click_mm ** 2 == pytest.approx(click_sd ** 2, abs=0.7 * model_sd ** 2), (model_sd, click_sd, found)
        share = found.click_mm ** 2 / (found.click_mm ** 2 + found.model_mm ** 2)
        # a click error below the model's is not acted on: the clicks are the better estimate
        assert found.shrink == (pytest.approx(share) if found.click_mm >= found.model_mm else 0.0), found
    assert found.shrink > 0.5  # the last: clicks twice as far off as the model's prediction
    coating = {n: v * 2.0 for n, v in d.items()}  # predictions twice as far from the coatings: a larger model error
    floor = landmark_noise(d, "i0", coating_differences=coating)
    assert floor.model_mm > found.model_mm and floor.click_mm < found.click_mm
    known = landmark_noise(d, "i0", click_mm=1.0)
    assert not known.estimated and known.click_mm == 1.0
    assert known.shrink == pytest.approx(1.0 / (1.0 + known.model_mm ** 2))
    assert landmark_noise(d, "i0", click_mm=0.0).shrink == 0.0  # exact landmarks stay
    assert landmark_noise({"i0": d["i0"]}, "i0").shrink == 0.0  # no other landmarked instance: nothing to estimate


def test_a_round_is_kept_only_when_the_instances_improve_together():
    """Kept: the mean transfer error falls by the margin and the instances' own figures fall in a
    paired test; a fall one instance carries, or one within the margin, keeps the start."""
    from ssm_addon.correspondence.rounds import round_helps

    rng = np.random.default_rng(2)
    before = {f"i{k}": 2.0 + rng.normal(scale=0.3) for k in range(20)}
    check = CorrespondenceCheck.from_landmarks
    b = check({n: {"L": v} for n, v in before.items()})
    together = check({n: {"L": v - 0.2 + rng.normal(scale=0.05)} for n, v in before.items()})
    one = check({n: {"L": v - (4.0 if n == "i3" else 0.0) + rng.normal(scale=0.05)} for n, v in before.items()})
    small = check({n: {"L": v * 0.995} for n, v in before.items()})
    assert round_helps(together, b) and not round_helps(one, b) and not round_helps(small, b)
    assert round_helps(check({}), b)  # nothing to judge by


def test_the_population_medoid_is_the_instance_nearest_the_mean_shape_whatever_its_frame():
    """The medoid is found from the coatings put onto the template instance's by their
    correspondence: an instance stored turned (its moments frame flipped) is still compared
    by shape, and only the candidates (instances with every landmark) can be chosen."""
    from ssm_addon.coating.coating import CoatingResult, FitFigures
    from ssm_addon.instances.importing import InstanceSpec
    from ssm_addon.pipeline.model_method import population_medoid
    from ssm_addon.pipeline.study import Study

    rng = np.random.default_rng(3)
    base = rng.normal(size=(200, 3)) * [20.0, 10.0, 5.0]
    scale = {"a": 1.30, "b": 1.12, "c": 0.98, "d": 0.80, "e": 1.02}
    points = {n: base * s + rng.normal(scale=0.05, size=base.shape) for n, s in scale.items()}
    points["e"] = points["e"] * np.array([-1.0, -1.0, 1.0])  # turned 180° about z in its object frame
    fit = FitFigures(0.0, 0.0, 0, 0, 1)
    study = Study(instances=tuple(InstanceSpec(name=n) for n in scale), template_instance="a")
    study.coatings = {n: CoatingResult(points_object=p, warped_points_object=p, fit=fit, name=n) for n, p in points.items()}
    medoid, distance = population_medoid(study, list(scale))
    assert medoid == "e" and distance["e"] < distance["c"] < distance["b"]  # mean scale 1.044: e (turned), then c
    assert population_medoid(study, ["a", "b", "d"])[0] == "b"


def test_a_large_study_checks_a_bounded_evenly_spaced_part():
    """Above the bounds the self-check checks evenly spaced instances, each against a model of
    evenly spaced others (its cost stops growing with the study); its jobs are made when the
    executor takes them, so a 1,000-instance study does not hold 1,000 copies of the others
    (15 GB). Below the bounds it is the whole check."""
    from ssm_addon.correspondence.rounds import evenly_spaced

    v, f, _axes, points, locations, given = _population(n=12)
    fit = FitParams(noise_mm=0.5, tolerance_mm=0.001)
    bounded = check_correspondence(points, f, locations, given, fit=fit, max_instances=4, max_others=5)
    assert list(bounded.instance_mm) == ["e0", "e4", "e7", "e11"] == evenly_spaced(list(points), 4)
    whole = check_correspondence(points, f, locations, given, fit=fit)
    assert set(whole.instance_mm) == set(points)
    # the linear population: a model of 5 others still carries the landmarks
    assert bounded.study_mm < 0.5 and whole.study_mm < 0.5
    # a model of 2 others cannot hold the 3 axes' variation: the bound is used, not ignored
    two = check_correspondence(points, f, locations, given, fit=fit, max_instances=4, max_others=2)
    assert list(two.instance_mm) == list(bounded.instance_mm) and two.study_mm > bounded.study_mm


def test_a_surface_whose_axes_came_out_swapped_is_fitted_from_that_rotation():
    # a surface alone in a frame whose second and third axes are swapped against the model's (a
    # quarter turn about the first: two moments nearly equal make object frames do this) is fitted
    # from the 24 rotations of the principal axes, not only the axes turned end for end
    from ssm_addon.correspondence.rounds import landmark_transfer

    v, f, axes, points, locations, _given = _population(n=8)
    others = np.stack([points[f"e{k}"] for k in range(8)])
    quarter = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    surface = (v * [40.0, 25.0, 15.0]) @ quarter.T + [3.0, -2.0, 1.0]  # axes 40, 15, 25 mm as it lies
    result, _predicted, _d = landmark_transfer(others, f, surface, locations, {}, fit=FitParams(), surface_faces=f)
    assert result.mean_distance_mm < 0.2 and result.mahalanobis < 3.0, (result.mean_distance_mm, result.mahalanobis)
    turned = quarter.T @ result.pose.rotation  # the fit's turn after the quarter turn: a symmetry of the ellipsoid
    assert np.allclose(np.abs(turned), np.eye(3), atol=0.05), turned
