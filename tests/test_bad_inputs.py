"""Hostile inputs, round three: damaged models, names and paths no file system takes, duplicates."""

from __future__ import annotations

import os
import re
import shutil

import numpy as np
import pytest

from ssm_addon.base.errors import InputError
from ssm_addon.cli import demo
from ssm_addon.cli.command import main
from ssm_addon.model.files import save_npz, save_statismo
from ssm_addon.model.pca import build_model
from ssm_addon.pipeline.project import read_project
from ssm_addon.pipeline.project_build import build


@pytest.fixture(scope="module")
def population(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bad") / "pop"
    demo.make_demo_population(folder, n=4, seed=5)
    return folder


def _project(population, folder, n=3, extra_instances=""):
    text = (population / "project.toml").read_text()
    head, *blocks = text.split("[[instances]]")
    head = head.split("[analysis]")[0]  # the demo's analysis needs more instances than these tests build
    body = "".join("[[instances]]" + b for b in blocks[:n])
    body = re.sub(r'(volume|landmarks) = "demo', rf'\1 = "{population}/demo', body)
    head = re.sub(r'instance = "demo_\d+"', 'instance = "demo_00"', head)
    path = folder / "project.toml"
    path.write_text(head + body + extra_instances)
    return path


def _model(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(6, 40, 3)) + np.linspace(0, 30, 40)[None, :, None]
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])
    model = build_model(pts, faces, [f"s{i}" for i in range(6)])
    return model, save_npz(model, tmp_path / "model.npz")


def _points(tmp_path):
    p = tmp_path / "points.csv"
    p.write_text("x,y,z\n" + "".join(f"{i},{i % 3},{i % 5}\n" for i in range(30)))
    return p


@pytest.mark.parametrize("damage, message", [
    ("truncated", r"damaged or not a model \.npz \(BadZipFile: File is not a zip file\)"),
    ("bit-flipped", r"damaged or not a model \.npz \(BadZipFile: Bad CRC-32"),
    ("nan", r"'mean' holds 1 NaN or infinite value\(s\); the model is damaged"),
])
def test_fit_on_a_damaged_model_says_so(tmp_path, capsys, damage, message):
    model, path = _model(tmp_path)
    data = path.read_bytes()
    if damage == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "bit-flipped":
        with np.load(path, allow_pickle=False) as z:
            names = z.files
        b = bytearray(data)
        start = data.find(b"instance_points.npy") + 200  # inside that member's data
        b[start] ^= 0x40
        path.write_bytes(bytes(b))
        assert "instance_points" in names
    else:
        mean = model.mean.copy()
        mean[3, 1] = np.nan
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["mean"] = mean
        np.savez(path, **arrays)
    assert main(["fit", str(path), "--points", str(_points(tmp_path)), "--out", str(tmp_path / "fit")]) == 2
    err = capsys.readouterr().err
    assert re.search(message, err) and str(path) in err and "Traceback" not in err
    assert not (tmp_path / "fit").exists()


def test_statismo_without_its_params_json_says_what_is_missing(tmp_path, capsys):
    import h5py

    model, _ = _model(tmp_path)
    h5 = save_statismo(model, tmp_path / "model.h5")
    with h5py.File(h5, "a") as f:
        del f["ssm/params_json"]
    assert main(["fit", str(h5), "--points", str(_points(tmp_path)), "--out", str(tmp_path / "fit")]) == 2
    err = capsys.readouterr().err
    assert "the /ssm group (SSM Builder's training data) lacks params_json" in err and "Traceback" not in err


def test_names_and_paths_no_file_system_takes_are_refused_when_read(population, tmp_path):
    long_name = "x" * 1000
    text = _project(population, tmp_path).read_text()
    (tmp_path / "long.toml").write_text(text.replace('name = "demo_02"', f'name = "{long_name}"'))
    with pytest.raises(InputError, match=r"name is 1000 characters; at most 200"):
        read_project(tmp_path / "long.toml")
    (tmp_path / "nul.toml").write_text(text.replace('name = "demo_02"', 'name = "demo\\u0000two"'))
    with pytest.raises(InputError, match=r"holds a control character"):
        read_project(tmp_path / "nul.toml")
    loop = tmp_path / "loop.nii.gz"
    os.symlink(loop, loop)
    (tmp_path / "loop.toml").write_text(re.sub(r'volume = "[^"]*demo_02.nii.gz"', f'volume = "{loop}"', text))
    with pytest.raises(InputError, match=r"volume .* is a symbolic link (loop|to nothing)"):
        read_project(tmp_path / "loop.toml")
    (tmp_path / "nulpath.toml").write_text(text.replace("demo_02.nii.gz", "demo_02\\u0000.nii.gz"))
    with pytest.raises(InputError, match=r"holds a control character .*not a file path"):
        read_project(tmp_path / "nulpath.toml")


