"""The study in the scene: where the core's :class:`~ssm_addon.pipeline.study.Study` lives in a .blend.

Every operator builds a study from the scene (:func:`study_from_scene`), calls one
core stage function on it, and writes the product back. What is stored where:

* **instances**: mesh objects (role INSTANCE) in the "SSM Instances" collection, in
  study order (``obj.ssm.order``). The source file (relative to the .blend once it is
  saved), label and mesh spacing are properties; the object frame (paper 2) and the
  import matrix are float64 ID properties (``obj["ssm_frame"]``). The mesh is a display
  surface only.
* **volumes**: never stored. They are recomputed from the source by the core's
  :func:`~ssm_addon.instances.importing.import_instance` (the same call as the command line) and
  kept in memory for the session (:data:`_VOLUMES`).
* **landmarks**: sphere empties parented to their instance; each keeps its position
  in the instance's file world mm as float64 (``emp["ssm_point_mm"]``). The empty's
  location is a view of it: an empty the user moved is read back from its location
  (deliberately), an unmoved one gives the stored value exactly.
* **template**, **coatings**: the template object and one coated object per instance,
  with their float64 points in ``obj["ssm_template"]`` / ``obj["ssm_coating"]``; their
  meshes are float32 views.
* **model**: the model object's ``obj["ssm_model"]`` (see ``operators/model.py``).
* **parameters**: the scene's property groups derived from :mod:`ssm_addon.base.params`.

So a saved and re-opened .blend continues exactly where it was, as long as the source
files are where the instances say.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from pathlib import Path

import bpy
import numpy as np
from mathutils import Vector

from ssm_addon.base import params as P
from ssm_addon.base.errors import InputError
from ssm_addon.base.progress import report, sub_progress
from ssm_addon.base.records import jsonable
from ssm_addon.coating.coating import CoatingResult, FitFigures
from ssm_addon.correspondence.optimisation import OptimisationCancelled
from ssm_addon.formats.landmarks import LandmarkSet
from ssm_addon.instances import importing as core_instances
from ssm_addon.instances.importing import InstanceSpec
from ssm_addon.instances.volume import ObjectFrame, ObjectVolume, mirrored, mirrored_frame
from ssm_addon.model.files import model_from_arrays
from ssm_addon.model.pca import ShapeModel
from ssm_addon.model.quality import Finding
from ssm_addon.pipeline.joint import JointStudy
from ssm_addon.pipeline.optimisation import optimisation_result, optimisation_stage
from ssm_addon.pipeline.stages import import_result
from ssm_addon.pipeline.store import RECORD_FIELDS, apply_joint_records, apply_records, joint_records, study_records
from ssm_addon.pipeline.study import StageResult, Study, apply_stage, merge_findings
from ssm_addon.segmentation.appearance import load_appearance
from ssm_addon.template.template import Template

from . import bridge
from .properties import scene_params, scene_study_params

FRAME_KEY = "ssm_frame"
TEMPLATE_KEY = "ssm_template"
COATING_KEY = "ssm_coating"
POINT_KEY = "ssm_point_mm"
LANDMARK_PROP = "ssm_landmark"
ORDER_PROP = "ssm_landmark_index"
TEMPLATE_NAME = "SSM Template"
TEMPLATE_COLLECTION = "SSM Template"
COATED_COLLECTION = "SSM Coated"
COATED_SUFFIX = " coated"
MOVED_TOLERANCE_MM = 1e-3
"""A landmark empty farther than this from its stored position was moved by the user."""

_VOLUMES: dict[tuple, ObjectVolume] = {}


# ---------------------------------------------------------------------------- instances
def is_instance(obj) -> bool:
    """True for an SSM instance (a mesh object with role INSTANCE)."""
    return obj is not None and obj.type == "MESH" and obj.ssm.role == "INSTANCE"


def scene_instances(context) -> list:
    """The scene's instance objects in study order."""
    return sorted((o for o in context.scene.objects if is_instance(o)), key=lambda o: (o.ssm.order, o.name))


def next_order(context) -> int:
    return max((o.ssm.order for o in context.scene.objects if is_instance(o)), default=-1) + 1


#: Model object property: the file an imported model was read from (what a segmentation's
#: segment.json names as its model).
MODEL_FILE_PROP = "ssm_model_file"
#: Instance property: 1 when the instance is mirrored into the template's side (its given side, or
#: the coating stage's decision, :mod:`ssm_addon.correspondence.sides`), 0 when it is not; absent:
#: not decided. The frame stored at import stays the file's; :func:`stored_frame` mirrors it.
MIRROR_PROP = "ssm_mirror"
#: Instance property: the side given for the instance ("left" or "right"), from a project.
SIDE_PROP = "ssm_side"


def stored_frame(obj) -> ObjectFrame | None:
    """The object frame of an instance (file world mm, float64), or None: mirrored
    (:func:`~ssm_addon.instances.volume.mirrored_frame`) where the instance is mirrored into the
    template's side, as the core's import of its spec gives it."""
    d = bridge.load_arrays(obj, FRAME_KEY)
    if d is None:
        return None
    frame = ObjectFrame(origin_world=d["origin_world"], axes_world=d["axes_world"],
                        second_moments_mm2=d.get("second_moments_mm2", np.zeros(3)), method=d.get("method", "moments"))
    return mirrored_frame(frame) if obj.get(MIRROR_PROP) == 1 else frame


def instance_mirror(obj) -> bool | None:
    """Whether the instance is mirrored into the template's side (None: not decided)."""
    return {1: True, 0: False}.get(obj.get(MIRROR_PROP))


