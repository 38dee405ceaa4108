"""Project files in Blender (Save / Open Project) and the Blender part of a headless build.

* ``ssm.save_project`` writes the scene's study as a ``project.toml`` (the format of
  :mod:`ssm_addon.pipeline.project_build`): every instance with its source, the landmarks as
  ``landmarks/<instance>.fcsv`` (full precision, so the headless build reads the same
  float64 numbers), Blender-mesh instances as ``meshes/<instance>.ply``, and every
  parameter of the scene (the same numbers the operators use). Saving, opening and
  saving again gives the same bytes.
* ``ssm.open_project`` imports the instances of a project with their landmarks and
  parameters (the same core import as File > Import); a joint project's, one object per
  structure per subject.
* ``ssm.build_joint_model`` builds a joint study from the scene (each structure's instances
  and landmarks as the scene holds them) with the build's computation
  (:func:`~ssm_addon.pipeline.joint.run_joint`) and shows the coated meshes and the joint model.
* :func:`write_build_outputs` is what ``build`` calls when ``bpy`` is available:
  ``modes.png`` (paper fig. 10) and ``model.blend`` with the study's objects.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import bpy
import numpy as np
from bpy.props import StringProperty
from bpy_extras.io_utils import ExportHelper, ImportHelper

from ssm_addon.base.errors import InputError, SSMError
from ssm_addon.base.params import OutputParams, QualityParams
from ssm_addon.formats import landmarks as core_landmarks
from ssm_addon.formats.meshes import write_ply
from ssm_addon.instances.importing import InstanceSpec, file_names, import_instance
from ssm_addon.instances.volume import display_surface
from ssm_addon.pipeline import project as core
from ssm_addon.pipeline.joint import JointStudy, run_joint
from ssm_addon.pipeline.store import study_records

from . import bridge, register
from .instances import add_instance_objects, import_items, write_instance
from .jobs import BackgroundJob
from .landmarks import add_schema_name
from .model import create_model_object
from .properties import SSMPanel, draw_params, set_scene_study_params
from .render import render_modes_figure
from .scene import (
    INSTANCE_ATTRIBUTES_KEY,
    JOINT_FINDINGS_KEY,
    JOINT_KEY,
    apply_sides,
    joint_study_from_scene,
    mesh_file_world,
    remember_joint_study,
    scene_instance_attributes,
    scene_instances,
    scene_structures,
    set_landmark,
    study_from_scene,
    write_coated,
    write_records,
    write_template_object,
)

# ------------------------------------------------------------------ scene construction


def _ensure_registered() -> None:
    """Register the Blender layer in a bare ``bpy`` module (``ssm build`` without Blender)."""
    if not hasattr(bpy.types.Object, "ssm"):
        register()


def place_landmarks(context, obj, landmarks) -> None:
    """Put an instance's landmarks (file world mm) on it as empties, their names in the scene's
    schema (in their order), nothing when ``landmarks`` is None."""
    if landmarks is None:
        return
    schema = context.scene.ssm_landmarks
    for name in landmarks.names:
        if name not in {i.name for i in schema.names}:
            add_schema_name(schema, name)
    for i, (name, p) in enumerate(zip(landmarks.names, landmarks.points_world)):
        set_landmark(context, obj, name, file_world=p, order=i)


def _instance_object(context, study, spec, order: int, name: str):
    """An instance of ``study`` as the scene shows it: the display surface of its resampled volume
    (read again when a streamed build kept none: the same frame), its records and landmarks."""
    ov = study.volumes.get(spec.name)
    if ov is None:
        ov = import_instance(spec, spacing_mm=study.params.template.spacing_mm, space=study.params.template.space,
                             frame_method=study.params.template.frame)
    verts, faces = display_surface(ov)
    obj = bridge.new_mesh_object(context, name, verts, faces, collection_name=bridge.INSTANCES_COLLECTION,
                                 matrix_world=ov.frame.matrix_world)
    obj.ssm.order = order
    write_instance(context, obj, spec, kind="VOLUME" if spec.volume_path is not None else "MESH_FILE", frame=ov.frame,
                   volume_mm3=ov.volume_mm3, voxels=int(np.count_nonzero(ov.mask)))
    place_landmarks(context, obj, spec.landmarks)
    return obj


def show_study(context, study) -> dict:
    """Put a study's products into the scene: instances, landmarks, template, coatings, model.

    The same writers the operators use; instances show the display surface of their
    resampled volume.
    """
    scene = context.scene
    bridge.ensure_mm_units(scene)
    set_scene_study_params(scene, study.params)
    objs = {spec.name: _instance_object(context, study, spec, order, spec.name)
            for order, spec in enumerate(study.instances)}
    scene.ssm_display.template_instance = objs[study.template_instance]
    out = {}
    if study.template is not None:
        out["template"] = write_template_object(context, objs[study.template_instance], study.template)
        for name, coating in study.coatings.items():
            write_coated(context, objs[name], coating, study.template.faces, study.template.points_object)
    if study.model is not None:
        out["model"] = create_model_object(context, study.model,
                                           template_points=study.template.points_object if study.template else None)
    write_records(scene, study_records(study))  # what the panels show and Save Model reports
    return out


def _write_blend(path, fill) -> str:
    """An empty file, ``fill(context)``'s objects in it, saved as a copy at ``path``."""
    _ensure_registered()
    bpy.ops.wm.read_homefile(use_empty=True)
    fill(bpy.context)
    path = str(Path(path).resolve())
    bpy.ops.wm.save_as_mainfile(filepath=path, check_existing=False, copy=True)
    return path


