"""Joint models: the structures of a joint or a spine in one model of shape and relative pose.

A project whose instances hold several structures (``meshes = {femur = …, tibia = …}``, or
``volume`` with ``labels = {L1 = 20, …}``) is built as one :class:`~ssm_addon.pipeline.study.Study`
per structure (its own template, coating, correspondence method and gates, on the build's
executor and cache), then one model of them all:

1. every subject's structures are concatenated in structure order, in the reference
   structure's object frame (paper 2; ``[joint] reference``, default the first structure), so
   the relative pose between the structures stays in the data;
2. each subject is aligned once (``[model] alignment``), on all its structures together or on
   the reference structure alone (``[joint] align_on``), never per structure;
3. one PCA (paper 5, eqs. 4–6) of the concatenation: ``structure_names`` and
   ``structure_offsets`` say which points are which structure, ``faces`` index the
   concatenation (one mesh with disconnected parts, as a statismo reader expects).

Besides the model: each structure's own model metrics, the decomposition of every subject
into each structure's shape (in its own frame) and its pose relative to the reference
(:func:`shape_and_pose`), and the overlap of the structures in shapes the model draws against
the training subjects' (:func:`collisions`).

References
----------
Bossa MN, Olmos S. Multi-object statistical pose+shape models. ISBI 2007.
Rasoulian A, Rohling R, Abolmaesumi P. Lumbar spine segmentation using a statistical
multi-vertebrae anatomical shape+pose model. IEEE TMI 32(10), 2013.
"""

from __future__ import annotations

import dataclasses
import itertools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..base.errors import InputError, check_cancelled
from ..base.params import StudyParams
from ..base.progress import CancelledFn, ProgressFn, report, sub_progress
from ..meshutil import MeshLocator, face_normals
from ..model import metrics as model_metrics
from ..model.metrics import ModelMetrics
from ..model.pca import ShapeModel, build_model, generalized_procrustes, procrustes_fit
from ..model.quality import Finding, check_model
from .runner import run
from .stages import make_model
from .study import Study, study_parameters

__all__ = ["JointStudy", "collisions", "joint_model", "relative_pose", "run_joint", "shape_and_pose",
           "structure_model"]

Log = Callable[[str], None] | None


@dataclass
class JointStudy:
    """A study of several structures per subject.

    Attributes
    ----------
    subjects : tuple of str
        The subjects, in project order (each structure study's instances carry these names).
    structures : dict name -> Study
        Each structure's study, in structure order.
    params : StudyParams
        The project's parameters (``[model]``, ``[output]``, ``[quality]``, ``[joint]`` …).
    model : ShapeModel or None
        The joint model (points of every structure, concatenated).
    metrics : ModelMetrics or None
        Compactness, generalization and specificity of the joint model.
    structure_metrics : dict name -> dict
        Per structure: the generalization and specificity of its rows of the joint model and of
        its own model from the same coatings (mm).
    shape_pose : dict
        :func:`shape_and_pose`'s figures.
    collisions : dict
        :func:`collisions`' figures.
    findings : list of Finding
        The joint model's findings (each structure's own are in its study).
    """

    subjects: tuple[str, ...]
    structures: dict[str, Study]
    params: StudyParams = field(default_factory=StudyParams)
    model: ShapeModel | None = None
    metrics: ModelMetrics | None = None
    structure_metrics: dict = field(default_factory=dict)
    shape_pose: dict = field(default_factory=dict)
    collisions: dict = field(default_factory=dict)
    findings: list = field(default_factory=list)
    outlier_scores: dict = field(default_factory=dict)
    timings_s: dict = field(default_factory=dict)

    @classmethod
    def from_project(cls, project) -> JointStudy:
        """The joint study of a multi-structure project (:class:`~ssm_addon.pipeline.project.Project`)."""
        if not project.structures:
            raise InputError(f"{project.path}: a project of one structure; a joint study needs several")
        studies = {name: Study(instances=st.instances, template_instance=st.template_instance, params=st.params)
                   for name, st in project.structures.items()}
        return cls(subjects=project.names, structures=studies, params=project.params)

    @property
    def names(self) -> tuple[str, ...]:
        """The structure names, in model order."""
        return tuple(self.structures)

    @property
    def reference(self) -> str:
        """The reference structure (``[joint] reference``, default the first)."""
        ref = self.params.joint.reference or self.names[0]
        if ref not in self.structures:
            raise InputError(f"[joint] reference {ref!r} is not a structure ({', '.join(self.names)})")
        return ref


