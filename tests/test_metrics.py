"""Model quality metrics: compactness, generalization, specificity, the report and fig. 9 plots."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from conftest import FACES, names, random_rotation, smooth_fields, sphere_points, synthetic_population

from ssm_addon.base.errors import InputError
from ssm_addon.model.files import load_npz, load_statismo
from ssm_addon.model.metrics import (
    ModelMetrics,
    aggregate_fit,
    compactness,
    evaluate,
    generalization,
    metric_bars,
    specificity,
    write_plots,
)
from ssm_addon.model.pca import build_model
from ssm_addon.pipeline.outputs import write_outputs

NOISE_MM = 0.02
# mean length of 3D isotropic Gaussian noise: 2 sqrt(2/pi) sigma
NOISE_POINT_ERROR_MM = NOISE_MM * 2 * np.sqrt(2 / np.pi)


@pytest.fixture(scope="module")
def population():
    shapes, mean, fields, lam = synthetic_population(n=40, noise_mm=NOISE_MM)
    return shapes, build_model(shapes, FACES, names(40))


def test_compactness_reaches_99_percent_at_three_modes(population):
    _, model = population
    c = compactness(model)
    assert c["cumulative"][2] >= 0.99
    assert c["cumulative"][1] < 0.99
    assert c["modes_for"]["0.99"] == 3
    assert c["cumulative"][-1] == pytest.approx(1.0)
    assert np.all(np.diff(c["cumulative"]) >= 0)


def test_compactness_standard_error_matches_the_spread_over_populations():
    """Davies' standard error of C(k) against its Monte Carlo truth: 300 populations of 40
    Gaussian shapes with variances 25, 9, 4 mm² along known fields. For k = 1 the spread of
    λ̂₁ over the populations is sqrt(2/n) λ₁ (the first entry); for k = 3 the spread of the
    sum is at most Davies' sum (an upper bound, the λ̂ being nearly independent)."""

    rng = np.random.default_rng(11)
    base = sphere_points(60)
    fields = smooth_fields(base)
    lam = np.array([25.0, 9.0, 4.0])
    n = 40
    got, reported = [], []
    for _ in range(300):
        b = rng.standard_normal((n, 3)) * np.sqrt(lam)
        shapes = base[None] + np.tensordot(b, fields, axes=1)
        model = build_model(shapes, FACES, names(n), alignment="none")
        c = compactness(model)
        total = model.total_variance
        got.append(np.cumsum(c["variance_mm2"][:3]) / lam.sum())  # the share of the true total
        reported.append(np.array(c["cumulative_std"][:3]) * total / lam.sum())
    spread, davies = np.std(got, axis=0, ddof=1), np.mean(reported, axis=0)
    print(f"\nC(1..3) spread {np.round(spread, 4)}, Davies {np.round(davies, 4)}")
    assert davies[0] == pytest.approx(spread[0], rel=0.15), (davies, spread)
    assert spread[2] <= davies[2] * 1.05 and spread[2] > 0.5 * davies[2], (davies, spread)


def test_generalization_decreases_to_noise_level_at_three_modes(population):
    shapes, _ = population
    g = generalization(shapes, ks=range(1, 9))
    assert g["method"] == "leave-one-out" and g["folds"] == 40
    mean = np.array(g["mean_mm"])
    assert mean[0] > mean[1] > mean[2]
    assert np.all(np.diff(mean) <= 1e-12)
    assert 0.8 * NOISE_POINT_ERROR_MM < mean[2] < 1.3 * NOISE_POINT_ERROR_MM
    # beyond the three generating modes only noise is left to fit
    assert mean[7] > 0.9 * mean[2]
    assert np.array(g["per_instance_mm"]).shape == (40, 8)
    np.testing.assert_allclose(g["std_mm"], np.array(g["per_instance_mm"]).std(axis=0))


