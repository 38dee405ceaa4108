"""Shape analysis: known group and covariate effects recovered, tests calibrated under the null, bad input named."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from conftest import BUMP_MM, analysis_population, shared_data_dir

from ssm_addon.analysis import (
    analyze,
    attributes_from_tables,
    benjamini_hochberg,
    centroid_size,
    read_attributes,
    term_test,
    write_analysis,
)
from ssm_addon.base.errors import InputError


@pytest.fixture(scope="module")
def known():
    model, attrs, truth = analysis_population()
    result = analyze(model, attrs, group="group", covariates=["age"], permutations=999)
    return model, attrs, truth, result


def test_effects_equal_an_independent_least_squares_solution(known):
    model, _, truth, result = known
    design = np.c_[np.ones(len(truth["age"])), truth["groups"] == "patient", truth["age"] - truth["age"].mean()]
    beta, *_ = np.linalg.lstsq(design, model.instance_points.reshape(len(design), -1), rcond=None)
    assert np.abs(result.effect("group: patient").displacement.ravel() - beta[1]).max() < 1e-8
    assert np.abs(result.effect("age").displacement.ravel() - beta[2]).max() < 1e-8


def test_known_group_displacement_and_age_effect_are_recovered(known):
    _, _, truth, result = known
    # standard error of a group difference: NOISE sqrt(2/15) = 0.11 mm; of the age slope about 0.0027 mm/year
    group = result.effect("group: patient")
    assert np.abs(group.displacement - truth["bump"]).max() < 0.5
    assert np.sqrt(np.mean((group.displacement - truth["bump"]) ** 2)) < 0.15
    # the normal component on the cap is the bump (outward), elsewhere zero
    assert abs(np.median(group.normal[truth["cap"]]) - BUMP_MM) < 0.1
    assert abs(np.median(group.normal[~truth["cap"]])) < 0.05
    age = result.effect("age")
    assert np.abs(age.displacement - truth["age_effect"]).max() < 0.015  # mm per year; the effect reaches 0.04
    assert result.units["age"] == "1 unit of age"
    assert result.group_test.p_value <= 0.002 and result.tests["age"].p_value <= 0.002


def test_affected_points_are_found_at_fdr_5_percent_with_few_outside(known):
    _, _, truth, result = known
    found = result.group_test.p_fdr <= 0.05
    assert found[truth["cap"]].mean() >= 0.95
    assert found[~truth["cap"]].mean() <= 0.02
    # the false discoveries among the found points stay near the FDR level
    assert (found & ~truth["cap"]).sum() / max(found.sum(), 1) <= 0.1


def test_two_group_statistic_is_hotellings_t2():
    model, attrs, truth = analysis_population(n=20, seed=3)
    result = analyze(model, attrs, group="group", permutations=99)
    x = model.instance_points
    a, b = x[truth["groups"] == "control"], x[truth["groups"] == "patient"]
    d = b.mean(0) - a.mean(0)
    s = (np.einsum("inj,ink->njk", a - a.mean(0), a - a.mean(0))
         + np.einsum("inj,ink->njk", b - b.mean(0), b - b.mean(0))) / (len(x) - 2)
    t2 = len(a) * len(b) / len(x) * np.einsum("nj,njk,nk->n", d, np.linalg.inv(s), d)
    np.testing.assert_allclose(result.group_test.hotelling_t2, t2, rtol=1e-8)
    # without covariates the group effect is exactly the difference of the group means
    np.testing.assert_allclose(result.effect("group: patient").displacement, d, atol=1e-10)
    np.testing.assert_allclose(result.group_means["patient"] - result.group_means["control"], d, atol=1e-10)


def test_same_seed_same_p_values_and_three_groups_are_tested_pairwise():
    model, attrs, truth = analysis_population(n=24, seed=4)
    three = {n: {"site": "abc"[i % 3], "age": a} for i, (n, a) in enumerate(zip(attrs.names, truth["age"]))}
    t = attributes_from_tables(three)
    r1 = analyze(model, t, group="site", permutations=199, seed=7)
    r2 = analyze(model, t, group="site", permutations=199, seed=7)
    np.testing.assert_array_equal(r1.group_test.p_point, r2.group_test.p_point)
    assert r1.group_test.df == 2 and set(r1.pairwise) == {"a vs b", "a vs c", "b vs c"}
    assert [e.name for e in r1.effects] == ["site: b", "site: c"]
    assert r1.group_test.p_value > 0.01  # site is unrelated to shape here


def test_a_study_with_more_shapes_than_coordinates_is_tested_through_the_small_scatter(monkeypatch):
    """n > 3N: the global statistics come from the 3N × 3N scatter instead of the n × n Gram
    matrix (no eigenproblem of n × n: 10⁴ shapes took gigabytes); points that no shape moves
    add coordinates and change no statistic, so the same shapes with such points (n < 3N,
    the Gram route) give the same test."""
    solved = []
    eigh = np.linalg.eigh
    monkeypatch.setattr(np.linalg, "eigh", lambda a, *args, **kw: solved.append(a.shape) or eigh(a, *args, **kw))
    rng = np.random.default_rng(5)
    n, npts = 120, 8
    group = (np.arange(n) % 2).astype(float)[:, None]
    age = rng.uniform(20, 80, size=(n, 1))
    x = rng.normal(size=(n, npts, 3)) + 0.4 * group[:, :, None] + 0.02 * age[:, :, None] * np.linspace(0, 1, 3)
    still = np.zeros((n, 40, 3)) + rng.normal(size=(1, 40, 3))  # the same place in every shape
    reduced = np.concatenate([np.ones((n, 1)), age], axis=1)
    small = term_test(x, reduced, group, permutations=199, seed=3, per_point=False)
    assert solved == [(3 * npts, 3 * npts)]
    large = term_test(np.concatenate([x, still], axis=1), reduced, group, permutations=199, seed=3, per_point=False)
    assert 3 * npts < n < 3 * (npts + 40)
    assert (small.p_value, small.p_value_f, small.global_modes) == (large.p_value, large.p_value_f, large.global_modes)
    for key in ("f", "r_squared", "global_pillai"):
        assert getattr(small, key) == pytest.approx(getattr(large, key), rel=1e-9), key
    assert small.p_value < 0.01  # the group moves every point


def test_benjamini_hochberg_matches_the_step_up_rule():
    p = np.array([0.001, 0.008, 0.039, 0.041, 0.042, 0.06, 0.074, 0.205, 0.212, 0.216])
    q = benjamini_hochberg(p)
    m = len(p)
    expect = [min(min(p[j] * m / (j + 1) for j in range(i, m)), 1.0) for i in range(m)]
    np.testing.assert_allclose(q, expect)
    assert (q <= 0.05).sum() == 2


def test_centroid_size_and_size_removed_analysis():
    model, attrs, truth = analysis_population(n=20, seed=5)
    sizes = centroid_size(model.instance_points_world)
    np.testing.assert_allclose(sizes[0], np.sqrt(np.sum((model.instance_points_world[0]
                                                         - model.instance_points_world[0].mean(0)) ** 2)))
    r = analyze(model, attrs, covariates=["centroid_size"], permutations=99)
    assert r.effect("centroid_size").unit == "1 mm"
    # with size removed every shape has the mean centroid size
    r2 = analyze(model, attrs, group="group", permutations=99, size_removed=True)
    m = r2.group_means
    assert r2.size_removed and abs(centroid_size(m["control"]) - centroid_size(m["patient"])) < 0.5


def _knee_femurs(k_points=1500):
    from ssm_addon.formats.meshes import read_mesh

    folder = shared_data_dir() / "knee30"
    files = sorted(folder.glob("*_Femur.ply"))
    if len(files) < 20:
        pytest.skip(f"knee30 femurs not found in {folder} (set SSM_SHARED_DATA to the shared data folder)")
    pts = [read_mesh(p)[0] for p in files]
    faces = read_mesh(files[0])[1]
    keep = np.linspace(0, len(pts[0]) - 1, k_points).astype(int)
    return np.stack(pts)[:, keep], faces, [p.stem for p in files]


@pytest.mark.slow
def test_null_calibration_on_real_femurs():
    """Random group labels on 30 real femurs: the global test's false-positive rate at 0.05 lies in
    its binomial interval, and the per-point FDR map rarely finds anything (its family-wise level)."""
    pts, _, names = _knee_femurs()
    n = len(names)
    rng = np.random.default_rng(11)
    p_global, any_found = [], []
    reduced = np.ones((n, 1))
    for _ in range(200):
        labels = rng.permutation(np.r_[np.zeros(n // 2), np.ones(n - n // 2)])
        t = term_test(pts, reduced, labels[:, None], permutations=199, seed=int(rng.integers(1 << 30)))
        p_global.append(t.p_value)
        any_found.append(bool(np.any(t.p_fdr <= 0.05)))
    p_global = np.array(p_global)
    # 200 tests at alpha 0.05: 10 expected; 99.9 % binomial interval [1, 22]
    assert 1 <= np.sum(p_global <= 0.05) <= 22
    from scipy import stats

    assert stats.kstest(p_global, "uniform").pvalue > 0.001
    assert np.mean(any_found) <= 0.05 + 3 * np.sqrt(0.05 * 0.95 / 200)


# ------------------------------------------------------------------------------- files
def test_files_hold_the_tests_maps_and_meshes(known, tmp_path):
    model, _, truth, result = known
    written = write_analysis(result, tmp_path, model=model)
    doc = json.loads((tmp_path / "analysis.json").read_text())
    assert doc["group_test"]["p_value"] == result.group_test.p_value
    assert doc["group"]["counts"] == {"control": 15, "patient": 15} and doc["group"]["reference"] == "control"
    assert doc["tests"]["age"]["adjusted_for"] == ["group"]
    with np.load(tmp_path / "analysis.npz", allow_pickle=False) as z:
        np.testing.assert_allclose(z["displacement"], result.effect("group: patient").displacement)
        np.testing.assert_allclose(z["p_fdr"], result.group_test.p_fdr)
        assert z["t2"].shape == (len(truth["sphere"]),) and list(z["term_names"]) == ["group", "age"]
    root = ET.parse(tmp_path / "effects" / "group_patient.vtp").getroot()
    piece = root.find("PolyData/Piece")
    assert int(piece.get("NumberOfPoints")) == len(result.mean) and int(piece.get("NumberOfPolys")) == len(model.faces)
    arrays = {a.get("Name"): a for a in piece.iter("DataArray")}
    normal = np.array(arrays["normal_mm"].text.split(), float)
    np.testing.assert_allclose(normal, result.effect("group: patient").normal, rtol=1e-8, atol=1e-9)
    scores = (tmp_path / "analysis_scores.csv").read_text().splitlines()
    assert scores[0].startswith("name,group,age,centroid_size,mode_1_sd") and len(scores) == 31
    assert "analysis_map.png" in written and (tmp_path / "analysis_map.png").stat().st_size > 10_000


def test_the_map_says_where_its_colours_are_clipped(known, tmp_path, monkeypatch):
    """analysis_map.png: the colour bar spans the 99th percentile; where the displacement reaches
    beyond it, the bar's arrows (extend) and its label say so with the extremes."""
    from matplotlib.figure import Figure

    from ssm_addon.analysis.files import analysis_map_picture

    _model, _, _truth, result = known
    saved, real = [], Figure.savefig
    monkeypatch.setattr(Figure, "savefig", lambda self, *a, **k: (saved.append(self), real(self, *a, **k))[1])
    analysis_map_picture(result, tmp_path / "map.png")
    e = result.effects[0]
    lim = float(np.percentile(np.abs(e.normal), 99))
    bar = saved[0].axes[-1]
    label = bar.get_ylabel()
    assert e.normal.max() > lim or e.normal.min() < -lim  # a few points beyond the 99th percentile
    assert "clipped at ±" in label and f"{e.normal.min():.2f} to {e.normal.max():.2f}" in label
    expected = {(True, True): "both", (True, False): "min", (False, True): "max"}[(e.normal.min() < -lim,
                                                                                  e.normal.max() > lim)]
    assert bar._colorbar.extend == expected  # the arrows at the clipped end(s)


