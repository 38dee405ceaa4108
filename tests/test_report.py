"""report.html: one self-contained page, checked in a real headless browser."""

from __future__ import annotations

import json
import re
import shutil
import subprocess

import numpy as np
import pytest

from ssm_addon.cli import demo
from ssm_addon.pipeline import report as report_module
from ssm_addon.pipeline.project import read_project
from ssm_addon.pipeline.project_build import build

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    folder = tmp_path_factory.mktemp("report")
    path = demo.make_demo_population(folder / "population", n=5, seed=8)
    path.write_text(path.read_text().replace("spacing = 1.0", "spacing = 1.0\nr_min_mm = 4.0\nr_max_mm = 8.0")
                    .replace("[model]", "[model]\nspecificity_samples = 50"))
    # one instance with a landmark clicked 25 mm off: its gates fail, the others' do not
    csv = folder / "population" / "demo_02.csv"
    rows = csv.read_text().splitlines()
    name, x, y, z = rows[1].split(",")
    rows[1] = ",".join([name, repr(float(x) + 25.0), y, z])
    csv.write_text("\n".join(rows) + "\n")
    result = build(read_project(path), folder / "out", log=None)
    return folder / "out", result


@pytest.mark.slow
def test_report_is_one_self_contained_file(built):
    out, result = built
    page = (out / "report.html").read_text()
    assert result.files["html"].endswith("report.html")
    srcs = re.findall(r'src="([^"]*)"', page) + re.findall(r'href="([^"]*)"', page)
    assert srcs and all(s.startswith("data:image/png;base64,") for s in srcs)  # nothing to fetch
    assert "http://" not in page and "https://" not in page
    names = list(result.study.names)
    for name in names:  # a row, with its picture, per instance
        assert f"<b>{name}</b>" in page and f'alt="{name}"' in page
    flagged = {f.instance for f in result.study.findings if f.instance}
    assert flagged == {"demo_02"}, flagged  # the instance with the landmark 25 mm off, and only it
    assert {f.gate for f in result.study.findings} >= {"landmark_transfer"}
    for f in result.study.findings:
        assert f.message.split(" (")[0][:40] in page.replace("&#x27;", "'")
    assert page.count('<tr class="warn">') == len(flagged)
    for fig in ("paper fig. 9", "Compactness, generalization and specificity by number of modes"):
        assert fig in page
    # σ = √λ is the whole shape's spread; the RMS per point √(λ/N) stands beside it
    lam, n_points = result.study.model.variances[0], result.study.model.n_points
    row = re.search(r"<tr class=\"\"><td>1</td><td>[^<]*</td><td>([^<]*)</td><td>([^<]*)</td>", page)
    assert float(row.group(1).replace(",", "")) == pytest.approx(np.sqrt(lam), abs=1e-3)
    assert float(row.group(2).replace(",", "")) == pytest.approx(np.sqrt(lam / n_points), abs=1e-3)
    assert "RMS per point at 1σ (mm)" in page and "over all" in page
    # the demo's [analysis]: its section with the tests of both terms and the map
    analysis = json.loads((out / "analysis" / "analysis.json").read_text())
    assert "Analysis: groups and covariates" in page and "Group difference along the surface normal" in page
    for term in ("group", "age"):
        assert f"<b>{term}</b>" in page and term in analysis["tests"]
    assert result.report["analysis"]["group_test"]["p_value"] == analysis["group_test"]["p_value"]


@pytest.mark.slow
def test_a_large_study_pictures_its_flagged_instances_and_a_spread_of_the_rest(built, tmp_path, monkeypatch):
    out, result = built
    monkeypatch.setattr(report_module, "MAX_THUMBNAILS", 3)
    shutil.copytree(out, tmp_path / "out")
    page = report_module.write_report_html(tmp_path / "out", result.study.model).read_text()
    pictured = re.findall(r'<img[^>]* alt="(demo_\d\d)"', page)
    assert pictured == ["demo_00", "demo_02", "demo_04"]  # the flagged demo_02, the others evenly spaced
    assert "Pictures of 3 of the 5 instances" in page
    for name in result.study.names:  # every instance keeps its row
        assert f"<b>{name}</b>" in page


def _chromium(*args, timeout=120):
    return subprocess.run([CHROMIUM, *CHROMIUM_FLAGS, *args], capture_output=True, text=True, timeout=timeout)


