"""Template in Blender (paper section 3): build the template from the active instance.

* ``Scene.ssm_template``: the :class:`~ssm_addon.base.params.TemplateParams` (derived
  properties; spacing and frame apply to every instance of the study);
* ``ssm.build_template``: a background job (status-bar progress, Esc cancels;
  synchronous from scripts) that runs the core's
  :func:`~ssm_addon.pipeline.stages.make_template` on the scene's study with the active instance
  as template instance, and creates or replaces the mesh object ``"SSM Template"``
  (collection "SSM Template"): its mesh is a view of the float64 template kept in
  ``obj["ssm_template"]`` (points in the instance's object frame, faces, curvature),
  placed with ``matrix_world`` = object frame -> Blender world so it overlays the
  instance; correspondence colours; a POINT attribute ``curvature`` (1/mm, paper fig. 3).
* Panel "Template" in the SSM sidebar, with an "Advanced" sub-panel.
"""

from __future__ import annotations

import time

import bpy

from ssm_addon.base.errors import InputError
from ssm_addon.base.params import TemplateParams
from ssm_addon.pipeline.stages import import_result, template_density, template_stage
from ssm_addon.pipeline.study import apply_stage

from . import bridge
from .jobs import BackgroundJob
from .properties import SSMPanel, draw_params
from .scene import (
    VolumeLoader,
    find_template,
    is_instance,
    record_stage,
    report_stage,
    scene_structures,
    study_from_scene,
    write_template_object,
)


def source_instance(context):
    """The active instance, or the instance of the active template/coated object/landmark."""
    obj = context.active_object
    if is_instance(obj):
        return obj
    if obj is not None and obj.ssm.role in {"TEMPLATE", "COATED", "LANDMARK"} and is_instance(obj.ssm.instance):
        return obj.ssm.instance
    return None


class SSM_OT_build_template(BackgroundJob, bpy.types.Operator):
    """Build the template from the active instance: point density reduction and triangulation (paper 3). Esc cancels"""

    bl_idname = "ssm.build_template"
    bl_label = "Build Template"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if scene_structures(context):  # each structure's template comes with its joint build
            cls.poll_message_set("The scene holds a joint study: Build Joint Model (Model panel) builds each "
                                 "structure's template")
            return False
        if source_instance(context) is None:
            cls.poll_message_set("Make the instance the template is built from active (import one first)")
            return False
        return True

    def prepare(self, context):
        instance = source_instance(context)
        if instance is None:
            raise InputError("build template: make an SSM instance active (import one with File > Import > "
                             "Segmentation)")
        study = study_from_scene(context, template_instance=instance.name, coatings=False)
        loader = VolumeLoader(context, [instance])
        self._instance_name, self._loader, self._params = instance.name, loader, study.params.template

        def work(progress, cancelled):
            t0 = time.perf_counter()
            imported = import_result(study, loader.load(progress, cancelled), time.perf_counter() - t0)
            apply_stage(study, imported)
            return imported, template_stage(study, progress=progress, cancelled=cancelled)

        return work

    def finish(self, context, outcome):
        self._loader.keep()
        imported, result = outcome
        instance = bpy.data.objects.get(self._instance_name)
        if instance is None:
            self.report({"ERROR"}, f"build template: instance {self._instance_name!r} was removed")
            return {"CANCELLED"}
        template = result.product["template"]
        obj = write_template_object(context, instance, template)
        found = record_stage(context, imported) + record_stage(context, result)
        msg = (f"template: {len(template.points_object)} points, {len(template.faces)} triangles, "
               f"genus {template.params.get('genus')} from {instance.name}"
               f"{template_density(template, self._params)}")
        report_stage(self, msg, found)
        bridge.select_only(context, [obj])
        return {"FINISHED"}


class SSM_PT_template(SSMPanel, bpy.types.Panel):
    bl_label = "Template"
    bl_idname = "SSM_PT_template"
    bl_order = 20
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        inst = source_instance(context)
        layout.label(text=f"From: {inst.name}" if inst else "Make an instance active", icon="OBJECT_DATA")
        draw_params(layout, context.scene.ssm_template, TemplateParams)
        layout.operator(SSM_OT_build_template.bl_idname, icon="MESH_ICOSPHERE")
        tpl = find_template(context)
        if tpl is not None:
            src = tpl.ssm.instance.name if tpl.ssm.instance else "?"
            layout.label(text=f"{tpl.name}: {len(tpl.data.vertices)} points, {len(tpl.data.polygons)} triangles",
                         icon="MESH_DATA")
            layout.label(text=f"from {src}")


class SSM_PT_template_advanced(SSMPanel, bpy.types.Panel):
    bl_label = "Advanced"
    bl_idname = "SSM_PT_template_advanced"
    bl_parent_id = "SSM_PT_template"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        draw_params(self.layout, context.scene.ssm_template, TemplateParams, advanced=True)


classes = (SSM_OT_build_template, SSM_PT_template, SSM_PT_template_advanced)
