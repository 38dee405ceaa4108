"""Model-guided correspondence (``[correspondence] method = "model"``): landmark-light projects,
refinement rounds, landmarks carried over to every instance, and its bad inputs."""

from __future__ import annotations

import hashlib
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import project_variant, template_of

from ssm_addon.base.errors import InputError
from ssm_addon.cli import demo
from ssm_addon.correspondence.rounds import refine_instance, round_landmarks
from ssm_addon.formats.landmarks import read_landmarks
from ssm_addon.pipeline.project import read_project
from ssm_addon.pipeline.project_build import build

QUICK = {"spacing = 1.0": "spacing = 1.0\nr_min_mm = 4.0\nr_max_mm = 8.0",
         "[model]": "[model]\nspecificity_samples = 50"}


@pytest.fixture(scope="module")
def population(tmp_path_factory):
    """Six demo vertebrae, coarse template (seconds per build)."""
    folder = tmp_path_factory.mktemp("corr")
    path = demo.make_demo_population(folder / "population", n=6, seed=5)
    text = path.read_text()
    for a, b in QUICK.items():
        text = text.replace(a, b)
    path.write_text(text)
    return path


def _landmark_ext(path) -> str:
    """The extension of the template instance's landmark file (e.g. ``mrk.json``)."""
    project = read_project(path)
    spec = next(i for i in project.instances if i.name == project.template_instance)
    return spec.landmarks_path.name.split(".", 1)[1]


def _swap_two_landmarks(population, prefix: str):
    """The project text with one instance's first landmark swapped with its farthest one:
    (instance, its landmarks, the swapped points, the far index, the project text)."""
    from ssm_addon.formats.landmarks import LandmarkSet, write_landmarks

    tpl = template_of(population)
    victim = "demo_00" if tpl != "demo_00" else "demo_01"
    project = read_project(population)
    spec = next(i for i in project.instances if i.name == victim)
    lm = read_landmarks(spec.landmarks_path)
    pts = lm.points_world.copy()
    far = int(np.argmax(np.linalg.norm(pts - pts[0], axis=1)))
    pts[[0, far]] = pts[[far, 0]]
    swapped = population.parent / f"{prefix}_{victim}.fcsv"
    write_landmarks(swapped, LandmarkSet(lm.names, pts, victim))
    text = population.read_text().replace(f'landmarks = "{spec.landmarks_path.name}"', f'landmarks = "{swapped.name}"')
    return victim, lm, pts, far, text


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.slow
def test_landmarks_method_is_the_single_pass(population, tmp_path):
    """method = "landmarks" (the default) builds exactly what a project without the table builds."""
    build(read_project(population), tmp_path / "a", log=None)
    explicit = project_variant(population, "explicit.toml", correspondence='[correspondence]\nmethod = "landmarks"')
    build(read_project(explicit), tmp_path / "b", log=None)
    assert _sha(tmp_path / "a" / "model.npz") == _sha(tmp_path / "b" / "model.npz")
    doc = json.loads((tmp_path / "a" / "report.json").read_text())
    assert doc["correspondence"]["method"] == "landmarks" and doc["correspondence"]["rounds"] == []
    assert set(doc["correspondence"]["start"].values()) <= {"landmark warp", "object frames"}
    assert {n: f["start"] for n, f in doc["instances"].items()} == doc["correspondence"]["start"]
    # carried-over landmarks: written for every instance, in the template instance's format
    written = sorted(p.name for p in (tmp_path / "a" / "landmarks").iterdir())
    ext = _landmark_ext(population)
    assert written == [f"demo_{i:02d}.{ext}" for i in range(6)]
    # on the template instance they are its own landmarks, located on the template (< 1 voxel off)
    d = doc["correspondence"]["carried_landmark_distance_mm"][template_of(population)]
    assert max(d.values()) < 1.0, d


