"""A study on disk: every product as arrays (``.npz``, read with ``allow_pickle=False``) and JSON.

Used to hand a finished study to another process (the Blender step of a headless build
runs in its own process) without pickling. Layout of the folder:

* ``study.json`` — the instances (sources, labels, landmark names), the parameters of
  every table, the template instance and the study's records (:func:`study_records`);
* ``arrays.npz`` — landmarks (world mm), volumes (mask, spacing, origin, frame), frames,
  the template, the coatings and the model, keyed ``<kind>/<instance>/<field>``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..base import params as P
from ..base.errors import InputError
from ..base.records import jsonable
from ..coating.coating import CoatingResult, CoatingStart, FitFigures
from ..correspondence.optimisation import Optimisation
from ..correspondence.rounds import CorrespondenceCheck, RoundFigures
from ..correspondence.sides import SideDecision
from ..formats.landmarks import LandmarkSet
from ..instances.importing import InstanceSpec
from ..instances.volume import ObjectVolume, frame_from_arrays, frame_to_arrays
from ..model.files import model_from_arrays, write_npz
from ..model.metrics import ModelMetrics
from ..model.quality import Finding
from ..pipeline.joint import JointStudy
from ..pipeline.study import Study
from ..template.template import Template

__all__ = ["RECORD_FIELDS", "apply_joint_records", "apply_records", "joint_records", "load_joint_study", "load_study",
           "load_study_or_joint", "save_joint_study", "save_study", "study_records"]

#: The study's records beside its arrays: what its stages found, decided and took.
RECORD_FIELDS = ("findings", "outlier_scores", "coating_start", "correspondence_rounds", "correspondence_check",
                 "template_choice", "metrics", "timings_s", "input_distances", "optimisation", "sides")


def study_records(study: Study) -> dict:
    """The study's records as JSON-ready values (:data:`RECORD_FIELDS`): the findings, outlier
    scores, each coating's start, the model method's rounds, the correspondence self-check,
    the template choice, the correspondence optimisation, the metrics and the stages' wall times (s). What a report needs
    besides the arrays; the Blender scene keeps them so *Save Model* writes the build's report."""
    check = study.correspondence_check
    return jsonable({
        "findings": [f.to_dict() for f in study.findings],
        "outlier_scores": study.outlier_scores,
        "coating_start": {n: str(v) for n, v in study.coating_start.items()},
        "correspondence_rounds": [r.to_dict() for r in study.correspondence_rounds],
        "correspondence_check": check.to_dict() if check is not None else None,
        "template_choice": study.template_choice,
        "metrics": study.metrics.to_dict() if study.metrics is not None else None,
        "timings_s": study.timings_s,
        "input_distances": study.input_distances,
        "optimisation": study.optimisation.to_dict() if study.optimisation is not None else None,
        "sides": {n: d.to_dict() for n, d in study.sides.items()},
    })


def apply_records(study: Study, records: dict) -> Study:
    """Put :func:`study_records`' values into ``study`` (in place) and return it; a field the
    records lack is left as it is."""
    if "findings" in records:
        study.findings = [Finding.from_dict(f) for f in records["findings"]]
    if "sides" in records:
        study.sides = {n: SideDecision.from_dict(d) for n, d in (records["sides"] or {}).items()}
    if "outlier_scores" in records:
        study.outlier_scores = dict(records["outlier_scores"] or {})
    if "coating_start" in records:
        study.coating_start = {n: CoatingStart(v) for n, v in (records["coating_start"] or {}).items()}
    if "correspondence_rounds" in records:
        study.correspondence_rounds = [RoundFigures.from_dict(r) for r in records["correspondence_rounds"] or ()]
    if "correspondence_check" in records:
        check = records["correspondence_check"]
        study.correspondence_check = CorrespondenceCheck.from_dict(check) if check else None
    if "template_choice" in records:
        study.template_choice = dict(records["template_choice"] or {})
    if "metrics" in records:
        study.metrics = ModelMetrics.from_dict(records["metrics"])
    if "input_distances" in records:
        study.input_distances = dict(records["input_distances"] or {})
    if "timings_s" in records:
        study.timings_s = {k: float(v) for k, v in (records["timings_s"] or {}).items()}
    if "optimisation" in records:
        study.optimisation = Optimisation.from_dict(records["optimisation"]) if records["optimisation"] else None
    return study