def test_gram_leave_one_out_equals_explicit_rebuilds(population):
    shapes, _ = population
    ks = [1, 2, 5]
    g = generalization(shapes[:12], ks=ks)
    for i in (0, 7):
        rest = np.delete(shapes[:12], i, axis=0)
        model = build_model(rest, FACES, names(11))
        for j, k in enumerate(ks):
            err = np.linalg.norm(model.reconstruct(shapes[i], k) - shapes[i], axis=1).mean()
            assert g["per_instance_mm"][i][j] == pytest.approx(err, rel=1e-9)


def test_generalization_switches_to_k_fold_beyond_max_loo(population):
    shapes, _ = population
    g = generalization(shapes, ks=[1, 3], max_loo=20, seed=4)
    assert g["folds"] == 10 and "10-fold" in g["method"]
    loo = generalization(shapes, ks=[1, 3])
    np.testing.assert_allclose(g["mean_mm"], loo["mean_mm"], rtol=0.1)
    with pytest.raises(InputError, match="folds"):
        generalization(shapes, folds=1)


def test_generalization_with_procrustes_ignores_rigid_motion(population):
    shapes, _ = population
    rng = np.random.default_rng(8)
    moved = np.stack([s @ random_rotation(rng).T + rng.normal(scale=20, size=3) for s in shapes[:15]])
    g_moved = generalization(moved, ks=[1, 3], alignment="rigid")
    g_ref = generalization(shapes[:15], ks=[1, 3], alignment="rigid")
    np.testing.assert_allclose(g_moved["mean_mm"], g_ref["mean_mm"], rtol=1e-5)
    plain = generalization(moved, ks=[3])
    assert plain["mean_mm"][0] > 10 * g_moved["mean_mm"][1]


def test_specificity_increases_then_flattens_after_three_modes(population):
    _, model = population
    s = specificity(model, ks=range(1, 9), n_samples=300, seed=1)
    mean = np.array(s["mean_mm"])
    assert mean[0] < mean[1] < mean[2]
    assert abs(mean[7] - mean[2]) < 0.05 * mean[2]
    assert np.all(np.array(s["std_mm"]) > 0)
    again = specificity(model, ks=range(1, 9), n_samples=300, seed=1)
    assert again["mean_mm"] == s["mean_mm"]


def test_specificity_equals_its_integral_on_a_one_mode_population():
    """Three training shapes at -d, 0 and +d along one field f: the mode's SD is
    σ = d sqrt(2/3) (S = P Pᵀ / n, eq. 5), so they sit at z_i = 0, ±d/σ. A sample at z lies
    |z - z_i| σ mean|f_p| from training shape i, so specificity at one mode is
    σ mean|f_p| E[min_i |z - z_i|], the expectation over z ~ N(0, 1) integrated
    numerically. The Monte Carlo estimate lies within 4 of its standard errors."""
    from scipy import integrate, stats

    base = sphere_points(50)
    f = smooth_fields(base)[1]  # unit as a 3N vector
    d = 3.0
    shapes = np.stack([base - d * f, base, base + d * f])
    model = build_model(shapes, FACES, names(3), alignment="none")
    sigma = d * np.sqrt(2 / 3)
    assert model.standard_deviations[0] == pytest.approx(sigma, rel=1e-12)
    s = specificity(model, ks=[1], n_samples=4000, seed=3)
    zi = d / sigma
    expected_z = integrate.quad(lambda z: min(abs(z + zi), abs(z), abs(z - zi)) * stats.norm.pdf(z), -12, 12,
                                points=[-zi, -zi / 2, 0.0, zi / 2, zi])[0]
    expected = sigma * np.linalg.norm(f, axis=1).mean() * expected_z
    se = s["std_mm"][0] / np.sqrt(4000)
    assert abs(s["mean_mm"][0] - expected) < 4 * se, (s["mean_mm"][0], expected, se)


def test_aggregate_fit_summarises_numeric_figures():
    per = {"a": {"rms_mm": 1.0, "folds": 2, "note": "x"}, "b": json.dumps({"rms_mm": 3.0, "folds": 0})}
    agg = aggregate_fit(per)
    assert agg["rms_mm"] == {"mean": 2.0, "std": 1.0, "min": 1.0, "max": 3.0, "n": 2}
    assert "note" not in agg