@pytest.mark.slow
def test_model_method_with_landmarks_on_the_template_only(population, tmp_path):
    """Only the template instance is landmarked: every other instance starts from the object
    frames, is refined with the model, and gets landmarks near its true (unused) ones."""
    tpl = template_of(population)
    proj = project_variant(population, "light.toml", correspondence='[correspondence]\nmethod = "model"\niterations = 2',
                    keep_landmarks={tpl})
    lines = []
    result = build(read_project(proj), tmp_path / "out", log=lines.append)
    doc = result.report
    corr = doc["correspondence"]
    assert corr["method"] == "model"
    assert all(s == "object frames" for s in corr["start"].values()), corr["start"]
    assert 1 <= len(corr["rounds"]) <= 2
    last = corr["rounds"][-1]
    assert set(last["instance_change_mm"]) == {f"demo_{i:02d}" for i in range(6)}
    assert sum(last["folds"].values()) == 0
    # exact landmarks (the default): the template instance's stay where given
    assert all(v == 0.0 for v in last["landmark_shift_mm"].values()), last["landmark_shift_mm"]
    # the self-check judges the rounds by the only landmarked instance
    check = corr["self_check"]
    assert set(check["instance_mm"]) == {tpl} and corr["stop"] in ("converged", "criterion", "limit")
    assert all(math.isfinite(r["transfer_before_mm"]) for r in corr["rounds"])
    assert any(line.startswith("correspondence round 1") for line in lines)
    # landmarks carried to the instances that had none, against the demo's true landmark files
    folder = population.parent
    errors = []
    for i in range(6):
        name = f"demo_{i:02d}"
        if name == tpl:
            continue
        truth_file = next(p for p in folder.iterdir() if p.stem.split(".")[0] == name and p.suffix != ".gz")
        truth = read_landmarks(truth_file).as_dict()
        ext = _landmark_ext(population)
        carried = read_landmarks(tmp_path / "out" / "landmarks" / f"{name}.{ext}")
        errors += [np.linalg.norm(p - truth[n]) for n, p in zip(carried.names, carried.points_world)]
    assert np.median(errors) < 2.5 and np.max(errors) < 8.0, np.round(errors, 2)
    assert corr["carried_landmark_distance_mm"].keys() == {tpl}


def test_model_method_needs_landmarks_on_the_template_instance(population, tmp_path):
    tpl = template_of(population)
    proj = project_variant(population, "nolm.toml", correspondence='[correspondence]\nmethod = "model"',
                    keep_landmarks={f"demo_{i:02d}" for i in range(6)} - {tpl})
    out = tmp_path / "out"
    with pytest.raises(InputError, match=rf"nolm.toml:\d+: \[template\] instance '{tpl}' has no landmarks"):
        build(read_project(proj), out, log=None)
    assert not out.exists()
    assert not list(tmp_path.glob(".out.building-*"))


@pytest.mark.slow
def test_landmarks_on_a_few_instances_under_the_default_method_use_the_model_method(population, tmp_path):
    """The default method with landmarks on the template instance only: the build no longer refuses
    ("missing key 'landmarks'"); it says that the model method supplies the others' and uses it."""
    tpl = template_of(population)
    proj = project_variant(population, "few.toml", keep_landmarks={tpl})
    lines = []
    result = build(read_project(proj), tmp_path / "out", log=lines.append, blend=False, cache="off")
    assert any(re.search(r"landmarks on 1 of 6 instances \(none on .*\): the model method supplies theirs", x)
               for x in lines), lines
    corr = result.report["correspondence"]
    assert len(corr["start"]) == 6 and corr["stop"] in ("converged", "criterion", "limit"), corr["stop"]


@pytest.mark.slow
def test_a_project_without_landmarks_builds_and_turns_a_turned_instance_back(population, tmp_path):
    """No instance has landmarks, and one instance lies turned by 180° about the scanner's z axis:
    its object frame (paired with the patient axes) does not turn with it, so the template is put on
    by the turn of its axes that fits the surface; the build says that no landmarks were given and
    what anchored the correspondence, and the model (rigid alignment, the default) has no frame
    finding: the turn is not modelled as shape."""
    import nibabel as nib

    folder = tmp_path / "pop"
    folder.mkdir()
    for f in population.parent.glob("demo_*.nii.gz"):
        img = nib.load(str(f))
        data = np.asarray(img.dataobj)
        if f.name == "demo_03.nii.gz":  # the voxels turned about the grid's third axis (scanner z, nearly)
            data = data[::-1, ::-1, :]
        nib.save(nib.Nifti1Image(data, img.affine), str(folder / f.name))
    text = re.sub(r'landmarks = "[^"]+"\n', "", population.read_text())
    (folder / "project.toml").write_text(text.replace('alignment = "none"', 'alignment = "rigid"'))
    lines = []
    result = build(read_project(folder / "project.toml"), tmp_path / "out", log=lines.append, blend=False,
                   cache="off")
    assert any(x.startswith("correspondence: no landmarks were given: the template was put onto every instance by "
                            "its object frame") for x in lines), lines
    choice = result.report["correspondence"]["template_choice"]
    starts = choice["starts"]
    assert starts["demo_03"]["turn"] == "turned about z", starts["demo_03"]
    # the template from the instance whose first coating is nearest the mean shape, said in report.html
    assert choice["by"] == "coatings" and choice["medoid"] in starts, choice
    assert result.report["correspondence"]["template_instance"] == (choice["medoid"] if choice["kept"] else
                                                                    choice["given"])
    page = (tmp_path / "out" / "report.html").read_text()
    assert f"coating is nearest the mean shape is {choice['medoid']}" in page
    # the others lie as their frames do: the input coordinates end in the frames' own basin, whose pose is
    # kept (the same for the inputs in any scanner pose)
    assert all(s["turn"] in ("frames", "input coordinates") for n, s in starts.items() if n != "demo_03"), starts
    assert all(abs(s["distances_mm"]["input coordinates"] - s["distances_mm"]["frames"]) < 0.05
               for n, s in starts.items() if n != "demo_03"), starts
    findings = result.report["quality"]["findings"]
    assert not [f for f in findings if f["gate"] == "frame"], findings
    with np.load(tmp_path / "out" / "model.npz", allow_pickle=False) as z:
        assert z["instance_points"].shape[0] == 6

    # landmarks on the template instance only (the model method's start from the object frames):
    # the turned instance's start is coated again in the turn that brings it to the others
    tpl = template_of(population)
    assert tpl != "demo_03", tpl  # the turned instance is not the template's
    text = population.read_text().replace('alignment = "none"', 'alignment = "rigid"')
    for f in population.parent.glob("demo_*"):
        if not f.name.endswith(".nii.gz") and f.name.startswith(tpl):
            (folder / f.name).write_bytes(f.read_bytes())
    blocks = text.split("[[instances]]")
    blocks = [blocks[0]] + [b if f'name = "{tpl}"' in b else re.sub(r'landmarks = "[^"]+"\n', "", b)
                            for b in blocks[1:]]
    (folder / "one.toml").write_text("[[instances]]".join(blocks))
    lines = []
    result = build(read_project(folder / "one.toml"), tmp_path / "one", log=lines.append, blend=False,
                   cache="off")
    assert any(x.startswith("correspondence: demo_03 its start from the object frames lay") for x in lines), lines
    findings = result.report["quality"]["findings"]
    assert not [f for f in findings if f["gate"] == "frame"], findings


