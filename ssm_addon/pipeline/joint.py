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
(:func:`~ssm_addon.model.joint.shape_and_pose`), and the overlap of the structures in shapes
the model draws against the training subjects' (:func:`~ssm_addon.model.joint.collisions`).

References
----------
Bossa MN, Olmos S. Multi-object statistical pose+shape models. ISBI 2007.
Rasoulian A, Rohling R, Abolmaesumi P. Lumbar spine segmentation using a statistical
multi-vertebrae anatomical shape+pose model. IEEE TMI 32(10), 2013.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from ..base.compute import done_future, run_one_thread
from ..base.errors import InputError, check_cancelled
from ..base.params import StudyParams
from ..base.progress import CancelledFn, ProgressFn, report, sub_progress
from ..correspondence.frames import coating_poses, twists_of
from ..correspondence.sides import subject_sides
from ..model import metrics as model_metrics
from ..model.joint import collision_findings, collisions, shape_and_pose, structure_model
from ..model.metrics import ModelMetrics
from ..model.pca import ShapeModel, build_model, generalized_procrustes, procrustes_fit
from ..model.quality import Finding, check_model
from .model_method import landmarked
from .runner import run
from .sides import decide_sides, sides_line, with_sides
from .stages import make_model, twist_findings
from .study import Study, study_parameters

__all__ = ["JointStudy", "joint_model", "joint_sides", "run_joint", "structure_metrics"]

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
    imported = joint_sides(joint, jobs=jobs, executor=executor, cancelled=cancelled, cache=cache, log=say,
                           progress=sub_progress(progress, 0.0, 0.1))
    for k, (name, study) in enumerate(joint.structures.items()):
        check_cancelled(cancelled)
        report(progress, 0.1 + 0.6 * k / n, f"{name}: import, template and coating")
        t0 = time.perf_counter()
        # sides are decided per subject (joint_sides, above) or given: none is decided per structure
        study.instances = tuple(dataclasses.replace(i, mirror=False) if i.mirror is None else i for i in study.instances)
        stages = ("coating",) if imported else ("import", "template", "coating")
        run(study, stages=stages, jobs=jobs, cancelled=cancelled, executor=executor,
            cache=cache, progress=sub_progress(progress, 0.1 + 0.6 * k / n, 0.1 + 0.6 * (k + 1) / n, f"{name}: "),
            log=lambda line, name=name: say(f"{name}: {line}"))
        joint.timings_s[f"{name}"] = imported.get(name, 0.0) + time.perf_counter() - t0
        if study.params.correspondence.optimise:
            say(f"{name}: correspondence: the optimisation across the population is not run in a joint build "
                "(each structure's coatings as the coating stage left them)")
    check_cancelled(cancelled)
    t0 = time.perf_counter()
    report(progress, 0.7, "joint model: PCA of every structure together")
    joint.model = joint_model(joint, cancelled=cancelled)
    findings, joint.outlier_scores = check_model(joint.model, joint.params.quality)
    joint.findings = list(findings)
    # each structure's coatings put on its mean shape by their points and by their surfaces: the
    # coatings turned on their own surface (twist), and the relative pose's share of noise below
    placed = coatings_placed(joint)
    for name, study in joint.structures.items():  # a structure's coating turned on its own surface
        joint.findings += [dataclasses.replace(f, message=f"{name}: {f.message}", stage="model")
                           for f in twist_findings(study, [s for s in study.names if s in study.coatings],
                                                   twists=twists_of(*placed[name]) if name in placed else None)]
    joint.timings_s["model"] = time.perf_counter() - t0
    say(f"joint model: {joint.model.n_modes} modes, {joint.model.n_points} points of {n} structures "
        f"({', '.join(joint.names)}) in {joint.timings_s['model']:.2f} s")
    t0 = time.perf_counter()
    report(progress, 0.8, "joint model: compactness, generalization, specificity")
    mp = joint.params.model
    # the joint model's metrics and each structure's (its rows, its own model) are independent:
    # begun on the build's workers, while this process finds the shape and relative pose and the
    # collisions; each runs with one BLAS thread wherever it runs (the same numbers)
    submit = executor.submit if executor is not None else done_future
    settings = (mp.specificity_samples, mp.seed, mp.max_loo)
    pending = {"": submit(_metrics_job, (joint.model, *settings))}
    modes = {}
    for name in joint.names:
        for label, m in _structure_models(joint, name):
            pending[f"{name}/{label}"] = submit(_metrics_job, (m, *settings))
            modes[f"{name}/{label}"] = m.n_modes
    t1 = time.perf_counter()
    report(progress, 0.9, "joint model: shape and relative pose, collisions")
    joint.shape_pose = shape_and_pose(joint.model, reference=joint.reference)
    joint.findings += relative_pose_noise(joint.shape_pose, placed, joint.reference)
    jp = joint.params.joint
    joint.collisions = collisions(joint.model, samples=jp.collision_samples, depth_mm=jp.penetration_mm,
                                  seed=mp.seed, cancelled=cancelled)
    joint.findings += collision_findings(joint.collisions, jp.max_collision_excess)
    joint.timings_s["shape_pose_collisions"] = time.perf_counter() - t1
    joint.metrics = pending[""].result()
    for name in joint.names:
        joint.structure_metrics[name] = {label: _structure_figures(pending[f"{name}/{label}"].result(),
                                                                   modes[f"{name}/{label}"])
                                         for label in ("joint", "separate")}
    joint.timings_s["metrics"] = time.perf_counter() - t0 - joint.timings_s["shape_pose_collisions"]
    check_cancelled(cancelled)
    for f in joint.findings:
        say(f"WARNING {f.instance or 'joint model'} [{f.gate}]: {f.message}")
    return joint


