"""Fitting the model in Blender: ``ssm.fit_model`` on the active mesh (paper 5's model in use).

The model object's shape-key values are set to the fitted coefficients (the fit seen as
slider positions) and a mesh ``"<target> fitted"`` shows the fitted shape at the target,
with its posterior standard deviation per vertex as the colour attribute
``posterior_sd`` (and the float attribute ``posterior_sd_mm``). In Edit Mode only the
selected vertices are the target: the rest of the shape is completed, its uncertainty in
the colours. Runs the core's :func:`~ssm_addon.fitting.fit.fit_model`; an error leaves the
scene as it was.
"""

from __future__ import annotations

import json

import bpy
import numpy as np
from bpy.props import BoolProperty, StringProperty

from ssm_addon.base.errors import InputError
from ssm_addon.base.params import FitParams
from ssm_addon.fitting.fit import Pose, Target, fit_any_pose
from ssm_addon.fitting.verdict import judge_fit

from . import bridge
from .jobs import BackgroundJob
from .properties import SSMPanel, draw_params, scene_params
from .scene import (
    find_model_object,
    is_instance,
    mode_sliders,
    model_from_object,
    model_structures,
    object_to_blender_matrix,
)

FIT_COLLECTION = "SSM Fits"


def _target_object(context):
    obj = context.active_object
    if obj is None or obj.type != "MESH" or obj.ssm.role in {"MODEL", "MODEL_PART", "SAMPLE", "LANDMARK"}:
        return None
    return obj


class SSM_OT_fit_model(BackgroundJob, bpy.types.Operator):
    """Fit the SSM model to the active mesh (its selected vertices in Edit Mode: completion); the model's sliders show the fit"""

    bl_idname = "ssm.fit_model"
    bl_label = "Fit Model"
    bl_options = {"REGISTER", "UNDO"}

    partial: BoolProperty(name="Selected vertices only", default=False, options={"SKIP_SAVE"},
                          description="Fit to the selected vertices and complete the rest (default in Edit Mode)")
    structures: StringProperty(name="Structures", default="",
                               description="A joint model: the structures the mesh holds, comma-separated (the "
                                           "others are predicted with their posterior SD); empty: all of them")

    @classmethod
    def poll(cls, context):
        if find_model_object(context) is None:
            cls.poll_message_set("Build (or open) a model first")
            return False
        if _target_object(context) is None:
            cls.poll_message_set("Make the mesh to fit active (not the model itself)")
            return False
        return True

    def prepare(self, context):
        model_obj = find_model_object(context)
        target = _target_object(context)
        model = model_from_object(model_obj)
        partial = self.partial or target.mode == "EDIT"
        if target.mode == "EDIT":
            target.update_from_editmode()
        verts = bridge.object_world_vertices(target)
        if partial:
            sel = np.zeros(len(target.data.vertices), dtype=bool)
            target.data.vertices.foreach_get("select", sel)
            if sel.sum() < 10:
                raise InputError(f"fit model: select at least 10 vertices of {target.name!r} to fit to "
                                 f"({int(sel.sum())} selected)")
            tgt = Target.from_points(verts[sel], source=target.name)
        else:
            tgt = Target.from_mesh(verts, bridge.mesh_triangles(target.data), source=target.name)
        frame = None
        if is_instance(target):  # the training's start among the others: the instance's object frame
            m = object_to_blender_matrix(target)
            frame = Pose(m[:3, :3], m[:3, 3])
        params = scene_params(context, "ssm_fit")
        self._names = (model_obj.name, target.name)
        given = [n.strip() for n in self.structures.split(",") if n.strip()]
        points = None
        if given:
            if not model.structure_names:
                raise InputError(f"fit model: {model_obj.name!r} is not a joint model; leave Structures empty")
            points = model.structure_points(given)  # names the model lacks: an error naming its structures

        def work(progress, cancelled):  # the pose search of ``ssm fit``, then the fit
            result, _search = fit_any_pose(model, tgt, params=params, frame_pose=frame, partial=partial, size_check=True,
                                           points=points, progress=progress, cancelled=cancelled)
            # the verdicts of ``ssm fit --mesh NAME=FILE``: coverage is not judged where structures are predicted
            return result, model.faces, judge_fit(result, tgt, model, params=params, partial=partial or bool(given))

        return work

    def finish(self, context, outcome):
        result, faces, verdict = outcome
        model_obj, target = (bpy.data.objects.get(n) for n in self._names)
        if model_obj is None or target is None:
            self.report({"ERROR"}, "fit model: the model or the target was removed meanwhile")
            return {"CANCELLED"}
        for slider, z in zip(mode_sliders(model_obj), result.coefficients):
            slider.set_range(min(-3.0, float(z) - 0.5), max(3.0, float(z) + 0.5))
            slider.value = float(z)
        obj = bridge.new_mesh_object(context, f"{target.name} fitted", result.points, faces,
                                     collection_name=FIT_COLLECTION, matrix_world=np.eye(4))
        bridge.set_vertex_colors(obj.data, bridge.sd_colours(result.posterior_sd_mm), name="posterior_sd")
        bridge.set_point_attribute(obj.data, "posterior_sd_mm", result.posterior_sd_mm)
        mat = bridge.color_material("SSM Posterior SD", attribute="posterior_sd")
        if not obj.data.materials:
            obj.data.materials.append(mat)
        else:
            obj.data.materials[0] = mat
        obj.ssm.role = "SAMPLE"
        bridge.sd_legend(context, result.points, FIT_COLLECTION)
        obj["ssm_fit_json"] = json.dumps({**result.to_dict(), **verdict.to_dict()})
        message = (f"{target.name}: Mahalanobis distance {result.mahalanobis:.2f} on {result.n_modes} modes "
                   f"(p = {result.p_value:.3g}); mean distance {result.mean_distance_mm:.2f} mm; posterior SD up to "
                   f"{result.posterior_sd_mm.max():.2f} mm")
        # the verdicts of ``ssm fit`` (one owner: ssm_addon.fitting.verdict), said the same way
        self.report({"WARNING" if verdict.warnings else "INFO"},
                    message + "".join(f"; {w}" for w in verdict.warnings.values()))
        return {"FINISHED"}


class SSM_PT_fit(SSMPanel, bpy.types.Panel):
    bl_label = "Fit"
    bl_idname = "SSM_PT_fit"
    bl_order = 45
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        target = _target_object(context)
        layout.label(text=f"Target: {target.name}" if target else "Make a mesh active", icon="OBJECT_DATA")
        if target is not None and target.mode == "EDIT":
            layout.label(text="Edit Mode: the selected vertices (completion)", icon="VERTEXSEL")
        draw_params(layout, context.scene.ssm_fit, FitParams)
        layout.operator(SSM_OT_fit_model.bl_idname, icon="MOD_SHRINKWRAP")
        model_obj = find_model_object(context)
        for name in model_structures(model_obj):  # a joint model: fit the structure the mesh is, predict the others
            layout.operator(SSM_OT_fit_model.bl_idname, text=f"Fit as {name}", icon="GROUP_VERTEX").structures = name
        fitted = bpy.data.objects.get(f"{target.name} fitted") if target else None
        if fitted is not None and "ssm_fit_json" in fitted:
            d = json.loads(fitted["ssm_fit_json"])
            layout.label(text=f"Mahalanobis {d['mahalanobis']:.2f} (p = {d['p_value']:.2g})")
            layout.label(text=f"mean distance {d['mean_distance_mm']:.2f} mm, SD up to "
                              f"{d['posterior_sd_mm']['max']:.2f} mm")


classes = (SSM_OT_fit_model, SSM_PT_fit)