def test_metric_bars_never_reach_below_the_smallest_distance_measured(population):
    """metrics.png's bars: one SD above the mean; below, one SD or down to the smallest distance the
    metric measured (never below 0 mm), for specificity (its own minimum) and generalization (its
    left-out instances')."""
    _, model = population
    mets = evaluate(model, ks=[1, 2, 3], n_samples=200)
    for m in (mets.generalization, mets.specificity):
        mean, bars = metric_bars(m)
        smallest = np.asarray(m["min_mm"] if "min_mm" in m else np.min(m["per_instance_mm"], axis=0))
        assert np.all(mean - bars[0] >= smallest - 1e-12) and np.all(bars >= 0)
        np.testing.assert_allclose(bars[1], m["std_mm"])
    mean, bars = metric_bars({"mean_mm": [0.5, 2.0], "std_mm": [1.0, 1.0]})  # no record of the smallest: 0
    np.testing.assert_allclose(bars, [[0.5, 1.0], [1.0, 1.0]])


def test_plots(tmp_path, population):
    _, model = population
    metrics = evaluate(model, ks=[1, 2, 3, 4], n_samples=100)
    assert metrics.to_dict()["generalization"]["k"] == [1, 2, 3, 4]
    files = write_plots(model, tmp_path, metrics)["files"]
    assert [os.path.basename(f) for f in files] == [
        "spectrum.png",
        "cumulative_variance.png",
        "variability.png",
        "metrics.png",
    ]
    for png in files:
        assert open(png, "rb").read(8) == b"\x89PNG\r\n\x1a\n"


def test_write_outputs_writes_every_file(tmp_path, population):
    _, model = population
    out = write_outputs(model, tmp_path / "out", metrics=ModelMetrics(compactness=compactness(model)), plots=False)
    assert load_npz(out["npz"]).n_modes == model.n_modes
    assert load_statismo(out["statismo"]).n_modes == model.n_modes
    assert out["plots"] == []
    # report.json lists the files where they are, relative to the output folder
    assert tmp_path / "out" / json.loads(open(out["report"]).read())["files"]["npz"] == Path(out["npz"])


def test_plots_are_skipped_with_a_clear_message_without_matplotlib(tmp_path, population, monkeypatch):
    import sys

    _, model = population
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)  # import fails as if not installed
    info = write_plots(model, tmp_path)
    assert info["files"] == [] and "matplotlib" in info["skipped"]
    out = write_outputs(model, tmp_path / "o")
    assert out["plots"] == [] and "matplotlib" in out["plots_skipped"]
    assert os.path.exists(out["report"]) and os.path.exists(out["npz"])


def test_large_study_generalization_agrees_with_the_gram_route():
    """k-fold generalization of large studies (randomized, no n x n Gram matrix) equals the exact route."""
    from ssm_addon.model import metrics as M

    rng = np.random.default_rng(8)
    n, npts = 300, 200
    basis = np.linalg.qr(rng.standard_normal((3 * npts, 5)))[0].T
    x = (rng.standard_normal((n, 5)) * [10.0, 7.0, 5.0, 3.0, 2.0]) @ basis + 0.1 * rng.standard_normal((n, 3 * npts))
    x = x.reshape(n, npts, 3)
    exact = M.generalization(x, ks=[1, 2, 3, 4, 5], folds=10, solver="gram")
    randomized = M.generalization(x, ks=[1, 2, 3, 4, 5], folds=10, solver="randomized")
    assert "randomized" in randomized["method"] and "randomized" not in exact["method"]
    fast = np.array(randomized["per_instance_mm"])
    # the same errors to float32 precision of the residuals (one power iteration, float32 residual vectors)
    np.testing.assert_allclose(fast, np.array(exact["per_instance_mm"]), rtol=2e-4)
    assert abs(fast.mean() / np.mean(exact["per_instance_mm"]) - 1) < 1e-5