@pytest.mark.skipif(CHROMIUM is None, reason="Chromium not installed (.ci/run installs Debian's chromium)")
def test_report_opens_in_a_headless_browser_without_errors(built, tmp_path):
    out, result = built
    url = (out / "report.html").as_uri()
    dom = _chromium(f"--user-data-dir={tmp_path / 'profile'}", "--enable-logging=stderr", "--v=0",
                    "--virtual-time-budget=5000", "--dump-dom", url)
    assert dom.returncode == 0, dom.stderr[-2000:]
    console = [ln for ln in dom.stderr.splitlines() if ":CONSOLE" in ln]
    assert console == [], console  # the page logs nothing, and raises nothing
    total = int(re.search(r'data-images="(\d+)"', dom.stdout).group(1))
    decoded = int(re.search(r'data-images-decoded="(\d+)"', dom.stdout).group(1))
    # every picture decodes: the instances', fig. 9, fig. 10 (drawn without Blender), metrics and (the demo
    # has [analysis]) the analysis map and scores; the correspondence optimisation is off by default
    assert not (out / "optimisation.png").exists()
    assert total == len(result.study.names) + 3 + 2 and decoded == total
    # at 1,300 px every table fits the window, the Instances table with its warnings included
    narrow = _chromium(f"--user-data-dir={tmp_path / 'profile3'}", "--window-size=1300,1600",
                       "--virtual-time-budget=5000", "--dump-dom", url)
    assert re.search(r'data-tables-past-the-window="0"', narrow.stdout), narrow.stdout[-500:]
    assert "⚠ demo_02: [landmark_transfer]" in narrow.stdout or "&#9888; demo_02" in narrow.stdout or \
        "\u26a0 demo_02" in narrow.stdout
    shot = tmp_path / "report.png"
    cap = _chromium(f"--user-data-dir={tmp_path / 'profile2'}", "--window-size=1200,1600",
                    f"--screenshot={shot}", url)
    assert cap.returncode == 0 and shot.is_file(), cap.stderr[-2000:]
    from PIL import Image

    img = np.asarray(Image.open(shot).convert("RGB")).astype(float) / 255
    assert img.shape == (1600, 1200, 3)
    assert img.std() > 0.05  # drawn, not blank
    warn = np.all(np.abs(img - np.array([0xFF, 0xF1, 0xE6]) / 255) < 0.02, axis=2)
    assert warn.sum() > 2000  # the warnings box is on the first screen


def _small_model():
    from ssm_addon.model.pca import build_model

    rng = np.random.default_rng(4)
    base = rng.normal(size=(12, 3)) * 10
    shapes = base + rng.normal(scale=0.5, size=(6, 12, 3))
    faces = np.array([[0, 1, 2], [0, 2, 3], [1, 3, 2], [0, 3, 1]])
    return build_model(shapes, faces, [f"s{i}" for i in range(6)])


def test_a_report_without_its_quality_section_never_says_passed(tmp_path):
    """A section a writer was not given is absent with its reason: the page says the gates are
    not known, and a report without the section cannot be made at all (the type requires it)."""
    from ssm_addon.pipeline.report import Absent, Report, model_report, write_html_report

    model = _small_model()
    report = model_report(model, why="a model opened from a file")
    assert isinstance(report.quality, Absent) and report.to_dict()["quality"] == {"absent": "a model opened from a file"}
    page = write_html_report(tmp_path / "a.html", report).read_text()
    assert "Every quality gate passed" not in page
    assert "Quality gates: not known" in page and "a model opened from a file" in page
    # a report.json from a writer that left the section out reads back as absent, not as passed
    doc = report.to_dict()
    del doc["quality"]
    again = Report.from_dict(doc)
    assert again.absent("quality") and "Every quality gate passed" not in write_html_report(
        tmp_path / "b.html", doc).read_text()
    with pytest.raises(TypeError, match="quality"):  # no writer can drop a section silently
        Report(project="p", parameters={}, model={}, template={}, correspondence={}, metrics={}, instances={},
               timings_s={})
    # with the section and no findings, it does say so
    passed = report.replace(quality={"parameters": {}, "findings": [], "outlier_scores": {}})
    assert "Every quality gate passed" in write_html_report(tmp_path / "c.html", passed).read_text()


def test_the_report_page_says_how_the_templates_density_was_set(built, tmp_path):
    """report.html's Model section names the template's instance, its points and how its density
    was set: the tolerance and the distance it reached, or eq. 1's radii."""
    from ssm_addon.pipeline.report import Report, write_html_report

    out, result = built  # the fixture's project states eq. 1's radii
    page = (out / "report.html").read_text()
    tpl = json.loads((out / "report.json").read_text())["template"]
    assert "max_distance_mm" not in tpl
    assert f"Template: {tpl['points']:,} points from <b>{tpl['instance']}</b>, its density from the radii of eq. 1" in page
    doc = json.loads((out / "report.json").read_text())
    doc["template"].update(max_distance_mm=1.0, largest_distance_mm=0.987, mean_distance_mm=0.41, tolerance_rounds=1)
    page = write_html_report(tmp_path / "t.html", Report.from_dict(doc)).read_text()
    assert "its triangles within 0.99 mm of the instance's surface (mean 0.41 mm; tolerance 1.00 mm" in page
    # and the other way: the instance's own surface from the template's triangles (built, not made up)
    back = tpl["surface_largest_distance_mm"]
    assert 0 < back < 10 and f"the instance's surface within {back:.2f} mm of its triangles" in page
