"""The suite in one process, in a fixed order: a Blender test file's tests first, then tests that need
worker processes and a fresh picture state. README's test command spreads the files over workers, so
which files share a process changes from run to run; this runs the order that once failed (any
``*_blender`` test before the joint build's picture test, the whole suite with ``-n 0``) every time."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Blender first (it imports and registers ``bpy``, opens files, renders), then the core's tests
#: that would notice: real worker processes, pictures drawn on them, the core without Blender.
ORDER = (
    "tests/test_joint_blender.py::test_import_shape_model_opens_a_joint_model_as_an_empty_driving_one_mesh_per_structure",
    "tests/test_model_blender.py",
    "tests/test_coating_blender.py::test_a_render_in_the_default_shading_shows_the_correspondence_colours",
    "tests/test_compute.py::test_processes_are_processes_after_bpy_is_imported_and_serial_only_inside_the_blender_program",
    "tests/test_joint.py::test_a_joint_build_draws_the_same_pictures_on_worker_processes_as_serially",
    "tests/test_structure.py::test_the_build_path_does_not_import_scipy_stats",
)

pytestmark = [pytest.mark.blender, pytest.mark.slow]


def test_blender_tests_then_worker_process_tests_pass_in_one_process():
    """The files above, in that order, in one pytest process (``-n 0``): every test passes."""
    pytest.importorskip("bpy", reason="the bpy module is not installed")
    missing = [n for n in ORDER if not (ROOT / n.split("::")[0]).is_file()]
    assert not missing, missing
    done = subprocess.run([sys.executable, "-m", "pytest", "-n", "0", "-q", "-p", "no:randomly",
                           "-p", "no:cacheprovider", *ORDER], cwd=ROOT, capture_output=True, text=True,
                          timeout=1800, env={**os.environ, "PYTHONPATH": str(ROOT)})
    tail = done.stdout[-3000:] + done.stderr[-2000:]
    assert done.returncode == 0, tail
    assert " passed" in done.stdout and "failed" not in done.stdout and "skipped" not in done.stdout, tail