def joint_sides(joint: JointStudy, *, jobs: int = 1, executor=None, cancelled: CancelledFn = None, cache=None,
                log: Log = None, progress: ProgressFn = None) -> dict:
    """Each subject's side, one for all its structures, before any is coated.

    Where ``[correspondence] sides = "detect"`` and some subject's side is not given, every
    structure's side of every such subject is found against that structure's template (by
    landmarks, or by the surface: :func:`~ssm_addon.pipeline.sides.decide_sides`, which needs
    the structures imported and their templates built first), the findings are pooled per
    subject (:func:`~ssm_addon.correspondence.sides.subject_sides`), and each structure's study
    takes them (:func:`~ssm_addon.pipeline.sides.with_sides`: its mirror images' volumes
    mirrored). A subject's structures are then mirrored together, so its relative poses are
    one side's.

    Returns
    -------
    dict
        structure -> seconds of its import, template and side test, for the structures imported
        here (empty when nothing was to decide: the coating's stages import them).
    """
    say = log or (lambda _m: None)
    open_sides = {name: [i.name for i in st.instances if i.mirror is None] for name, st in joint.structures.items()}
    if not any(open_sides.values()) or any(st.params.correspondence.sides != "detect"
                                           for st in joint.structures.values()):
        return {}
    by_landmarks = all(len(landmarked(st)) == len(st.names) for st in joint.structures.values())
    seconds, found = {}, {}
    n = len(joint.structures)
    for k, (name, study) in enumerate(joint.structures.items()):
        check_cancelled(cancelled)
        t0 = time.perf_counter()
        if not by_landmarks:  # the surface test needs the volumes and the template
            report(progress, k / n, f"{name}: import and template, for the subjects' sides")
            run(study, stages=("import", "template"), jobs=jobs, cancelled=cancelled, executor=executor, cache=cache,
                progress=sub_progress(progress, k / n, (k + 1) / n, f"{name}: "),
                log=lambda line, name=name: say(f"{name}: {line}"))
        found[name] = decide_sides(study, open_sides[name], jobs=jobs, executor=executor, cancelled=cancelled,
                                   surface=not by_landmarks)
        seconds[name] = time.perf_counter() - t0
    ref = joint.reference
    ref_template = joint.structures[ref].template_instance
    parity = {}
    for name, study in joint.structures.items():  # a structure's template subject against the reference's
        tpl = study.template_instance
        given = joint.structures[ref].instance(tpl).mirror if tpl != ref_template else False
        parity[name] = bool(given if given is not None else found[ref].get(tpl) and found[ref][tpl].mirror)
    pooled = subject_sides(found, parity=parity)
    for name, study in list(joint.structures.items()):
        joint.structures[name] = sided = with_sides(study, pooled[name])
        line = sides_line(sided, pooled[name])
        if line:
            say(f"{name}: {line}")
    return seconds if not by_landmarks else {}


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
              # subjects mirrored into the template's side: their world points are their own side's
              "mirrored": [s for s in subjects if ref_study.frame(s).mirrored],
              "spacing_mm": float(ref_study.params.template.spacing_mm),
              "frame_methods": sorted({study.frame(s).method for study in joint.structures.values() for s in subjects}),
              "fit": {f"{name}/{s}": {k: v for k, v in study.coatings[s].fit.to_dict().items() if k != "time_s"}
                      for name, study in joint.structures.items() for s in subjects}}
    check_cancelled(cancelled)
    model = build_model(local, faces, subjects, instance_points_world=world_all, alignment=alignment,
                        n_modes=mp.n_modes, variance_fraction=mp.variance_fraction, solver=mp.solver,
                        precision=mp.precision, params=params, cancelled=cancelled)
    return dataclasses.replace(model, structure_names=tuple(joint.names), structure_offsets=offsets)



