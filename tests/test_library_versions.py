"""The same inputs give the same model with the libraries the extension zip bundles.

The extension bundles the versions of ``constraints.txt`` (scipy 1.15.3, ...; ``wheels_cache/``)
while a fresh ``pip install .`` resolves the newest allowed ones; Blender's own numpy is the same
in both. A venv with the constraints' versions (and this interpreter's numpy) builds the demo
population headless; its ``model.npz`` arrays must equal this interpreter's bit for bit.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT

from ssm_addon.cli import demo

WHEELS = ROOT / "wheels_cache" / "linux-x64"
ARRAYS = ("mean", "faces", "modes", "variances", "instance_points", "instance_points_world")


def _bundled_scipy_venv(folder: Path) -> Path:
    import scipy

    bundled = sorted(WHEELS.glob("scipy-*.whl"))
    if not bundled or not sys.platform.startswith("linux"):
        pytest.skip("no bundled scipy wheel for this platform in wheels_cache/linux-x64")
    version = bundled[0].name.split("-")[1]
    if version == scipy.__version__:
        pytest.skip(f"this interpreter already has the bundled scipy {version}")
    subprocess.run([sys.executable, "-m", "venv", str(folder)], check=True, capture_output=True)
    py = folder / "bin" / "python"
    local = subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-index", "--find-links", str(WHEELS),
                            "-c", str(ROOT / "constraints.txt"), "scipy", "scikit-image", "nibabel", "pynrrd", "h5py",
                            "matplotlib", "threadpoolctl"], capture_output=True, text=True)
    same_numpy = subprocess.run([str(py), "-m", "pip", "install", "-q", f"numpy=={np.__version__}"],
                                capture_output=True, text=True)
    if local.returncode or same_numpy.returncode:
        pytest.skip(f"cannot make a venv with scipy {version} and numpy {np.__version__}: "
                    f"{(local.stderr + same_numpy.stderr)[-300:]}")
    return py


def _build(python, project: Path, out: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([str(python), "-m", "ssm_addon", "build", str(project), "--out", str(out), "--no-blend",
                           "--cache", "off", "--jobs", "1"], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    with np.load(out / "model.npz", allow_pickle=False) as z:
        return {k: z[k] for k in ARRAYS}


@pytest.mark.slow
def test_the_bundled_scipy_builds_the_same_model_bit_for_bit(tmp_path):
    py = _bundled_scipy_venv(tmp_path / "venv")
    version = subprocess.run([str(py), "-c", "import scipy; print(scipy.__version__)"], capture_output=True,
                             text=True).stdout.strip()
    project = demo.make_demo_population(tmp_path / "population", n=6, seed=2)
    here = _build(sys.executable, project, tmp_path / "here")
    there = _build(py, project, tmp_path / "bundled")
    for key in ARRAYS:
        assert np.array_equal(here[key], there[key]), (key, version)


def test_the_constraints_file_states_the_versions_the_zip_bundles():
    import json

    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, _, version = line.partition("==")
            pins[name.strip().lower().replace("-", "_")] = version.strip()
    resolved = json.loads((WHEELS / "resolved.json").read_text())["wheels"]
    bundled = {w.split("-")[0].lower(): w.split("-")[1] for w in resolved}
    assert pins and "numpy" not in pins  # Blender's own numpy
    for name, version in pins.items():
        assert bundled.get(name) == version, (name, version, bundled.get(name))
