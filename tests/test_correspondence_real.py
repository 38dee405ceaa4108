"""Correspondence on real bones with dense truth (``../shared/data``): femur10 and knee30.

Every mesh of a set shares one connectivity, so the true place of a template point on
another instance is the same place of that instance's mesh. Landmarks are farthest-point
samples of the template instance's vertices, at their true places on the others. The
error of a coating is the distance of its points from their true places (mm): not a
surface distance. Skipped where the data is absent (a user's fresh clone).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_data_dir

from ssm_addon.base.params import CorrespondenceParams, StudyParams
from ssm_addon.formats.landmarks import LandmarkSet, read_landmarks, write_landmarks
from ssm_addon.formats.meshes import read_mesh
from ssm_addon.instances.importing import InstanceSpec
from ssm_addon.meshutil import MeshLocation, MeshLocator
from ssm_addon.pipeline.runner import run
from ssm_addon.pipeline.study import Study

DATA = shared_data_dir()

pytestmark = pytest.mark.slow


def _meshes(folder: Path, pattern: str, limit: int | None = None):
    files = sorted(folder.glob(pattern))[:limit]
    if len(files) < 3:
        pytest.skip(f"dense-truth meshes {pattern} not found under {folder} (set SSM_SHARED_DATA)")
    return files, [read_mesh(f) for f in files]


def _farthest(points: np.ndarray, k: int) -> np.ndarray:
    chosen = [int(np.argmax(points[:, 2]))]
    d = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(k - 1):
        chosen.append(int(np.argmax(d)))
        d = np.minimum(d, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return np.array(chosen)


_BUILT = {}


def _build(files, meshes, tmp_path, *, landmarks: int, on: int, method: str, jitter_mm: float = 0.0,
           choice: str = "medoid"):
    """A study coated by ``method``; returns (study, per-instance true error mean in mm, all errors).
    ``jitter_mm``: Gaussian click error per axis of every instance's landmarks but the template's.
    The last two builds are kept for a later test of this process that asks for the same inputs (the
    femurs unmoved without landmarks, in scanner poses and beside their mirror images; the tests read a
    study, never change it)."""
    key = (tuple(str(f) for f in files), landmarks, on, method, jitter_mm, choice)
    if key not in _BUILT:
        _BUILT[key] = _built(files, meshes, tmp_path, landmarks=landmarks, on=on, method=method, jitter_mm=jitter_mm,
                             choice=choice)
        while len(_BUILT) > 2:
            _BUILT.pop(next(iter(_BUILT)))
    return _BUILT[key]


def _built(files, meshes, tmp_path, *, landmarks: int, on: int, method: str, jitter_mm: float, choice: str):
    v0 = meshes[0][0]
    idx = _farthest(v0, landmarks)
    rng = np.random.default_rng(0)
    specs = []
    for i, (f, (v, _f)) in enumerate(zip(files, meshes)):
        lm = None
        if i < on:
            lm = tmp_path / f"{method}-{on}-{jitter_mm}-{f.stem}.csv"
            clicks = v[idx] + (rng.normal(scale=jitter_mm, size=(len(idx), 3)) if i else 0.0)
            write_landmarks(lm, LandmarkSet(tuple(f"L{j:02d}" for j in range(len(idx))), clicks, f.stem))
        specs.append(InstanceSpec(name=f.stem, mesh_path=f, landmarks_path=lm, landmarks=read_landmarks(lm) if lm else None))
    study = Study(instances=specs, template_instance=files[0].stem,
                  params=StudyParams(correspondence=CorrespondenceParams(method=method, template_choice=choice)))
    run(study, stages=("import", "template", "coating"), jobs=2)
    # the model method may build its template again from another instance (the medoid)
    t = [f.stem for f in files].index(study.template_instance)
    vt, ft = meshes[t]
    _c, _d, tri, bary = MeshLocator(vt, ft).query(study.frame(files[t].stem).to_world(study.template.points_object), k=12)
    truth = MeshLocation(tri, bary)
    errors = {f.stem: np.linalg.norm(study.frame(f.stem).to_world(study.coatings[f.stem].points_object)
                                     - truth.evaluate(v, ft), axis=1) for f, (v, _f) in zip(files, meshes)}
    return study, errors


def test_model_method_at_its_defaults_is_no_worse_than_the_single_pass_on_femur10(tmp_path):
    """15 exact landmarks on all ten femurs: the model method keeps a round only when the
    landmark transfer error falls, so it ends no worse than the single pass (mean and 95th
    percentile), and its rounds end by the tolerance or by the criterion, never silently
    at the limit."""
    files, meshes = _meshes(DATA / "femur10", "femur*.ply")
    single, e_single = _build(files, meshes, tmp_path, landmarks=15, on=len(files), method="landmarks")
    model, e_model = _build(files, meshes, tmp_path, landmarks=15, on=len(files), method="model")
    a, b = np.concatenate(list(e_single.values())), np.concatenate(list(e_model.values()))
    print(f"femur10 single pass {a.mean():.3f} / {np.percentile(a, 95):.2f} mm, model method {b.mean():.3f} / "
          f"{np.percentile(b, 95):.2f} mm; stop {model.correspondence_check.stop}, kept round "
          f"{model.correspondence_check.kept_round}")
    assert b.mean() <= a.mean() + 0.01 and np.percentile(b, 95) <= np.percentile(a, 95) + 0.05
    # absolute too (a frame bug that ruined both would pass the comparison): measured 2.341 / 6.90 mm and
    # 1.710 / 4.12 mm, landmarks of 15 exact points on every femur
    assert a.mean() < 2.6 and np.percentile(a, 95) < 7.6
    assert b.mean() < 1.9 and np.percentile(b, 95) < 4.6
    # femur00 is farther from the mean femur than femur07, whose template takes its place (paper 3.3)
    assert model.template_instance != files[0].stem and b.mean() < 0.85 * a.mean()
    check = model.correspondence_check
    assert check.stop in ("converged", "criterion"), check.stop  # at the defaults the rounds end by themselves
    assert not any(f.gate == "rounds" for f in model.findings)
    # the single pass measured the same self-check; it ranks the instances by their true error
    from scipy.stats import spearmanr

    assert single.correspondence_check is not None and set(single.correspondence_check.instance_mm) == set(e_single)
    names = [n for n in e_single if n != single.template_instance]
    rho, p = spearmanr([e_single[n].mean() for n in names], [single.correspondence_check.instance_mm[n] for n in names])
    print(f"self-check rank correlation with the true error across instances: {rho:.2f} (p = {p:.3f})")
    assert rho >= 0.55  # measured 0.62 over 9 instances; a self-check blind to the error gives this 6 % of the time


def test_knee30_patellas_frames_and_landmarks_on_three(tmp_path):
    """Patellas are near-symmetric: their moments frames flip (the frame gate names the
    instances, and the self-check sees through it, aligning by correspondence). With
    landmarks on 3 of 12, the rest start from the model of those three (poses tried by the
    axis turns, the input coordinates preferred, the fitted shape relaxed onto the surface) and
    land within 1.3× of the single pass with landmarks on all."""
    files, meshes = _meshes(DATA / "knee30", "*_Patella.ply", limit=12)
    single, e_single = _build(files, meshes, tmp_path, landmarks=15, on=len(files), method="landmarks")
    # the frame gate watches the paper's object-frame alignment (the default, "rigid", aligns frames away)
    single.params = single.params.replace(model=dataclasses.replace(single.params.model, alignment="none"))
    run(single, stages=("model",))
    turned = {f.instance for f in single.findings if f.gate == "frame"}
    print(f"frame gate: {sorted(turned)}; self-check {single.correspondence_check.study_mm:.2f} mm")
    assert turned, "no patella frame flipped: the fixture no longer tests the frame gate"
    assert single.correspondence_check.study_mm < 2.0
    few, e_few = _build(files, meshes, tmp_path, landmarks=15, on=3, method="model")
    a, b = np.concatenate(list(e_single.values())), np.concatenate(list(e_few.values()))
    starts = set(few.coating_start[f.stem] for f in files[3:])
    print(f"patellas: landmarks on all {a.mean():.3f} mm, on 3 {b.mean():.3f} mm (worst {b.max():.1f}); {starts}")
    assert starts == {"model fit"}
    assert b.mean() < 1.3 * a.mean() and b.max() < 10.0


def test_clicked_landmarks_are_denoised_by_the_population_on_knee30_patellas(tmp_path):
    """Landmarks clicked 1.5 mm off per axis on 29 of 30 patellas: the model method estimates the
    click error (about 1.5 mm) and the model's, moves the clicks towards the population's
    prediction, keeps the round, and ends closer to the true correspondence than the single pass
    (mean and 95th percentile); with exact clicks it moves nothing."""
    files, meshes = _meshes(DATA / "knee30", "*_Patella.ply")
    single, e_single = _build(files, meshes, tmp_path, landmarks=15, on=len(files), method="landmarks", jitter_mm=1.5)
    model, e_model = _build(files, meshes, tmp_path, landmarks=15, on=len(files), method="model", jitter_mm=1.5)
    a, b = np.concatenate(list(e_single.values())), np.concatenate(list(e_model.values()))
    first = model.correspondence_rounds[0]
    print(f"patellas, clicks 1.5 mm off: single pass {a.mean():.3f} / {np.percentile(a, 95):.2f} mm, model method "
          f"{b.mean():.3f} / {np.percentile(b, 95):.2f} mm; estimated {first.landmark_noise}")
    assert 1.2 < first.landmark_noise.click_mm < 1.8 and first.landmark_noise.shrink > 0.5
    assert model.correspondence_check.kept_round >= 1
    assert b.mean() < 0.9 * a.mean() and np.percentile(b, 95) < 0.9 * np.percentile(a, 95)
    exact, e_exact = _build(files, meshes, tmp_path, landmarks=15, on=len(files), method="model")
    assert all(r.landmark_noise.shrink == 0.0 or not r.kept for r in exact.correspondence_rounds)


def test_femurs_in_scanner_poses_without_landmarks_are_coated_as_unmoved(tmp_path):
    """Five femurs of femur10, each in its own random scanner pose (any axis, up to 180°) as 3D Slicer
    writes it (LPS PLY), no landmarks: the start's registration from every rotation of the frame's
    axes finds each femur however its moments axes were paired with the patient's, so every coating
    lies within 4 mm (mean) of its true places and the set within 10 % of the same femurs unmoved
    (before this start: femur03 coated end for end, 249 mm, in the coating alone)."""
    from foreign_data import random_rigid, slicer_ply

    files, meshes = _meshes(DATA / "femur10", "femur*.ply", limit=5)
    rng = np.random.default_rng(7)
    moved_files, moved = [], []
    for f, (v, faces) in zip(files, meshes):
        rot, shift = random_rigid(rng, shift_mm=200.0)
        w = v @ rot.T + shift
        moved_files.append(slicer_ply(tmp_path / f.name, w, faces))
        moved.append((w, faces))
    _study, unmoved = _build(files, meshes, tmp_path, landmarks=0, on=0, method="landmarks")
    _study, posed = _build(moved_files, moved, tmp_path, landmarks=0, on=0, method="landmarks")
    per = {n: float(e.mean()) for n, e in posed.items()}
    a, b = np.concatenate(list(unmoved.values())).mean(), np.concatenate(list(posed.values())).mean()
    change = {n: round(per[n] - float(unmoved[n].mean()), 3) for n in per}
    print(f"femurs without landmarks: unmoved {a:.3f} mm, in scanner poses {b:.3f} mm; {per}; per femur {change}")
    assert max(per.values()) < 4.0, per
    assert b < 1.1 * a, (a, b)
    # each femur's coating lands as near its truth as unmoved (the object grids differ by the frames' voxel
    # noise, so the coatings are not the same points: measured within 0.11 mm on femur10 in three pose sets)
    assert max(abs(c) for c in change.values()) < 0.25, change



def test_without_landmarks_the_template_comes_from_the_medoid_and_the_points_land_nearer(tmp_path):
    """knee30 tibias, no landmarks. What a coating leaves wrong grows with the instance's difference
    from the template's shape, so the template is built again from the instance whose first coating
    is nearest the mean shape and every tibia coated from it. S001 with S010-S025 (S001 lies 1.5x as
    far from the mean as S021): the points land nearer their true places than from the given S001
    (mean; measured 1.303 -> 1.250 mm, 95th percentile 2.68 -> 2.77; all 30 tibias 1.359 -> 1.279,
    2.82 -> 2.78). The first twelve (S001 is the truth's medoid, S012 a near tie that the coatings put
    8.8 % nearer): within the tie, the given template is kept and nothing is coated twice."""
    files, meshes = _meshes(DATA / "knee30", "*_Tibia.ply")
    chosen = [i for i, f in enumerate(files) if f.stem == "S001_Tibia" or 10 <= int(f.stem[1:4]) <= 25]
    files, meshes = [files[i] for i in chosen], [meshes[i] for i in chosen]
    given, e_given = _build(files, meshes, tmp_path, landmarks=0, on=0, method="landmarks", choice="given")
    medoid, e_medoid = _build(files, meshes, tmp_path, landmarks=0, on=0, method="landmarks")
    a, b = np.concatenate(list(e_given.values())), np.concatenate(list(e_medoid.values()))
    choice = medoid.template_choice
    print(f"tibias without landmarks: from {files[0].stem} {a.mean():.3f} / {np.percentile(a, 95):.2f} mm, from the "
          f"medoid {medoid.template_instance} {b.mean():.3f} / {np.percentile(b, 95):.2f} mm; {choice['rms_from_mean_mm']}")
    assert given.template_instance == files[0].stem and given.template_choice.get("medoid") is None
    assert choice["by"] == "coatings" and choice["kept"] and medoid.template_instance == choice["medoid"] != files[0].stem
    assert b.mean() < 0.97 * a.mean() and np.percentile(b, 95) < 1.05 * np.percentile(a, 95), (a.mean(), b.mean())
    files, meshes = _meshes(DATA / "knee30", "*_Tibia.ply", limit=12)
    near, _e = _build(files, meshes, tmp_path, landmarks=0, on=0, method="landmarks")
    tie = near.template_choice
    assert not tie["kept"] and near.template_instance == files[0].stem and tie["medoid"] != files[0].stem, tie
    rms = tie["rms_from_mean_mm"]
    assert rms[files[0].stem] <= tie["tie"] * rms[tie["medoid"]], tie


def _mirror_some(files, meshes, folder: Path, which=(1, 3)):
    """The meshes with those of ``which`` mirrored left <-> right (world x), their triangles turned to face
    outwards, written as PLY into ``folder``: a set of left and right femurs; the mirrored vertices are
    the truth's (the same order)."""
    from ssm_addon.formats.meshes import write_ply

    out_files, out = [], []
    for i, (f, (v, faces)) in enumerate(zip(files, meshes)):
        if i in which:
            v, faces = v * np.array([-1.0, 1.0, 1.0]), faces[:, ::-1]
            f = write_ply(folder / f.name, v, faces, space="RAS") or folder / f.name
        out_files.append(Path(f))
        out.append((v, faces))
    return out_files, out