def show_joint_study(context, joint) -> dict:
    """Put a joint study's products into the scene as *Open Project* and *Build Joint Model* leave
    it: one object per structure per subject (``"<subject> <structure>"``) with its landmarks and
    coated mesh, the project's parameters and each structure's own tables, the joint model (an
    empty with one slider per mode driving a mesh per structure) keeping its joint study
    (:func:`~.scene.remember_joint_study`, so *Save Model* writes the build's files after the
    .blend is reopened) and the build's findings for the Model panel."""
    scene = context.scene
    bridge.ensure_mm_units(scene)
    set_scene_study_params(scene, joint.params)
    # the project's template instances (a build may have coated from a medoid's template: it chooses
    # again from the given one, as ssm build does)
    scene[JOINT_KEY] = json.dumps({"tables": core.structure_overrides(joint), "template_instances": {
        name: (study.template_choice or {}).get("given", study.template_instance)
        for name, study in joint.structures.items()}})
    first = None
    for name, study in joint.structures.items():
        for order, spec in enumerate(study.instances):
            obj = _instance_object(context, study, spec, order, f"{spec.name} {name}")
            obj.ssm.structure, obj.ssm.subject = name, spec.name
            write_coated(context, obj, study.coatings[spec.name], study.template.faces, study.template.points_object)
            if first is None and spec.name == study.template_instance:
                first = obj
    scene.ssm_display.template_instance = first
    obj = create_model_object(context, joint.model, activate=False)
    remember_joint_study(obj, joint)
    scene[JOINT_FINDINGS_KEY] = json.dumps(joint_findings_lines(joint))
    return {"model": obj}


def joint_findings_lines(joint) -> list[str]:
    """A joint build's findings, one line each, named ``structure/subject`` (the Model panel's)."""
    lines = [f"{name}/{f.instance or 'study'} [{f.gate}]: {f.message}" for name, study in
             joint.structures.items() for f in study.findings]
    return lines + [f"joint model [{f.gate}]: {f.message}" for f in joint.findings]


def _hide_coated_instances(context) -> None:
    """Opened as saved: the correspondence colours in Solid shading, and the coated meshes not hidden
    by the voxel surfaces they sit on (the instances are hidden, Alt+H shows them)."""
    coated = {o.ssm.instance.name for o in bpy.data.objects if o.ssm.role == "COATED" and o.ssm.instance}
    for layer in context.scene.view_layers:
        layer.update()  # synced with the collections the objects were just linked to
        for obj in layer.objects:
            if obj.ssm.role == "INSTANCE" and obj.name in coated:
                obj.hide_set(True, view_layer=layer)


def write_model_blend(study, path) -> str:
    """Write ``model.blend`` for a built study (a :class:`~ssm_addon.pipeline.joint.JointStudy`
    too): an empty file plus the study's objects."""

    def fill(context):
        (show_joint_study if isinstance(study, JointStudy) else show_study)(context, study)
        _hide_coated_instances(context)

    return _write_blend(path, fill)