def set_side(obj, *, mirror: bool | None, side: str | None = None) -> None:
    """Record an instance's side: ``mirror`` (None: not decided) and the ``side`` given, if any."""
    if mirror is None:
        obj.pop(MIRROR_PROP, None)
    else:
        obj[MIRROR_PROP] = int(bool(mirror))
    if side:
        obj[SIDE_PROP] = str(side)
    else:
        obj.pop(SIDE_PROP, None)


def apply_sides(decisions: dict, objects: dict | None = None) -> None:
    """Record a coating stage's side decisions (``product["sides"]``) on the instance objects, before
    their coatings are written (a mirrored instance's coating is shown through its mirrored frame).
    ``objects``: instance name -> object (a joint structure's, named by subject); default by name."""
    for name, decision in (decisions or {}).items():
        obj = bpy.data.objects.get(name) if objects is None else objects.get(name)
        if obj is not None and obj.ssm.role == "INSTANCE":
            obj[MIRROR_PROP] = int(bool(decision.mirror))


def import_matrix(obj) -> np.ndarray:
    """(4, 4) ``matrix_world`` at import (float64); maps Blender world back to file world."""
    d = bridge.load_arrays(obj, FRAME_KEY)
    return d["import_matrix"] if d is not None and "import_matrix" in d else np.eye(4)


def write_frame(obj, frame: ObjectFrame, import_mat: np.ndarray) -> None:
    """Store an instance's object frame as its file gives it (a mirrored frame unmirrored: the
    instance's :data:`MIRROR_PROP` says it is mirrored, :func:`set_side`)."""
    if frame.mirrored:
        frame = mirrored_frame(frame)
    bridge.store_arrays(obj, FRAME_KEY, {
        "origin_world": frame.origin_world, "axes_world": frame.axes_world,
        "second_moments_mm2": frame.second_moments_mm2, "method": frame.method, "import_matrix": import_mat,
    })


def _moved(obj) -> np.ndarray | None:
    """Blender world -> file world of an instance the user moved, else None (identity)."""
    imp = import_matrix(obj)
    cur = bridge.matrix_to_numpy(obj.matrix_world)
    if np.allclose(cur, imp.astype(np.float32), rtol=0, atol=1e-4 * max(1.0, float(np.abs(imp).max()))):
        return None
    return imp @ np.linalg.inv(cur)


def blender_to_file_world(obj, points_blender_world) -> np.ndarray:
    """(M, 3) Blender world mm -> the instance's file world mm.

    file world = import_matrix @ inverse(matrix_world) @ p, so moving an instance in the
    viewport after import does not change landmark coordinates in the file's frame.
    """
    pts = np.asarray(points_blender_world, dtype=float).reshape(-1, 3)
    m = _moved(obj)
    return pts if m is None else pts @ m[:3, :3].T + m[:3, 3]


def file_to_blender_world(obj, points_file_world) -> np.ndarray:
    """(M, 3) file world mm -> Blender world mm (inverse of :func:`blender_to_file_world`)."""
    pts = np.asarray(points_file_world, dtype=float).reshape(-1, 3)
    m = _moved(obj)
    if m is None:
        return pts
    inv = np.linalg.inv(m)
    return pts @ inv[:3, :3].T + inv[:3, 3]


def object_to_blender_matrix(instance) -> np.ndarray:
    """(4, 4) the instance's object frame (mm) -> Blender world (mm)."""
    frame = stored_frame(instance)
    if frame is None:
        raise InputError(f"instance {instance.name!r} has no object frame (import it with SSM)")
    m = _moved(instance)
    fw = frame.matrix_world
    return fw if m is None else np.linalg.inv(m) @ fw


def absolute_source_path(obj) -> str:
    return os.path.normpath(bpy.path.abspath(obj.ssm.source)) if obj.ssm.source else ""


def relative_source(path: str) -> str:
    """``//``-relative path when the .blend is saved (and on the same drive), else absolute."""
    path = os.path.abspath(path)
    if not bpy.data.filepath:
        return path
    try:
        return bpy.path.relpath(path)
    except ValueError:
        return path


def mesh_file_world(obj) -> tuple[np.ndarray, np.ndarray]:
    """A Blender-mesh instance's current mesh in its file world mm, and its triangles."""
    verts = blender_to_file_world(obj, bridge.object_world_vertices(obj))
    return verts, bridge.mesh_triangles(obj.data)


def instance_spec(context, obj) -> InstanceSpec:
    """The instance as the core sees it (source, label, landmarks in file world mm)."""
    ssm = obj.ssm
    lm = instance_landmarks(context, obj)
    lm = lm if len(lm) else None
    path = Path(absolute_source_path(obj)) if obj.ssm.source else None
    mesh_spacing = float(ssm.mesh_spacing_mm) or None
    sides = {"side": obj.get(SIDE_PROP) or None, "mirror": instance_mirror(obj)}
    if ssm.source_kind == "VOLUME":
        return InstanceSpec(name=obj.name, volume_path=path, label=None if ssm.label < 0 else int(ssm.label), landmarks=lm,
                            **sides)
    if ssm.source_kind == "MESH_FILE":
        return InstanceSpec(name=obj.name, mesh_path=path, mesh_spacing_mm=mesh_spacing, landmarks=lm, **sides)
    return InstanceSpec(name=obj.name, mesh_spacing_mm=mesh_spacing, landmarks=lm, **sides)


# ---------------------------------------------------------------------------- landmarks
def schema_names(context) -> tuple[str, ...]:
    """The landmark schema: ordered names."""
    return tuple(item.name for item in context.scene.ssm_landmarks.names)


