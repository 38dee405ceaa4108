"""A build writes only its own files: foreign files kept, stale outputs removed, no escapes,
identical builds give identical model files, and permissions follow the umask."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
import pytest

from ssm_addon.__main__ import main
from ssm_addon.base.errors import InputError
from ssm_addon.cli import demo
from ssm_addon.pipeline.outputs import MANIFEST
from ssm_addon.pipeline.project import read_project
from ssm_addon.pipeline.project_build import build


@pytest.fixture(scope="module")
def quick_project(tmp_path_factory):
    """Four demo vertebrae and a coarse, short build (seconds)."""
    folder = tmp_path_factory.mktemp("owned")
    path = demo.make_demo_population(folder / "population", n=4, seed=11)
    path.write_text(path.read_text().replace("spacing = 1.0", "spacing = 1.0\nr_min_mm = 4.0\nr_max_mm = 8.0")
                    .replace("[model]", "[model]\nspecificity_samples = 50"))
    return path


def _digest(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.slow
def test_existing_folder_with_a_foreign_file_is_refused_then_kept_with_force(quick_project, tmp_path):
    out = tmp_path / "out"
    (out / "coated").mkdir(parents=True)
    (out / "notes.txt").write_text("mine")
    (out / "coated" / "my_mesh.ply").write_text("also mine")
    with pytest.raises(InputError, match=r"holds 2 file\(s\) an SSM build did not write .*--force"):
        build(read_project(quick_project), out, log=None)
    assert sorted(_digest(out)) == ["coated/my_mesh.ply", "notes.txt"]
    build(read_project(quick_project), out, log=None, force=True)
    assert (out / "notes.txt").read_text() == "mine" and (out / "coated" / "my_mesh.ply").read_text() == "also mine"
    assert (out / "model.npz").is_file() and (out / MANIFEST).is_file()


@pytest.mark.slow
def test_rebuild_leaves_exactly_its_own_outputs_and_identical_model_bytes(quick_project, tmp_path):
    out = tmp_path / "out"
    build(read_project(quick_project), out, log=None)
    first = _digest(out)
    assert "model.h5" in first and any(k.startswith("coated/") for k in first)
    (out / "mine.txt").write_text("a file of mine")
    quiet = quick_project.with_name("quiet.toml")
    quiet.write_text(quick_project.read_text().replace("[model]", "[output]\ncoated_meshes = false\nstatismo = false\n\n[model]"))
    build(read_project(quiet), out, log=None, force=True)
    second = _digest(out)
    assert "model.h5" not in second and not any(k.startswith("coated/") for k in second)  # stale outputs gone
    assert not (out / "coated").exists()
    assert second["mine.txt"] == hashlib.sha256(b"a file of mine").hexdigest()  # foreign file untouched
    assert second["model.npz"] == first["model.npz"]  # identical builds: identical model file


def test_output_folder_may_not_hold_an_input(quick_project):
    folder = quick_project.parent
    with pytest.raises(InputError, match="holds an input of the build"):
        build(read_project(quick_project), folder, log=None, force=True)
    with pytest.raises(InputError, match="holds an input of the build"):
        build(read_project(quick_project), folder.parent, log=None, force=True)


@pytest.mark.slow
def test_failed_build_leaves_an_earlier_output_byte_identical(quick_project, tmp_path):
    out = tmp_path / "out"
    build(read_project(quick_project), out, log=None)
    before = _digest(out)
    bad = quick_project.with_name("bad.toml")
    bad.write_text(quick_project.read_text().replace("label = 20", "label = 99", 1))
    with pytest.raises(InputError, match="label 99 is not present"):
        build(read_project(bad), out, log=None)
    assert _digest(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "out.cache"]  # no temporary folder left


@pytest.mark.slow
def test_instance_names_cannot_escape_the_output_folder(quick_project, tmp_path):
    text = quick_project.read_text()
    first = read_project(quick_project).names[0]
    escaping = quick_project.with_name("escape.toml")
    escaping.write_text(text.replace(f'name = "{first}"', 'name = "../../escaped"', 1))
    out = tmp_path / "deep" / "out"
    build(read_project(escaping), out, log=None)
    assert (out / "coated" / "escaped.ply").is_file()
    assert not list(tmp_path.rglob("escaped.ply"))[1:] and not (tmp_path / "escaped.ply").exists()


@pytest.mark.slow
def test_output_permissions_follow_the_umask(quick_project, tmp_path):
    old = os.umask(0o022)
    try:
        build(read_project(quick_project), tmp_path / "out", log=None)
    finally:
        os.umask(old)
    assert (tmp_path / "out").stat().st_mode & 0o777 == 0o755
    assert (tmp_path / "out" / "model.npz").stat().st_mode & 0o777 == 0o644


@pytest.mark.slow
def test_command_line_force_and_foreign_file_message(quick_project, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.me").write_text("x")
    assert main(["build", str(quick_project), "--out", str(out), "--no-blend"]) == 2
    assert "--force" in capsys.readouterr().err
    assert main(["build", str(quick_project), "--out", str(out), "--no-blend", "--force"]) == 0
    assert (out / "keep.me").read_text() == "x"


@pytest.mark.slow
def test_score_tables_hold_the_models_projections(quick_project, tmp_path):
    """scores.csv: each instance's mode weights in SD and mm, equal to model.npz's
    projections; eigenvalues.csv: the variances with their shares; [output] scores = false
    writes neither."""
    import csv

    import numpy as np

    from ssm_addon.model.files import load_npz

    result = build(read_project(quick_project), tmp_path / "out", log=None)
    model = load_npz(tmp_path / "out" / "model.npz")
    rows = list(csv.DictReader(open(tmp_path / "out" / "scores.csv", encoding="utf-8")))
    assert [r["instance"] for r in rows] == list(model.instance_names)
    k = model.n_modes
    for r, pts in zip(rows, model.instance_points):
        b = model.project(pts)
        np.testing.assert_allclose([float(r[f"b{i + 1}_mm"]) for i in range(k)], b, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose([float(r[f"z{i + 1}"]) for i in range(k)], b / model.standard_deviations,
                                   rtol=1e-5, atol=1e-6)
    eig = list(csv.DictReader(open(tmp_path / "out" / "eigenvalues.csv", encoding="utf-8")))
    np.testing.assert_allclose([float(e["variance_mm2"]) for e in eig], model.variances, rtol=1e-8)
    assert abs(float(eig[-1]["cumulative"]) - 1.0) < 1e-5
    assert {"scores", "eigenvalues"} <= set(result.files)
    off = quick_project.with_name("noscores.toml")
    text = quick_project.read_text()
    off.write_text(text.replace("[model]", "[output]\nscores = false\n\n[model]") if "[output]" not in text
                   else text.replace("[output]", "[output]\nscores = false"))
    build(read_project(off), tmp_path / "off", log=None)
    assert not (tmp_path / "off" / "scores.csv").exists() and not (tmp_path / "off" / "eigenvalues.csv").exists()


def test_exchange_meshes_open_at_their_real_size(tmp_path):
    """model.glb is in metres (glTF's unit) with a morph target per mode; the VTK meshes are the mean
    and the mean ±2 SD per mode in mm."""
    import xml.etree.ElementTree as ET

    from ssm_addon.formats.gltf import Z_UP_TO_Y_UP, read_glb, read_glb_mesh
    from ssm_addon.model.files import write_exchange_meshes
    from ssm_addon.model.pca import build_model

    rng = np.random.default_rng(4)
    base = np.c_[np.cos(np.linspace(0, 6, 30)), np.sin(np.linspace(0, 6, 30)), np.linspace(0, 1, 30)] * 40.0
    base = base + [100.0, -1000.0, 150.0]  # scanner-like coordinates, mm
    shapes = base[None] + rng.normal(scale=1.0, size=(8, 30, 3))
    faces = np.array([[i, i + 1, i + 2] for i in range(28)])
    model = build_model(shapes, faces, [f"s{i}" for i in range(8)])
    written = write_exchange_meshes(model, tmp_path, modes=3)
    doc, binary = read_glb(written["gltf"])
    pos = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    # metres, and glTF's +Y up: the model's +Z (superior) is the file's +Y, its +Y the file's -Z
    up = model.mean @ Z_UP_TO_Y_UP.T
    np.testing.assert_allclose(up[:, 1], model.mean[:, 2])
    np.testing.assert_allclose(up[:, 2], -model.mean[:, 1])
    np.testing.assert_allclose(pos["max"], up.max(axis=0) / 1000, rtol=1e-6)
    view = doc["bufferViews"][pos["bufferView"]]
    stored = np.frombuffer(binary[view["byteOffset"]:view["byteOffset"] + view["byteLength"]], np.float32)
    np.testing.assert_allclose(stored.reshape(-1, 3), up / 1000, rtol=1e-6, atol=1e-7)
    assert doc["extras"]["up"].startswith("+Y")
    back, back_faces, back_targets = read_glb_mesh(written["gltf"])  # and back, mm, +Z up
    np.testing.assert_allclose(back, model.mean, atol=1e-3)
    np.testing.assert_array_equal(back_faces, faces)
    np.testing.assert_allclose(back_targets["Mode 1 (+1 SD)"], model.standard_deviations[0] * model.modes[0], atol=1e-3)
    targets = doc["meshes"][0]["primitives"][0]["targets"]
    assert len(targets) == 3 and doc["meshes"][0]["extras"]["targetNames"][0] == "Mode 1 (+1 SD)"
    t = doc["accessors"][targets[0]["POSITION"]]
    tv = doc["bufferViews"][t["bufferView"]]
    shift = np.frombuffer(binary[tv["byteOffset"]:tv["byteOffset"] + tv["byteLength"]], np.float32).reshape(-1, 3)
    np.testing.assert_allclose(shift, model.standard_deviations[0] * model.modes[0] @ Z_UP_TO_Y_UP.T / 1000, atol=1e-7)
    plus = ET.parse(tmp_path / "vtk" / "mode_2_plus2sd.vtp").getroot().find("PolyData/Piece/Points/DataArray")
    pts = np.array(plus.text.split(), float).reshape(-1, 3)
    np.testing.assert_allclose(pts, model.mean + 2 * model.standard_deviations[1] * model.modes[1], atol=1e-6)
    extent = np.array(pos["max"]) - np.array(pos["min"])
    np.testing.assert_allclose(extent, np.ptp(up, axis=0) / 1000, rtol=1e-6)  # 80 mm wide: 0.08 m
    assert abs(extent[0] - 0.08) < 0.01
    # VTK's own readers (vtk is in requirements-dev.txt, so this runs in CI; only its I/O modules, no OpenGL)
    io_xml = pytest.importorskip("vtkmodules.vtkIOXML", reason="VTK's readers: pip install -r requirements-dev.txt")
    io_legacy = pytest.importorskip("vtkmodules.vtkIOLegacy", reason="VTK's readers: pip install -r requirements-dev.txt")
    for name, reader in (("mean.vtp", io_xml.vtkXMLPolyDataReader()), ("mean.vtk", io_legacy.vtkPolyDataReader())):
        reader.SetFileName(str(tmp_path / "vtk" / name))
        reader.Update()
        poly = reader.GetOutput()
        assert poly.GetNumberOfPoints() == 30 and poly.GetNumberOfPolys() == 28, name
        got = np.array([poly.GetPoint(i) for i in range(30)])
        np.testing.assert_allclose(got, model.mean, atol=1e-6)
        var = poly.GetPointData().GetArray("variance_mm2")
        np.testing.assert_allclose([var.GetValue(i) for i in range(30)], model.point_variance, rtol=1e-8)
    legacy = (tmp_path / "vtk" / "mean.vtk").read_text().splitlines()
    assert legacy[0] == "# vtk DataFile Version 4.2" and "POINTS 30 double" in legacy
    assert "SCALARS variance_mm2 double 1" in legacy and "POLYGONS 28 112" in legacy


def test_vtp_files_of_meshes_with_other_triangles_hold_their_own(tmp_path):
    """The connectivity text is kept for the next file (a study's coatings share the template's
    triangles); a file of other triangles, and one of the first again, hold their own."""
    import xml.etree.ElementTree as ET

    from ssm_addon.formats.vtk import write_vtp

    pts = np.random.default_rng(0).normal(size=(5, 3))
    first, other = np.array([[0, 1, 2], [0, 2, 3]]), np.array([[1, 2, 4], [2, 3, 4], [0, 1, 4]])
    for k, faces in enumerate((first, other, first, first)):
        root = ET.parse(write_vtp(tmp_path / f"{k}.vtp", pts, faces)).getroot()
        polys = {a.get("Name"): a.text for a in root.iter("DataArray") if a.get("Name")}
        assert np.array_equal(np.array(polys["connectivity"].split(), int).reshape(-1, 3), faces), k
        assert np.array_equal(np.array(polys["offsets"].split(), int), 3 * np.arange(1, len(faces) + 1)), k


def test_every_series_a_legend_names_has_data_when_drawn_from_the_builds_copy():
    """The build draws fig. 9 on a worker from a copy of the model without its training shapes
    (:func:`~ssm_addon.pipeline.outputs.drawing_copy`): the dashed curve of the point-coordinate
    variances, which the legend names, must come with it (it was empty: the copy has no shapes
    to take the variances of)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from ssm_addon.model.metrics import draw_cumulative, draw_spectrum
    from ssm_addon.model.pca import build_model
    from ssm_addon.pipeline.outputs import drawing_copy

    rng = np.random.default_rng(0)
    base = rng.normal(size=(60, 3)) * 10
    shapes = np.stack([base + rng.normal(scale=1.0, size=base.shape) for _ in range(8)])
    model = build_model(shapes, np.array([[0, 1, 2]]), [f"s{k}" for k in range(8)], alignment="none")
    drawn, coordinate = drawing_copy(model, 2)
    assert drawn.instance_points.shape[1] == 0  # what a worker is sent holds no shapes
    fig = Figure()
    FigureCanvasAgg(fig)
    ax, bx = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    draw_spectrum(ax, drawn)
    draw_cumulative(bx, drawn, coordinate)
    handles, labels = bx.get_legend_handles_labels()
    assert len(labels) == 2 and any("coordinate" in x for x in labels), labels
    for line in bx.get_lines():
        assert len(line.get_xdata()) > 0 and np.isfinite(line.get_ydata()).all(), line.get_label()
    full = model.variability_concentration("coordinate")
    assert np.allclose(coordinate[: len(full)], full[: len(coordinate)])