def test_view_orientation_names_where_the_axes_point_and_the_scale_bar_is_round():
    from ssm_addon.model.metrics import AXIS_NAMES, scale_bar_mm, view_orientation

    assert view_orientation(np.eye(3)) == "R → · A ↑"
    coronal = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])  # seen from the front
    assert view_orientation(coronal) == "L → · S ↑"
    assert view_orientation(coronal, AXIS_NAMES) == "−x → · +z ↑"
    assert scale_bar_mm(0.5, 320) == 50.0 and scale_bar_mm(0.1, 320) == 10.0


def test_patient_planes_are_named_only_for_patient_oriented_frames(population):
    """modes.png's columns say axial, sagittal, coronal (and R, A, S) only where every object frame
    paired its axes with the patient axes; meshes whose convention nobody stated get 'view along z'."""
    import dataclasses

    from ssm_addon.model.metrics import AXIS_LETTERS, AXIS_NAMES, axis_letters, view_names

    _, model = population
    patient = dataclasses.replace(model, params={**model.params, "frame_methods": ["patient"]})
    mixed = dataclasses.replace(model, params={**model.params, "frame_methods": ["moments", "patient"]})
    views = ("axial", "sagittal", "coronal")
    assert view_names(patient, views) == list(views) and axis_letters(patient) is AXIS_LETTERS
    assert view_names(mixed, views) == ["view along z", "view along x", "view along y"]
    assert axis_letters(mixed) is AXIS_NAMES


def _saved_figures(monkeypatch) -> list:
    """Every matplotlib figure saved from here on (the figure objects, for their geometry)."""
    from matplotlib.figure import Figure

    saved, real = [], Figure.savefig

    def keep(self, *args, **kwargs):
        saved.append(self)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", keep)
    return saved


def test_legends_stand_clear_of_the_curves(tmp_path, population, monkeypatch):
    """metrics.png and variability.png: every legend lies outside its axes (it covers no curve), and
    the error bars are said to be ± SD over what they are over."""
    _shapes, model = population
    metrics = evaluate(model, ks=range(1, 6), n_samples=50)
    saved = _saved_figures(monkeypatch)
    write_plots(model, tmp_path, metrics)
    legends = 0
    for fig in saved:
        fig.canvas.draw()
        for ax in fig.axes:
            leg = ax.get_legend()
            if leg is None:
                continue
            legends += 1
            box, area = leg.get_window_extent(), ax.get_window_extent()
            assert box.y1 <= area.y0, (fig, [t.get_text() for t in leg.get_texts()])
    assert legends >= 3  # cumulative_variance.png, variability.png, metrics.png
    texts = [t.get_text() for fig in saved for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts()]
    assert "generalization: mean ± SD over the left-out instances" in texts
    assert "specificity: mean ± SD over the random model shapes" in texts


@pytest.mark.parametrize("alignment", ["none", "rigid"])
def test_folds_with_more_shapes_than_coordinates_use_the_covariance_and_equal_the_gram_route(alignment):
    # 150 shapes of 10 points, 10 folds: 135 training shapes against 30 coordinates
    shapes, _mean, _fields, _var = synthetic_population(n=150, n_points=10, variances=(25.0, 9.0, 4.0),
                                                         noise_mm=0.05, seed=5)
    auto = generalization(shapes, ks=[1, 2, 3, 5, 8], folds=10, alignment=alignment)
    gram = generalization(shapes, ks=[1, 2, 3, 5, 8], folds=10, alignment=alignment, solver="gram")
    assert "3N × 3N" in auto["method"] and "3N × 3N" not in gram["method"]
    np.testing.assert_allclose(auto["per_instance_mm"], gram["per_instance_mm"], rtol=1e-7, atol=1e-10)
    assert auto["mean_mm"][2] < 0.2 < auto["mean_mm"][0]  # three modes hold the population