@pytest.mark.slow
def test_landmarks_on_a_few_instances_start_the_rest_from_their_model(population, tmp_path):
    """Landmarks on the template instance and one other: the other four start from the
    model of those two coatings fitted to their surface (``start = "model fit"``), and
    their landmarks are carried near the true (unused) ones."""
    tpl = template_of(population)
    other = "demo_00" if tpl != "demo_00" else "demo_01"
    proj = project_variant(population, "few.toml", correspondence='[correspondence]\nmethod = "model"\niterations = 2',
                    keep_landmarks={tpl, other})
    lines = []
    result = build(read_project(proj), tmp_path / "out", log=lines.append)
    corr = result.report["correspondence"]
    assert {n: s for n, s in corr["start"].items() if s != "model fit"} == {tpl: "landmark warp", other: "landmark warp"}
    assert {s for n, s in corr["start"].items() if n not in (tpl, other)} == {"model fit"}, corr["start"]
    # one source of truth: each instance's own record says the same
    assert {n: f["start"] for n, f in result.report["instances"].items()} == corr["start"]
    assert any("2 by landmarks, 4 from the landmarked instances' model" in line for line in lines), lines
    assert corr["stop"] in ("converged", "criterion", "limit") and set(corr["self_check"]["instance_mm"]) == {tpl, other}
    if corr["stop"] == "limit":
        assert any(f.gate == "rounds" for f in result.study.findings)
    # the command, report.json and report.html say how the rounds ended
    assert any(line.startswith(f"correspondence: {corr['stop']}; kept") for line in lines), lines[-8:]
    page = (tmp_path / "out" / "report.html").read_text(encoding="utf-8")
    assert "<h2>Correspondence</h2>" in page and "Self-check: landmark transfer error" in page
    assert page.count("<td>kept</td>") + page.count("<td>dropped</td>") == len(corr["rounds"])
    folder = population.parent
    errors = []
    for i in range(6):
        name = f"demo_{i:02d}"
        if name in (tpl, other):
            continue
        truth_file = next(p for p in folder.iterdir() if p.stem.split(".")[0] == name and p.suffix != ".gz")
        truth = read_landmarks(truth_file).as_dict()
        carried = read_landmarks(tmp_path / "out" / "landmarks" / f"{name}.{_landmark_ext(population)}")
        errors += [np.linalg.norm(p - truth[n]) for n, p in zip(carried.names, carried.points_world)]
    print(f"carried landmarks: median {np.median(errors):.2f} mm, max {np.max(errors):.2f} mm")
    assert np.median(errors) < 2.5 and np.max(errors) < 8.0, np.round(errors, 2)


