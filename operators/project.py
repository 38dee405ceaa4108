"""The project stage in Blender: Save/Open Project, and the headless build's ``model.blend``.

* ``ssm.save_project`` writes the scene's instances, their landmarks (exported next to
  the project as ``landmarks/<instance>.fcsv``) and the stage parameters
  (``Scene.ssm_template`` / ``ssm_coating`` / ``ssm_model`` where present) as a TOML
  project file, so a build set up by hand reruns headless
  (``python -m ssm_addon build`` or ``blender -b --command ssm build``).
* ``ssm.open_project`` loads a project file into the scene: every instance through
  ``ssm.import_segmentation`` and its landmarks as empties.
* :func:`write_build_outputs` is what the headless build calls (through
  ``ssm_addon/_blender.py``) when ``bpy`` is available: ``model.blend`` with the
  instances (display surfaces), their landmarks, the template, the coated instances and
  the model object with one shape key per mode, and ``modes.png`` (paper fig. 10).
"""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path

import bpy
import numpy as np
from bpy.props import StringProperty
from bpy_extras.io_utils import ExportHelper, ImportHelper

from ..ssm_addon import landmarks as core_landmarks
from ..ssm_addon import project as core
from ..ssm_addon import volume as core_volume
from ..ssm_addon.errors import InputError, SSMError
from ..ssm_addon.meshutil import write_ply
from . import bridge

# ------------------------------------------------------------------ scene construction


def _ensure_registered() -> None:
    """Register the extension in a bare ``bpy`` module (``python -m ssm_addon build``)."""
    if not hasattr(bpy.types.Object, "ssm"):
        from .. import register

        register()


def add_instance_object(context, name: str, spec, object_volume):
    """An instance object from a resampled volume: display surface in object mm, frame as matrix_world."""
    from .instances import write_instance_metadata

    verts, faces = core_volume.display_surface(object_volume)
    frame = object_volume.frame
    obj = bridge.new_mesh_object(context, name, verts, faces, collection_name=bridge.INSTANCES_COLLECTION,
                                 matrix_world=frame.matrix_world)
    kind = "VOLUME" if spec.volume is not None else "MESH_FILE"
    write_instance_metadata(
        obj,
        kind=kind,
        source=str(spec.source),
        label=spec.label,
        spacing=object_volume.spacing_mm,
        method=frame.method.upper() if frame.method.upper() in ("PATIENT", "MOMENTS") else "AUTO",
        frame=frame,
        import_matrix=frame.matrix_world,
        volume_mm3=object_volume.volume_mm3,
        voxels=int(np.count_nonzero(object_volume.mask)),
    )
    return obj


def add_landmarks(context, instance_obj, landmark_set) -> None:
    """Landmark empties (file world mm) for an instance; extends the schema with new names."""
    from .instances import file_to_blender_world
    from .landmarks import _add_name, schema_names, set_landmark

    settings = context.scene.ssm_landmarks
    for name in landmark_set.names:
        if name not in schema_names(context):
            _add_name(settings, name)
    pts = file_to_blender_world(instance_obj, landmark_set.points_world)
    for i, (name, p) in enumerate(zip(landmark_set.names, pts)):
        set_landmark(context, instance_obj, name, p, order=i)


def write_model_blend(result, path) -> str:
    """Write ``model.blend`` for a build result (an empty file plus the build's objects).

    Contents: the instances (display surfaces at their world positions, with the
    metadata of ``ssm.import_segmentation``), their landmarks (empties), the template
    (one colour per triangle, curvature attribute), the coated instances and the model
    object (mean shape, one shape key per mode; ``operators/model.py``).
    """
    from .coating import write_coated
    from .model import create_model_object
    from .template import write_template_object

    _ensure_registered()
    bpy.ops.wm.read_homefile(use_empty=True)
    context = bpy.context
    scene = context.scene
    bridge.ensure_mm_units(scene)
    objs = {}
    for spec, ov, lms in zip(result.project.instances, result.objects, result.landmarks_world):
        objs[spec.name] = add_instance_object(context, spec.name, spec, ov)
        add_landmarks(context, objs[spec.name], lms)
    names = list(result.project.names)
    ti = names.index(result.project.template_instance)
    template = result.template
    write_template_object(context, objs[names[ti]], template)
    for name, coating in zip(names, result.coatings):
        write_coated(context, objs[name], coating, np.asarray(template.faces))
    create_model_object(context, result.model, name="SSM Model")
    path = str(Path(path).resolve())
    bpy.ops.wm.save_as_mainfile(filepath=path, check_existing=False, copy=True)
    return path