@pytest.mark.slow
def test_duplicate_instances_are_a_finding_by_name(population, tmp_path):
    copy = tmp_path / "copy_of_demo_01.nii.gz"
    shutil.copy(population / "demo_01.nii.gz", copy)
    lm = next(population.glob("demo_01.*[!z]"))  # its landmark file
    extra = (f'\n[[instances]]\nname = "again"\nvolume = "{population}/demo_01.nii.gz"\nlabel = 20\n'
             f'landmarks = "{lm}"\n'
             f'\n[[instances]]\nname = "copied"\nvolume = "{copy}"\nlabel = 20\nlandmarks = "{lm}"\n')
    result = build(read_project(_project(population, tmp_path, 3, extra)), tmp_path / "out", blend=False)
    dup = {f.instance: f.message for f in result.study.findings if f.gate == "duplicate"}
    assert set(dup) == {"again", "copied"}
    assert "the same file and label as instance 'demo_01' (demo_01.nii.gz, label 20)" in dup["again"]
    assert "identical to instance 'demo_01' (bit for bit)" in dup["copied"]


def test_geometry_problems_are_named_not_blamed_on_the_landmarks(population, tmp_path):
    import gzip
    import struct

    import nibabel as nib
    import nrrd

    from ssm_addon.formats.label_maps import read_label_map

    data = np.zeros((12, 12, 12), np.uint8)
    data[3:9, 3:9, 3:9] = 20
    img = nib.Nifti1Image(data, np.eye(4))
    img.set_qform(None, code=0)
    img.set_sform(None, code=0)
    nib.save(img, tmp_path / "ok.nii.gz")
    raw = bytearray(gzip.open(tmp_path / "ok.nii.gz").read())
    raw[80:84] = struct.pack("<f", 0.0)  # pixdim[1] = 0 (nibabel would mend it to 1 on reading)
    (tmp_path / "zero.nii").write_bytes(bytes(raw))
    with pytest.raises(InputError, match=r"zero\.nii: the header gives voxel size \[0\.0, 1\.0, 1\.0\] .*no size in mm"):
        read_label_map(tmp_path / "zero.nii")
    nrrd.write(str(tmp_path / "bare.nrrd"), data)
    with pytest.raises(InputError, match=r"bare\.nrrd: the NRRD header has neither 'space directions' nor 'spacings'"):
        read_label_map(tmp_path / "bare.nrrd")
    # a template instance of one voxel: the voxel count is the cause, not its landmarks
    one = np.zeros((10, 10, 10), np.uint8)
    one[5, 5, 5] = 20
    nib.save(nib.Nifti1Image(one, np.eye(4)), tmp_path / "one.nii.gz")
    proj = _project(population, tmp_path)
    text = proj.read_text()
    proj.write_text(re.sub(r'volume = "[^"]*demo_00.nii.gz"', f'volume = "{tmp_path / "one.nii.gz"}"', text))
    with pytest.raises(InputError, match=r"instance 'demo_00' .*only 1 voxel\(s\) at 1 mm; at least 64"):
        build(read_project(proj), tmp_path / "out", blend=False)
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_model_method_names_an_instance_whose_frame_disagrees(tmp_path):
    """One instance turned 180° about S in its scanner, without landmarks, in a model-method build:
    the finding says which instance's frame disagrees (not only the symptoms)."""
    import nibabel as nib

    pop = tmp_path / "pop"
    demo.make_demo_population(pop, n=6, seed=1)
    img = nib.load(pop / "demo_03.nii.gz")
    centre = img.affine @ np.r_[np.array(img.shape) / 2, 1]
    turn = np.diag([-1.0, -1.0, 1.0, 1.0])
    move, back = np.eye(4), np.eye(4)
    move[:3, 3], back[:3, 3] = centre[:3], -centre[:3]
    affine = move @ turn @ back @ img.affine
    turned = nib.Nifti1Image(np.asarray(img.dataobj), affine)
    turned.set_qform(affine, code=1)
    turned.set_sform(affine, code=1)
    nib.save(turned, pop / "demo_03_turned.nii.gz")
    text = (pop / "project.toml").read_text().split("[analysis]")[0]
    blocks = (pop / "project.toml").read_text().split("[[instances]]")[1:]
    text += "[correspondence]\nmethod = \"model\"\n\n"
    for b in blocks:
        if "demo_03" in b:
            b = re.sub(r'landmarks = "[^"]*"\n', "", b.replace("demo_03.nii.gz", "demo_03_turned.nii.gz"))
        text += "[[instances]]" + b
    (pop / "turned.toml").write_text(text)
    result = build(read_project(pop / "turned.toml"), tmp_path / "out", blend=False)
    frames = [f for f in result.study.findings if f.gate == "frame"]
    assert [f.instance for f in frames] == ["demo_03"]
    assert "turned 180°" in frames[0].message and "the frames disagree" in frames[0].message