def landmark_empties(instance) -> dict:
    """``{landmark name: empty}`` of an instance: its children that are its landmarks.

    Landmark empties are parented to their instance (:func:`set_landmark`), so this reads
    the instance's children, not every object of the file (panels call it while drawing).
    """
    out = {}
    for obj in instance.children:
        if obj.ssm.role == "LANDMARK" and obj.ssm.instance == instance and LANDMARK_PROP in obj:
            out[str(obj[LANDMARK_PROP])] = obj
    return out


def ordered_landmark_names(context, empties: dict) -> list[str]:
    schema = schema_names(context)
    extra = sorted((n for n in empties if n not in schema), key=lambda n: (empties[n].get(ORDER_PROP, 1 << 30), n))
    return [n for n in schema if n in empties] + extra


def landmark_point(instance, emp) -> np.ndarray:
    """A landmark in the instance's file world mm (float64).

    The stored value, unless the empty was moved away from it in the viewport; then the
    empty's location, converted.
    """
    here = np.array(emp.matrix_world.translation, dtype=float)
    stored = emp.get(POINT_KEY)
    if stored is not None:
        stored = np.array(stored, dtype=float)
        if np.linalg.norm(file_to_blender_world(instance, stored)[0] - here) <= MOVED_TOLERANCE_MM:
            return stored
    return blender_to_file_world(instance, here)[0]


def instance_landmarks(context, instance) -> LandmarkSet:
    """An instance's landmarks in file world mm (schema order, then extra names)."""
    empties = landmark_empties(instance)
    names = ordered_landmark_names(context, empties)
    pts = np.array([landmark_point(instance, empties[n]) for n in names], dtype=float).reshape(-1, 3)
    return LandmarkSet(tuple(names), pts, instance.name)


def landmark_sets_by_instance(context) -> dict[str, LandmarkSet]:
    """``{instance name: LandmarkSet}`` (file world mm) for every instance with landmarks."""
    out = {}
    for inst in scene_instances(context):
        lm = instance_landmarks(context, inst)
        if len(lm):
            out[inst.name] = lm
    return out


def _marker_size(context, instance) -> float:
    size = context.scene.ssm_landmarks.marker_size_mm
    return size if size > 0 else max(0.5, 0.015 * max(instance.dimensions))


def set_landmark(context, instance, name: str, *, file_world=None, blender_world=None, order: int | None = None):
    """Create or move the landmark ``name`` of ``instance``.

    Give its position in the instance's file world mm (``file_world``, kept exactly) or
    in Blender world mm (``blender_world``, e.g. a click).
    """
    if file_world is None:
        file_world = blender_to_file_world(instance, blender_world)[0]
    file_world = np.asarray(file_world, dtype=float).reshape(3)
    loc = Vector(file_to_blender_world(instance, file_world)[0].tolist())
    emp = landmark_empties(instance).get(name)
    if emp is None:
        emp = bridge.add_empty(context, f"{instance.name} {name}", loc, parent=instance,
                               size=_marker_size(context, instance))
        emp.ssm.role = "LANDMARK"
        emp.ssm.instance = instance
        emp[LANDMARK_PROP] = name
        schema = schema_names(context)
        emp[ORDER_PROP] = schema.index(name) if name in schema else (order if order is not None else len(schema))
        emp.show_name = False
    else:
        emp.matrix_world.translation = loc
    emp[POINT_KEY] = file_world.astype(np.float64)
    return emp


# ------------------------------------------------------------------------------ volumes
def _volume_key(context, obj):
    tp = scene_params(context, "ssm_template")
    ssm = obj.ssm
    base = (tp.spacing_mm, tp.frame, tp.space, ssm.source_kind, ssm.label, float(ssm.mesh_spacing_mm),
            bool(instance_mirror(obj)))  # undecided and "not mirrored" import the same volume
    if ssm.source_kind == "BLENDER_MESH":
        verts, faces = mesh_file_world(obj)
        digest = hashlib.sha1(verts.astype(np.float32).tobytes() + faces.astype(np.int32).tobytes()).hexdigest()
        return (*base, "mesh", digest)
    path = absolute_source_path(obj)
    if not os.path.isfile(path):
        raise InputError(f"instance {obj.name!r}: source file {path or '(none)'} not found (moved? set its Source "
                         f"path in the Instances panel)")
    return (*base, path, os.path.getmtime(path))


class VolumeLoader:
    """The volumes a job needs: cached ones at once, the others read in the worker thread.

    Built on the main thread (it reads the scene); :meth:`load` uses only the core, so
    it runs in a worker; :meth:`keep` caches what was read (main thread again).
    """

    def __init__(self, context, objs):
        self.ready: dict[str, ObjectVolume] = {}
        self.todo: list = []
        self.keys: dict[str, tuple] = {}
        self.loaded: dict[str, ObjectVolume] = {}
        tp = scene_params(context, "ssm_template")
        self.spacing, self.frame_method, self.space = tp.spacing_mm, tp.frame, tp.space
        for obj in objs:
            key = _volume_key(context, obj)
            self.keys[obj.name] = key
            if key in _VOLUMES:
                self.ready[obj.name] = _VOLUMES[key]
                continue
            spec = instance_spec(context, obj)
            mesh = mesh_file_world(obj) if obj.ssm.source_kind == "BLENDER_MESH" else None
            self.todo.append((spec, mesh, stored_frame(obj)))

    def load(self, progress=None, cancelled=None) -> dict[str, ObjectVolume]:
        """Every requested volume (reads the missing ones with the core's import)."""
        out = dict(self.ready)
        n = len(self.todo)
        for k, (spec, mesh, frame) in enumerate(self.todo):
            prog = sub_progress(progress, k / max(n, 1), (k + 1) / max(n, 1), f"{spec.name}: ")
            report(prog, 0.0, "reading")
            if mesh is not None:
                ov = core_instances.object_from_mesh(mesh[0], mesh[1], spacing_mm=self.spacing,
                                                     mesh_spacing_mm=spec.mesh_spacing_mm,
                                                     frame_method=self.frame_method, source=spec.name,
                                                     cancelled=cancelled)
                ov = mirrored(ov) if spec.mirror else ov
            else:
                ov = core_instances.import_instance(spec, spacing_mm=self.spacing, frame_method=self.frame_method,
                                                    space=self.space,
                                                    progress=prog, cancelled=cancelled)
            if frame is not None and not (np.allclose(ov.frame.origin_world, frame.origin_world, atol=1e-6)
                                          and np.allclose(ov.frame.axes_world, frame.axes_world, atol=1e-9)):
                raise InputError(f"instance {spec.name!r}: its object frame differs from the one at import (the "
                                 f"source or the frame setting changed); import it again")
            out[spec.name] = ov
            self.loaded[spec.name] = ov
        return out

    def keep(self) -> None:
        for name, ov in self.loaded.items():
            _VOLUMES[self.keys[name]] = ov