@pytest.mark.slow
def test_a_diverging_refinement_falls_back_to_the_start_and_says_so(population, tmp_path, monkeypatch):
    """A round whose mean shape jumps by more than the shapes' size is refused by name; the rounds
    are an optional refinement, so the build keeps the start's coatings and finishes, the
    divergence a fallback finding (it used to stop the build and write nothing)."""
    import ssm_addon.correspondence.rounds as corr

    real = corr.coat_mean_shape

    def runaway(*args, **kwargs):
        from dataclasses import replace

        coated = real(*args, **kwargs)
        return replace(coated, points_object=coated.points_object * 50.0)

    monkeypatch.setattr(corr, "coat_mean_shape", runaway)
    proj = project_variant(population, "diverge.toml",
                    correspondence='[correspondence]\nmethod = "model"\nround_template = "mean"')
    out = tmp_path / "out"
    result = build(read_project(proj), out, log=None)
    assert result.report["correspondence"]["stop"] == "failed"
    found = [f for f in result.report["quality"]["findings"] if f["gate"] == "fallback"]
    assert found and "diverged in round 1" in found[0]["message"] and "start's coatings" in found[0]["message"]
    assert (out / "model.npz").is_file() and result.study.template.is_mean_shape is False


@pytest.mark.slow
def test_model_method_keeps_the_template_points_on_the_template_instance(population, monkeypatch):
    """The mean shape's coating slides the template's points along the surfaces; the
    re-sampling puts them back: on the template instance point i ends at template point i.
    (Every round kept here, whatever the self-check says: the re-sampling is under test.)"""
    from scipy.spatial import cKDTree

    import ssm_addon.correspondence.rounds as corr
    from ssm_addon.pipeline.runner import run
    from ssm_addon.pipeline.study import Study

    monkeypatch.setattr(corr, "round_helps", lambda *args, **kwargs: True)

    proj = project_variant(population, "keep.toml",
                    correspondence='[correspondence]\nmethod = "model"\niterations = 2\nround_template = "mean"')
    study = Study.from_project(read_project(proj))
    run(study, stages=("import", "template"), jobs=2)
    template_points = study.template.points_object.copy()
    run(study, stages=("coating",), jobs=2)
    slide = study.correspondence_rounds[-1].sampling_slide_mm
    final = study.coatings[study.template_instance].points_object
    off = np.linalg.norm(final - template_points, axis=1)
    print(f"slide {slide:.3f} mm; template instance vs the template's points: mean {off.mean():.3f}, "
          f"max {off.max():.3f} mm")
    assert slide > 0.05 and off.mean() < 0.5 * slide
    assert np.array_equal(cKDTree(template_points).query(final)[1], np.arange(len(final)))
    assert study.template.is_mean_shape


@pytest.mark.slow
def test_a_round_moves_given_landmarks_by_the_share_it_is_given(population):
    """A round warps the template's landmarks onto the given ones moved ``shrink`` of the way
    to the other instances' prediction: exactly onto the given ones at 0 (exact landmarks),
    onto the prediction at 1, halfway at 0.5 (and says how far). One round of
    :func:`refine_instance` on the single pass's coatings."""
    from ssm_addon.base.params import CorrespondenceParams, FitParams
    from ssm_addon.pipeline.runner import run
    from ssm_addon.pipeline.study import Study

    assert CorrespondenceParams().landmark_noise_mm is None  # estimated by default
    study = Study.from_project(read_project(population))
    run(study, stages=("import", "template", "coating"), jobs=2)
    loc = study.template.landmark_locations
    faces = np.asarray(study.template.faces)
    names = list(study.names)
    points = np.stack([study.coatings[n].points_object for n in names])
    off, shifts = {0.0: [], 0.5: [], 1.0: []}, {0.0: [], 0.5: [], 1.0: []}
    for i, name in enumerate(names[:3]):
        lm = study.landmarks(name)
        given = dict(zip(lm.names, study.frame(name).to_object(lm.points_world)))
        found = round_landmarks(np.delete(points, i, axis=0), faces, study.volume(name), loc, given,
                                fit=FitParams(tolerance_mm=0.01), current=points[i], name=name)
        assert found.given.all() and np.allclose(found.warp, [given[n] for n in loc.names])
        for shrink in off:
            warp, shift = found.shrunk(shrink)
            target = np.array([given[n] for n in loc.names]) + shrink * found.difference
            np.testing.assert_allclose(warp, target, atol=1e-12)
            coated, _d, shift2, transfer = refine_instance(
                np.delete(points, i, axis=0), faces, study.template.points_object, study.volume(name), loc, given,
                fit=FitParams(tolerance_mm=0.01), coating=study.params.coating, shrink=shrink, current=points[i],
                name=name)
            assert shift2 == pytest.approx(shift)
            warped = loc.evaluate(coated.warped_points_object, faces)
            off[shrink].append(np.linalg.norm(warped - target, axis=1).mean())
            shifts[shrink].append(shift)
            if shrink == 0.0:
                assert coated.fit.warp_regularization == 0.0
            assert set(transfer) == set(lm.names) and all(math.isfinite(v) for v in transfer.values())
    # the warp puts the landmark points where the round asked (the barycentric reading: ~0.1 mm)
    assert max(max(v) for v in off.values()) < 0.4, off
    assert all(v == 0.0 for v in shifts[0.0]), shifts
    assert all(a == pytest.approx(2 * b) and a > 0 for a, b in zip(shifts[1.0], shifts[0.5])), shifts


