"""A shape study: its instances and parameters, and what each stage of the method made.

The study is the state both front ends share. The command line builds one from a
project file (:meth:`Study.from_project`), Blender from the scene; both then call the
same stage functions, which read the study and return a product:

====================  ==========================================  ===================
stage                 function                                    product
====================  ==========================================  ===================
import (paper 2)      :func:`import_instances`                    ``volumes``
template (paper 3)    :func:`make_template`                       ``template``
coating (paper 4)     :func:`coat_instances`                      ``coatings``
optimisation          :func:`optimisation_stage`                  ``coatings``
model (paper 5)       :func:`make_model`                          ``model``
metrics               :func:`evaluate_model`                      ``metrics``
====================  ==========================================  ===================

:func:`run` is the loop over them. Every number that feeds a later stage is float64
and lives here (Blender meshes are only views of it), so the same inputs give the same
model in Blender and on the command line.

Frames: landmarks are world mm of each instance's input file; volumes, the template
and coatings are object mm (paper 2) of their instance; the model is in the model frame
(the object frame, or Procrustes-aligned).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..base.errors import InputError
from ..base.params import StudyParams
from ..base.records import versions
from ..coating.coating import CoatingResult, CoatingStart
from ..formats.label_maps import label_map_coordinates
from ..formats.landmarks import LandmarkSet
from ..instances.importing import InstanceSpec, mesh_coordinates
from ..instances.volume import ObjectFrame, ObjectVolume
from ..meshutil import LandmarkLocations
from ..model.metrics import ModelMetrics
from ..model.pca import ShapeModel
from ..model.quality import (
    Finding,
)
from ..template.template import Template

__all__ = ["input_coordinates", "STAGES", "StageResult", "Study", "apply_stage", "carried_landmarks", "common_landmark_names", "instance_sources", "landmark_distances", "merge_findings", "study_parameters", "template_landmark_locations"]


Log = Callable[[str], None] | None


@dataclass
class Study:
    """A shape study (paper fig. 1): inputs and the products of each stage.

    Attributes
    ----------
    instances : tuple of InstanceSpec
        The instances in study order (their sources and landmarks, world mm).
    template_instance : str
        Name of the instance the template is built from (paper 3).
    params : StudyParams
        Every stage's parameters, one field per project table
        (:class:`ssm_addon.base.params.StudyParams`); ``params.template.spacing_mm`` and
        ``.frame`` also set every instance's import.
    volumes : dict name -> ObjectVolume
        Each imported instance, resampled in its object frame (paper 2).
    frames : dict name -> ObjectFrame
        Object frames known without the volume (e.g. stored with a Blender scene);
        :meth:`frame` prefers the volume's.
    template : Template or None
    coatings : dict name -> CoatingResult
        The template coated onto each instance (object mm of that instance).
    model : ShapeModel or None
    metrics : ModelMetrics or None
        Compactness, generalization, specificity.
    findings : list of Finding
        Failed quality gates (:mod:`ssm_addon.model.quality`), in stage order.
    outlier_scores : dict name -> dict
        Leave-one-out Mahalanobis distance and reconstruction error per instance.
    timings_s : dict
        Wall time per stage.
    streamed : dict
        After a streamed build (:func:`stream_instances`): instances taken from the cache
        (``cached``) and coated (``computed``).
    coating_start : dict name -> CoatingStart
        How each instance's correspondence began (where it differs from its coating's own
        ``fit.start``: the model method's start).
    correspondence_rounds : list of RoundFigures
        The model method's refinement rounds.
    correspondence_check : CorrespondenceCheck or None
        The correspondence self-check (landmark transfer error) of the coatings.
    template_choice : dict
        The model method's choice of the template's instance: ``given``, ``medoid``, ``kept`` and
        ``rms_from_mean_mm`` (RMS distance from the mean, mm: of the given landmarks with
        ``template_choice = "landmark-medoid"``, which records ``by = "landmarks"``; of the
        coatings' points with ``"medoid"``, which records both templates' landmark transfer
        errors, mm). ``"medoid"`` tries the landmark medoid first: confirmed by its coatings,
        the record is that guess's (``by = "landmarks"``, ``coatings_medoid``, ``confirmed``);
        else the given template's route, with the guess under ``landmark_medoid``.
    sides : dict name -> SideDecision
        The coating stage's decision of each instance's side whose side was not given
        (:mod:`ssm_addon.correspondence.sides`): mirrored into the template's side or not, by
        landmarks, surface or undecided.
    optimisation : Optimisation or None
        The correspondence optimisation's record (``[correspondence] optimise``): its
        iterations, stop and how far each instance's points moved.
    input_distances : dict name -> dict
        Instances given as meshes: their coating against the mesh, both ways (mm:
        ``to_input``, ``from_input``, each mean, p95 and max; the mesh's outer surface, and in
        ``cavities`` how many closed parts inside the object were left out).
    cut_off : dict name -> MeshLocation
        Of those, the mesh's vertices beyond ``[quality] max_input_distance_mm``, each as its
        nearest point of the coating (a triangle and barycentric weights: the same places on the
        template); what the template's refinement reads (not saved).
    appearance : Appearance or None
        The appearance stage's boundary profiles learned from the instances' images
        (:mod:`ssm_addon.pipeline.appearance`); None without images.
    appearance_record : dict or None
        Its record for ``report.json`` (images, levels, the grey values inside and outside, seconds);
        None when the stage has not run or found no image.
    fallbacks : list of Finding
        Optional refinements of the running stage that failed and fell back to what the study
        had (the medoid's template, the model's starts, the rounds); the stage reports them.
    """

    instances: tuple[InstanceSpec, ...]
    template_instance: str = ""
    params: StudyParams = field(default_factory=StudyParams)
    volumes: dict[str, ObjectVolume] = field(default_factory=dict)
    frames: dict[str, ObjectFrame] = field(default_factory=dict)
    template: Template | None = None
    coatings: dict[str, CoatingResult] = field(default_factory=dict)
    model: ShapeModel | None = None
    metrics: ModelMetrics | None = None
    findings: list = field(default_factory=list)
    outlier_scores: dict = field(default_factory=dict)
    coating_start: dict[str, CoatingStart] = field(default_factory=dict)
    correspondence_rounds: list = field(default_factory=list)
    correspondence_check: object | None = None
    template_choice: dict = field(default_factory=dict)
    timings_s: dict[str, float] = field(default_factory=dict)
    streamed: dict = field(default_factory=dict)
    fallbacks: list = field(default_factory=list)
    input_distances: dict = field(default_factory=dict)
    cut_off: dict = field(default_factory=dict)
    optimisation: object | None = None
    sides: dict = field(default_factory=dict)
    appearance: object | None = None
    appearance_record: dict | None = None

    def __post_init__(self):
        self.instances = tuple(self.instances)
        names = [i.name for i in self.instances]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise InputError(f"study: instance names are not unique: {', '.join(dup)}")
        if not self.template_instance and names:
            self.template_instance = names[0]
        if names and self.template_instance not in names:
            raise InputError(f"study: the template instance {self.template_instance!r} is not one of the instances")

    @classmethod
    def from_project(cls, project) -> Study:
        """The study of a parsed project file (:func:`ssm_addon.pipeline.project_build.read_project`)."""
        return cls(instances=project.instances, template_instance=project.template_instance, params=project.params)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(i.name for i in self.instances)

    def instance(self, name: str) -> InstanceSpec:
        for inst in self.instances:
            if inst.name == name:
                return inst
        raise InputError(f"study: no instance named {name!r} (instances: {', '.join(self.names)})")

    def landmarks(self, name: str) -> LandmarkSet | None:
        """The instance's landmarks (world mm of its file), or None."""
        lm = self.instance(name).landmarks
        return lm if lm is not None and len(lm) else None

    def landmarks_object(self, name: str, frame: ObjectFrame | None = None) -> dict[str, np.ndarray]:
        """The instance's landmarks by name, (3,) mm in its object frame (``frame``, default
        :meth:`frame`); empty without landmarks."""
        lm = self.landmarks(name)
        if lm is None:
            return {}
        return dict(zip(lm.names, (frame or self.frame(name)).to_object(lm.points_world)))

    def frame(self, name: str) -> ObjectFrame:
        """The instance's object frame (paper 2): its volume's, else a known one."""
        if name in self.volumes:
            return self.volumes[name].frame
        if name in self.frames:
            return self.frames[name]
        raise InputError(f"study: instance {name!r} is not imported yet (no object frame)")

    def volume(self, name: str) -> ObjectVolume:
        if name not in self.volumes:
            raise InputError(f"study: instance {name!r} is not imported yet")
        return self.volumes[name]