def cache_volume(context, obj, ov: ObjectVolume) -> None:
    _VOLUMES[_volume_key(context, obj)] = ov


def clear_volume_cache() -> None:
    """Forget every cached object volume (they are reloaded from source on demand)."""
    _VOLUMES.clear()


# ------------------------------------------------------------------ template and coatings
def find_template(context):
    """The template object (role TEMPLATE with stored points), or None."""
    obj = bpy.data.objects.get(TEMPLATE_NAME)
    if obj is not None and obj.type == "MESH" and obj.ssm.role == "TEMPLATE" and TEMPLATE_KEY in obj:
        return obj
    return next((o for o in context.scene.objects
                 if o.type == "MESH" and o.ssm.role == "TEMPLATE" and TEMPLATE_KEY in o), None)


def write_template_object(context, instance, template):
    """Create or replace ``"SSM Template"`` for ``template`` built from ``instance``."""
    faces = np.asarray(template.faces)
    obj = find_template(context) or bpy.data.objects.get(TEMPLATE_NAME)
    name = obj.name if obj is not None else TEMPLATE_NAME
    obj = bridge.new_mesh_object(context, name, template.points_object, faces,
                                 collection_name=TEMPLATE_COLLECTION, matrix_world=object_to_blender_matrix(instance))
    bridge.store_arrays(obj, TEMPLATE_KEY, template.to_arrays())
    bridge.colour_correspondence(obj, template.points_object, context.scene.ssm_display.colouring)
    bridge.set_point_attribute(obj.data, "curvature", np.asarray(template.curvature))
    obj.ssm.role = "TEMPLATE"
    obj.ssm.instance = instance
    context.scene.ssm_display.template_instance = instance
    return obj


def template_from_object(obj) -> Template:
    """The float64 template stored on the template object."""
    d = bridge.load_arrays(obj, TEMPLATE_KEY)
    if d is None or obj.ssm.instance is None:
        raise InputError(f"{obj.name!r}: no template stored (build the template)")
    return Template.from_arrays(d, stored_frame(obj.ssm.instance))


def coated_objects(context) -> list:
    """Coated meshes of the scene whose instance exists, in study order."""
    order = {o: i for i, o in enumerate(scene_instances(context))}
    objs = [o for o in context.scene.objects if o.type == "MESH" and o.ssm.role == "COATED" and o.ssm.instance in order]
    return sorted(objs, key=lambda o: order[o.ssm.instance])


def coated_object_of(instance):
    """The coated mesh of an instance (found by its instance pointer, so renames are safe)."""
    return next((o for o in bpy.data.objects if o.ssm.role == "COATED" and o.ssm.instance == instance), None)


def coating_from_object(obj) -> CoatingResult:
    d = bridge.load_arrays(obj, COATING_KEY)
    if d is None:
        raise InputError(f"{obj.name!r}: no coating stored (coat the template again)")
    fit = FitFigures.from_json(obj.ssm.fit_json) if obj.ssm.fit_json else FitFigures(0, 0, 0, 0, 0)
    return CoatingResult(points_object=d["points_object"], warped_points_object=d.get("warped_points_object",
                         d["points_object"]), fit=fit, name=obj.ssm.instance.name)


# --------------------------------------------------------------------------------- study
# ---------------------------------------------------------------------------------------
# the model kept with its object
# ---------------------------------------------------------------------------------------
MODEL_KEY = "ssm_model"
MODEL_COLLECTION = "SSM Model"
MODEL_NAME = "SSM Model"


def store_model(obj: bpy.types.Object, model: ShapeModel) -> None:
    """Keep ``model`` in ``obj["ssm_model"]`` (binary arrays; survives save/reopen)."""
    n, npts, k = model.n_instances, model.n_points, model.n_modes
    obj[MODEL_KEY] = {
        "shape_json": json.dumps({"n": n, "N": npts, "K": k, "F": int(len(model.faces))}),
        "mean": np.ascontiguousarray(model.mean, dtype=np.float64).ravel(),
        "faces": np.ascontiguousarray(model.faces, dtype=np.int32).ravel(),
        "modes": np.ascontiguousarray(model.modes, dtype=np.float64).ravel(),
        "variances": np.ascontiguousarray(model.variances, dtype=np.float64),
        "fractions": np.asarray(model.variances / max(model.total_variance, 1e-300), dtype=np.float64),
        "instance_points": np.ascontiguousarray(model.instance_points, dtype=np.float64).ravel(),
        "instance_points_world": np.ascontiguousarray(model.instance_points_world, dtype=np.float64).ravel(),
        "names_json": json.dumps([str(s) for s in model.instance_names]),
        "params_json": json.dumps(model.params),
        "structures_json": json.dumps({"names": list(model.structure_names), "offsets": [
            int(x) for x in (model.structure_offsets if model.structure_offsets is not None else ())]}),
    }


