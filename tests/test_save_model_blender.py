"""Save Model is the build's writer applied to the scene's study.

A flawed study (VerSe L1–L3, an L4 label map whose label has a second, far-away component,
and two of L3's landmarks swapped) through the Blender workflow (``bpy.ops``: import,
landmarks, Build Template, Coat Template, Build Model, Save Model) and headless from its
saved project: both ``report.json`` files hold the same findings (stage, gate, instance,
figure) and the same ``correspondence``, ``template`` and ``parameters`` entries, and both
``report.html`` pages show the same warnings box. Save Model refuses a folder holding a
file no SSM command wrote, as the build does.
"""

from __future__ import annotations

import json
import math
import re

import nibabel as nib
import numpy as np
import pytest
from conftest import VERSE_FILE, VERSE_LABELS

from ssm_addon.pipeline.project import read_project
from ssm_addon.pipeline.project_build import build

pytestmark = [pytest.mark.blender, pytest.mark.slow]


def _select(bpy, obj):
    for o in bpy.context.view_layer.objects:
        o.select_set(o == obj)
    bpy.context.view_layer.objects.active = obj


@pytest.fixture(scope="module")
def flawed_inputs(verse_dir, tmp_path_factory):
    """L4 as its own label map with a far-away second component; L3's landmarks with
    ``superior`` and ``inferior`` swapped (both on the surface, about 48 mm from where they belong)."""
    folder = tmp_path_factory.mktemp("flawed_verse")
    img = nib.load(VERSE_FILE)
    labels = np.asarray(img.dataobj).astype(np.int16)
    l4 = np.where(labels == VERSE_LABELS["L4"], VERSE_LABELS["L4"], 0).astype(np.int16)
    ijk = np.argwhere(l4)
    far = ijk.max(axis=0) + 1
    size = np.array([16, 16, 12])  # about 3,000 voxels: 12 % of the vertebra's, far beyond the 5 % gate
    l4 = np.pad(l4, [(0, max(0, int(n) + 24 - (s - f))) for s, f, n in zip(l4.shape, far, size)])
    c = far + 8
    l4[c[0]:c[0] + size[0], c[1]:c[1] + size[1], c[2]:c[2] + size[2]] = VERSE_LABELS["L4"]
    l4_path = folder / "L4_two_components.nii.gz"
    nib.save(nib.Nifti1Image(l4, img.affine), str(l4_path))
    lm = {}
    for name in ("L1", "L2", "L3", "L4"):
        text = (verse_dir / "landmarks" / f"{name}.fcsv").read_text()
        if name == "L3":
            text = text.replace(",superior,", ",TMP,").replace(",inferior,", ",superior,").replace(",TMP,", ",inferior,")
        lm[name] = folder / f"{name}.fcsv"
        lm[name].write_text(text)
    return {"L1": VERSE_FILE, "L2": VERSE_FILE, "L3": VERSE_FILE, "L4": l4_path}, lm


def _blender_study(bpy, volumes, landmarks):
    insts = {}
    for name, path in volumes.items():
        before = set(bpy.data.objects)
        assert bpy.ops.ssm.import_segmentation(filepath=str(path), label=VERSE_LABELS[name]) == {"FINISHED"}
        (obj,) = [o for o in bpy.data.objects if o not in before and o.ssm.role == "INSTANCE"]
        obj.name = name
        insts[name] = obj
        _select(bpy, obj)
        assert bpy.ops.ssm.import_landmarks(filepath=str(landmarks[name])) == {"FINISHED"}
    _select(bpy, insts["L1"])
    assert bpy.ops.ssm.build_template() == {"FINISHED"}
    assert bpy.ops.ssm.coat_template() == {"FINISHED"}
    assert bpy.ops.ssm.build_model() == {"FINISHED"}
    return insts