@pytest.mark.slow
def test_a_swapped_landmark_is_named_by_the_self_check(population, tmp_path):
    """A swapped pair of landmarks: the landmark transfer self-check (the other instances'
    model predicts them elsewhere) names the instance and one of the two landmarks, in the
    single pass and in the model method (which estimates the landmarks' error, by default)."""
    victim, lm, pts, far, text = _swap_two_landmarks(population, "swapped2")
    for method in ("landmarks", "model"):
        proj = population.with_name(f"swapped-{method}.toml")
        proj.write_text(text.replace("[coating]", f'[correspondence]\nmethod = "{method}"\niterations = 2\n\n'
                                                  '[coating]'))
        lines = []
        result = build(read_project(proj), tmp_path / method, log=lines.append)
        named = [f for f in result.study.findings if f.gate == "landmark_transfer"]
        assert [f.instance for f in named] == [victim], [str(f) for f in result.study.findings]
        assert re.search(rf"given landmark '({lm.names[0]}|{lm.names[far]})'", named[0].message), named[0].message
        check = result.report["correspondence"]["self_check"]
        assert max(check["instance_mm"], key=check["instance_mm"].get) == victim
        assert any(victim in line and "landmark_transfer" in line for line in lines), lines[-5:]


def test_a_swapped_landmark_is_named_although_the_model_corrects_it(population, tmp_path):
    """With rough landmarks (``landmark_noise_mm = 3``) the model method moves them towards
    the fit's estimate, so a landmark the user swapped with another may be corrected; kept or
    not, the coating lies far from the given landmark, and the landmark-residual gate names
    the instance (against the given landmarks, not the estimate) and the landmark."""
    victim, lm, pts, far, text = _swap_two_landmarks(population, "swapped")
    proj = population.with_name("swapped.toml")
    proj.write_text(text.replace("[coating]", '[correspondence]\nmethod = "model"\niterations = 2\n'
                                              'landmark_noise_mm = 3.0\n\n[coating]'))
    result = build(read_project(proj), tmp_path / "out", log=None)
    gap = float(np.linalg.norm(pts[0] - pts[far]))
    named = [f for f in result.study.findings if f.gate == "landmark_residual"]
    assert [f.instance for f in named] == [victim], (gap, [str(f) for f in result.study.findings])
    # the swapped pair is where the coating is far from the given landmarks
    res = result.study.coatings[victim].fit.landmark_residuals_mm
    dist = result.report["correspondence"]["carried_landmark_distance_mm"][victim]
    print(f"swapped {gap:.1f} mm apart; coating to the given landmarks: {np.round(sorted(dist.values()), 1)}")
    assert max(res) == pytest.approx(max(dist.values())) and max(res) > 0.5 * gap, (gap, dist)
    assert set(sorted(dist, key=dist.get)[-2:]) == {lm.names[0], lm.names[far]}, (gap, dist)
    assert re.search(rf"from given landmark '({lm.names[0]}|{lm.names[far]})'", named[0].message), named[0].message


@pytest.mark.slow
@pytest.mark.parametrize("template_choice", ["landmark-medoid", "medoid"])
def test_an_optional_refinement_that_fails_falls_back_and_the_build_finishes(population, tmp_path, monkeypatch,
                                                                             template_choice):
    """The medoid's template (either choice) is a refinement: when its triangulation fails (forced
    here), the build keeps the given template, says so by name, and finishes; the same for rounds
    that fail."""
    from ssm_addon.base.errors import SSMError
    from ssm_addon.pipeline import model_method
    from ssm_addon.pipeline.runner import run
    from ssm_addon.pipeline.study import Study

    project = project_variant(population, "medoid.toml", correspondence=(
        f'[correspondence]\nmethod = "model"\niterations = 1\nround_template = "mean"\n'
        f'template_choice = "{template_choice}"'))
    if template_choice == "medoid":
        medoid = template_of(project)  # this population's medoid gives the template: start from another instance
    else:
        study = Study.from_project(read_project(project))
        run(study, stages=("import", "template"))
        medoid, _d = model_method.landmark_medoid(study, list(study.names))
    given = next(i.name for i in read_project(project).instances if i.name != medoid)
    project.write_text(re.sub(r'instance = "[^"]+"', f'instance = "{given}"', project.read_text(), count=1))
    real = model_method.make_template

    def failing_for_others(study, **kw):
        if study.template_instance != given:
            raise SSMError("triangulation: cannot refine further (failing regions have no free vertex)")
        return real(study, **kw)

    monkeypatch.setattr(model_method, "make_template", failing_for_others)
    result = build(read_project(project), tmp_path / "out", log=None)
    choice = result.report["correspondence"]["template_choice"]
    assert choice.get("medoid") and choice["medoid"] != given, choice  # the medoid was another instance: it was tried
    assert choice["kept"] is False and "cannot refine further" in choice["failed"]
    found = [f for f in result.report["quality"]["findings"] if f["gate"] == "fallback"]
    assert found and found[0]["instance"] == choice["medoid"] and given in found[0]["message"]
    assert result.study.template_instance == given and (tmp_path / "out" / "model.npz").is_file()

    def failing_rounds(*_a, **_kw):
        raise SSMError("model-guided correspondence diverged in round 1")

    monkeypatch.setattr(model_method, "refine_rounds", failing_rounds)
    result = build(read_project(project), tmp_path / "out2", log=None)
    assert result.report["correspondence"]["stop"] == "failed"
    assert any(f["gate"] == "fallback" and "rounds failed" in f["message"] for f in result.report["quality"]["findings"])
    assert (tmp_path / "out2" / "model.npz").is_file()