# ------------------------------------------------------------------------------- attributes
def test_attribute_csv_reads_names_kinds_and_missing_values(tmp_path):
    p = tmp_path / "subjects.csv"
    p.write_text("Subject;group;age;sex\nL1;lumbar;63;F\nL2;lumbar;NA;M\nT9;thoracic;55,5;\n")
    t = read_attributes(p)
    assert t.names == ("L1", "L2", "T9")
    # a semicolon file's decimal comma: "55,5" is 55.5
    assert t.kinds == {"group": "category", "age": "number", "sex": "category"} and t.column("age")[2] == 55.5
    p.write_text("Subject;group;age;sex\nL1;lumbar;63;F\nL2;lumbar;NA;M\nT9;thoracic;55.5;\n")
    t = read_attributes(p)
    assert t.kinds["age"] == "number" and np.isnan(t.column("age")[1]) and t.values["sex"][2] is None


@pytest.mark.parametrize("text, message", [
    ("", "empty"),
    ("name\nL1\n", "one column"),
    ("name,age,age\nL1,1,2\n", "appears twice in the header"),
    ("name,age\nL1,1\nL1,2\n", "line 3: instance 'L1' appears twice"),
    ("name,age\nL1,1,3\n", "line 2: 3 cells"),
])
def test_bad_attribute_tables_name_the_file_and_line(tmp_path, text, message):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(InputError, match=message) as err:
        read_attributes(p)
    assert str(p) in str(err.value)