STAGES = ("import", "template", "coating", "optimisation", "model", "appearance", "metrics")


def study_parameters(study: Study, landmark_names: Sequence[str] = ()) -> dict:
    """Every parameter of the study as JSON-ready values (what ``model.npz`` records).

    Deterministic: the same study gives the same dict (no times, dates or paths of the
    machine), so identical builds give identical model files.
    """
    return {
        "spacing_mm": float(study.params.template.spacing_mm),
        "frame_method": study.params.template.frame,
        "template_instance": study.template_instance,
        "template": study.params.template.to_dict(),
        "coating": study.params.coating.to_dict(),
        "model": dataclasses.asdict(study.params.model),
        "landmarks": list(landmark_names),
        "versions": versions(),
    }


def common_landmark_names(study: Study, names: Sequence[str]) -> tuple[str, ...]:
    """The landmark names of the template instance that every one of ``names`` also has.

    In the template instance's order; the landmark warp (eq. 2) uses exactly these.
    """
    ref = study.landmarks(study.template_instance)
    if ref is None:
        raise InputError(f"coating: the template's instance {study.template_instance!r} has no landmarks")
    missing = [n for n in names if study.landmarks(n) is None]
    if missing:
        raise InputError(f"coating: instance(s) without landmarks: {', '.join(missing)}")
    sets = [study.landmarks(n) for n in names]
    common = tuple(x for x in ref.names if all(x in s.names for s in sets))
    if len(common) < 4:
        raise InputError(f"coating: only {len(common)} landmark name(s) shared by {study.template_instance} and "
                         f"{', '.join(names)}; the landmark warp (eq. 2) needs at least 4")
    return common