#: A pair's relative pose is said to be in large part the correspondence's own noise when the
#: coatings' poses could explain at least this share of the variance of its turn or of its shift
#: (the estimate falls short of the truth: knee30 in scanner poses without landmarks, 49 % where
#: the true correspondence says 97 %; docs/history.md).
POSE_NOISE_SHARE = 0.25


def coatings_placed(joint: JointStudy) -> dict:
    """Per structure where some subject has no landmarks: its subjects' coatings (world mm) put on
    the structure's mean shape by their points and by their surfaces
    (:func:`~ssm_addon.correspondence.frames.coating_poses`), and the mean shape: ``{structure:
    ({subject: (by points, by surface)}, mean (N, 3))}``. Landmarks on every subject pin the turns
    a coating could take on its surface (the twist gate is not run there either), and the measure
    costs about 0.1 s a coating (knee30, 30 subjects with landmarks: 6 s of a 45 s build)."""
    out = {}
    ref = joint.structures[joint.reference]
    for name, study in joint.structures.items():
        names = [s for s in joint.subjects if s in study.coatings]
        if len(names) < 3 or study.template is None or all(study.landmarks(s) is not None for s in names):
            continue
        reference = study.template_instance if study.template_instance in names else names[0]
        # a subject of the other side in one side's world (x negated for all its structures alike, by
        # its reference structure's frame), so that rotations place every subject's coatings
        flip = {s: np.array([-1.0, 1.0, 1.0]) if s in ref.names and ref.frame(s).mirrored else 1.0 for s in names}
        out[name] = coating_poses({s: study.frame(s).to_world(study.coatings[s].points_object) * flip[s] for s in names},
                                  study.template.faces, reference)
    return out


