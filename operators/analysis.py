"""Shape analysis in Blender: ``ssm.run_analysis`` on the model object (groups and covariates).

Reads the attribute table (CSV) and the ``[analysis]`` settings of the Analysis panel, runs
the core's :func:`~ssm_addon.analysis.files.run_analysis` (the same route as ``ssm analyze``
and a build's ``[analysis]``; with an output folder it writes the same files), and puts the
result on the model's mean mesh:

- one shape key per effect (``Effect: group: patient (per patient − control)``, slider =
  units: 1 is the level against the reference group, or one unit of a covariate), one for
  the discriminant (slider in within-group SD) and one per group mean;
- point attributes ``analysis_normal_mm`` (the first effect's normal displacement, mm) and
  ``analysis_p_fdr``, and the colour attribute ``analysis_map`` (blue–red, mm; grey where
  not significant at FDR 5 %), made the active colours;
- the tests' summary in ``Scene["ssm_analysis_record"]``, drawn by the panel.

An error leaves the scene as it was.
"""

from __future__ import annotations

import json
from pathlib import Path

import bpy
import numpy as np
from bpy.props import StringProperty

from ssm_addon.analysis.attributes import attributes_from_tables, read_attributes
from ssm_addon.analysis.files import (
    FDR_LEVEL,
    SHAPE_KEY_PREFIXES,
    analysis_shape_keys,
    analysis_summary,
    diverging_colours,
    run_analysis,
)
from ssm_addon.base.errors import InputError
from ssm_addon.base.params import AnalysisParams

from . import bridge
from .jobs import BackgroundJob
from .properties import SSMPanel, draw_params, scene_params
from .scene import find_model_object, model_from_object, scene_instance_attributes

RECORD_KEY = "ssm_analysis_record"


def apply_analysis(obj, result) -> list[str]:
    """Put an analysis on the model object: its shape keys, point attributes and map colours.
    Returns the names of the shape keys made (earlier analysis keys are replaced)."""
    keys = obj.data.shape_keys
    if keys is None:
        obj.shape_key_add(name="Basis", from_mix=False)
        keys = obj.data.shape_keys
    for kb in list(keys.key_blocks):
        if kb.name.startswith(SHAPE_KEY_PREFIXES):
            obj.shape_key_remove(kb)
    base = bridge.mesh_vertices(obj.data).astype(float)
    made = []
    for name, (positions, lo, hi) in analysis_shape_keys(result, base).items():
        kb = obj.shape_key_add(name=name, from_mix=False)
        kb.data.foreach_set("co", np.ascontiguousarray(positions, dtype=np.float32).ravel())
        kb.slider_min, kb.slider_max, kb.value = float(lo), float(hi), 0.0
        made.append(kb.name)
    first = result.effects[0]
    test = result.tests[first.term]
    bridge.set_point_attribute(obj.data, "analysis_normal_mm", first.normal)
    bridge.set_point_attribute(obj.data, "analysis_p_fdr", test.p_fdr)
    bridge.set_vertex_colors(obj.data, diverging_colours(first.normal, mask=test.p_fdr <= FDR_LEVEL),
                             name="analysis_map")
    obj.data.update()
    return made


class SSM_OT_run_analysis(BackgroundJob, bpy.types.Operator):
    """Group differences and covariate effects of the model's training shapes: permutation tests, maps on the mean mesh, one shape key per effect"""

    bl_idname = "ssm.run_analysis"
    bl_label = "Run Analysis"
    bl_options = {"REGISTER", "UNDO"}

    out_dir: StringProperty(name="Output folder", subtype="DIR_PATH", options={"SKIP_SAVE"},
                            description="Also write analysis.json, analysis.npz, the VTK meshes and the maps here "
                                        "(empty: only in the scene)")

    @classmethod
    def poll(cls, context):
        if find_model_object(context) is None:
            cls.poll_message_set("Build or import a model first (Model panel)")
            return False
        return True

    def prepare(self, context):
        obj = find_model_object(context)
        if obj is None:
            raise InputError("Run Analysis: no SSM model in the scene")
        params = scene_params(context, "ssm_analysis")
        if not params.requested:
            raise InputError("Run Analysis: give a group column, covariates, or both")
        own = scene_instance_attributes(context)  # an opened project's instance attributes
        if params.attributes:
            attributes = read_attributes(bpy.path.abspath(params.attributes))
            if own:
                attributes = attributes_from_tables(own, source="the project's instance attributes").merged(
                    attributes)
        elif own:
            attributes = attributes_from_tables(own, source="the project's instance attributes")
        else:
            raise InputError("Run Analysis: choose the attribute table (a CSV with a name column) in the Analysis "
                             "panel, or open a project whose instances have attributes")
        model = model_from_object(obj)
        self._object_name = name = obj.name
        out = Path(bpy.path.abspath(self.out_dir)) if self.out_dir else None
        if out is not None and out.exists() and any(out.iterdir()):
            raise InputError(f"Run Analysis: {out} is not empty; choose an empty or new folder")

        def work(progress, cancelled):
            result, doc, _ = run_analysis(model, attributes, params, out, model_path=name, progress=progress,
                                          cancelled=cancelled)
            return result, doc

        return work

    def finish(self, context, result):
        analysis, doc = result
        obj = bpy.data.objects.get(self._object_name)
        if obj is None:
            self.report({"ERROR"}, "Run Analysis: the model object was removed meanwhile")
            return {"CANCELLED"}
        made = apply_analysis(obj, analysis)
        lines = analysis_summary(analysis)
        context.scene[RECORD_KEY] = json.dumps({"lines": lines, "warnings": list(analysis.warnings),
                                                "keys": made, "group_p": doc.get("group_test", {}).get("p_value")})
        for w in analysis.warnings:
            self.report({"WARNING"}, f"analysis: {w}")
        self.report({"INFO"}, f"{obj.name}: {lines[0]}; {len(made)} shape keys")
        return {"FINISHED"}


class SSM_PT_analysis(SSMPanel, bpy.types.Panel):
    """Analysis: attribute table, group and covariates, Run; the tests and the effect sliders."""

    bl_idname = "SSM_PT_analysis"
    bl_label = "Analysis"
    bl_order = 45
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        draw_params(layout, context.scene.ssm_analysis, AnalysisParams)
        layout.operator("ssm.run_analysis", icon="GRAPH")
        raw = context.scene.get(RECORD_KEY)
        if not raw:
            return
        record = json.loads(raw)
        box = layout.box()
        for line in record["lines"]:
            box.label(text=line)
        for w in record["warnings"]:
            box.label(text=w, icon="ERROR")
        obj = find_model_object(context)
        keys = obj.data.shape_keys if obj is not None else None
        if keys is not None:
            col = layout.column(align=True)
            for name in record["keys"]:
                kb = keys.key_blocks.get(name)
                if kb is not None:
                    col.prop(kb, "value", text=name, slider=True)


class SSM_PT_analysis_advanced(SSMPanel, bpy.types.Panel):
    bl_label = "Advanced"
    bl_idname = "SSM_PT_analysis_advanced"
    bl_parent_id = "SSM_PT_analysis"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        draw_params(self.layout, context.scene.ssm_analysis, AnalysisParams, advanced=True)


classes = (SSM_OT_run_analysis, SSM_PT_analysis, SSM_PT_analysis_advanced)