def has_model(obj) -> bool:
    return obj is not None and obj.get(MODEL_KEY) is not None


def model_from_object(obj: bpy.types.Object) -> ShapeModel:
    """The ShapeModel stored on a model object (raises InputError naming the object)."""
    if not has_model(obj):
        raise InputError(f"object '{getattr(obj, 'name', obj)}': no SSM model stored (build the model first)")
    g = obj[MODEL_KEY]
    try:
        shp = json.loads(g["shape_json"])
        n, npts, k, nf = shp["n"], shp["N"], shp["K"], shp["F"]

        def arr(key, shape, dtype=np.float64):
            return np.array(np.asarray(g[key]), dtype=dtype).reshape(shape)

        arrays = {
            "mean": arr("mean", (npts, 3)),
            "faces": arr("faces", (nf, 3), np.int64),
            "modes": arr("modes", (k, npts, 3)),
            "variances": arr("variances", (k,)),
            "instance_points": arr("instance_points", (n, npts, 3)),
            "instance_points_world": arr("instance_points_world", (n, npts, 3)),
            "instance_names": np.asarray(json.loads(g["names_json"]), dtype=str).reshape(n),
            "params": json.loads(g["params_json"]),
        }
        structures = json.loads(g.get("structures_json", "{}") or "{}")
        if structures.get("names"):
            arrays["structure_names"] = np.asarray(structures["names"])
            arrays["structure_offsets"] = np.asarray(structures["offsets"], dtype=np.int64)
    except (KeyError, ValueError, TypeError) as err:
        raise InputError(f"object '{obj.name}': the stored SSM model is damaged ({err})") from err
    return model_from_arrays(arrays, f"object '{obj.name}'")


def model_structures(obj) -> list[str]:
    """The structure names of a joint model object (empty for a model of one structure)."""
    if obj is None or MODEL_KEY not in obj:
        return []
    return list(json.loads(obj[MODEL_KEY].get("structures_json", "{}") or "{}").get("names") or [])


class ModeSlider:
    """One mode's slider of a model object, in standard deviations (b_k / √λ_k, eq. 7): a shape
    key of the mean mesh, or (a joint model) the custom property ``"Mode k"`` of the model's
    empty, which drives that mode's shape key of every structure."""

    def __init__(self, owner, name: str, key=None):
        self.owner, self.name, self.key = owner, name, key

    @property
    def value(self) -> float:
        return float(self.key.value if self.key is not None else self.owner[self.name])

    @value.setter
    def value(self, v: float) -> None:
        if self.key is not None:
            self.key.value = float(v)
        else:
            self.owner[self.name] = float(v)
            self.owner.update_tag()  # the structures' drivers read it on the next evaluation

    def keyframe(self, frame: int) -> None:
        if self.key is not None:
            self.key.keyframe_insert("value", frame=frame)
        else:
            self.owner.keyframe_insert(f'["{self.name}"]', frame=frame)

    def set_range(self, lo: float, hi: float) -> None:
        if self.key is not None:
            self.key.slider_min, self.key.slider_max = float(lo), float(hi)
        else:
            self.owner.id_properties_ui(self.name).update(soft_min=float(lo), soft_max=float(hi))

    def draw(self, layout) -> None:
        if self.key is not None:
            layout.prop(self.key, "value", text="", slider=True)
        else:
            layout.prop(self.owner, f'["{self.name}"]', text="", slider=True)


def mode_sliders(obj) -> list[ModeSlider]:
    """The mode sliders ("Mode 1", ...) of a model object, in order: the shape keys of a mesh
    model, the custom properties of a joint model's empty."""
    if obj is None:
        return []
    if obj.type == "MESH":
        return [ModeSlider(obj, kb.name, kb) for kb in mode_keys(obj)]
    names = sorted((k for k in obj.keys() if k.startswith("Mode ") and k[5:].isdigit()), key=lambda k: int(k[5:]))
    return [ModeSlider(obj, k) for k in names]


def clear_mode_animation(obj) -> None:
    """Remove the keyframes of a model object's mode sliders."""
    owner = obj.data.shape_keys if obj.type == "MESH" else obj
    if owner is not None:
        owner.animation_data_clear()


def model_parts(obj) -> list:
    """The structure meshes of a joint model's empty (its MODEL_PART children), in structure order."""
    if obj is None or obj.type == "MESH":
        return []
    order = {n: i for i, n in enumerate(model_structures(obj))}
    parts = [c for c in obj.children if c.ssm.role == "MODEL_PART"]
    return sorted(parts, key=lambda c: order.get(c.get("ssm_structure", ""), len(order)))


def mode_keys(obj) -> list:
    """The mode shape keys ("Mode 1", ...) of a model object, in order."""
    keys = obj.data.shape_keys if obj is not None and obj.type == "MESH" else None
    if keys is None:
        return []
    return [kb for kb in keys.key_blocks if kb.name.startswith("Mode ")]


def find_model_object(context) -> bpy.types.Object | None:
    """The active object if it is a model, else the first model object in the scene."""
    obj = context.active_object
    if obj is not None and obj.ssm.role == "MODEL_PART" and obj.parent is not None:
        obj = obj.parent  # a structure of a joint model: the model is its empty
    if obj is not None and obj.ssm.role == "MODEL" and has_model(obj):
        return obj
    for ob in context.scene.objects:
        if ob.ssm.role == "MODEL" and has_model(ob):
            return ob
    return None