def write_build_outputs(study, output: OutputParams, out_dir: Path, log=print) -> dict:
    """The Blender part of a headless build: ``modes.png`` (paper fig. 10) and ``model.blend``.

    Parameters
    ----------
    study : Study
        The built study (template, coatings, model).
    output : OutputParams
        The build's ``[output]`` table (which pictures; the .blend keeps it).
    out_dir : Path
        Where the files go.
    log : callable or None
        Gets one line per file written.

    A :class:`~ssm_addon.pipeline.joint.JointStudy` gets ``modes.png`` of the joint model and a
    ``model.blend`` with every structure's instances, landmarks and coated meshes and the joint
    model, as *Open Project* and *Build Joint Model* leave the scene.

    Returns ``{"picture": "modes.png", "blend": "model.blend"}`` (names inside ``out_dir``).
    """
    _ensure_registered()
    out = {}
    if output.picture:
        render_modes_figure(study.model, Path(out_dir) / "modes.png", n_modes=int(output.picture_modes))
        out["picture"] = "modes.png"
        if log:
            log("picture: modes.png (mean and ±2σ of the first modes, axial / sagittal / coronal)")
    write_model_blend(dataclasses.replace(study, params=study.params.replace(output=output)),
                      Path(out_dir) / "model.blend")
    if log:
        log("blend: model.blend (" + ("every structure's instances, landmarks and coated meshes; the joint model: an "
                                      "empty with one slider per mode driving a mesh per structure)"
                                      if isinstance(study, JointStudy) else
                                      "instances, landmarks, template, coated instances, model with shape keys)"))
    out["blend"] = "model.blend"
    return out


# ------------------------------------------------------------------------ save / open


def _saved_spec(spec: InstanceSpec, obj, folder: Path, stem: str) -> InstanceSpec:
    """``spec`` as a project file states it: its landmarks written to ``landmarks/<stem>.fcsv``
    (LPS, file world mm, full precision), a Blender mesh to ``meshes/<stem>.ply``."""
    lm_path = None
    if spec.landmarks is not None:
        (folder / "landmarks").mkdir(parents=True, exist_ok=True)
        lm_path = folder / "landmarks" / f"{stem}.fcsv"
        core_landmarks.write_landmarks(lm_path, spec.landmarks)
    mesh_path = spec.mesh_path
    if spec.source is None:  # a Blender mesh: written out
        (folder / "meshes").mkdir(parents=True, exist_ok=True)
        mesh_path = folder / "meshes" / f"{stem}.ply"
        verts, faces = mesh_file_world(obj)
        write_ply(mesh_path, verts, faces)
    return InstanceSpec(name=spec.name, landmarks_path=lm_path, volume_path=spec.volume_path, label=spec.label,
                        mesh_path=mesh_path, mesh_spacing_mm=spec.mesh_spacing_mm, landmarks=spec.landmarks)


def project_from_scene(context, path) -> core.Project:
    """The scene's study as a Project for ``path``, writing its landmark (and mesh) files.

    Landmarks go to ``<folder>/landmarks/<instance>.fcsv`` (LPS, file world mm, full
    precision); instances made from Blender meshes to ``<folder>/meshes/<instance>.ply``.
    A joint study's files are named ``<subject>_<structure>``.
    """
    path = Path(path).resolve()
    folder = path.parent
    if scene_structures(context):
        return _joint_project_from_scene(context, path)
    study = study_from_scene(context, coatings=False)
    if len(study.instances) < 2:
        raise InputError(f"the scene has {len(study.instances)} SSM instance(s); a project needs at least two")
    _check_landmarks(study, "")
    files = file_names(i.name for i in study.instances)
    objs = {o.name: o for o in scene_instances(context)}
    specs = [_saved_spec(spec, objs[spec.name], folder, files[spec.name]) for spec in study.instances]
    return core.Project(path=path, instances=tuple(specs), template_instance=study.template_instance,
                        params=study.params, landmark_names=study.landmarks(study.template_instance).names,
                        instance_attributes={n: a for n, a in scene_instance_attributes(context).items()
                                             if n in {i.name for i in specs}})


def _check_landmarks(study, where: str) -> None:
    """Landmarks on every instance (on the template instance alone for the model method)."""
    missing = [i.name for i in study.instances if i.landmarks is None]
    if missing and study.params.correspondence.method != "model":
        raise InputError(f"{where}no landmarks on instance(s) {', '.join(missing)}: place or import them first (or "
                         "set the correspondence method to Model, which needs them on the template instance only)")
    if study.template_instance in missing:
        raise InputError(f"{where}no landmarks on the template instance {study.template_instance}: place or import "
                         "them first")