def test_the_model_method_computes_each_distance_map_once_and_gives_the_same_coatings(population, monkeypatch):
    """The start, the medoid's template and the rounds coat every instance again; each
    instance's distance map is computed once (kept in the build's scratch folder) and the
    coatings are those of computing it every time, bit for bit. The folder goes with the
    build and the study keeps its own volumes."""
    import contextlib
    import tempfile

    import ssm_addon.pipeline.model_method as mm
    from ssm_addon.coating.distance_map import DistanceMap
    from ssm_addon.pipeline.runner import run
    from ssm_addon.pipeline.study import Study

    built = []
    real_build = DistanceMap._build.__func__
    monkeypatch.setattr(DistanceMap, "_build", classmethod(lambda cls, ov, band: built.append(ov.source) or
                                                           real_build(cls, ov, band)))
    proj = project_variant(population, "kept.toml", correspondence=('[correspondence]\nmethod = "model"\n'
                                                                      'iterations = 1\nround_template = "mean"'))

    def coat(study):
        run(study, stages=("import", "template"), jobs=1)
        volumes = dict(study.volumes)
        del built[:]
        run(study, stages=("coating",), jobs=1)
        assert all(study.volumes[n] is v for n, v in volumes.items())
        return {n: c.points_object for n, c in study.coatings.items()}, list(built)

    folders, real_kept = [], mm.distance_maps_kept

    @contextlib.contextmanager
    def recorded(study):
        with real_kept(study) as folder:
            folders.append(Path(folder))
            yield folder

    monkeypatch.setattr(mm, "distance_maps_kept", recorded)
    kept, kept_builds = coat(Study.from_project(read_project(proj)))
    assert len(folders) == 1 and folders[0].parent == Path(tempfile.gettempdir()) and not folders[0].exists()
    monkeypatch.setattr(mm, "distance_maps_kept", lambda _study: contextlib.nullcontext(""))
    every_time, builds = coat(Study.from_project(read_project(proj)))
    print(f"distance maps computed: {len(kept_builds)} kept, {len(builds)} without")
    assert sorted(kept_builds) == sorted(set(builds)) and len(set(kept_builds)) == 6
    assert len(builds) >= 2 * len(kept_builds)
    assert kept.keys() == every_time.keys()
    assert all(np.array_equal(kept[n], every_time[n]) for n in kept)


def test_the_workers_compute_the_distance_maps_while_the_template_is_made(population, monkeypatch):
    """With local worker processes the model method's distance maps are computed on the workers
    while this process builds the template, into the folder its coatings read: every map is
    there before the first coating, the coatings equal the serial build's bit for bit, and the
    folder goes with the build."""
    import os
    import sys
    import time

    import ssm_addon.pipeline.runner as runner
    from ssm_addon.base.compute import Executor
    from ssm_addon.pipeline.study import Study

    proj = project_variant(population, "ahead.toml", correspondence=('[correspondence]\nmethod = "model"\n'
                                                                       'iterations = 1\nround_template = "mean"'))
    serial = runner.run(Study.from_project(read_project(proj)), jobs=1)
    folders, maps, real = [], [], runner.refine_correspondence

    def coating(study, **kw):  # the maps ahead: all there before the first coating (the workers finish them)
        folder = Path(next(iter(study.volumes.values())).distance_map_store)
        deadline = time.monotonic() + 120
        while len([f for f in os.listdir(folder) if f.endswith(".npy")]) < len(study.names):
            assert time.monotonic() < deadline, os.listdir(folder)
            time.sleep(0.05)
        folders.append(folder)
        maps.append(len(os.listdir(folder)))
        return real(study, **kw)

    monkeypatch.setattr(runner, "refine_correspondence", coating)
    monkeypatch.delitem(sys.modules, "bpy", raising=False)
    with Executor("processes", 2) as ex:
        ahead = runner.run(Study.from_project(read_project(proj)), jobs=2, executor=ex)
    assert maps == [len(ahead.names)] and not folders[0].exists()
    assert all(v.distance_map_store in (None, "") for v in ahead.volumes.values())
    assert ahead.coatings.keys() == serial.coatings.keys()
    for name in serial.coatings:
        assert np.array_equal(ahead.coatings[name].points_object, serial.coatings[name].points_object), name