def run_joint(joint: JointStudy, *, jobs: int = 1, progress: ProgressFn = None, cancelled: CancelledFn = None,
              log: Log = None, executor=None, cache=None) -> JointStudy:
    """Every structure's import, template and coating (:func:`~ssm_addon.pipeline.runner.run`, the
    structures one after the other on ``executor``), then the joint model and its figures."""
    say = log or (lambda _m: None)
    n = len(joint.structures)
    for k, (name, study) in enumerate(joint.structures.items()):
        check_cancelled(cancelled)
        report(progress, 0.7 * k / n, f"{name}: import, template and coating")
        t0 = time.perf_counter()
        run(study, stages=("import", "template", "coating"), jobs=jobs, cancelled=cancelled, executor=executor,
            cache=cache, progress=sub_progress(progress, 0.7 * k / n, 0.7 * (k + 1) / n, f"{name}: "),
            log=lambda line, name=name: say(f"{name}: {line}"))
        joint.timings_s[f"{name}"] = time.perf_counter() - t0
    check_cancelled(cancelled)
    t0 = time.perf_counter()
    report(progress, 0.7, "joint model: PCA of every structure together")
    joint.model = joint_model(joint, cancelled=cancelled)
    findings, joint.outlier_scores = check_model(joint.model, joint.params.quality)
    joint.findings = list(findings)
    joint.timings_s["model"] = time.perf_counter() - t0
    say(f"joint model: {joint.model.n_modes} modes, {joint.model.n_points} points of {n} structures "
        f"({', '.join(joint.names)}) in {joint.timings_s['model']:.2f} s")
    t0 = time.perf_counter()
    report(progress, 0.8, "joint model: compactness, generalization, specificity")
    mp = joint.params.model
    joint.metrics = model_metrics.evaluate(joint.model, n_samples=mp.specificity_samples, seed=mp.seed,
                                           max_loo=mp.max_loo, cancelled=cancelled)
    for name in joint.names:
        joint.structure_metrics[name] = structure_metrics(joint, name, cancelled=cancelled)
    joint.timings_s["metrics"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    report(progress, 0.9, "joint model: shape and relative pose, collisions")
    joint.shape_pose = shape_and_pose(joint.model, reference=joint.reference)
    jp = joint.params.joint
    joint.collisions = collisions(joint.model, samples=jp.collision_samples, depth_mm=jp.penetration_mm,
                                  seed=mp.seed, cancelled=cancelled)
    joint.findings += collision_findings(joint.collisions, jp.max_collision_excess)
    joint.timings_s["shape_pose_collisions"] = time.perf_counter() - t0
    for f in joint.findings:
        say(f"WARNING {f.instance or 'joint model'} [{f.gate}]: {f.message}")
    return joint


# ----------------------------------------------------------------------------- the joint model
def _coated_world(study: Study, subjects: Sequence[str]) -> np.ndarray:
    return np.stack([study.frame(s).to_world(study.coatings[s].points_object) for s in subjects])


def joint_model(joint: JointStudy, *, cancelled: CancelledFn = None) -> ShapeModel:
    """The joint model of the coated structures (see the module docstring).

    Points are mm in the reference structure's object frame (then aligned), ``instance_points_world``
    the subjects' world mm (RAS). The parameters record each structure's study parameters.
    """
    subjects = list(joint.subjects)
    for name, study in joint.structures.items():
        missing = [s for s in subjects if s not in study.coatings]
        if missing:
            raise InputError(f"joint model: structure {name!r} is not coated on {', '.join(missing[:5])}")
    world = [_coated_world(study, subjects) for study in joint.structures.values()]
    sizes = [w.shape[1] for w in world]
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    faces = np.concatenate([np.asarray(study.template.faces, np.int64) + offsets[i]
                            for i, study in enumerate(joint.structures.values())])
    world_all = np.concatenate(world, axis=1)
    ref_study = joint.structures[joint.reference]
    local = np.stack([ref_study.frame(s).to_object(world_all[i]) for i, s in enumerate(subjects)])
    mp = joint.params.model
    alignment = mp.alignment
    if joint.params.joint.align_on == "reference" and alignment != "none":
        r = list(joint.structures).index(joint.reference)
        part = local[:, offsets[r]:offsets[r + 1]]
        aligned, _info = generalized_procrustes(part, scale=alignment == "similarity")
        moved = []  # each subject moved as the alignment moves its reference structure
        for i in range(len(subjects)):
            si, ri, ti = procrustes_fit(part[i][None], aligned[i], alignment == "similarity")
            moved.append(si[0] * local[i] @ ri[0].T + ti[0])
        local, alignment = np.stack(moved), "none"
    params = {"structures": {name: study_parameters(study, study.model.params.get("landmarks", ()) if study.model
                                                    else ()) for name, study in joint.structures.items()},
              "joint": dataclasses.asdict(joint.params.joint), "reference": joint.reference,
              "model": dataclasses.asdict(mp),
              "spacing_mm": float(ref_study.params.template.spacing_mm),
              "frame_methods": sorted({study.frame(s).method for study in joint.structures.values() for s in subjects}),
              "fit": {f"{name}/{s}": {k: v for k, v in study.coatings[s].fit.to_dict().items() if k != "time_s"}
                      for name, study in joint.structures.items() for s in subjects}}
    check_cancelled(cancelled)
    model = build_model(local, faces, subjects, instance_points_world=world_all, alignment=alignment,
                        n_modes=mp.n_modes, variance_fraction=mp.variance_fraction, solver=mp.solver,
                        precision=mp.precision, params=params, cancelled=cancelled)
    return dataclasses.replace(model, structure_names=tuple(joint.names), structure_offsets=offsets)


def structure_model(model: ShapeModel, name: str) -> ShapeModel:
    """Structure ``name``'s rows of a joint model, exactly: the mean's rows and the marginal
    covariance of its points (Q_s Λ Q_sᵀ) as its own orthonormal modes and variances; the
    instances' rows; the structure's faces."""
    sl = model.structure_slice(name)
    npts = sl.stop - sl.start
    scaled = (np.asarray(model.modes[:, sl], float).reshape(model.n_modes, -1)
              * np.sqrt(np.asarray(model.variances, float))[:, None])  # (K, 3 n_s): rows of Q_s √Λ, transposed
    u, sv, vt = np.linalg.svd(scaled, full_matrices=False)
    keep = sv > 1e-9 * max(float(sv.max(initial=0.0)), 1e-300)
    faces = np.asarray(model.faces)
    inside = (faces >= sl.start).all(axis=1) & (faces < sl.stop).all(axis=1)
    return ShapeModel(mean=np.asarray(model.mean[sl], float), faces=faces[inside] - sl.start,
                      modes=vt[keep].reshape(-1, npts, 3), variances=sv[keep] ** 2,
                      instance_names=np.asarray(model.instance_names),
                      instance_points=np.asarray(model.instance_points[:, sl], float),
                      instance_points_world=np.asarray(model.instance_points_world[:, sl], float),
                      params={**model.params, "structure": name})


def structure_metrics(joint: JointStudy, name: str, *, cancelled: CancelledFn = None) -> dict:
    """Generalization and specificity (mm, per number of modes) of structure ``name``: its rows of the
    joint model (:func:`structure_model`, relative pose included) and its own model from the same
    coatings (aligned on itself, as a separate build makes it)."""
    mp = joint.params.model
    rows = structure_model(joint.model, name)
    own = make_model(joint.structures[name])
    out = {}
    for label, m in (("joint", rows), ("separate", own)):
        mets = model_metrics.evaluate(m, n_samples=mp.specificity_samples, seed=mp.seed, max_loo=mp.max_loo,
                                      cancelled=cancelled)
        out[label] = {"generalization_mm": list(mets.generalization["mean_mm"]),
                      "specificity_mm": list(mets.specificity["mean_mm"]), "modes": m.n_modes}
    return out


# ------------------------------------------------------------------------ shape and pose
def relative_pose(points: np.ndarray, reference: np.ndarray, mean_points: np.ndarray,
                  mean_reference: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """One structure's pose relative to the reference structure, in the reference's frame.

    Each structure is put onto its mean shape by a similarity (Procrustes); the pose of the
    structure relative to the reference is R = R_refᵀ R_s (a rotation vector, the log map,
    radians), t the structure's centroid in the reference's aligned frame minus the mean's
    (mm), and the log of the scale ratio. Returns (rotation vector (3,), translation (3,), log scale).
    """
    s_r, r_r, t_r = procrustes_fit(reference[None], mean_reference, True)
    s_s, r_s, t_s = procrustes_fit(points[None], mean_points, True)
    rel = r_r[0] @ r_s[0].T  # the structure's pose (mean -> it) as the reference's alignment sees it
    in_ref = s_r[0] * points.mean(axis=0) @ r_r[0].T + t_r[0]  # the structure's centroid where the reference sits
    return _log_rotation(rel), in_ref - mean_points.mean(axis=0), float(np.log(s_s[0] / s_r[0]))


def _log_rotation(rot: np.ndarray) -> np.ndarray:
    """The rotation vector (axis × angle, radians) of a rotation matrix (the log map)."""
    angle = float(np.arccos(np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0)))
    if angle < 1e-12:
        return np.zeros(3)
    w = np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    if np.pi - angle < 1e-6:  # a half turn: the axis from the symmetric part
        axis = np.sqrt(np.maximum((np.diag(rot) + 1.0) / 2.0, 0.0))
        axis *= np.where(np.sign(w) == 0, 1.0, np.sign(w))
        return axis / max(np.linalg.norm(axis), 1e-300) * angle
    return w / (2.0 * np.sin(angle)) * angle


def _decompose(model: ShapeModel, shapes: np.ndarray, reference: str) -> tuple[np.ndarray, dict]:
    """Per shape: each structure's aligned shape (mm) and its pose relative to the reference."""
    names = list(model.structure_names)
    ref = model.structure_slice(reference)
    mean = np.asarray(model.mean, float)
    rows, poses = [], {n: [] for n in names if n != reference}
    for shape in shapes:
        parts = []
        for n in names:
            sl = model.structure_slice(n)
            _s, rot, t = procrustes_fit(shape[sl][None], mean[sl], True)
            parts.append((_s[0] * shape[sl] @ rot[0].T + t[0]).ravel())
            if n != reference:
                poses[n].append(relative_pose(shape[sl], shape[ref], mean[sl], mean[ref]))
        rows.append(np.concatenate(parts))
    return np.stack(rows), poses


def shape_and_pose(model: ShapeModel, *, reference: str, samples: int = 300, seed: int = 0) -> dict:
    """Each structure's shape (in its own frame) and its pose relative to the reference structure,
    and one PCA over both.

    Pose is the rotation vector (log map) times the structure's RMS radius, the translation
    and the log scale times the RMS radius, each times √(number of the structure's points):
    a pose that moves every point of a structure by d mm then weighs N d², as the same
    displacement does among the shape coordinates, so shape and pose are measured alike. Returns, per mode of that PCA, the share of its variance that is
    relative pose; per structure pair (reference, other) the spread of the relative pose in
    the training subjects and in ``samples`` shapes the joint model draws (SD of the turn,
    degrees, and of the shift, mm).
    """
    if len(model.structure_names) < 2 or not model.n_instances:
        return {}
    names = [n for n in model.structure_names if n != reference]
    mean = np.asarray(model.mean, float)
    shapes, poses = _decompose(model, np.asarray(model.instance_points, float), reference)
    radius = {n: float(np.sqrt(((mean[model.structure_slice(n)] - mean[model.structure_slice(n)].mean(0)) ** 2)
                               .sum(1).mean())) for n in names}
    count = {n: model.structure_slice(n).stop - model.structure_slice(n).start for n in names}
    pose_rows = np.stack([np.concatenate([np.sqrt(count[n]) * np.concatenate(
        [poses[n][i][0] * radius[n], poses[n][i][1], [poses[n][i][2] * radius[n]]]) for n in names])
        for i in range(len(shapes))])
    data = np.concatenate([shapes, pose_rows], axis=1)
    centred = data - data.mean(axis=0)
    _u, sv, vt = np.linalg.svd(centred, full_matrices=False)
    var = sv ** 2 / max(len(data), 1)
    keep = var > 1e-9 * max(float(var.max(initial=0.0)), 1e-300)
    n_shape = shapes.shape[1]
    pose_share = (vt[keep][:, n_shape:] ** 2).sum(axis=1)
    rng = np.random.default_rng(seed)
    drawn = model.sample(samples, seed=int(rng.integers(2**31)), sd_limit=3.0) if model.n_modes else np.zeros((0,))
    _shapes_m, poses_m = _decompose(model, drawn, reference) if len(drawn) else (None, {n: [] for n in names})

    def spread(items):
        if not items:
            return {"turn_sd_deg": float("nan"), "shift_sd_mm": float("nan")}
        rv = np.array([p[0] for p in items])
        tr = np.array([p[1] for p in items])
        return {"turn_sd_deg": float(np.degrees(np.sqrt(((rv - rv.mean(0)) ** 2).sum(1).mean()))),
                "shift_sd_mm": float(np.sqrt(((tr - tr.mean(0)) ** 2).sum(1).mean()))}

    return {"reference": reference, "weighting": "rotation vector and log scale times the structure's RMS radius, "
                                                 "translation in mm; each times the square root of its point count",
            "modes_pose_share": [float(x) for x in pose_share], "variances_mm2": [float(x) for x in var[keep]],
            "pairs": {f"{reference}-{n}": {"data": spread(poses[n]), "model": spread(poses_m[n])} for n in names}}


# ----------------------------------------------------------------------------- collisions
def _penetration(points: np.ndarray, other: np.ndarray, other_faces: np.ndarray) -> float:
    """How deep points reach into the closed surface ``other`` (mm; 0 when none is inside): a point
    is inside when it lies behind the outward normal of its closest triangle. Only the points
    within ``other``'s bounding box can be inside it, so only they are queried."""
    lo, hi = other.min(axis=0), other.max(axis=0)
    points = points[((points >= lo) & (points <= hi)).all(axis=1)]
    if not len(points):
        return 0.0
    closest, dist, tri, _b = MeshLocator(other, other_faces).query(points, k=12)
    normals = face_normals(other, other_faces)[tri]
    inside = np.einsum("ij,ij->i", points - closest, normals) < 0.0
    return float(dist[inside].max()) if inside.any() else 0.0


def collisions(model: ShapeModel, *, samples: int = 200, depth_mm: float = 0.5, seed: int = 0,
               cancelled: CancelledFn = None) -> dict:
    """Per structure pair: how deep one reaches into the other (mm), in the training subjects (as they
    are: ``instance_points_world``) and in shapes the model draws (±3 SD along each mode, and ``samples`` random ones within 3 SD), and the
    share of each with a penetration beyond ``depth_mm``."""
    names = list(model.structure_names)
    if len(names) < 2:
        return {}
    faces = np.asarray(model.faces)
    parts = {}
    for n in names:
        sl = model.structure_slice(n)
        inside = (faces >= sl.start).all(axis=1) & (faces < sl.stop).all(axis=1)
        parts[n] = (sl, faces[inside] - sl.start)
    sd = model.standard_deviations
    extremes = [model.mean + sign * 3.0 * sd[k] * model.modes[k] for k in range(model.n_modes) for sign in (-1.0, 1.0)]
    drawn = list(model.sample(samples, seed=seed, sd_limit=3.0)) if samples and model.n_modes else []
    # the subjects as they are (their world coordinates: every structure where the scanner saw it)
    sets = {"data": list(np.asarray(model.instance_points_world, float)), "model": extremes + drawn}
    out = {}
    for a, b in itertools.combinations(names, 2):
        check_cancelled(cancelled)
        figures = {}
        for label, shapes in sets.items():
            depths = []
            for shape in shapes:
                sa, fa = parts[a]
                sb, fb = parts[b]
                depths.append(max(_penetration(shape[sa], shape[sb], fb), _penetration(shape[sb], shape[sa], fa)))
            d = np.asarray(depths)
            figures[label] = {"shapes": len(d), "max_mm": float(d.max(initial=0.0)),
                              "mean_mm": float(d.mean()) if len(d) else 0.0,
                              "colliding_share": float((d > depth_mm).mean()) if len(d) else 0.0}
        out[f"{a}-{b}"] = figures
    return out


def collision_findings(figures: dict, excess: float) -> list[Finding]:
    """A structure pair whose model shapes collide in ``excess`` more of the draws than the training
    subjects do: the model lets the structures overlap where the data never do (relative pose left
    out of the model, or too few subjects)."""
    out = []
    for pair, f in figures.items():
        more = f["model"]["colliding_share"] - f["data"]["colliding_share"]
        if more > excess:
            out.append(Finding("", "collision", f"{pair}: {100 * f['model']['colliding_share']:.0f} % of the model's "
                               f"shapes overlap by more than the limit (up to {f['model']['max_mm']:.1f} mm), against "
                               f"{100 * f['data']['colliding_share']:.0f} % of the subjects: the structures' relative "
                               "pose is not held by the model", more, excess))
    return out