def _close(a, b, path="", tol=1e-6):
    """Nested JSON values equal, numbers within ``tol`` (relative to their size)."""
    if isinstance(a, dict) and isinstance(b, dict):
        assert set(a) == set(b), f"{path}: keys {sorted(set(a) ^ set(b))}"
        for k in a:
            if k != "seconds":  # wall time, not a figure of the computation
                _close(a[k], b[k], f"{path}.{k}", tol)
    elif isinstance(a, list) and isinstance(b, list):
        assert len(a) == len(b), f"{path}: {len(a)} against {len(b)} items"
        for i, (x, y) in enumerate(zip(a, b)):
            _close(x, y, f"{path}[{i}]", tol)
    elif isinstance(a, float | int) and isinstance(b, float | int) and not isinstance(a, bool):
        assert math.isclose(a, b, rel_tol=tol, abs_tol=tol), f"{path}: {a} against {b}"
    else:
        assert a == b, f"{path}: {a!r} against {b!r}"


def _finding_keys(report: dict) -> set:
    return {(f["stage"], f["gate"], f["instance"], round(f["value"], 4) if f["value"] is not None else None)
            for f in report["quality"]["findings"]}


def _warnings_box(page: str) -> str:
    found = re.search(r'<div class="(warnings|ok)">.*?</div>', page, re.S)
    assert found, "no warnings box"
    return found.group(0)


def test_save_model_writes_the_reports_of_the_headless_build(bpy_clean, flawed_inputs, tmp_path):
    bpy = bpy_clean
    volumes, landmarks = flawed_inputs
    _blender_study(bpy, volumes, landmarks)
    project_file = tmp_path / "study" / "project.toml"
    assert bpy.ops.ssm.save_project(filepath=str(project_file)) == {"FINISHED"}
    saved = tmp_path / "saved"
    assert bpy.ops.ssm.save_model(directory=str(saved)) == {"FINISHED"}
    headless = build(read_project(project_file), tmp_path / "headless", log=None)

    blender_report = json.loads((saved / "report.json").read_text())
    headless_report = json.loads((tmp_path / "headless" / "report.json").read_text())
    gates = {(f[1], f[2]) for f in _finding_keys(headless_report)}
    assert ("components", "L4") in gates  # the import gate on the far-away component
    assert any(gate in ("landmark_transfer", "landmark_residual") and inst == "L3" for gate, inst in gates), gates
    assert _finding_keys(blender_report) == _finding_keys(headless_report)
    for section in ("correspondence", "template", "parameters"):
        _close(blender_report[section], headless_report[section], section)
    # what Blender cannot know is said, not left out; what only Blender knows is its own
    assert blender_report["project"]["absent"].startswith("built interactively in Blender")
    assert blender_report["model_object"] == "SSM Model"
    assert set(blender_report["timings_s"]) >= {"import", "template", "coating", "model", "metrics"}
    assert blender_report["metrics"]["generalization"]["mean_mm"] == pytest.approx(
        headless_report["metrics"]["generalization"]["mean_mm"], abs=1e-6)
    # every file where it is after the move, relative to the output folder
    for report, folder in ((blender_report, saved), (headless_report, tmp_path / "headless")):
        assert report["files"]["npz"] == "model.npz"
        for value in report["files"].values():
            for rel in (value if isinstance(value, list) else [value]):
                assert (folder / rel).exists(), rel
    # both pages carry the same warnings box
    box = _warnings_box((saved / "report.html").read_text())
    assert box == _warnings_box((tmp_path / "headless" / "report.html").read_text())
    assert "L4" in box and "components" in box and "Every quality gate passed" not in box
    assert headless.report["quality"]["findings"]

    # a folder holding a file no SSM command wrote is refused, as by the build; nothing changes there
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(RuntimeError, match="did not write"):  # the operator's ERROR report
        bpy.ops.ssm.save_model(directory=str(foreign))
    assert sorted(p.name for p in foreign.iterdir()) == ["notes.txt"]
    with pytest.raises(Exception, match="did not write"):
        build(read_project(project_file), foreign, log=None)
    # saving again into its own folder replaces exactly its own files
    assert bpy.ops.ssm.save_model(directory=str(saved)) == {"FINISHED"}
    assert json.loads((saved / "report.json").read_text())["quality"] == blender_report["quality"]