def save_study(study: Study, folder, *, extra: dict | None = None) -> Path:
    """Write ``study`` into ``folder`` (created); returns the folder."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, np.ndarray] = {}
    insts = []
    for i, spec in enumerate(study.instances):
        lm = spec.landmarks
        insts.append({"name": spec.name, "landmarks": spec.landmarks_path, "volume": spec.volume_path, "label": spec.label,
                      "mesh": spec.mesh_path, "mesh_spacing": spec.mesh_spacing_mm, "space": spec.space,
                      "landmark_names": list(lm.names) if lm is not None else None,
                      "landmark_source": lm.source if lm is not None else ""})
        if lm is not None:
            arrays[f"landmarks/{i}"] = np.asarray(lm.points_world, float)
    index = {n: i for i, n in enumerate(study.names)}
    for name, ov in study.volumes.items():
        k = index[name]
        arrays[f"volume/{k}/mask"] = np.asarray(ov.mask, bool)
        arrays[f"volume/{k}/spacing_mm"] = np.asarray(ov.spacing_mm, float)
        arrays[f"volume/{k}/origin_object"] = np.asarray(ov.origin_object, float)
        arrays[f"volume/{k}/source"] = np.asarray(ov.source)
        frame_to_arrays(f"volume/{k}/frame", ov.frame, arrays)
    for name, frame in study.frames.items():
        frame_to_arrays(f"frame/{index[name]}", frame, arrays)
    t = study.template
    if t is not None:
        arrays.update({f"template/{k}": np.asarray(v) for k, v in t.to_arrays().items()})
        frame_to_arrays("template/frame", t.frame, arrays)
    for name, c in study.coatings.items():
        k = index[name]
        arrays[f"coating/{k}/points_object"] = np.asarray(c.points_object, float)
        arrays[f"coating/{k}/warped_points_object"] = np.asarray(c.warped_points_object, float)
        arrays[f"coating/{k}/fit_json"] = np.asarray(c.fit.to_json())
    if study.model is not None:
        _model_arrays(study.model, arrays)
    doc = {
        "instances": insts,
        "template_instance": study.template_instance,
        "parameters": study.params.to_tables(),
        "records": study_records(study),
        "extra": extra or {},
    }
    (folder / "study.json").write_text(json.dumps(jsonable(doc)), encoding="utf-8")
    write_npz(folder / "arrays.npz", arrays)
    return folder


def _read_stored(folder: Path, doc_name: str, arrays_name: str, what: str) -> tuple[dict, dict]:
    """A stored folder's JSON document and arrays (read without pickles)."""
    try:
        doc = json.loads((folder / doc_name).read_text(encoding="utf-8"))
        with np.load(folder / arrays_name, allow_pickle=False) as npz:
            return doc, {k: npz[k] for k in npz.files}
    except (OSError, ValueError) as err:
        raise InputError(f"{folder}: not a stored {what} ({err})") from None


def load_study(folder) -> tuple[Study, dict]:
    """Read a study written by :func:`save_study`; returns (study, extra)."""
    folder = Path(folder)
    doc, a = _read_stored(folder, "study.json", "arrays.npz", "study")
    specs = []
    for i, d in enumerate(doc["instances"]):
        lm = None
        if d["landmark_names"] is not None:
            lm = LandmarkSet(tuple(d["landmark_names"]), a[f"landmarks/{i}"], d.get("landmark_source", ""))
        specs.append(InstanceSpec(name=d["name"], landmarks_path=Path(d["landmarks"]) if d["landmarks"] else None,
                                  volume_path=Path(d["volume"]) if d["volume"] else None, label=d["label"],
                                  mesh_path=Path(d["mesh"]) if d["mesh"] else None, mesh_spacing_mm=d["mesh_spacing"],
                                  space=d.get("space"),
                                  landmarks=lm))
    par = doc["parameters"]
    study = Study(instances=tuple(specs), template_instance=doc["template_instance"],
                  params=P.StudyParams.from_tables(par, where=f"{folder}:"))
    for k, spec in enumerate(specs):
        if f"volume/{k}/mask" in a:
            study.volumes[spec.name] = ObjectVolume(
                mask=a[f"volume/{k}/mask"], spacing_mm=float(a[f"volume/{k}/spacing_mm"]),
                origin_object=a[f"volume/{k}/origin_object"], frame=frame_from_arrays(f"volume/{k}/frame", a),
                source=str(a[f"volume/{k}/source"]))
        if f"frame/{k}/origin_world" in a:
            study.frames[spec.name] = frame_from_arrays(f"frame/{k}", a)
        if f"coating/{k}/points_object" in a:
            study.coatings[spec.name] = CoatingResult(
                points_object=a[f"coating/{k}/points_object"], warped_points_object=a[f"coating/{k}/warped_points_object"],
                fit=FitFigures.from_json(str(a[f"coating/{k}/fit_json"])), name=spec.name)
    if "template/points_object" in a:
        study.template = Template.from_arrays({k.removeprefix("template/"): v for k, v in a.items()
                                               if k.startswith("template/")}, frame_from_arrays("template/frame", a))
    study.model = _model_from_arrays(a, folder)
    apply_records(study, doc.get("records") or {})
    return study, doc.get("extra", {})