# ---------------------------------------------------------------------------------------
# the records of the stages run in this scene: findings, starts, rounds, self-check, timings
# ---------------------------------------------------------------------------------------
RECORDS_KEY = "ssm_study_records"
#: Keys of the scene's records before they were one record (read from older .blend files).
_OLD_KEYS = {"findings": "ssm_findings", "correspondence_check": "ssm_correspondence_check",
             "correspondence_rounds": "ssm_correspondence_rounds", "template_choice": "ssm_template_choice"}


def scene_records(context) -> dict:
    """The study records of the stages run in this scene (``Scene["ssm_study_records"]``,
    :func:`ssm_addon.pipeline.store.study_records`' form): what *Save Model* writes into the
    report beside the arrays, and what the panels draw."""
    return records_of(context.scene)


def records_of(scene) -> dict:
    """:func:`scene_records` of ``scene``."""
    raw = scene.get(RECORDS_KEY)
    if raw is not None:
        try:
            return json.loads(raw)
        except ValueError:
            return {}
    out = {}
    for key, old in _OLD_KEYS.items():  # a .blend saved before the records were one
        if old in scene:
            try:
                out[key] = json.loads(scene[old])
            except ValueError:
                pass
    return out


def write_records(scene, records: dict) -> None:
    """Keep ``records`` (:func:`ssm_addon.pipeline.store.study_records`' form) in the scene."""
    scene[RECORDS_KEY] = json.dumps(jsonable(records))
    for old in _OLD_KEYS.values():
        if old in scene:
            del scene[old]


def scene_findings(context) -> list[Finding]:
    """The findings of the stages run in this scene, in stage order: the same findings (stage,
    gate, instance, figure) a headless build of the scene's project writes into ``report.json``."""
    try:
        return [Finding.from_dict(d) for d in scene_records(context).get("findings") or ()]
    except (ValueError, KeyError, TypeError):
        return []


def record_stage(context, result, *, fresh: bool = True) -> list[Finding]:
    """Keep a stage result's records in the scene; returns the stage's findings.

    Findings as :func:`ssm_addon.pipeline.study.merge_findings` (the stage's earlier findings
    of the instances it covers replaced), the stage's wall times, and the records it made
    (outlier scores, each coating's start, rounds, self-check, template choice, metrics). A
    coating stage replaces the correspondence records (its self-check, or none, describes
    the coatings now in the scene); one that continues the model method's rounds
    (``fresh=False``) extends the rounds.
    """
    holder = apply_records(Study(instances=()), scene_records(context))
    recorded = list(holder.findings)
    product = {k: v for k, v in result.product.items() if k in RECORD_FIELDS}
    if result.stage == "model":
        holder.metrics = None  # the metrics described the model this one replaces
    if result.stage == "coating":
        if fresh:
            holder.correspondence_rounds = []
        holder.template_choice = {}
        holder.optimisation = None  # new coatings: not optimised (yet)
        product.setdefault("correspondence_check", None)
    apply_stage(holder, StageResult(result.stage, product, (), dict(result.timings_s)))
    holder.findings = merge_findings(recorded, result)
    write_records(context.scene, study_records(holder))
    return [f for f in holder.findings if f.stage == result.stage]


def report_stage(op, message: str, findings: list[Finding]) -> None:
    """Report a stage's outcome on ``op``: a WARNING naming every failed gate, else INFO."""
    if findings:
        op.report({"WARNING"}, f"{message}; quality gates failed: " + "; ".join(str(f) for f in findings))
    else:
        op.report({"INFO"}, message)


def instance_findings(context, name: str, stage: str | None = None) -> list[Finding]:
    """The recorded findings of instance ``name`` (of ``stage`` only, when given)."""
    return [f for f in scene_findings(context) if f.instance == name and stage in (None, f.stage)]


def study_from_scene(context, *, template_instance: str | None = None, template: bool = True,
                     coatings: bool = True, records: bool = False) -> Study:
    """The scene's study: instances (study order), parameters, frames, template, coatings, and
    (``records``) the records of the stages run in the scene (:func:`scene_records`).

    Volumes are not loaded here (see :class:`VolumeLoader`).
    """
    objs = scene_instances(context)
    if not objs:
        raise InputError("no SSM instances in the scene: import segmentations first (File > Import > "
                         "Segmentation (SSM))")
    tpl = find_template(context) if template else None
    if template_instance is None:
        chosen = context.scene.ssm_display.template_instance
        if tpl is not None and tpl.ssm.instance is not None and is_instance(tpl.ssm.instance):
            template_instance = tpl.ssm.instance.name
        elif is_instance(chosen) and chosen in objs:
            template_instance = chosen.name
        else:
            template_instance = objs[0].name
    study = Study(instances=tuple(instance_spec(context, o) for o in objs), template_instance=template_instance,
                  params=scene_study_params(context))
    for o in objs:
        frame = stored_frame(o)
        if frame is not None:
            study.frames[o.name] = frame
    if tpl is not None and tpl.ssm.instance is not None and tpl.ssm.instance.name == template_instance:
        study.template = template_from_object(tpl)
    if coatings:
        for obj in coated_objects(context):
            if COATING_KEY in obj:
                study.coatings[obj.ssm.instance.name] = coating_from_object(obj)
    if records:
        apply_records(study, scene_records(context))
    return study