def _joint_project_from_scene(context, path: Path) -> core.Project:
    """:func:`project_from_scene` of a joint study: each structure's instances (named by subject)
    with its own tables, as *Build Joint Model* reads them."""
    joint = joint_study_from_scene(context)
    objs = {(o.ssm.structure, o.ssm.subject or o.name): o for o in scene_instances(context)}
    files = file_names(joint.subjects)
    structures = {}
    for name, study in joint.structures.items():
        _check_landmarks(study, f"structure {name}: ")
        specs = tuple(_saved_spec(spec, objs[(name, spec.name)], path.parent, f"{files[spec.name]}_{name}")
                      for spec in study.instances)
        structures[name] = core.Structure(name=name, instances=specs, template_instance=study.template_instance,
                                          params=study.params,
                                          landmark_names=study.landmarks(study.template_instance).names)
    first = structures[next(iter(structures))]
    return core.Project(path=path, instances=first.instances, template_instance=first.template_instance,
                        params=joint.params, landmark_names=first.landmark_names,
                        instance_attributes={n: a for n, a in scene_instance_attributes(context).items()
                                             if n in joint.subjects}, structures=structures)


def load_project_into_scene(context, project: core.Project) -> list:
    """Import every instance of ``project`` with its landmarks, and its parameters.

    The instances go through the same core import as File > Import; an error leaves
    the scene as it was (nothing is created before every instance has been read).
    """
    scene = context.scene
    if project.structures:
        return load_joint_project_into_scene(context, project)
    items = import_items(project.instances, spacing_mm=project.params.template.spacing_mm,
                         frame_method=project.params.template.frame, space=project.params.template.space)
    set_scene_study_params(scene, project.params)
    scene[INSTANCE_ATTRIBUTES_KEY] = json.dumps(project.instance_attributes)
    created = add_instance_objects(context, items)
    for obj, spec in zip(created, project.instances):
        if obj.name != spec.name and bpy.data.objects.get(spec.name) is None:
            obj.name = spec.name
        place_landmarks(context, obj, spec.landmarks)
    template = next((o for o in created if o.name == project.template_instance), created[0] if created else None)
    scene.ssm_display.template_instance = template
    bridge.select_only(context, created, active=template)
    return created


def load_joint_project_into_scene(context, project: core.Project) -> list:
    """Import every structure's instances of a joint project: one object per structure per
    subject (``"<subject> <structure>"``, ``obj.ssm.structure`` and ``obj.ssm.subject`` set) with
    its landmarks, the project's parameters into the scene and each structure's own tables
    (``[[structures]]``) into ``Scene["ssm_joint"]``, so *Build Joint Model* runs what ``ssm build``
    runs. An error leaves the scene as it was (every instance is read first)."""
    scene = context.scene
    if any(o.ssm.structure == "" for o in scene_instances(context)):  # before reading any file
        raise InputError(f"{project.path}: the scene holds a study of one structure; open the joint project in a new "
                         "file (File > New) so the two studies do not mix")
    per_structure = {}
    for name, st in project.structures.items():  # read everything before the scene changes
        tp = st.params.template
        per_structure[name] = import_items(st.instances, spacing_mm=tp.spacing_mm, frame_method=tp.frame,
                                           space=tp.space)
    set_scene_study_params(scene, project.params)
    scene[INSTANCE_ATTRIBUTES_KEY] = json.dumps(project.instance_attributes)
    scene[JOINT_KEY] = json.dumps({"tables": core.structure_overrides(project), "template_instances": {
        name: st.template_instance for name, st in project.structures.items()}})
    created = []
    for name, st in project.structures.items():
        objs = add_instance_objects(context, per_structure[name])
        for obj, spec in zip(objs, st.instances):
            wanted = f"{spec.name} {name}"
            if obj.name != wanted and bpy.data.objects.get(wanted) is None:
                obj.name = wanted
            obj.ssm.structure, obj.ssm.subject = name, spec.name
            place_landmarks(context, obj, spec.landmarks)
        created += objs
    first = project.structures[next(iter(project.structures))]
    template = next((o for o in created if o.ssm.subject == first.template_instance), created[0] if created else None)
    scene.ssm_display.template_instance = template
    bridge.select_only(context, created, active=template)
    return created