def write_build_outputs(result, out_dir: Path, log=print) -> dict:
    """The Blender part of a headless build: ``modes.png`` (paper fig. 10) and ``model.blend``.

    Returns ``{"picture": "modes.png", "blend": "model.blend"}`` (names inside ``out_dir``).
    """
    from .render import render_modes_figure

    _ensure_registered()
    out = {}
    opts = result.project.output_options
    if opts.get("picture", True):
        render_modes_figure(result.model, Path(out_dir) / "modes.png", n_modes=int(opts.get("picture_modes", 2)))
        out["picture"] = "modes.png"
        if log:
            log("picture: modes.png (mean and ±2σ of the first modes, axial / sagittal / coronal)")
    write_model_blend(result, Path(out_dir) / "model.blend")
    out["blend"] = "model.blend"
    if log:
        log("blend: model.blend (instances, landmarks, template, coated instances, model with shape keys)")
    return out


# ------------------------------------------------------------------------ save / open


def _safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("_") or "instance"


def _scene_options(group, schema: dict) -> dict:
    """Values of a Scene property group whose names are keys of ``schema`` (TOML-typed)."""
    out = {}
    if group is None:
        return out
    for key, kind in schema.items():
        if not hasattr(group, key) or key not in group.bl_rna.properties:
            continue
        value = getattr(group, key)
        prop = group.bl_rna.properties[key]
        if prop.type == "ENUM":
            value = str(value).lower()
        elif kind == "float":
            value = float(value)
        elif kind == "int":
            value = int(value)
        elif kind == "bool":
            value = bool(value)
        elif kind == "tuple":
            value = tuple(value)
        elif kind == "str":
            value = str(value)
        else:
            continue
        out[key] = value
    return out


def _template_options(group) -> dict:
    """[template] options from ``Scene.ssm_template`` (TemplateParams fields, spacing apart)."""
    if group is None:
        return {}
    from .template import params_from_settings

    opts = dataclasses.asdict(params_from_settings(group))
    opts.pop("spacing_mm", None)
    return {k: v for k, v in opts.items() if v is not None}


def _model_options(group) -> dict:
    """[model] options from ``Scene.ssm_model`` (0 modes there means all; metrics_samples)."""
    opts = _scene_options(group, {"alignment": "str", "n_modes": "int"})
    if not opts.get("n_modes"):
        opts.pop("n_modes", None)
    if group is not None and "metrics_samples" in group.bl_rna.properties:
        opts["specificity_samples"] = int(group.metrics_samples)
    return opts


def _set_scene_options(group, options: dict) -> None:
    if group is None:
        return
    for key, value in options.items():
        if key not in group.bl_rna.properties:
            continue
        prop = group.bl_rna.properties[key]
        if prop.type == "ENUM":
            ids = {item.identifier.lower(): item.identifier for item in prop.enum_items}
            value = ids.get(str(value).lower())
            if value is None:
                continue
        try:
            setattr(group, key, value)
        except (TypeError, ValueError, AttributeError):
            pass


def project_from_scene(context, path) -> core.Project:
    """The scene's instances, landmarks and parameters as a Project for ``path``.

    Landmarks are exported as ``<folder>/landmarks/<instance>.fcsv`` (LPS, file world mm);
    instances made from Blender meshes as ``<folder>/meshes/<instance>.ply`` (file world mm).
    """
    from .instances import absolute_source_path, mesh_file_world, scene_instances
    from .landmarks import landmark_sets_by_instance

    path = Path(path).resolve()
    folder = path.parent
    objs = scene_instances(context)
    if len(objs) < 2:
        raise InputError(f"the scene has {len(objs)} SSM instance(s); a project needs at least two")
    lm_sets = landmark_sets_by_instance(context)
    missing = [o.name for o in objs if o.name not in lm_sets]
    if missing:
        raise InputError(f"no landmarks on instance(s) {', '.join(missing)}: place or import them first")
    (folder / "landmarks").mkdir(parents=True, exist_ok=True)
    specs = []
    for obj in objs:
        lm_path = folder / "landmarks" / f"{_safe_name(obj.name)}.fcsv"
        core_landmarks.write_landmarks(lm_path, lm_sets[obj.name])
        ssm = obj.ssm
        if ssm.source_kind == "VOLUME":
            spec = core.InstanceSpec(name=obj.name, landmarks=lm_path, volume=Path(absolute_source_path(obj)),
                                     label=None if ssm.label < 0 else int(ssm.label))
        else:
            if ssm.source_kind == "MESH_FILE":
                mesh_path = Path(absolute_source_path(obj))
            else:
                (folder / "meshes").mkdir(exist_ok=True)
                mesh_path = folder / "meshes" / f"{_safe_name(obj.name)}.ply"
                verts, faces = mesh_file_world(obj)
                write_ply(mesh_path, verts, faces)
            spec = core.InstanceSpec(name=obj.name, landmarks=lm_path, mesh=mesh_path, mesh_spacing=float(ssm.spacing_mm))
        specs.append(spec)
    active = context.active_object
    if active is not None and active.ssm.role == "TEMPLATE" and active.ssm.instance is not None:
        active = active.ssm.instance
    template_instance = active.name if active is not None and active.name in {s.name for s in specs} else specs[0].name
    scene = context.scene
    t_group = getattr(scene, "ssm_template", None)
    spacing = float(t_group.spacing_mm) if t_group is not None else float(objs[0].ssm.spacing_mm)
    t_opts = _template_options(t_group)
    c_group = getattr(scene, "ssm_coating", None)
    c_opts = {k: v for k, v in dataclasses.asdict(c_group.params()).items() if v is not None} if c_group else {}
    m_opts = {**core.MODEL_DEFAULTS, **_model_options(getattr(scene, "ssm_model", None))}
    method = objs[0].ssm.frame_method.lower()
    return core.Project(path=path, instances=tuple(specs), template_instance=template_instance, spacing_mm=spacing,
                        frame_method=method if method in core.FRAME_METHODS else "auto", template_options=t_opts,
                        coating_options=c_opts, model_options=m_opts)