#: Scene property (JSON) of a joint study opened from a project: each structure's tables that
#: differ from the scene's (``{"tables": {structure: {table: {key: value}}}}``) and the subject
#: its template comes from (``{"template_instances": {structure: subject}}``).
JOINT_KEY = "ssm_joint"
#: Scene property (JSON list of lines) of the last joint build's failed gates, for the Model panel.
JOINT_FINDINGS_KEY = "ssm_joint_findings"


#: The joint study last built in this Blender session, by its model object's session id: what
#: *Save Model* writes through the build's writer. The .blend keeps it too, on the model object
#: (:data:`JOINT_RECORDS_KEY`, :data:`JOINT_TEMPLATE_KEY`), with the scene's instances and coatings.
_JOINT_BUILDS: dict = {}
#: Model object property (JSON): the joint build's records (:func:`~ssm_addon.pipeline.store.joint_records`).
JOINT_RECORDS_KEY = "ssm_joint_records"
#: Model object property (arrays): structure ``k``'s template (``JOINT_TEMPLATE_KEY.format(k)``).
JOINT_TEMPLATE_KEY = "ssm_joint_template_{}"


def remember_joint_study(obj, joint: JointStudy) -> None:
    """Keep the joint study a *Build Joint Model* (or a headless joint build) made ``obj`` from: for
    this session (the last build only, without its resampled volumes: its writer needs frames,
    templates and coatings), and in the .blend (its records and each structure's template on
    ``obj``; the instances, their frames and coatings are the scene's objects)."""
    for study in joint.structures.values():
        for name, ov in study.volumes.items():
            study.frames.setdefault(name, ov.frame)
        study.volumes.clear()
    _JOINT_BUILDS.clear()
    _JOINT_BUILDS[obj.session_uid] = joint
    obj[JOINT_RECORDS_KEY] = json.dumps(joint_records(joint))
    for k, study in enumerate(joint.structures.values()):
        bridge.store_arrays(obj, JOINT_TEMPLATE_KEY.format(k), study.template.to_arrays())


def joint_study_of(context, obj, model: ShapeModel) -> tuple[JointStudy | None, str]:
    """The joint study ``obj``'s model was built from: this session's build, else the one the .blend
    keeps (:func:`remember_joint_study`) with the scene's instances and coatings. Returns
    ``(joint, "")``, or ``(None, why)`` when the scene does not hold it (a model imported from a
    file, a model changed since, instances or coatings removed)."""
    joint = _JOINT_BUILDS.get(obj.session_uid)
    if joint is not None and joint.model is not None:
        same = all(np.array_equal(getattr(joint.model, k), getattr(model, k)) for k in ("mean", "modes", "variances"))
        if same:
            return joint, ""
    raw = obj.get(JOINT_RECORDS_KEY)
    if raw is None:
        return None, "a joint model without its build in this scene (an imported model): the model's own files"
    records = json.loads(raw)
    try:
        joint = joint_study_from_scene(context)
    except InputError as err:
        return None, f"a joint model whose instances are no longer in the scene ({err}): the model's own files"
    order = list(records.get("structures") or {})
    if list(joint.names) != list(model.structure_names) or sorted(order) != sorted(joint.names) \
            or [str(n) for n in model.instance_names] != list(joint.subjects):
        return None, (f"a joint model of {', '.join(model.structure_names)} whose scene now holds "
                      f"{', '.join(joint.names)} of other subjects: the model's own files")
    objs = {(o.ssm.structure, o.ssm.subject or o.name): o for o in scene_instances(context)}
    coated = {(o.ssm.instance.ssm.structure, o.ssm.instance.ssm.subject or o.ssm.instance.name): o
              for o in coated_objects(context) if COATING_KEY in o}
    for name, study in joint.structures.items():
        study.template_instance = records["structures"][name]["template_instance"]
        for subject in joint.subjects:
            frame = stored_frame(objs[(name, subject)])
            if frame is not None:
                study.frames[subject] = frame
            if (name, subject) not in coated:
                return None, (f"a joint model whose coated {name} of {subject} is no longer in the scene: the "
                              "model's own files")
            study.coatings[subject] = dataclasses.replace(coating_from_object(coated[(name, subject)]), name=subject)
        arrays = bridge.load_arrays(obj, JOINT_TEMPLATE_KEY.format(order.index(name)))
        if arrays is None:
            return None, f"a joint model without structure {name}'s template: the model's own files"
        study.template = Template.from_arrays(arrays, study.frame(study.template_instance))
    apply_joint_records(joint, records)
    joint.model = model
    return joint, ""


def scene_structures(context) -> list[str]:
    """The structures of the scene's instances, in study order (empty: a study of one structure)."""
    out = []
    for o in scene_instances(context):
        if o.ssm.structure and o.ssm.structure not in out:
            out.append(o.ssm.structure)
    return out


