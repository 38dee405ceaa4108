"""The same inputs give the same model with the libraries the extension zip bundles.

The extension bundles the versions of ``constraints.txt`` (scipy 1.15.3, ...; ``wheels_cache/``)
while a fresh ``pip install .`` resolves the newest allowed ones; Blender's own numpy is the same
in both. A copy of this test environment with the constraints' versions installed from the
zip's wheels (offline) builds the same projects headless, and runs the Blender-vs-headless
test; the ``model.npz`` arrays must equal this environment's bit for bit.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, VERSE_FILE, VERSE_LABELS, shared_data_dir

from ssm_addon.cli import demo

ARRAYS = ("mean", "faces", "modes", "variances", "instance_points", "instance_points_world")
PACKAGES = ("scipy", "scikit-image", "nibabel", "pynrrd", "h5py", "matplotlib", "threadpoolctl")


def _pins() -> dict:
    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, _, version = line.partition("==")
            pins[name.strip().lower().replace("-", "_")] = version.strip()
    return pins


def test_the_constraints_file_states_the_versions_the_zip_bundles(zip_wheels):
    pins = _pins()
    resolved = json.loads((zip_wheels / "resolved.json").read_text())["wheels"]
    bundled = {w.split("-")[0].lower(): w.split("-")[1] for w in resolved}
    assert pins and "numpy" not in pins  # Blender's own numpy
    for name, version in pins.items():
        assert bundled.get(name) == version, (name, version, bundled.get(name))


@pytest.fixture(scope="module")
def constraints_env(tmp_path_factory, zip_wheels):
    """A copy of this venv with the constraints' versions installed from wheels_cache (no network)."""
    import scipy

    if sys.prefix == sys.base_prefix or not sys.platform.startswith("linux"):
        pytest.skip("needs this test run's venv on Linux")
    if scipy.__version__ == _pins()["scipy"]:
        pytest.skip(f"this environment already has the zip's scipy {scipy.__version__}")
    copy = tmp_path_factory.mktemp("constraints") / "venv"
    shutil.copytree(sys.prefix, copy, symlinks=True)
    py = copy / "bin" / "python"
    proc = subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-index", "--find-links", str(zip_wheels), "-c",
                           str(ROOT / "constraints.txt"), *PACKAGES], capture_output=True, text=True)
    if proc.returncode:
        pytest.skip(f"cannot install the constraints' versions from wheels_cache: {proc.stderr[-300:]}")
    got = subprocess.run([str(py), "-c", "import scipy; print(scipy.__version__)"], capture_output=True,
                         text=True).stdout.strip()
    assert got == _pins()["scipy"]
    return py


def _build(python, project: Path, out: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([str(python), "-m", "ssm_addon", "build", str(project), "--out", str(out), "--no-blend",
                           "--cache", "off", "--jobs", "1"], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    with np.load(out / "model.npz", allow_pickle=False) as z:
        return {k: z[k] for k in ARRAYS}


def _verse_project(folder: Path) -> Path | None:
    data = shared_data_dir() / "verse004"
    if not (data / VERSE_FILE.name).is_file():
        return None
    lines = ["[template]", 'instance = "L1"', "spacing = 1.0", "", "[model]", 'alignment = "none"', ""]
    for name in ("L1", "L2", "L3"):
        lines += ["[[instances]]", f'name = "{name}"', f'volume = "{(data / VERSE_FILE.name).as_posix()}"',
                  f"label = {VERSE_LABELS[name]}", f'landmarks = "{(data / "landmarks" / f"{name}.fcsv").as_posix()}"',
                  ""]
    path = folder / "verse_l1_l3.toml"
    path.write_text("\n".join(lines))
    return path


@pytest.mark.slow
def test_the_zips_libraries_build_the_same_models_bit_for_bit(constraints_env, tmp_path):
    verse = _verse_project(tmp_path)  # real vertebrae where the shared data are, else the demo
    projects = ({"verse004 L1-L3": verse} if verse is not None
                else {"demo": demo.make_demo_population(tmp_path / "population", n=6, seed=2)})
    for name, project in projects.items():
        here = _build(sys.executable, project, tmp_path / f"{name}-here")
        there = _build(constraints_env, project, tmp_path / f"{name}-zip")
        for key in ARRAYS:
            assert np.array_equal(here[key], there[key]), (name, key)


@pytest.mark.slow
@pytest.mark.blender
def test_blender_and_headless_agree_with_the_zips_libraries(constraints_env):
    """The Blender-vs-headless test (tests/test_cli_blender.py) under the constraints' versions."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([str(constraints_env), "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           "tests/test_cli_blender.py::test_blender_command_build_equals_python_build"],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0 and "1 passed" in proc.stdout, proc.stdout[-3000:] + proc.stderr[-2000:]
