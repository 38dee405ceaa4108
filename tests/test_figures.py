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


def _standing_population(turn: np.ndarray, *, frame_methods):
    """Ten cigars 60 mm long along the model's x, whose files held them turned by ``turn``
    (and a few degrees more, a different few for each) and moved."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    points, faces = icosphere(1.0, 2)
    base = np.asarray(points, float) * [30.0, 8.0, 5.0]  # a cigar along the model's x
    shapes = np.stack([base * (1 + rng.normal(0, 0.03, 3)) for _ in range(10)])
    world = np.stack([s @ (Rotation.from_rotvec(rng.normal(0, 0.1, 3)).as_matrix() @ turn).T + rng.normal(0, 50, 3)
                      for s in shapes])
    return build_model(shapes, faces, [f"i{k}" for k in range(10)], instance_points_world=world,
                       params={"frame_methods": frame_methods})


@pytest.mark.parametrize("turn", [np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]]),  # model x -> world z
                                  np.array([[0.0, 1, 0], [0, 0, 1], [1, 0, 0]]),  # x -> z, y -> x, z -> y
                                  np.eye(3)])
def test_a_moments_frame_model_is_shown_as_its_instances_lay_in_their_files(turn):
    """Moments frames put the longest axis on x (a femur lies down); the pictures, model.blend and
    model.glb turn the model by the signed axis permutation nearest the instances' turn into their
    files (a bone scanned standing stands), a proper rotation. Patient-axis models are shown as
    they are."""
    from ssm_addon.model.metrics import display_axes

    model = _standing_population(turn, frame_methods=["moments"])
    shown = display_axes(model)
    np.testing.assert_array_equal(shown, turn)
    assert np.linalg.det(shown) == pytest.approx(1.0)
    from ssm_addon.pipeline.outputs import drawing_copy

    np.testing.assert_array_equal(display_axes(drawing_copy(model, 1)[0]), turn)  # a worker draws it the same
    patient = _standing_population(turn, frame_methods=["patient"])
    np.testing.assert_array_equal(display_axes(patient), np.eye(3))


def test_the_modes_figure_draws_a_moments_model_standing(tmp_path):
    """The core's modes.png of cigars that stood along z in their files: in the coronal view (z up on
    screen) the mean cell's drawn pixels are taller than wide."""
    import matplotlib.image as mpimg

    model = _standing_population(np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]]), frame_methods=["moments"])
    render_modes_figure(model, tmp_path / "modes.png", n_modes=1, cell_px=200)
    img = mpimg.imread(tmp_path / "modes.png")[..., :3]
    # the grid sits below the title/labels and right of the row labels; find the coronal (third) mean cell
    h, w = img.shape[:2]
    dark = img.max(axis=2) < 0.5  # the outlines (not the grey grid lines)
    cell = dark[h - 2 * 200:h - 200, w - 200:w]
    rows, cols = np.flatnonzero(cell.any(axis=1)), np.flatnonzero(cell.any(axis=0))
    assert rows.size and cols.size
    assert (rows[-1] - rows[0]) > 3 * (cols[-1] - cols[0]), (rows[[0, -1]], cols[[0, -1]])