def load_project_into_scene(context, project: core.Project) -> list:
    """Import every instance of ``project`` (``ssm.import_segmentation``) with its landmarks."""
    created = []
    for spec in project.instances:
        spacing = spec.mesh_spacing or project.spacing_mm
        before = set(bpy.data.objects)
        result = bpy.ops.ssm.import_segmentation(
            filepath=str(spec.source), label=-1 if spec.label is None else int(spec.label), spacing_mm=spacing,
            frame_method=project.frame_method.upper(),
        )
        new = [o for o in bpy.data.objects if o not in before and o.ssm.role == "INSTANCE"]
        if "FINISHED" not in result or not new:
            raise InputError(f"instance {spec.name!r}: could not import {spec.source}")
        obj = new[0]
        obj.name = spec.name
        add_landmarks(context, obj, spec.landmark_set)
        created.append(obj)
    scene = context.scene
    t_opts = {**project.template_options, "spacing_mm": project.spacing_mm}
    if t_opts.get("topology_radius_mm") is not None:
        t_opts.update(topology_auto=False, topology_value_mm=t_opts.pop("topology_radius_mm"))
    _set_scene_options(getattr(scene, "ssm_template", None), t_opts)
    c_opts = dict(project.coating_options)
    if "registration_sigmas_mm" in c_opts:  # the panel holds the coarsest width and the number of halvings
        sigmas = list(c_opts.pop("registration_sigmas_mm"))
        c_opts["use_registration"] = bool(sigmas)
        if sigmas:
            c_opts.update(registration_sigma_mm=float(sigmas[0]), registration_levels=len(sigmas))
    _set_scene_options(getattr(scene, "ssm_coating", None), c_opts)
    m_opts = dict(project.model_options)
    m_opts["n_modes"] = m_opts.get("n_modes") or 0  # the panel's 0 means every mode
    m_opts["metrics_samples"] = m_opts.pop("specificity_samples", 300)
    _set_scene_options(getattr(scene, "ssm_model", None), m_opts)
    if created:
        template = next((o for o in created if o.name == project.template_instance), created[0])
        for obj in context.view_layer.objects:
            obj.select_set(obj in created)
        context.view_layer.objects.active = template
    return created


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
    """Load a project file (TOML): import its instances and their landmarks into the scene"""

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
        self.report({"INFO"}, f"Opened {os.path.basename(self.filepath)}: {len(created)} instances")
        return {"FINISHED"}


class SSM_PT_project(bpy.types.Panel):
    bl_label = "Project"
    bl_idname = "SSM_PT_project"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "SSM"
    bl_order = 50

    def draw(self, context):
        layout = self.layout
        row = layout.row(align=True)
        row.operator(SSM_OT_open_project.bl_idname, text="Open Project", icon="FILE_FOLDER")
        row.operator(SSM_OT_save_project.bl_idname, text="Save Project", icon="FILE_TICK")
        n = sum(1 for o in context.scene.objects if o.type == "MESH" and o.ssm.role == "INSTANCE")
        layout.label(text=f"{n} instance(s); headless: python -m ssm_addon build project.toml --out DIR")


classes = (SSM_OT_save_project, SSM_OT_open_project, SSM_PT_project)