def test_left_and_right_femurs_are_coated_as_one_side_and_written_in_their_own(tmp_path):
    """Five femurs of femur10, the 2nd and 4th mirrored into right femurs. Without landmarks the surface
    finds the two mirror images, with 15 landmarks the landmarks do; each is mirrored into the template's
    side before coating, so the set's true error is within 5 % of the same femurs all of one side (before:
    a right femur could only be turned, never reflected). A project that gives the sides builds the same,
    writes each coating in its own side (on its own mesh, facing outwards) and says which it mirrored."""
    import json

    from ssm_addon.meshutil import signed_volume
    from ssm_addon.pipeline.project import read_project
    from ssm_addon.pipeline.project_build import build

    files, meshes = _meshes(DATA / "femur10", "femur*.ply", limit=5)
    (tmp_path / "mixed").mkdir()
    mfiles, mmeshes = _mirror_some(files, meshes, tmp_path / "mixed")
    names = [f.stem for f in files]
    for landmarks, by in ((0, "surface"), (15, "landmarks")):
        _s, plain = _build(files, meshes, tmp_path, landmarks=landmarks, on=len(files) if landmarks else 0,
                           method="landmarks")
        study, mixed = _build(mfiles, mmeshes, tmp_path, landmarks=landmarks, on=len(files) if landmarks else 0,
                              method="landmarks")
        a, b = np.concatenate(list(plain.values())).mean(), np.concatenate(list(mixed.values())).mean()
        print(f"femurs, {landmarks} landmarks: one side {a:.3f} mm, 2 of 5 mirrored {b:.3f} mm")
        assert {n for n, d in study.sides.items() if d.mirror} == {names[1], names[3]}, study.sides
        assert all(d.by == by for d in study.sides.values()), study.sides
        assert b < 1.05 * a, (landmarks, a, b)
    lines = [f"[template]\ninstance = {names[0]!r}\n", "[correspondence]\noptimise = false\n",
             "[model]\nspecificity_samples = 20\n"]
    for i, f in enumerate(mfiles):
        lines.append(f'[[instances]]\nname = "{f.stem}"\nmesh = "{f}"\nside = "{"right" if i in (1, 3) else "left"}"\n')
    (tmp_path / "p.toml").write_text("\n".join(lines).replace("'", '"'))
    said = []
    build(read_project(tmp_path / "p.toml"), tmp_path / "out", jobs=2, log=said.append)
    line = next(m for m in said if m.startswith("sides:"))
    assert f"{names[1]}: side right given" in line and f"{names[3]}: side right given" in line, line
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["correspondence"]["sides"]["mirrored"] == [names[1], names[3]]
    assert report["correspondence"]["sides"]["template"] == "left"
    for i in (0, 1):
        v, faces = read_mesh(tmp_path / "out" / "coated" / f"{names[i]}.ply")
        own = MeshLocator(*mmeshes[i])
        assert signed_volume(v, faces) > 0  # facing outwards in its own side
        assert own.query(v)[1].mean() < 1.0  # on its own mesh (mm), not on its mirror image
