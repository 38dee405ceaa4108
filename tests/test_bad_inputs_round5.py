"""Hostile inputs, round five: folders for files, a byte-order mark, joint projects whose structures
collide in their folder names, copy one another's input or name an unknown reference; all refused
before anything is coated, naming the file, the structure and the fault."""

from __future__ import annotations

import time

import pytest
from conftest import joint_project

from ssm_addon.base.errors import InputError
from ssm_addon.cli import demo
from ssm_addon.formats.label_maps import read_label_map
from ssm_addon.formats.landmarks import read_landmarks
from ssm_addon.formats.meshes import read_mesh
from ssm_addon.pipeline.project import read_project


def test_a_folder_where_a_file_belongs_is_named_as_a_folder(tmp_path):
    folder = tmp_path / "case.nii.gz"
    folder.mkdir()
    for reader in (read_label_map, read_mesh, read_landmarks):
        with pytest.raises(InputError, match="is a folder"):
            reader(folder)
    with pytest.raises(InputError, match="is a folder, not a project file"):
        read_project(tmp_path)
    project = demo.make_demo_population(tmp_path / "pop", n=3, seed=1)
    text = project.read_text()
    (tmp_path / "pop" / "demo_01.nii.gz").rename(tmp_path / "pop" / "moved.nii.gz")
    (tmp_path / "pop" / "demo_01.nii.gz").mkdir()
    with pytest.raises(InputError, match=r"demo_01.*is a folder, not a file"):
        read_project(project)
    assert text == project.read_text()


def test_a_project_file_with_a_byte_order_mark_reads(tmp_path):
    project = demo.make_demo_population(tmp_path / "pop", n=3, seed=1)
    plain = read_project(project)
    project.write_bytes(b"\xef\xbb\xbf" + project.read_bytes())  # as Windows Notepad saves UTF-8
    assert [i.name for i in read_project(project).instances] == [i.name for i in plain.instances]


def _joint(tmp_path, edit):
    path = joint_project(tmp_path, 4)
    path.write_text(edit(path.read_text()))
    return path


def test_joint_projects_that_cannot_build_are_refused_before_any_coating(tmp_path):
    t0 = time.perf_counter()
    # two structure names that write one folder
    (tmp_path / "a").mkdir()
    p = _joint(tmp_path / "a", lambda t: t.replace("meshes = { a = ", "meshes = { \"f b\" = ").replace(", b = ", ", f_b = ")
               .replace("landmarks = { a = ", "landmarks = { \"f b\" = ").replace(", b = \"", ", f_b = \""))
    with pytest.raises(InputError, match=r"structures 'f b' and 'f_b' would write the same files"):
        read_project(p)
    # a subject whose b entry is a copy of its a entry
    (tmp_path / "c").mkdir()
    p = _joint(tmp_path / "c", lambda t: t.replace('b = "S2_b.ply"', 'b = "S2_a.ply"'))
    with pytest.raises(InputError, match=r"subject 'S2': structures 'a' and 'b' are the same input .*S2_a.ply"):
        read_project(p)
    # [joint] reference naming no structure: the file and its line
    (tmp_path / "d").mkdir()
    p = _joint(tmp_path / "d", lambda t: '[joint]\nreference = "femur"\n\n' + t)
    with pytest.raises(InputError, match=r"project.toml:2: .*\[joint\] reference 'femur' is not a structure .*a, b"):
        read_project(p)
    assert time.perf_counter() - t0 < 60  # read, never coated (seconds; the bound only catches a build)


