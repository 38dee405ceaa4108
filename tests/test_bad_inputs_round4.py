"""Hostile inputs, round four: two targets at once, tracebacks turned into one line, cells that
are not numbers, asked-for values the data cannot give, non-Latin names, two builds into one folder."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT

from ssm_addon.analysis import analyze, attributes_from_tables, read_attributes
from ssm_addon.base.errors import InputError
from ssm_addon.cli import demo
from ssm_addon.cli.command import main
from ssm_addon.formats.meshes import read_mesh, write_ply
from ssm_addon.instances.importing import file_names, safe_file_name
from ssm_addon.model.files import save_npz
from ssm_addon.model.pca import build_model


@pytest.fixture(scope="module")
def population(tmp_path_factory):
    folder = tmp_path_factory.mktemp("round4") / "pop"
    demo.make_demo_population(folder, n=4, seed=5)
    return folder


def _model(tmp_path, n=6):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(n, 40, 3)) + np.linspace(0, 30, 40)[None, :, None]
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])
    model = build_model(pts, faces, [f"s{i}" for i in range(n)])
    return model, save_npz(model, tmp_path / "model.npz")


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, err
    return lines[0]


# ------------------------------------------------------------------------ two targets at once
def test_fit_refuses_a_mesh_and_a_project_naming_both(tmp_path, capsys):
    _model_, path = _model(tmp_path)
    mesh = tmp_path / "target.ply"
    write_ply(mesh, np.random.default_rng(1).normal(size=(10, 3)), np.array([[0, 1, 2]]))
    project = tmp_path / "project.toml"
    project.write_text("")
    assert main(["fit", str(path), "--mesh", str(mesh), "--project", str(project), "--out", str(tmp_path / "o")]) == 2
    line = _one_line_error(capsys)
    assert f"--project {project}" in line and f"--mesh {mesh}" in line and "two targets at once" in line
    assert not (tmp_path / "o").exists()
    assert main(["fit", str(path), "--mesh", str(mesh), "--points", str(mesh), "--out", str(tmp_path / "o")]) == 2
    assert "two targets at once" in _one_line_error(capsys)


# ------------------------------------------------------------------------ one line, not a traceback
def test_demo_with_two_instances_is_one_line(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "d"), "--n", "2", "--no-blend"]) == 2
    assert "--n 2: the demo needs at least 3 instances" in _one_line_error(capsys)
    assert not (tmp_path / "d").exists()


def test_demo_into_an_existing_file_is_refused_naming_it(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("mine")
    assert main(["demo", "--out", str(f), "--n", "3", "--no-blend"]) == 2
    assert f"--out {f}: is a file, not a folder" in _one_line_error(capsys)
    assert f.read_text() == "mine"


def test_template_into_a_read_only_folder_is_refused_before_the_work(population, tmp_path, capsys, monkeypatch):
    """A read-only mount (EROFS): refused naming the folder, before the template is built."""
    from ssm_addon.cli import command

    def read_only(*args, dir=None, **kwargs):
        raise OSError(30, "Read-only file system")

    monkeypatch.setattr(command.tempfile, "TemporaryFile", read_only)
    ro = tmp_path / "ro"
    ro.mkdir()
    t0 = time.perf_counter()
    assert main(["template", str(population / "demo_00.nii.gz"), "--out", str(ro / "t.ply")]) == 2
    assert _one_line_error(capsys) == f"error: --out: cannot write in {ro}: Read-only file system"
    assert time.perf_counter() - t0 < 60  # against a hang only; the template was never started:
    assert "[" not in capsys.readouterr().out  # no progress line


# ------------------------------------------------------------------------ cells that are not numbers
@pytest.mark.parametrize("cell", ["sixty", "inf"])
def test_a_covariate_cell_that_is_not_a_number_is_named_with_its_instance(tmp_path, cell):
    model, _p = _model(tmp_path)
    ages = {f"s{i}": str(40 + 3 * i) for i in range(6)}
    ages["s3"] = cell
    attrs = attributes_from_tables({n: {"age": a} for n, a in ages.items()}, source="ages.csv")
    with pytest.raises(InputError, match=rf"ages\.csv: covariate 'age' has cells that are not numbers: "
                                         rf"'{cell}' \(s3\)"):
        analyze(model, attrs, covariates=["age"], permutations=99)


def test_decimal_commas_in_a_semicolon_file_are_numbers(tmp_path):
    path = tmp_path / "attrs.csv"
    path.write_text("name;age;group\ns0;51,5;a\ns1;60;b\ns2;-3,25;a\n")
    attrs = read_attributes(path)
    assert attrs.kinds["age"] == "number" and attrs.column("age").tolist() == [51.5, 60.0, -3.25]
    assert attrs.kinds["group"] == "category"


def test_attributes_naming_a_folder_say_it_is_a_folder(tmp_path):
    with pytest.raises(InputError, match=rf"{re.escape(str(tmp_path))}: is a folder, not an attribute table"):
        read_attributes(tmp_path)


def test_a_text_column_as_covariate_is_said_once(tmp_path):
    model, _p = _model(tmp_path)
    attrs = attributes_from_tables({f"s{i}": {"site": "ab"[i % 2]} for i in range(6)})
    result = analyze(model, attrs, covariates=["site"], permutations=99)
    said = [w for w in result.warnings if "'site'" in w]
    assert said == ["covariate 'site' holds text, not numbers: used as a group (its values are categories)"]


def test_a_fit_target_in_metres_says_metres(tmp_path):
    from ssm_addon.instances.voxelize import voxelize_mesh

    v = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]], float) + 0.37  # a 100 mm object in m
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    with pytest.raises(InputError, match=r"it is 0\.1 units across, so it looks like metres \(× 1000 for mm\)"):
        voxelize_mesh(v, f, 1.0, source="m.ply")


# ------------------------------------------------------------------------ what was asked, what was used
def test_fit_says_what_it_used_for_n_modes_and_jobs(tmp_path, capsys):
    model, path = _model(tmp_path)
    pts = tmp_path / "points.csv"
    pts.write_text("x,y,z\n" + "".join(f"{x!r},{y!r},{z!r}\n" for x, y, z in model.mean))
    assert main(["fit", str(path), "--points", str(pts), "--out", str(tmp_path / "o"), "--n-modes", "1000",
                 "--jobs", "0"]) == 0
    out = capsys.readouterr().out
    assert out.count(f"--n-modes 1000: the model has {model.n_modes} modes; used {model.n_modes}") == 1
    assert out.count("--jobs 0 is not a number of workers; used 1") == 1


def test_fit_help_shows_no_internal_names():
    proc = subprocess.run([sys.executable, "-m", "ssm_addon", "fit", "--help"], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0 and "__" not in proc.stdout and "--n-modes N" in proc.stdout


def test_exchange_modes_beyond_the_model_are_said(population, tmp_path, capsys):
    """A build of 4 instances (3 modes) asked for 100 exchange modes says what it wrote, once."""
    text = (population / "project.toml").read_text()
    project = population / "exchange.toml"
    project.write_text(text.replace("[analysis]", "[output]\nexchange_modes = 100\n\n[analysis]", 1))
    assert main(["build", str(project), "--out", str(tmp_path / "out"), "--no-blend"]) == 0
    out = capsys.readouterr().out
    assert out.count("note: [output] exchange_modes = 100: the model has 3 modes; model.glb and vtk/ hold 3") == 1
    assert sorted(p.name for p in (tmp_path / "out" / "vtk").glob("mode_*_plus2sd.vtp")) == [
        f"mode_{k}_plus2sd.vtp" for k in (1, 2, 3)]


# ------------------------------------------------------------------------ names in any script
def test_non_latin_names_keep_their_letters_and_stay_apart():
    assert file_names(["позвонок", "椎骨", "L1"]) == {"позвонок": "позвонок", "椎骨": "椎骨", "L1": "L1"}
    assert safe_file_name("../позвонок/1") == "позвонок_1"


# ------------------------------------------------------------------------ two builds into one folder
def test_a_second_build_into_the_same_folder_is_refused_while_the_first_writes(tmp_path):
    from ssm_addon.pipeline.outputs import output_lock

    out = tmp_path / "out"
    with output_lock(out):
        # another process (a second `ssm build`) meets the lock the first one holds
        code = ("import sys; from pathlib import Path; from ssm_addon.pipeline.outputs import output_lock\n"
                "from ssm_addon.base.errors import InputError\n"
                "try:\n    with output_lock(Path(sys.argv[1])): print('got it')\n"
                "except InputError as e: print(e)")
        proc = subprocess.run([sys.executable, "-c", code, str(out)], cwd=ROOT, capture_output=True, text=True,
                              timeout=120)
    assert proc.stdout.strip().startswith(f"{out}: another SSM command is writing it now (pid ")
    assert not (tmp_path / ".out.lock").exists()  # removed with the writing
    with output_lock(out):  # and free again
        pass


def test_two_builds_at_once_leave_one_output_and_one_refusal(population, tmp_path):
    proj = population / "project.toml"
    out = tmp_path / "out"
    env = {"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin", "HOME": tempfile.gettempdir()}
    cmd = [sys.executable, "-m", "ssm_addon", "build", str(proj), "--out", str(out), "--no-blend", "--cache", "off"]
    first = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while not (tmp_path / ".out.lock").exists():  # the first build holds the folder
        assert first.poll() is None and time.monotonic() < deadline, first.communicate()
        time.sleep(0.02)
    second = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    first_out, first_err = first.communicate(timeout=600)
    assert first.returncode == 0, first_err[-2000:]
    assert second.returncode == 2 and "another SSM command is writing it now" in second.stderr
    assert "outputs in" not in second.stdout
    assert (out / "model.npz").is_file()


# ------------------------------------------------------------------------ the template command's file
def test_template_refuses_to_write_over_its_input(population, tmp_path, capsys):
    volume = tmp_path / "demo_00.nii.gz"
    shutil.copy(population / "demo_00.nii.gz", volume)
    before = volume.read_bytes()
    assert main(["template", str(volume), "--out", str(volume)]) == 2
    assert _one_line_error(capsys) == (f"error: --out {volume}: is the input itself; give another file for the "
                                       f"template, e.g. {tmp_path / 'demo_00_template.ply'}")
    assert volume.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["demo_00.nii.gz"]


def test_template_leaves_an_earlier_file_whole_when_its_writing_fails(population, tmp_path, monkeypatch, capsys):
    from ssm_addon.formats import meshes

    out = tmp_path / "t.ply"
    assert main(["template", str(population / "demo_00.nii.gz"), "--out", str(out)]) == 0
    earlier = out.read_bytes()
    assert read_mesh(out)[0].shape[0] > 100 and oct(out.stat().st_mode & 0o777) == oct(0o666 & ~_umask_now())

    def disk_full(path, *args, **kwargs):
        Path(path).write_bytes(b"ply\nformat binary_little_endian 1.0\n")  # a start, then the disk is full
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(meshes, "write_ply", disk_full)
    with pytest.raises(OSError, match="No space left"):
        main(["template", str(population / "demo_00.nii.gz"), "--out", str(out)])
    assert out.read_bytes() == earlier and sorted(p.name for p in tmp_path.iterdir()) == ["t.ply"]


def _umask_now() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