def joint_study_from_scene(context) -> JointStudy:
    """The scene's joint study: each structure's instances as the scene holds them (sources and
    landmarks, named by subject), the scene's parameters with each structure's own tables over
    them, the subjects in study order. What a joint project's build runs on
    (:meth:`~ssm_addon.pipeline.joint.JointStudy.from_project`), read from the scene."""
    names = scene_structures(context)
    if len(names) < 2:
        raise InputError("the scene holds no joint study (its instances are of one structure): open a project whose "
                         "instances hold several structures (meshes = { … } or labels = { … })")
    doc = json.loads(context.scene.get(JOINT_KEY, "") or "{}")
    base = scene_study_params(context)
    objs = scene_instances(context)
    stray = [o.name for o in objs if not o.ssm.structure]
    if stray:
        raise InputError(f"instance(s) {', '.join(stray[:5])} belong to no structure of the scene's joint study "
                         f"({', '.join(names)}): remove them or set their structure")
    subjects = list(dict.fromkeys(o.ssm.subject or o.name for o in objs))
    studies = {}
    for name in names:
        mine = {o.ssm.subject or o.name: o for o in objs if o.ssm.structure == name}
        missing = [s for s in subjects if s not in mine]
        if missing:
            raise InputError(f"structure {name!r}: no instance of subject(s) {', '.join(missing[:5])}")
        specs = tuple(dataclasses.replace(instance_spec(context, mine[s]), name=s) for s in subjects)
        over = (doc.get("tables") or {}).get(name, {})
        tables = {t: P.from_table(P.TABLES[t], {**P.to_table(getattr(base, t)), **over.get(t, {})},
                                  where=f"structure {name} [{t}]:") for t in over}
        template_instance = (doc.get("template_instances") or {}).get(name) or subjects[0]
        studies[name] = Study(instances=specs, template_instance=template_instance, params=base.replace(**tables))
    return JointStudy(subjects=tuple(subjects), structures=studies, params=base)


#: Scene property holding the instances' own attribute tables of an opened project (JSON), written
#: back when the project is saved and used by Run Analysis when no attribute file is given.
INSTANCE_ATTRIBUTES_KEY = "ssm_instance_attributes"


def scene_instance_attributes(context) -> dict:
    """``{instance name: {column: value}}`` of the project opened into the scene (empty if none)."""
    raw = context.scene.get(INSTANCE_ATTRIBUTES_KEY)
    return json.loads(raw) if raw else {}


def write_coated(context, instance, result: CoatingResult, faces, template_points):
    """Create or replace the coated mesh of ``instance`` for one coating result."""
    obj = coated_object_of(instance)
    name = instance.name + COATED_SUFFIX
    if obj is not None and obj.name != name and bpy.data.objects.get(name) is None:
        obj.name = name  # the instance was renamed
    obj = bridge.new_mesh_object(context, obj.name if obj is not None else name, result.points_object, faces,
                                 collection_name=COATED_COLLECTION, matrix_world=object_to_blender_matrix(instance))
    bridge.store_arrays(obj, COATING_KEY, {"points_object": result.points_object,
                                           "warped_points_object": result.warped_points_object})
    bridge.colour_correspondence(obj, template_points, context.scene.ssm_display.colouring)
    obj.ssm.role = "COATED"
    obj.ssm.instance = instance
    obj.ssm.fit_json = result.fit.to_json()
    return obj


def prepare_optimisation(op, context, *, then=None):
    """The work of the correspondence optimisation on the scene's study (the core's
    :func:`~ssm_addon.pipeline.optimisation.optimisation_stage`, the build's step): each
    iteration's objective in the status bar; Esc keeps the last complete iteration. ``then(study)``,
    optional: more work on the optimised study (Build Model's PCA), its result returned fourth."""
    study = study_from_scene(context, records=True)
    if study.template is None or any(n not in study.coatings for n in study.names):
        raise InputError("optimise correspondence: coat every instance first (Coating panel)")
    loader = VolumeLoader(context, scene_instances(context))
    op._loader, op._faces, op._template_points = loader, study.template.faces, study.template.points_object
    cancel_after = getattr(op, "cancel_after", -1)
    iterations = study.params.correspondence.optimise_iterations
    done = [0]

    def work(progress, cancelled):
        def stop():
            return bool(cancelled and cancelled()) or 0 <= cancel_after <= done[0]

        def step(s):
            done[0] = s.iteration
            if progress is not None:
                progress(0.1 + 0.8 * s.iteration / max(iterations, 1),
                         f"optimisation: iteration {s.iteration}/{iterations}, objective {s.objective:.4f}")

        t0 = time.perf_counter()
        imported = import_result(study, loader.load(sub_progress(progress, 0.0, 0.1), stop), time.perf_counter() - t0)
        apply_stage(study, imported)
        t0 = time.perf_counter()
        try:
            result, was_cancelled = optimisation_stage(study, cancelled=stop, on_step=step), False
        except OptimisationCancelled as err:  # Esc: the last complete iteration is kept
            result, was_cancelled = optimisation_result(study, err.result, time.perf_counter() - t0), True
        if then is None:
            return imported, result, was_cancelled
        apply_stage(study, result)
        return imported, result, was_cancelled, (None if was_cancelled else then(study))

    return work


def finish_optimisation(op, context, imported, result) -> list:
    """Write the optimised coatings and the optimisation's record into the scene; the findings."""
    op._loader.keep()
    for name, coating in result.product["coatings"].items():
        inst = bpy.data.objects.get(name)
        if inst is not None:
            start = coated_object_of(inst).get("ssm_coating_start") if coated_object_of(inst) is not None else None
            obj = write_coated(context, inst, coating, op._faces, op._template_points)
            if start is not None:
                obj["ssm_coating_start"] = start
    return record_stage(context, imported) + record_stage(context, result)


def scene_optimisation(context) -> dict:
    """The record of the correspondence optimisation of the coatings in this scene (empty when none ran)."""
    return scene_records(context).get("optimisation") or {}


APPEARANCE_KEY = "ssm_appearance"
"""The model object's ID property holding a model file's learned boundary appearance."""


def store_appearance(obj, path, n_points: int) -> bool:
    """Keep a model file's learned appearance on the model object (for *Segment with Model*)."""
    appearance = load_appearance(path, n_points)
    if appearance is None:
        return False
    arrays = appearance.to_arrays()
    arrays["appearance_images"] = json.dumps(list(appearance.images))  # names as text (ID properties hold numbers)
    bridge.store_arrays(obj, APPEARANCE_KEY, arrays)
    return True
