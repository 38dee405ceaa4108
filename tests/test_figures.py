"""The paper's fig. 10 without Blender: the rasterizer's exact pixels, and the picture of a build."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import icosphere

from ssm_addon.cli.command import main
from ssm_addon.model.figures import FIGURE_COLOURS, rasterize_meshes, render_modes_figure
from ssm_addon.model.pca import build_model


def test_a_square_covers_exactly_its_pixel_centres():
    """Two triangles spanning x, y in [2, 6] cover the 16 pixels whose centres lie inside, no more;
    facing the viewer they are shaded at full light (0.35 + 0.65 · 1)."""
    pts = np.array([[2, 2, 0], [6, 2, 0], [6, 6, 0], [2, 6, 0]], float)
    img = rasterize_meshes([(pts, [[0, 1, 2], [0, 2, 3]], (1.0, 0.0, 0.0))], (10, 10), outline=None)
    expected = np.zeros((10, 10), bool)
    expected[2:6, 2:6] = True  # rows are y (pixels down), columns x
    assert np.array_equal((img[..., 0] == 1.0) & (img[..., 1] == 0.0), expected)
    assert np.all(img[~expected] == 1.0)  # the background


def test_the_nearer_mesh_wins_and_ties_go_to_the_first():
    square = np.array([[0, 0, 0], [8, 0, 0], [8, 8, 0], [0, 8, 0]], float)
    faces = [[0, 1, 2], [0, 2, 3]]
    far, near = square + [0, 0, -1.0], square + [0, 0, 1.0]
    img = rasterize_meshes([(far, faces, (0.0, 0.0, 1.0)), (near, faces, (1.0, 0.0, 0.0))], (8, 8), outline=None)
    assert np.all(img[..., 0] == 1.0) and np.all(img[..., 2] == 0.0)  # red (nearer) everywhere
    tie = rasterize_meshes([(square, faces, (0.0, 0.0, 1.0)), (square, faces, (1.0, 0.0, 0.0))], (8, 8),
                           outline=None)
    assert np.all(tie[..., 2] == 1.0) and np.all(tie[..., 0] == 0.0)  # the first mesh


def test_a_sphere_is_shaded_by_its_normals():
    """An icosphere of radius 40 px at the centre: its disc of pixels (area within 2 %
    of π 40²), bright in the middle (normal towards the viewer), dark at the rim."""
    v, f = icosphere(40.0, 4)
    img = rasterize_meshes([(v + [50, 50, 0], f, (1.0, 1.0, 1.0))], (100, 100), background=(0.0, 0.0, 0.0),
                           outline=None)
    lit = img[..., 0] > 0
    assert abs(lit.sum() - np.pi * 40**2) < 0.02 * np.pi * 40**2
    assert img[50, 50, 0] > 0.99 and 0.35 <= img[50, 88, 0] < 0.7


@pytest.fixture(scope="module")
def ellipsoid_model():
    """Ellipsoids (30, 20, 12 mm) moved along x by 6 mm SD (mode 1: -2σ reaches further on one side,
    +2σ on the other) and scaled in z by 5 % SD."""
    v, f = icosphere(1.0, 3)
    rng = np.random.default_rng(0)
    shapes = [v * [30.0, 20.0, 12.0 * (1 + 0.05 * rng.standard_normal())] + [6.0 * rng.standard_normal(), 0, 0]
              for _ in range(8)]
    return build_model(np.stack(shapes), f, [f"e{i}" for i in range(8)], alignment="none")


def test_the_figure_has_grey_mean_blue_and_red_modes_and_a_scale(ellipsoid_model, tmp_path):
    from PIL import Image

    path = render_modes_figure(ellipsoid_model, tmp_path / "modes.png", n_modes=2, cell_px=120)
    img = np.asarray(Image.open(path).convert("RGB"), float) / 255
    h, w, _ = img.shape
    assert w > 3 * 120 and h > 3 * 120  # three rows of three cells, with their labels

    # hue, whatever the shading: blue where -2σ reaches further, red where +2σ does, grey for the mean
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    blue, red = (b > r + 0.3) & (b > g + 0.2), (r > b + 0.3) & (r > g + 0.3)
    grey = (np.abs(r - g) < 0.05) & (np.abs(g - b) < 0.08) & (r > 0.3) & (r < 0.85)
    assert FIGURE_COLOURS["minus"][2] > FIGURE_COLOURS["minus"][0] and FIGURE_COLOURS["plus"][0] > 0.9
    assert blue.mean() > 0.005 and red.mean() > 0.005 and grey.mean() > 0.005
    rows = np.array_split(np.arange(h), 3)  # roughly the three rows (the title and labels aside)
    assert red[rows[0]].sum() < 0.05 * red.sum()  # the mean row holds no mode colours
    grid = np.asarray(Image.open(path).convert("L"))
    assert (grid < 40).any()  # outlines and the scale bar


def test_a_headless_build_without_blender_writes_fig_10(tmp_path, capsys):
    from ssm_addon.cli import demo

    project = demo.make_demo_population(tmp_path / "pop", n=6, seed=1)
    assert main(["build", str(project), "--out", str(tmp_path / "out"), "--no-blend"]) == 0
    said = capsys.readouterr().out
    assert said.count("picture: modes.png (mean and ±2σ of the first modes, axial / sagittal / coronal; drawn "
                      "without Blender)") == 1
    assert (tmp_path / "out" / "modes.png").is_file()
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["files"]["picture"] == "modes.png"