def assert_same_model(a, b):
    """Two builds' ``model.npz``: the same arrays, each equal to the last bit."""
    a, b = (np.load(r.out_dir / "model.npz", allow_pickle=False) for r in (a, b))
    assert sorted(a.files) == sorted(b.files)
    for key in a.files:
        assert np.array_equal(a[key], b[key]), key


def test_the_landmark_medoid_is_the_configuration_nearest_the_mean_in_any_frame():
    """``landmark_medoid``: the instance whose given landmarks are nearest their mean (RMS, mm),
    the same when one instance's landmarks are turned and moved (object frames that disagree),
    ties to the earlier instance."""
    from types import SimpleNamespace

    from ssm_addon.pipeline.model_method import landmark_medoid

    rng = np.random.default_rng(4)
    base = rng.normal(scale=20.0, size=(8, 3))
    offsets = rng.normal(scale=1.5, size=(2, 8, 3))
    configs = {"a": base + offsets[0], "b": base - offsets[0], "c": base + offsets[1], "d": base - offsets[1],
               "m": base.copy()}  # "m" is the mean of the others
    names = tuple(f"L{k}" for k in range(8))

    def study_of(cfg):
        return SimpleNamespace(names=list(cfg), template_instance="a",
                               template=SimpleNamespace(landmark_locations=SimpleNamespace(names=names)),
                               landmarks_object=lambda n: dict(zip(names, cfg[n])))

    medoid, distance = landmark_medoid(study_of(configs), list(configs))
    assert medoid == "m" and distance["m"] < 0.2 * min(d for n, d in distance.items() if n != "m"), distance
    q, _r = np.linalg.qr(rng.normal(size=(3, 3)))
    turned = dict(configs, c=configs["c"] @ (q * np.sign(np.linalg.det(q))).T + [40.0, -7.0, 3.0])
    again, moved = landmark_medoid(study_of(turned), list(turned))
    assert again == "m" and all(abs(moved[n] - distance[n]) < 1e-9 for n in configs)
    twins = dict(configs, e=configs["m"].copy())  # "m" and "e" alike: the earlier wins
    assert landmark_medoid(study_of(twins), list(twins))[0] == "m"
    assert landmark_medoid(study_of({"e": twins["e"], **configs}), ["e", *configs])[0] == "e"


def _template_points(project) -> int:
    """The point count of the template the project's parameters give its [template] instance."""
    from ssm_addon.pipeline.runner import run
    from ssm_addon.pipeline.study import Study

    study = Study.from_project(read_project(project))
    run(study, stages=("import", "template"))
    return len(study.template.points_object)


def test_the_landmark_medoid_template_is_chosen_before_the_first_coating(population, tmp_path, monkeypatch):
    """``template_choice = "landmark-medoid"``: the template is built from the instance whose landmarks
    are nearest their mean before any coating, with the given template's point count (within 2 %: the
    same radii give another instance another count), and every instance is coated once for the start."""
    from ssm_addon.pipeline import model_method
    from ssm_addon.pipeline.runner import run
    from ssm_addon.pipeline.study import Study

    corr = '[correspondence]\nmethod = "model"\niterations = 1\ntemplate_choice = "{}"'
    project = project_variant(population, "lm_medoid.toml", correspondence=corr.format("landmark-medoid"))
    study = Study.from_project(read_project(project))
    run(study, stages=("import", "template"))
    medoid, _d = model_method.landmark_medoid(study, list(study.names))
    if medoid == study.template_instance:  # start from another instance, so that the choice changes the template
        other = next(n for n in study.names if n != medoid)
        project.write_text(re.sub(r'instance = "[^"]+"', f'instance = "{other}"', project.read_text(), count=1))
    starts = []
    real = model_method.start_coatings

    def counted(study_, names=None, **kw):
        starts.append((study_.template_instance, list(names)))
        return real(study_, names, **kw)

    monkeypatch.setattr(model_method, "start_coatings", counted)
    result = build(read_project(project), tmp_path / "chosen", log=None)
    choice = result.report["correspondence"]["template_choice"]
    assert choice["by"] == "landmarks" and choice["medoid"] == medoid and choice["kept"] is True, choice
    assert result.study.template_instance == medoid
    assert starts == [(medoid, list(study.names))], starts  # one start pass, from the medoid's template
    given_points = _template_points(project)
    assert abs(result.report["template"]["points"] / given_points - 1) <= 0.02, (result.report["template"],
                                                                                given_points)