def template_landmark_locations(study: Study) -> LandmarkLocations:
    """The template instance's landmarks as points of the template mesh (triangle, barycentric).

    With the template's connectivity they are the same points of every coated instance
    and of the mean shape: the landmarks a model knows (``ssm fit --landmarks``) and the
    ones written for every instance. Located once, on the template built from the
    template instance (kept in ``template.landmark_locations`` when the mean shape takes
    its place).
    """
    if study.template is not None and len(study.template.landmark_locations):
        return study.template.landmark_locations
    lm = study.landmarks(study.template_instance)
    if lm is None or study.template is None:
        return LandmarkLocations.none()
    pts = study.frame(study.template_instance).to_object(lm.points_world)
    return LandmarkLocations.locate(lm.names, study.template.points_object, study.template.faces, pts)


def carried_landmarks(study: Study) -> dict[str, LandmarkSet]:
    """The template instance's landmarks carried over to every coated instance (world mm).

    Each landmark is a fixed point of the template's triangles
    (:func:`template_landmark_locations`); on an instance it is that point of the
    instance's coating, in the instance's file-world frame. These are the landmarks a
    build writes for review (``landmarks/<name>.<ext>``), also for instances that had none.
    """
    loc = template_landmark_locations(study)
    if not len(loc):
        return {}
    out = {}
    for name in study.names:
        if name not in study.coatings:
            continue
        pts = study.frame(name).to_world(loc.evaluate(study.coatings[name].points_object, study.template.faces))
        out[name] = LandmarkSet(loc.names, pts, f"{name} (carried over by the coating)")
    return out


def input_coordinates(study: Study) -> dict[str, dict]:
    """Per instance: its source file, how that file's coordinates were taken (the convention it
    states, or the one given, turned into RAS world mm) and its landmark file's (report.json's
    ``inputs``)."""
    out = {}
    for spec in study.instances:
        if spec.mesh_path is not None:
            _space, note = mesh_coordinates(spec.mesh_path, spec.given_space(study.params.template.space))
        elif spec.volume_path is not None:
            note = label_map_coordinates(spec.volume_path)
        else:
            note = "a Blender mesh (Blender world mm)"
        lm = spec.landmarks
        out[spec.name] = {"source": str(spec.source) if spec.source is not None else "", "coordinates": note,
                          "landmarks": str(spec.landmarks_path) if spec.landmarks_path is not None else "",
                          "landmark_coordinates": lm.coordinates if lm is not None else ""}
    return out