def test_bad_analysis_inputs_say_what_is_wrong():
    model, attrs, truth = analysis_population(n=12, seed=6)
    names = attrs.names

    def table(**cols):
        return attributes_from_tables({n: {k: v[i] for k, v in cols.items()} for i, n in enumerate(names)},
                                      source="subjects.csv")

    one = ["a"] * 11 + ["b"]
    with pytest.raises(InputError, match="group 'b' has 1 instance"):
        analyze(model, table(group=one), group="group", permutations=99)
    with pytest.raises(InputError, match="covariate 'age' is constant"):
        analyze(model, table(group=list(truth["groups"]), age=[60] * 12), group="group", covariates=["age"],
                permutations=99)
    ages = [60.0 + i if i < 4 else None for i in range(12)]
    with pytest.raises(InputError, match="'age' is missing for 8 of 12"):
        analyze(model, table(group=list(truth["groups"]), age=ages), group="group", covariates=["age"],
                permutations=99)
    with pytest.raises(InputError, match="no attribute column 'gruop' .*did you mean 'group'"):
        analyze(model, table(group=list(truth["groups"])), group="gruop", permutations=99)
    stranger = attributes_from_tables({"x1": {"group": "a"}, "x2": {"group": "b"}}, source="subjects.csv")
    with pytest.raises(InputError, match="no row names an instance"):
        analyze(model, stranger, group="group", permutations=99)
    many = table(**{f"c{k}": list(np.random.default_rng(k).normal(size=12)) for k in range(11)})
    with pytest.raises(InputError, match="12 instances for a model of 12 columns"):
        analyze(model, many, covariates=[f"c{k}" for k in range(11)], permutations=99)
    from ssm_addon.model.pca import ShapeModel

    bare = ShapeModel(mean=model.mean, faces=model.faces, modes=model.modes, variances=model.variances,
                      instance_names=np.zeros(0, "<U1"), instance_points=np.zeros((0, model.n_points, 3)),
                      instance_points_world=np.zeros((0, model.n_points, 3)), params={"source": "femur.h5"})
    with pytest.raises(InputError, match=r"model \(femur.h5\) holds no training shapes"):
        analyze(bare, table(group=list(truth["groups"])), group="group", permutations=99)
    with pytest.raises(InputError, match="permutations must be >= 99"):
        analyze(model, table(group=list(truth["groups"])), group="group", permutations=10)
    # rows naming no instance are a warning; instances without values are left out and said
    extra = attributes_from_tables({**{n: {"group": g} for n, g in zip(names[:11], truth["groups"])},
                                    "ghost": {"group": "control"}}, source="subjects.csv")
    r = analyze(model, extra, group="group", permutations=99)
    assert len(r.names) == 11 and r.excluded == {names[11]: "missing group"}
    assert any("'ghost'" in w for w in r.warnings) and any("left out" in w for w in r.warnings)