@pytest.mark.slow
def test_the_medoid_route_starts_from_the_landmark_medoid_and_falls_back_to_the_given_template(population, tmp_path,
                                                                                            monkeypatch):
    """``template_choice = "medoid"`` (the default) tries the landmark medoid first: when the
    coatings of its template have that instance nearest their mean shape, the study is coated
    once (no second pass, no comparison) with the given template's point count; when they name
    another instance, the route from the given template runs as it does without the guess, and the
    model is that route's, array for array."""
    from ssm_addon.pipeline import model_method
    from ssm_addon.pipeline.runner import run
    from ssm_addon.pipeline.study import Study

    corr = '[correspondence]\nmethod = "model"\niterations = 1\ntemplate_choice = "{}"'
    project = project_variant(population, "confirmed.toml", correspondence=corr.format("medoid"))
    study = Study.from_project(read_project(project))
    run(study, stages=("import", "template"))
    medoid, _d = model_method.landmark_medoid(study, list(study.names))
    if medoid == study.template_instance:  # start from another instance, so that the guess is tried
        other = next(n for n in study.names if n != medoid)
        project.write_text(re.sub(r'instance = "[^"]+"', f'instance = "{other}"', project.read_text(), count=1))
    given = template_of(project)
    starts = []
    real_starts, real_medoid = model_method.start_coatings, model_method.population_medoid

    def counted(study_, names=None, **kw):
        starts.append(study_.template_instance)
        return real_starts(study_, names, **kw)

    monkeypatch.setattr(model_method, "start_coatings", counted)
    confirmed = build(read_project(project), tmp_path / "confirmed", log=None)
    choice = confirmed.report["correspondence"]["template_choice"]
    print(f"landmark medoid {medoid}, given {given}: {choice}")
    assert choice.get("confirmed") is True, choice  # this population confirms its landmark medoid
    assert choice["medoid"] == choice["coatings_medoid"] == medoid and choice["given"] == given, choice
    assert confirmed.study.template_instance == medoid and starts == [medoid], starts  # one start pass
    assert abs(confirmed.report["template"]["points"] / _template_points(project) - 1) <= 0.02

    # the coatings of the landmark medoid's template have another instance nearest their mean,
    # beyond a tie: the guess is dropped
    def elsewhere(study_, candidates):
        found, distance = real_medoid(study_, candidates)
        if study_.template_instance == medoid:
            other = next(n for n in candidates if n != medoid)
            return other, {**distance, other: distance[medoid] / (model_method.MEDOID_TIE + 0.01)}
        return found, distance

    monkeypatch.setattr(model_method, "population_medoid", elsewhere)
    del starts[:]
    dropped = build(read_project(project), tmp_path / "dropped", log=None)
    choice = dropped.report["correspondence"]["template_choice"]
    guess = choice["landmark_medoid"]
    assert guess["medoid"] == medoid and guess["confirmed"] is False and guess["coatings_medoid"] != medoid, choice
    assert starts[:2] == [medoid, given], starts  # the guess, then the given template's route
    monkeypatch.setattr(model_method, "confirmed_landmark_medoid", lambda study_, **_kw: (study_, {}))
    without = build(read_project(project), tmp_path / "without", log=None)
    route = without.report["correspondence"]["template_choice"]
    assert {k: v for k, v in choice.items() if k != "landmark_medoid"} == route
    assert dropped.study.template_instance == without.study.template_instance
    assert_same_model(dropped, without)


def test_a_template_from_another_instance_keeps_the_given_templates_point_count(population):
    """The medoid's template has the given template's point count within 2 %: the same radii give
    another instance another count (eq. 1 follows its curvature), so they are scaled until it does;
    the study's parameters stay as given."""
    from ssm_addon.pipeline.model_method import POINT_COUNT_TOLERANCE, template_of_count
    from ssm_addon.pipeline.runner import run
    from ssm_addon.pipeline.study import Study

    study = Study.from_project(read_project(population))
    run(study, stages=("import", "template"))
    given = len(study.template.points_object)
    params = study.params.template
    for other in ("demo_00", "demo_02", "demo_05"):
        if other == study.template_instance:
            continue
        work = Study(instances=study.instances, template_instance=other, params=study.params, volumes=study.volumes)
        target = int(round(given * 1.3))  # a count the radii as given do not reach
        template = template_of_count(work, target)
        assert abs(len(template.points_object) / target - 1) <= POINT_COUNT_TOLERANCE, (other, len(template.points_object), target)
        assert work.params.template == params