def landmark_distances(study: Study, carried: dict[str, LandmarkSet]) -> dict[str, dict[str, float]]:
    """Per instance with given landmarks: distance (mm) of each carried-over landmark to the given one."""
    out = {}
    for name, lm in carried.items():
        given = study.landmarks(name)
        if given is None:
            continue
        g = given.as_dict()
        out[name] = {n: float(np.linalg.norm(p - g[n])) for n, p in zip(lm.names, lm.points_world) if n in g}
    return out


@dataclass(frozen=True)
class StageResult:
    """What one stage made: its product, its quality findings, its time and its summary.

    Both front ends apply the same result: the command line with :func:`apply_stage` and
    its log, Blender by writing the product into the scene and the findings into the
    panel (``operators/scene.record_stage``), so both show the same findings.

    Attributes
    ----------
    stage : str
        One of :data:`STAGES` (a streamed build's result is ``"coating"`` and covers three).
    product : dict
        The study fields the stage sets (``volumes``, ``template``, ``coatings``, ...);
        dict-valued fields are merged into the study's, ``correspondence_rounds`` extended.
    findings : tuple of Finding
        The stage's failed quality gates (:mod:`ssm_addon.model.quality`).
    timings_s : dict
        Wall time (s) per stage.
    summary : tuple of str
        The stage's summary lines (what the command line prints after the findings).
    """

    stage: str
    product: dict
    findings: tuple = ()
    timings_s: dict = field(default_factory=dict)
    summary: tuple[str, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, "findings", tuple(f if f.stage else dataclasses.replace(f, stage=self.stage)
                                                   for f in self.findings))

    def lines(self) -> list[str]:
        """The log lines of the result: one ``WARNING`` per finding, then the summary."""
        return [f"WARNING {f.instance or 'study'} [{f.gate}]: {f.message}" for f in self.findings] + list(self.summary)


def apply_stage(study: Study, result: StageResult) -> Study:
    """Put a stage's product, findings and timings into ``study`` (in place) and return it.

    A finding replaces an earlier one of the same instance and gate.
    """
    for key, value in result.product.items():
        if key == "correspondence_rounds":
            study.correspondence_rounds = list(study.correspondence_rounds) + list(value)
        elif isinstance(getattr(study, key), dict):
            getattr(study, key).update(value)
        else:
            setattr(study, key, value)
    keep = {(f.instance, f.gate) for f in result.findings}
    study.findings = [f for f in study.findings if (f.instance, f.gate) not in keep] + list(result.findings)
    study.timings_s.update(result.timings_s)
    return study


def merge_findings(recorded: Sequence[Finding], result: StageResult) -> list[Finding]:
    """Findings kept across runs of single stages (Blender): ``recorded`` updated by ``result``.

    A stage's result replaces the earlier findings of that stage for the instances it
    covers (the volumes or coatings it made; every instance for the template, model and
    metrics), so an instance coated again without a problem loses its old coating finding;
    and, as :func:`apply_stage`, any earlier finding of an instance and gate it finds again
    (the optimisation's landmark residual replaces the coating's).
    """
    product = result.product
    covered = set(product.get("coatings", {})) | set(product.get("volumes", {}))
    if result.stage not in ("import", "coating"):
        covered = None
    again = {(f.instance, f.gate) for f in result.findings}  # as :func:`apply_stage`: a finding replaces its gate's

    def replaced(f: Finding) -> bool:
        return ((f.stage == result.stage and (covered is None or f.instance in covered or not f.instance))
                or (f.instance, f.gate) in again)

    return [f for f in recorded if not replaced(f)] + list(result.findings)


def instance_sources(study: Study, names) -> dict[str, tuple]:
    """``{name: (file, label)}`` of instances: what makes two of them the same input."""
    out = {}
    for n in names:
        spec = study.instance(n)
        path = spec.volume_path if spec.volume_path is not None else spec.mesh_path
        out[n] = (str(Path(path).resolve()) if path is not None else f"<{n}>", spec.label)
    return out