# ------------------------------------------------------------------------------- command line
def test_ssm_analyze_writes_the_files_and_refuses_bad_input(tmp_path, capsys):
    from ssm_addon.analysis import write_attributes
    from ssm_addon.cli.command import main
    from ssm_addon.model.files import save_npz

    model, attrs, _ = analysis_population(n=20, seed=8)
    build = tmp_path / "build"
    build.mkdir()
    save_npz(model, build / "model.npz")
    out = tmp_path / "analysis"
    assert main(["analyze", str(build), "--group", "group", "--out", str(out)]) == 2
    assert "no attributes.csv" in capsys.readouterr().err and not out.exists()
    write_attributes(attrs, build / "attributes.csv")
    assert main(["analyze", str(build), "--group", "group", "--covariate", "age", "--permutations", "199",
                 "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "analysis of 20 instances (control 10, patient 10)" in said and "group: p " in said
    doc = json.loads((out / "analysis.json").read_text())
    direct = analyze(model, attrs, group="group", covariates=["age"], permutations=199)
    assert doc["group_test"]["p_value"] == direct.group_test.p_value  # one computation, two routes
    assert {"analysis.npz", "analysis_scores.csv", "analysis_map.png"} <= {p.name for p in out.iterdir()}
    for args, message in ((["--group", "gruop"], "no attribute column 'gruop'"),
                          (["--group", "group", "--permutations", "5"], "permutations must be an integer >= 99"),
                          ([], "give --group COLUMN, --covariate COLUMN, or both")):
        target = tmp_path / f"bad{len(args)}"
        assert main(["analyze", str(build), *args, "--out", str(target)]) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err and not target.exists()
    # the build folder holds the inputs: never written into
    assert main(["analyze", str(build), "--group", "group", "--out", str(build)]) == 2
    assert sorted(p.name for p in build.iterdir()) == ["attributes.csv", "model.npz"]