class SSM_OT_build_joint_model(BackgroundJob, bpy.types.Operator):
    """Build the joint model of the scene's structures: each structure's template, coating and gates, then one model of their shapes and relative poses (what ssm build runs on a joint project)"""

    bl_idname = "ssm.build_joint_model"
    bl_label = "Build Joint Model"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if len(scene_structures(context)) < 2:
            cls.poll_message_set("Open a joint project first (instances of several structures)")
            return False
        return True

    def prepare(self, context):
        joint = joint_study_from_scene(context)  # read here: the worker thread must not touch bpy
        self._lines = []

        def work(progress, cancelled):
            return run_joint(joint, progress=progress, cancelled=cancelled, log=self._lines.append)

        return work

    def finish(self, context, joint):
        objs = {(o.ssm.structure, o.ssm.subject or o.name): o for o in scene_instances(context)}
        for name, study in joint.structures.items():
            # each subject's side, one for all its structures (run_joint), before its coatings are shown
            apply_sides(study.sides, {s: objs.get((name, s)) for s in study.sides})
            for subject, coating in study.coatings.items():
                inst = objs.get((name, subject))
                if inst is not None:
                    write_coated(context, inst, coating, study.template.faces, study.template.points_object)
        obj = create_model_object(context, joint.model, activate=False)
        remember_joint_study(obj, joint)  # Save Model writes it as ssm build does, in this session and after
        findings = joint_findings_lines(joint)
        context.scene[JOINT_FINDINGS_KEY] = json.dumps(findings)
        share = joint.model.variability_concentration()
        k3 = min(3, joint.model.n_modes)
        msg = (f"{obj.name}: joint model of {', '.join(joint.names)}: {joint.model.n_modes} modes from "
               f"{joint.model.n_instances} subjects; first {k3}: {100 * share[k3 - 1] if k3 else 0.0:.1f} %")
        self.report({"WARNING"} if findings else {"INFO"}, msg + "".join(f"; {f}" for f in findings))
        return {"FINISHED"}


class SSM_OT_save_project(bpy.types.Operator, ExportHelper):
    """Save the scene's instances, landmarks and parameters as a project file (TOML) to rerun the build headless"""

    bl_idname = "ssm.save_project"
    bl_label = "Save Project"
    bl_options = {"REGISTER"}

    filename_ext = ".toml"
    filter_glob: StringProperty(default="*.toml", options={"HIDDEN"})

    def execute(self, context):
        try:
            project = project_from_scene(context, self.filepath)
            path = core.write_project(self.filepath, project)
            core.read_project(path)  # what the headless build will see
        except SSMError as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Saved project with {len(project.instances)} instances to {path}")
        return {"FINISHED"}


class SSM_OT_open_project(bpy.types.Operator, ImportHelper):
    """Load a project file (TOML): import its instances, their landmarks and the parameters into the scene"""

    bl_idname = "ssm.open_project"
    bl_label = "Open Project"
    bl_options = {"REGISTER", "UNDO"}

    filename_ext = ".toml"
    filter_glob: StringProperty(default="*.toml", options={"HIDDEN"})

    def execute(self, context):
        try:
            project = core.read_project(self.filepath)
            created = load_project_into_scene(context, project)
        except SSMError as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        structures = scene_structures(context)
        self.report({"INFO"}, f"Opened {os.path.basename(self.filepath)}: {len(created)} instances"
                              + (f" of {len(structures)} structures ({', '.join(structures)}); Model panel: Build "
                                 "Joint Model" if structures else ""))
        return {"FINISHED"}


class SSM_PT_project(SSMPanel, bpy.types.Panel):
    bl_label = "Project"
    bl_idname = "SSM_PT_project"
    bl_order = 50

    def draw(self, context):
        layout = self.layout
        row = layout.row(align=True)
        row.operator(SSM_OT_open_project.bl_idname, text="Open Project", icon="FILE_FOLDER")
        row.operator(SSM_OT_save_project.bl_idname, text="Save Project", icon="FILE_TICK")
        n = len(scene_instances(context))
        layout.label(text=f"{n} instance(s); headless: ssm build project.toml --out DIR")
        layout.prop(context.scene.ssm_display, "template_instance")


class SSM_PT_project_output(SSMPanel, bpy.types.Panel):
    bl_label = "Build outputs"
    bl_idname = "SSM_PT_project_output"
    bl_parent_id = "SSM_PT_project"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):

        draw_params(self.layout, context.scene.ssm_output, OutputParams)


class SSM_PT_project_quality(SSMPanel, bpy.types.Panel):
    bl_label = "Quality gates"
    bl_idname = "SSM_PT_project_quality"
    bl_parent_id = "SSM_PT_project"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):

        draw_params(self.layout, context.scene.ssm_quality, QualityParams)
        draw_params(self.layout, context.scene.ssm_quality, QualityParams, advanced=True)


classes = (SSM_OT_save_project, SSM_OT_open_project, SSM_OT_build_joint_model, SSM_PT_project, SSM_PT_project_output, SSM_PT_project_quality)