def relative_pose_noise(shape_pose: dict, placed: dict, reference: str) -> list:
    """How much of each structure pair's relative pose over the subjects the correspondence's own
    error could explain; written into ``shape_pose["pairs"][pair]["correspondence"]``, and a
    ``pose_noise`` finding where it is at least :data:`POSE_NOISE_SHARE` of the turn's or the
    shift's variance.

    Per subject, each structure's coating is put on its mean shape by its points (A_p) and by its
    surface (A_s; :func:`coatings_placed`). The structure's pose relative to the reference is
    Q = A_ref A_struct⁻¹ (the structure's mean frame to the reference's), by points (Q_p, as the
    model reads it) and by surfaces (Q_s, which no correspondence enters). D = Q_s Q_p⁻¹ is the
    turn and move the correspondence alone gives the relative pose: its rotation vector (degrees)
    and the move of the structure's centroid (mm). Their spread over the subjects (RMS about the
    mean, as :func:`~ssm_addon.model.joint.shape_and_pose` measures the data's) is the noise; its
    square over the data's variance the share it could explain (at most 1). The surface poses have
    errors of their own (shapes that differ fit a mean shape in poses of their own), so the share
    is what the correspondence *could* explain, not a proof that it does.
    """
    findings = []
    for pair, figures in (shape_pose.get("pairs") or {}).items():
        other = pair[len(reference) + 1:] if pair.startswith(f"{reference}-") else ""
        if reference not in placed or other not in placed:
            figures["correspondence"] = {"not_measured": "every subject has landmarks on both structures (they pin "
                                                         "the coatings' turns; the self-check measures them)"}
            continue
        ref_poses, _ref_mean = placed[reference]
        poses, mean = placed[other]
        subjects = [s for s in poses if s in ref_poses]
        if len(subjects) < 3:
            continue
        centre = np.append(mean.mean(axis=0), 1.0)
        turns, moves = [], []
        for s in subjects:
            q_p = ref_poses[s][0].matrix @ np.linalg.inv(poses[s][0].matrix)
            q_s = ref_poses[s][1].matrix @ np.linalg.inv(poses[s][1].matrix)
            d = q_s @ np.linalg.inv(q_p)
            scale = float(np.cbrt(np.linalg.det(d[:3, :3])))
            turns.append(Rotation.from_matrix(d[:3, :3] / scale).as_rotvec())
            c = q_p @ centre
            moves.append((d @ c - c)[:3])
        turns, moves = np.asarray(turns), np.asarray(moves)
        turn_sd = float(np.degrees(np.sqrt(((turns - turns.mean(0)) ** 2).sum(1).mean())))
        shift_sd = float(np.sqrt(((moves - moves.mean(0)) ** 2).sum(1).mean()))
        data = figures.get("data") or {}

        def share(noise, of):
            return float(min(1.0, (noise / of) ** 2)) if of and np.isfinite(of) and of > 0 else float("nan")

        noise = {"turn_sd_deg": turn_sd, "shift_sd_mm": shift_sd,
                 "turn_share": share(turn_sd, data.get("turn_sd_deg")),
                 "shift_share": share(shift_sd, data.get("shift_sd_mm")), "subjects": len(subjects),
                 "method": "each subject's relative pose by the coatings' points against by their surfaces "
                           "(each structure put on its mean shape both ways); the spread of the difference"}
        figures["correspondence"] = noise
        worst = max((x for x in (noise["turn_share"], noise["shift_share"]) if np.isfinite(x)), default=float("nan"))
        if worst >= POSE_NOISE_SHARE:
            findings.append(Finding(
                "", "pose_noise",
                f"{pair}: the correspondence's own error could explain {100 * noise['turn_share']:.0f} % of the "
                f"relative pose's turn variance (SD {turn_sd:.2f}° of {data.get('turn_sd_deg', float('nan')):.2f}°) "
                f"and {100 * noise['shift_share']:.0f} % of its shift variance (SD {shift_sd:.2f} of "
                f"{data.get('shift_sd_mm', float('nan')):.2f} mm): much of the model's relative pose may be the "
                "coatings' noise, not the joint's; give the subjects landmarks (three or more per structure) "
                "before reading its modes as kinematics", worst, POSE_NOISE_SHARE, stage="model"))
    return findings

def _metrics_job(args) -> ModelMetrics:
    model, n_samples, seed, max_loo = args
    return model_metrics.evaluate(model, n_samples=n_samples, seed=seed, max_loo=max_loo)


def _structure_models(joint: JointStudy, name: str) -> tuple[tuple[str, ShapeModel], ...]:
    """Structure ``name``'s two models whose metrics the report gives: its rows of the joint model
    (``"joint"``) and its own model of the same coatings (``"separate"``)."""
    return ("joint", structure_model(joint.model, name)), ("separate", make_model(joint.structures[name]))


def _structure_figures(mets: ModelMetrics, n_modes: int) -> dict:
    return {"generalization_mm": list(mets.generalization["mean_mm"]),
            "specificity_mm": list(mets.specificity["mean_mm"]), "modes": n_modes}


def structure_metrics(joint: JointStudy, name: str, *, cancelled: CancelledFn = None) -> dict:
    """Generalization and specificity (mm, per number of modes) of structure ``name``: its rows of the
    joint model (:func:`structure_model`, relative pose included) and its own model from the same
    coatings (aligned on itself, as a separate build makes it). :func:`run_joint` computes the same
    on the build's executor."""
    mp = joint.params.model
    out = {}
    for label, m in _structure_models(joint, name):
        out[label] = _structure_figures(run_one_thread(_metrics_job, (m, mp.specificity_samples, mp.seed,
                                                                      mp.max_loo)), m.n_modes)
        check_cancelled(cancelled)
    return out
