"""Dense-truth populations for the correspondence tests (``../shared/data``: femur10, knee30).

Every mesh of a set shares one connectivity, so the true place of a template point on another
instance is the same place of that instance's mesh. Landmarks are farthest-point samples of the
template instance's vertices, at their true places on the others. The error of a coating is the
distance of its points from their true places (mm): not a surface distance.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ssm_addon.base.params import CorrespondenceParams, StudyParams
from ssm_addon.formats.landmarks import LandmarkSet, read_landmarks, write_landmarks
from ssm_addon.formats.meshes import read_mesh
from ssm_addon.instances.importing import InstanceSpec
from ssm_addon.meshutil import MeshLocation, MeshLocator
from ssm_addon.pipeline.runner import run
from ssm_addon.pipeline.study import Study


def meshes_or_skip(folder: Path, pattern: str, limit: int | None = None):
    """(files, [(vertices, faces)]) of the first ``limit`` meshes ``pattern`` under ``folder``;
    the test is skipped, saying where it looked, when fewer than 3 are there."""
    files = sorted(folder.glob(pattern))[:limit]
    if len(files) < 3:
        pytest.skip(f"dense-truth meshes {pattern} not found under {folder} (set SSM_SHARED_DATA)")
    return files, [read_mesh(f) for f in files]


def farthest_points(points: np.ndarray, k: int) -> np.ndarray:
    """Indices of ``k`` farthest-point samples of ``points``, from the highest (largest z)."""
    chosen = [int(np.argmax(points[:, 2]))]
    d = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(k - 1):
        chosen.append(int(np.argmax(d)))
        d = np.minimum(d, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return np.array(chosen)


#: the last two studies built (:func:`built_study`), keyed by their inputs
BUILT = {}


def built_study(files, meshes, tmp_path, *, landmarks: int, on: int, method: str, jitter_mm: float = 0.0,
                choice: str = "medoid"):
    """A study coated by ``method``; returns (study, per-instance true error mean in mm, all errors).
    ``jitter_mm``: Gaussian click error per axis of every instance's landmarks but the template's.
    The last two builds are kept for a later test of this process that asks for the same inputs (the
    femurs unmoved without landmarks, in scanner poses and beside their mirror images; the tests read a
    study, never change it)."""
    key = (tuple(str(f) for f in files), landmarks, on, method, jitter_mm, choice)
    if key not in BUILT:
        BUILT[key] = build_study(files, meshes, tmp_path, landmarks=landmarks, on=on, method=method,
                                 jitter_mm=jitter_mm, choice=choice)
        while len(BUILT) > 2:
            BUILT.pop(next(iter(BUILT)))
    return BUILT[key]


def build_study(files, meshes, tmp_path, *, landmarks: int, on: int, method: str, jitter_mm: float, choice: str):
    """:func:`built_study` without the memory: import, template and coating of a new study."""
    v0 = meshes[0][0]
    idx = farthest_points(v0, landmarks)
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