def test_one_structures_mesh_fitted_to_a_joint_model_asks_for_the_structure(tmp_path, capsys):
    from conftest import joint_model, joint_population

    from ssm_addon.cli.command import main
    from ssm_addon.formats.meshes import write_ply
    from ssm_addon.model.files import save_npz

    a, b, fa, fb, _t = joint_population(n=10, seed=2)
    save_npz(joint_model(a[1:], b[1:], fa, fb), tmp_path / "joint.npz")
    write_ply(tmp_path / "a.ply", a[0], fa)
    code = main(["fit", str(tmp_path / "joint.npz"), "--mesh", str(tmp_path / "a.ply"), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2 and "name the structure it is, e.g. --mesh a=" in err and not (tmp_path / "o").exists()
    # named, it fits and predicts the other
    code = main(["fit", str(tmp_path / "joint.npz"), "--mesh", f"a={tmp_path / 'a.ply'}", "--out", str(tmp_path / "o")])
    assert code == 0, capsys.readouterr().err


def test_a_joint_fit_says_a_structure_in_another_unit(tmp_path, capsys):
    from conftest import joint_model, joint_population

    from ssm_addon.cli.command import main
    from ssm_addon.formats.meshes import write_ply
    from ssm_addon.model.files import save_npz

    a, b, fa, fb, _t = joint_population(n=10, seed=2)
    save_npz(joint_model(a[1:], b[1:], fa, fb), tmp_path / "joint.npz")
    write_ply(tmp_path / "a_m.ply", a[0] / 1000.0, fa)  # the same femur in metres
    code = main(["fit", str(tmp_path / "joint.npz"), "--mesh", f"a={tmp_path / 'a_m.ply'}", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 0 and "a: the target is 0.001 times the structure's size" in err and "another unit" in err


def test_the_demos_findings_are_read_against_its_truth(tmp_path):
    """`ssm demo` ends by saying whether an instance a gate named lies at the population's edge in its
    true shape parameters (an expected finding) or not (one to look at)."""
    import json

    from ssm_addon.cli.demo import explain_findings

    truth = {"modes": {"body_height": {}, "body_radius": {}},
             "instances": [{"name": "d0", "b": [-2.3, 0.2]}, {"name": "d1", "b": [0.4, -0.9]},
                           {"name": "d2", "b": [1.1, 0.1]}, {"name": "d3", "b": [1.9, 1.9]}]}
    report = {"quality": {"findings": [{"instance": "d0", "gate": "reconstruction"},
                                       {"instance": "d1", "gate": "outlier"},
                                       {"instance": "d3", "gate": "reconstruction"}]}}
    (tmp_path / "truth.json").write_text(json.dumps(truth))
    (tmp_path / "report.json").write_text(json.dumps(report))
    lines = explain_findings(tmp_path / "report.json", tmp_path / "truth.json")
    # |b| = 2.31 SD: exp(-2.31² / 2) = 7 % of a normal population (2 degrees of freedom) lies farther
    assert lines[0].startswith("demo: d0 [reconstruction] is at the population's edge: its true body_height is "
                               "-2.30 SD (truth.json; the most extreme of 4; all 2 together 2.31 SD from the "
                               "mean, number 2, 7 % of a normal population farther), so the model of the others "
                               "reconstructs it poorly; expected")
    assert lines[1].startswith("demo: d1 [outlier] is not at the population's edge") and "look at it" in lines[1]
    assert "so the model" not in lines[1]
    # no parameter beyond 2 SD, but both together 2.69 SD: 3 % farther, the edge
    assert lines[2].startswith("demo: d3 [reconstruction] is at the population's edge: its true body_height is "
                               "+1.90 SD (truth.json; number 2 by extremity of 4; all 2 together 2.69 SD from the "
                               "mean, number 1")
    assert "3 % of a normal population farther" in lines[2] and lines[2].endswith("(report.html, Instances: d3)")


@pytest.mark.parametrize("fault", ["empty", "flat"])
def test_an_empty_or_flat_structure_mesh_is_refused_before_any_coating(tmp_path, fault):
    import numpy as np

    from ssm_addon.formats.meshes import read_mesh, write_ply
    from ssm_addon.pipeline.project_build import build

    path = joint_project(tmp_path, 4)
    v, f = read_mesh(tmp_path / "S2_b.ply")
    if fault == "empty":
        write_ply(tmp_path / "S2_b.ply", np.zeros((0, 3)), np.zeros((0, 3), int), space="RAS")
    else:
        v = v.copy()
        v[:, 2] = 0.0
        write_ply(tmp_path / "S2_b.ply", v, f, space="RAS")
    t0 = time.perf_counter()
    with pytest.raises(InputError, match=rf"subject 'S2', structure 'b': .*S2_b.ply.*({fault}|no faces|empty)"):
        build(read_project(path), tmp_path / "out", log=None)
    assert time.perf_counter() - t0 < 60 and not (tmp_path / "out").exists()  # before any coating


def test_structures_the_inputs_put_inside_each_other_are_a_finding():
    """Every subject's b placed 8 mm into its a (b from another coordinate system, say): the data collide,
    so a finding names the inputs, not the model."""
    import numpy as np
    from conftest import joint_model, joint_population

    from ssm_addon.model.joint import collision_findings, collisions

    a, b, fa, fb, _t = joint_population(n=12)
    inside = b - [14.0, 0.0, 0.0]  # b's inner face 8 mm within a's outer one, in every subject
    model = joint_model(a, inside, fa, fb)
    figures = collisions(model, samples=30, depth_mm=0.5)
    assert figures["a-b"]["data"]["colliding_share"] == 1.0 and figures["a-b"]["data"]["max_mm"] > 5.0
    found = [f for f in collision_findings(figures, 0.2) if "the inputs put one inside the other" in f.message]
    assert found and found[0].gate == "collision" and "a-b" in found[0].message
    assert not [f for f in collision_findings(collisions(joint_model(a, b, fa, fb), samples=30), 0.2)
                if "inputs" in f.message]
    assert np.isfinite(found[0].value)


def test_every_option_that_takes_a_value_names_the_value():
    """Help a new user reads in one pass: an option's value is named for what it is (``FILE``,
    ``MM``, ``N``, ``NAME``…) or its choices are listed; never argparse's upper-cased option name
    (``--volume VOLUME``, ``--scheduler COMPUTE__SCHEDULER``)."""
    import argparse

    from ssm_addon.cli.command import argument_parser

    parser = argument_parser()
    subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    unnamed = []
    for command, sub in subparsers.choices.items():
        for action in sub._actions:
            if not action.option_strings or action.nargs == 0 or action.choices is not None:
                continue
            if isinstance(action, argparse._HelpAction | argparse.BooleanOptionalAction):
                continue
            if action.metavar is None:
                unnamed.append(f"ssm {command} {action.option_strings[-1]}")
    assert not unnamed, unnamed
