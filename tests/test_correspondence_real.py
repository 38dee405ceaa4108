"""Correspondence on real femurs with dense truth (``../shared/data``): femur10 (knee30's
patellas and tibias: ``test_correspondence_real_knees.py``, on another worker).

Every mesh of a set shares one connectivity, so the true place of a template point on
another instance is the same place of that instance's mesh. Landmarks are farthest-point
samples of the template instance's vertices, at their true places on the others. The
error of a coating is the distance of its points from their true places (mm): not a
surface distance. Skipped where the data is absent (a user's fresh clone).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import shared_data_dir
from dense_truth import built_study, meshes_or_skip

from ssm_addon.formats.meshes import read_mesh
from ssm_addon.meshutil import MeshLocator

DATA = shared_data_dir()

pytestmark = pytest.mark.slow


def test_model_method_at_its_defaults_is_no_worse_than_the_single_pass_on_femur10(tmp_path):
    """15 exact landmarks on all ten femurs: the model method keeps a round only when the
    landmark transfer error falls, so it ends no worse than the single pass (mean and 95th
    percentile), and its rounds end by the tolerance or by the criterion, never silently
    at the limit."""
    files, meshes = meshes_or_skip(DATA / "femur10", "femur*.ply")
    single, e_single = built_study(files, meshes, tmp_path, landmarks=15, on=len(files), method="landmarks")
    model, e_model = built_study(files, meshes, tmp_path, landmarks=15, on=len(files), method="model")
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


def test_femurs_in_scanner_poses_without_landmarks_are_coated_as_unmoved(tmp_path):
    """Five femurs of femur10, each in its own random scanner pose (any axis, up to 180°) as Scalismo
    and ShapeWorks write them (PLY in scanner mm, no convention stated), no landmarks. The object
    frames come from the solids' exact moments (the moved frame of a moved mesh) and the start keeps
    the input coordinates only to choose between basins, so every femur is coated as unmoved: the
    same points to 0.1 mm (the files' float32 coordinates flip a few voxels), not only as near the
    truth (before: 0.11 mm apart in the mean error, 1.2 mm at the worst point; before the start's
    registration from every rotation of the frame's axes, femur03 coated end for end, 249 mm)."""
    from foreign_data import random_rigid, slicer_ply

    files, meshes = meshes_or_skip(DATA / "femur10", "femur*.ply", limit=5)
    rng = np.random.default_rng(7)
    moved_files, moved, motions = [], [], {}
    for f, (v, faces) in zip(files, meshes):
        rot, shift = random_rigid(rng, shift_mm=200.0)
        w = v @ rot.T + shift
        moved_files.append(slicer_ply(tmp_path / f.name, w, faces, space=None))
        moved.append((w, faces))
        motions[f.stem] = (rot, shift)
    study, unmoved = built_study(files, meshes, tmp_path, landmarks=0, on=0, method="landmarks")
    posed_study, posed = built_study(moved_files, moved, tmp_path, landmarks=0, on=0, method="landmarks")
    assert posed_study.template_instance == study.template_instance
    apart = {}
    for n, (rot, shift) in motions.items():  # the posed coating moved back into the unmoved femur's place
        back = (posed_study.frame(n).to_world(posed_study.coatings[n].points_object) - shift) @ rot
        apart[n] = np.linalg.norm(back - study.frame(n).to_world(study.coatings[n].points_object), axis=1)
    a, b = np.concatenate(list(unmoved.values())).mean(), np.concatenate(list(posed.values())).mean()
    print(f"femurs without landmarks: unmoved {a:.3f} mm, in scanner poses {b:.3f} mm; the same points to "
          + ", ".join(f"{n} {d.mean():.4f} / {d.max():.3f}" for n, d in apart.items()) + " mm (mean / largest)")
    assert max(float(e.mean()) for e in posed.values()) < 4.0, posed
    # measured: four of five bit for bit alike, femur03 0.008 mm in the mean, 0.06 mm at the largest point
    assert all(d.mean() < 0.02 and np.percentile(d, 99) < 0.1 and d.max() < 0.3 for d in apart.values()), apart
    assert abs(a - b) < 0.01, (a, b)


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

    files, meshes = meshes_or_skip(DATA / "femur10", "femur*.ply", limit=5)
    (tmp_path / "mixed").mkdir()
    mfiles, mmeshes = _mirror_some(files, meshes, tmp_path / "mixed")
    names = [f.stem for f in files]
    for landmarks, by in ((0, "surface"), (15, "landmarks")):
        _s, plain = built_study(files, meshes, tmp_path, landmarks=landmarks, on=len(files) if landmarks else 0,
                           method="landmarks")
        study, mixed = built_study(mfiles, mmeshes, tmp_path, landmarks=landmarks, on=len(files) if landmarks else 0,
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