def _model_arrays(m, arrays: dict) -> None:
    """A model's arrays into ``arrays`` (keys ``model/<field>``)."""
    for key in ("mean", "faces", "modes", "variances", "instance_points", "instance_points_world"):
        arrays[f"model/{key}"] = np.asarray(getattr(m, key))
    arrays["model/instance_names"] = np.asarray([str(s) for s in m.instance_names])
    arrays["model/params_json"] = np.asarray(json.dumps(jsonable(m.params)))
    if m.structure_names:  # a joint model
        arrays["model/structure_names"] = np.asarray([str(s) for s in m.structure_names])
        arrays["model/structure_offsets"] = np.asarray(m.structure_offsets, np.int64)


def _model_from_arrays(a: dict, folder):
    """The model :func:`_model_arrays` wrote, or None."""
    if "model/mean" not in a:
        return None
    keys = ("mean", "faces", "modes", "variances", "instance_names", "instance_points", "instance_points_world",
            "structure_names", "structure_offsets")
    return model_from_arrays({**{k: a[f"model/{k}"] for k in keys if f"model/{k}" in a},
                              "params": json.loads(str(a["model/params_json"]))}, str(folder))


# ------------------------------------------------------------------------------ a joint study
def joint_records(joint: JointStudy) -> dict:
    """A joint study's records as JSON-ready values: each structure's template instance and
    :func:`study_records`, and the joint model's own (metrics, each structure's metrics, shape and
    relative pose, collisions, findings, outlier scores, wall times). With the arrays (templates,
    frames, coatings, the model) they are what the joint build's writer needs; Blender keeps them
    in the .blend so *Save Model* of a reopened joint model writes the build's files."""
    return jsonable({
        "subjects": list(joint.subjects),
        "structures": {name: {"template_instance": study.template_instance, "records": study_records(study)}
                       for name, study in joint.structures.items()},
        "joint": {"metrics": joint.metrics.to_dict() if joint.metrics is not None else None,
                  "structure_metrics": joint.structure_metrics, "shape_pose": joint.shape_pose,
                  "collisions": joint.collisions, "findings": [f.to_dict() for f in joint.findings],
                  "outlier_scores": joint.outlier_scores, "timings_s": joint.timings_s},
    })


def apply_joint_records(joint: JointStudy, records: dict) -> JointStudy:
    """Put :func:`joint_records`' values into ``joint`` and its structures' studies (in place)."""
    for name, rec in (records.get("structures") or {}).items():
        if name in joint.structures:
            apply_records(joint.structures[name], rec.get("records") or {})
    j = records.get("joint") or {}
    joint.metrics = ModelMetrics.from_dict(j.get("metrics")) if j.get("metrics") else None
    joint.structure_metrics = dict(j.get("structure_metrics") or {})
    joint.shape_pose = dict(j.get("shape_pose") or {})
    joint.collisions = dict(j.get("collisions") or {})
    joint.findings = [Finding.from_dict(f) for f in j.get("findings") or ()]
    joint.outlier_scores = dict(j.get("outlier_scores") or {})
    joint.timings_s = {k: float(v) for k, v in (j.get("timings_s") or {}).items()}
    return joint


def save_joint_study(joint: JointStudy, folder, *, extra: dict | None = None) -> Path:
    """Write a joint study into ``folder`` (created): ``joint.json`` (subjects, structure order, the
    project's parameters, :func:`joint_records`), each structure's study under ``structures/<k>/``
    (:func:`save_study`) and the joint model in ``model.npz``. Returns the folder."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for k, study in enumerate(joint.structures.values()):
        save_study(study, folder / "structures" / str(k))
    arrays: dict[str, np.ndarray] = {}
    if joint.model is not None:
        _model_arrays(joint.model, arrays)
    write_npz(folder / "model.npz", arrays)
    doc = {"structures": list(joint.structures), "parameters": joint.params.to_tables(),
           "records": joint_records(joint), "extra": extra or {}}
    (folder / "joint.json").write_text(json.dumps(jsonable(doc)), encoding="utf-8")
    return folder


def load_joint_study(folder) -> tuple[JointStudy, dict]:
    """Read a joint study written by :func:`save_joint_study`; returns (joint study, extra)."""
    folder = Path(folder)
    doc, a = _read_stored(folder, "joint.json", "model.npz", "joint study")
    studies = {name: load_study(folder / "structures" / str(k))[0] for k, name in enumerate(doc["structures"])}
    records = doc.get("records") or {}
    joint = JointStudy(subjects=tuple(records.get("subjects") or next(iter(studies.values())).names),
                       structures=studies, params=P.StudyParams.from_tables(doc["parameters"], where=f"{folder}:"))
    joint.model = _model_from_arrays(a, folder)
    joint.metrics = None
    apply_joint_records(joint, {"joint": records.get("joint") or {}})  # each study's records came with it
    return joint, doc.get("extra", {})


def load_study_or_joint(folder):
    """:func:`load_joint_study` or :func:`load_study`, whichever ``folder`` holds."""
    return load_joint_study(folder) if (Path(folder) / "joint.json").is_file() else load_study(folder)
