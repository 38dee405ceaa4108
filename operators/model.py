"""Blender layer of the model stage (paper section 5): build, show, animate, sample, save.

The model object ("SSM Model") is a mesh of the mean shape with the template's faces and
triangle-index colours, one shape key per mode ("Mode 1", ...) whose key is the mean
plus one standard deviation along the mode (key = p̄ + √λ_k q_k, slider -3..3, so a
slider value v is b_k = v √λ_k and the evaluated mesh is p̄ + Σ v_k √λ_k q_k, eq. 7),
and a POINT attribute ``variance`` (per-point variance, mm², for a heat map).

Storage: the full :class:`~ssm_addon.model.pca.ShapeModel` (float64 mean, modes, variances,
instance points in the model and world frames, names and parameters) is kept in the
object's ID property group ``obj["ssm_model"]`` as binary float64/int32 arrays (numpy
buffers, no lists), so it survives save/reopen exactly and "Save Model" writes the same
files as the command line. The shape keys are the editable view of it (float32).

A joint model (several structures) is an empty holding the model and one custom property
per mode ("Mode 1", ... in standard deviations), with one mesh per structure parented to
it; each structure's shape key of a mode is driven by the empty's property, so one slider
(and one animation channel) moves the whole joint.
"""

from __future__ import annotations

import json
import os

import bpy
import numpy as np
from bpy.props import BoolProperty, FloatProperty, IntProperty, StringProperty
from bpy_extras import anim_utils
from bpy_extras.io_utils import ImportHelper
from mathutils import Vector

from ssm_addon.base.errors import InputError, SSMError
from ssm_addon.base.params import ModelParams
from ssm_addon.base.progress import sub_progress
from ssm_addon.formats.registry import file_glob
from ssm_addon.model import metrics as core_metrics
from ssm_addon.model.files import load_model
from ssm_addon.model.pca import ShapeModel
from ssm_addon.model.quality import check_model
from ssm_addon.pipeline.outputs import owned_output_folder, save_joint_outputs, save_study_outputs, write_outputs
from ssm_addon.pipeline.report import Absent, write_report_html
from ssm_addon.pipeline.stages import metrics_stage, model_stage
from ssm_addon.pipeline.study import apply_stage

from . import bridge
from .jobs import BackgroundJob
from .properties import SSMPanel, draw_params, scene_params
from .scene import (
    JOINT_FINDINGS_KEY,
    MODEL_COLLECTION,
    MODEL_FILE_PROP,
    MODEL_KEY,
    MODEL_NAME,
    clear_mode_animation,
    coated_objects,
    find_model_object,
    finish_optimisation,
    joint_study_of,
    mode_sliders,
    model_from_object,
    model_parts,
    model_structures,
    prepare_optimisation,
    record_stage,
    report_stage,
    scene_findings,
    scene_instances,
    scene_optimisation,
    scene_structures,
    store_appearance,
    store_model,
    study_from_scene,
)


def _poll_model(cls, context) -> bool:
    if find_model_object(context) is None:
        cls.poll_message_set("Build the model first (Model panel)")
        return False
    return True


def _require_model(context) -> bpy.types.Object:
    obj = find_model_object(context)
    if obj is None:
        raise InputError("no SSM model in the scene: run 'Build Model' first")
    return obj


def model_location(context, model: ShapeModel, turn: np.ndarray | None = None) -> np.ndarray:
    """Where the model object goes (Blender world mm): right of the instances, level with them.

    The mean shape is in the model frame (object mm), turned as shown (``turn``, default
    :func:`~ssm_addon.model.metrics.display_axes`);
    the object's origin is put a quarter model width to the right (+x) of the instances'
    bounding box, at the height and depth of their centre, so the model is seen beside the
    population.
    """
    insts = scene_instances(context)
    turn = core_metrics.display_axes(model) if turn is None else turn
    shown = np.asarray(model.mean, float) @ turn.T
    width = float(np.ptp(shown[:, 0])) if model.n_points else 0.0
    if not insts:
        return np.zeros(3)
    corners = np.concatenate([np.array([ob.matrix_world @ Vector(c) for c in ob.bound_box]) for ob in insts])
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    centre = (lo + hi) / 2.0
    return np.array([hi[0] + 0.25 * width - float(shown[:, 0].min()) if model.n_points else hi[0], centre[1],
                     centre[2]])


def _remove_model_objects(name: str) -> None:
    """Remove the model object ``name`` when it is a joint model's empty, with its structures."""
    old = bpy.data.objects.get(name)
    if old is None or old.type == "MESH":
        return
    for child in model_parts(old):
        mesh = child.data
        bpy.data.objects.remove(child)
        if mesh is not None and mesh.users == 0:
            bpy.data.meshes.remove(mesh)
    bpy.data.objects.remove(old)


def _drive_by(key_block, owner, prop: str) -> None:
    """Drive a shape key's value by the custom property ``prop`` of ``owner``."""
    key_block.driver_remove("value")
    fc = key_block.driver_add("value")
    drv = fc.driver
    drv.type = "AVERAGE"
    var = drv.variables.new()
    var.name, var.type = "v", "SINGLE_PROP"
    var.targets[0].id_type = "OBJECT"
    var.targets[0].id = owner
    var.targets[0].data_path = f'["{prop}"]'


def create_joint_model_object(context, model: ShapeModel, name: str = MODEL_NAME, n_keys: int | None = None,
                              activate: bool = True):
    """Create (or replace) a joint model's objects: an empty ``name`` (role MODEL, the model in
    ``obj["ssm_model"]``, one custom property "Mode k" per mode in SD, soft range -3..3) and
    one mesh per structure, ``"<name> <structure>"`` (role MODEL_PART, parented to the empty,
    its points of the mean, its faces, a POINT attribute ``variance`` in mm²), whose shape key
    "Mode k" (p̄ + √λ_k q_k on its rows, eq. 7) is driven by the empty's "Mode k".
    """
    scene = context.scene
    bridge.ensure_mm_units(scene)
    _remove_model_objects(name)
    existing = bpy.data.objects.get(name)
    if existing is not None:  # a mesh model of the same name: replaced by the joint one
        bpy.data.objects.remove(existing)
    empty = bpy.data.objects.new(name, None)
    empty.empty_display_type = "PLAIN_AXES"
    empty.empty_display_size = 0.1 * float(np.ptp(model.mean, axis=0).max()) if model.n_points else 1.0
    bridge.ensure_collection(scene, MODEL_COLLECTION).objects.link(empty)
    matrix = np.eye(4)
    matrix[:3, :3] = core_metrics.display_axes(model)  # stands as its instances lay in their files
    matrix[:3, 3] = model_location(context, model, matrix[:3, :3])
    bridge.set_matrix_world(empty, matrix)
    k = model.n_modes if n_keys is None else min(int(n_keys), model.n_modes)
    for i in range(k):
        prop = f"Mode {i + 1}"
        empty[prop] = 0.0
        empty.id_properties_ui(prop).update(min=-10.0, max=10.0, soft_min=-3.0, soft_max=3.0,
                                            description=f"Mode {i + 1} of the joint model, in standard deviations")
    empty.ssm.role = "MODEL"
    empty.ssm.source = str(model.params.get("source", ""))
    store_model(empty, model)
    sd = model.standard_deviations
    variance = model.point_variance
    for structure in model.structure_names:
        sl = model.structure_slice(structure)
        part = bridge.new_mesh_object(context, f"{name} {structure}", model.mean[sl], model.structure_faces(structure),
                                      collection_name=MODEL_COLLECTION, matrix_world=np.eye(4), replace=False)
        part.parent = empty
        part.matrix_parent_inverse.identity()
        part.matrix_basis.identity()
        bridge.colour_correspondence(part, model.mean[sl], scene.ssm_display.colouring)
        keys = {f"Mode {i + 1}": model.mean[sl] + sd[i] * model.modes[i][sl] for i in range(k)}
        bridge.set_shape_keys(part, keys, slider_min=-10.0, slider_max=10.0)
        for i in range(k):
            _drive_by(part.data.shape_keys.key_blocks[f"Mode {i + 1}"], empty, f"Mode {i + 1}")
        bridge.set_point_attribute(part.data, "variance", variance[sl])
        part.ssm.role = "MODEL_PART"
        part["ssm_structure"] = structure
    if activate:
        bridge.select_only(context, [empty], active=empty)
    return empty


def create_model_object(context, model: ShapeModel, name: str = MODEL_NAME, n_keys: int | None = None,
                        template_points: np.ndarray | None = None, activate: bool = True):
    """Create (or replace) the model mesh object from a ShapeModel.

    Mean shape with the template faces and triangle-index colours, one shape key per mode
    (key = p̄ + √λ_k q_k, slider -3..3 = b_k / √λ_k), POINT attribute ``variance`` (mm²),
    ``obj.ssm.role = "MODEL"`` and the model arrays in ``obj["ssm_model"]``. A joint model:
    :func:`create_joint_model_object` (an empty with the sliders, a mesh per structure).

    Parameters
    ----------
    n_keys : int, optional
        Number of mode shape keys (default: every mode of the model).
    activate : bool
        Make the model the selected, active object (Import Shape Model); Build Model leaves
        the active instance active, so Build Template still finds it.

    Returns
    -------
    bpy.types.Object
    """
    if model.structure_names:
        return create_joint_model_object(context, model, name=name, n_keys=n_keys, activate=activate)
    scene = context.scene
    bridge.ensure_mm_units(scene)
    _remove_model_objects(name)  # a joint model of the same name: replaced by the mesh
    matrix = np.eye(4)
    matrix[:3, :3] = core_metrics.display_axes(model)  # stands as its instances lay in their files
    matrix[:3, 3] = model_location(context, model, matrix[:3, :3])
    obj = bridge.new_mesh_object(context, name, model.mean, model.faces, collection_name=MODEL_COLLECTION,
                                 matrix_world=matrix)
    if obj.data.shape_keys is not None and obj.data.shape_keys.animation_data is not None:
        obj.data.shape_keys.animation_data_clear()
    mesh = obj.data
    bridge.colour_correspondence(obj, model.mean if template_points is None else template_points,
                                 scene.ssm_display.colouring)
    k = model.n_modes if n_keys is None else min(int(n_keys), model.n_modes)
    sd = model.standard_deviations
    keys = {f"Mode {i + 1}": model.mean + sd[i] * model.modes[i] for i in range(k)}
    bridge.set_shape_keys(obj, keys, slider_min=-3.0, slider_max=3.0)
    bridge.set_point_attribute(mesh, "variance", model.point_variance)
    obj.ssm.role = "MODEL"
    obj.ssm.source = str(model.params.get("source", ""))
    store_model(obj, model)
    if activate:
        bridge.select_only(context, [obj], active=obj)
    return obj


# ---------------------------------------------------------------------------------------
# operators
# ---------------------------------------------------------------------------------------
class SSM_OT_build_model(BackgroundJob, bpy.types.Operator):
    """Build the statistical shape model (mean, eigenmodes, eq. 4-6) from the coated instances"""

    bl_idname = "ssm.build_model"
    bl_label = "Build Model"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if scene_structures(context):
            cls.poll_message_set("The scene holds a joint study: Build Joint Model")
            return False
        n = len(coated_objects(context))
        if n < 2:
            cls.poll_message_set(f"Coat the template onto at least 2 instances first ({n} coated)")
            return False
        return True

    def prepare(self, context):
        study = study_from_scene(context)
        if len(study.coatings) < 2:
            raise InputError(f"Build Model: need at least 2 coated instances, found {len(study.coatings)}")
        self._template_points = study.template.points_object if study.template is not None else None
        # the build's order: the coatings optimised first when [correspondence] optimise is on and
        # the scene's are not yet (every instance coated)
        done = scene_optimisation(context)
        self._optimise = (study.params.correspondence.optimise and (not done or done.get("stop") == "cancelled")
                          and all(n in study.coatings for n in study.names))
        self._note = ""
        if self._optimise:
            try:
                return prepare_optimisation(self, context, then=lambda optimised: model_stage(optimised))
            except InputError as err:  # an instance's source is not readable: the coatings as they are
                self._optimise = False
                self._note = f"; the coatings were not optimised ({err})"

        def work(progress, cancelled):
            return model_stage(study, progress=progress, cancelled=cancelled)

        return work

    def finish(self, context, result):
        if self._optimise:
            imported, optimised, was_cancelled, result = result
            found = finish_optimisation(self, context, imported, optimised)
            if was_cancelled:
                report_stage(self, f"cancelled during the correspondence optimisation: kept iteration "
                                   f"{optimised.product['optimisation'].iterations}; no model built", found)
                return {"CANCELLED"}
        model = result.product["model"]
        obj = create_model_object(context, model, template_points=self._template_points, activate=False)
        found = record_stage(context, result)
        conc = model.variability_concentration()
        k3 = min(3, model.n_modes)
        share = conc[k3 - 1] * 100 if k3 else 0.0
        loc = np.array(obj.matrix_world.translation)
        report_stage(self, f"{obj.name}: {model.n_modes} modes from {model.n_instances} instances; first {k3}: "
                           f"{share:.1f} %; placed at ({loc[0]:.0f}, {loc[1]:.0f}, {loc[2]:.0f}) mm, right of "
                           "the instances" + self._note, found)
        return {"FINISHED"}


def _channelbag(keys):

    ad = keys.animation_data
    if ad is None or ad.action is None:
        return None
    return anim_utils.action_get_channelbag_for_slot(ad.action, ad.action_slot)


def mode_fcurves(obj) -> dict:
    """{mode name: F-curve} of the animated mode sliders of a model object (its shape keys'
    values, or a joint model's custom properties)."""
    owner = obj.data.shape_keys if obj.type == "MESH" else obj
    bag = _channelbag(owner) if owner is not None else None
    out = {}
    if bag is None:
        return out
    head, tail = ('key_blocks["', '"].value') if obj.type == "MESH" else ('["', '"]')
    for fc in bag.fcurves:
        if fc.data_path.startswith(head) and fc.data_path.endswith(tail):
            out[fc.data_path[len(head) : -len(tail)]] = fc
    return out


def sweep_keyframes(n_modes: int, frames_per_mode: int, amplitude: float, start: int = 1) -> dict:
    """Keyframes (frame, value in σ) sweeping each mode 0, -a, +a, -a, 0 in turn (paper fig. 10).

    Every mode also gets 0 keys at the first and last frame, so all F-curves share one
    period and loop together. Returns {mode index: [(frame, value), ...]} and the end frame
    under the key ``"end"``.
    """
    f = int(frames_per_mode)
    end = start + n_modes * f
    out: dict = {"end": end}
    for i in range(n_modes):
        s = start + i * f
        pts = [(s, 0.0), (s + round(f / 6), -amplitude), (s + round(f / 2), amplitude), (s + round(5 * f / 6), -amplitude), (s + f, 0.0)]
        if s > start:
            pts.insert(0, (start, 0.0))
        if s + f < end:
            pts.append((end, 0.0))
        out[i] = pts
    return out


class SSM_OT_animate_modes(bpy.types.Operator):
    """Keyframe the mode sliders: each mode sweeps -2σ…+2σ…-2σ in turn (paper fig. 10), loopable"""

    bl_idname = "ssm.animate_modes"
    bl_label = "Animate Modes"
    bl_options = {"REGISTER", "UNDO"}

    n_modes: IntProperty(name="Modes", description="Animate the first modes (default: the panel's)", default=3, min=1,
                         options={"SKIP_SAVE"})
    frames_per_mode: IntProperty(name="Frames per mode", default=48, min=6, options={"SKIP_SAVE"},
                                 description="Frames of one mode's sweep (default: the panel's)")
    amplitude: FloatProperty(name="Amplitude (σ)", default=2.0, min=0.1, max=3.0, options={"SKIP_SAVE"},
                             description="Sweep amplitude in standard deviations (default: the panel's)")
    cyclic: BoolProperty(name="Loop", description="Cycles modifier on every F-curve", default=True)

    @classmethod
    def poll(cls, context):
        return _poll_model(cls, context)

    def execute(self, context):
        try:
            obj = _require_model(context)
        except InputError as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        s = context.scene.ssm_model
        for prop, setting in (("n_modes", "anim_modes"), ("frames_per_mode", "anim_frames"),
                              ("amplitude", "anim_amplitude")):
            if not self.properties.is_property_set(prop):
                setattr(self, prop, getattr(s, setting))
        sliders = mode_sliders(obj)
        m = min(self.n_modes, len(sliders))
        if m == 0:
            self.report({"ERROR"}, f"{obj.name}: no mode sliders")
            return {"CANCELLED"}
        clear_mode_animation(obj)
        for slider in sliders:
            slider.value = 0.0
        plan = sweep_keyframes(m, self.frames_per_mode, self.amplitude, start=1)
        for i in range(m):
            slider = sliders[i]
            for frame, value in plan[i]:
                slider.value = value
                slider.keyframe(frame)
            slider.value = 0.0
        fcurves = mode_fcurves(obj)
        for i in range(m):
            fc = fcurves.get(sliders[i].name)
            if fc is None:
                continue
            for mod in list(fc.modifiers):
                fc.modifiers.remove(mod)
            if self.cyclic:
                fc.modifiers.new("CYCLES")
        scene = context.scene
        scene.frame_start = 1
        scene.frame_end = plan["end"] - 1 if self.cyclic else plan["end"]
        scene.frame_set(1)
        self.report({"INFO"}, f"{obj.name}: {m} modes animated over frames 1-{scene.frame_end}"
                              f"{' (looping)' if self.cyclic else ''}")
        return {"FINISHED"}


class SSM_OT_random_shape(bpy.types.Operator):
    """New object sampled from the model: b_k ~ N(0, λ_k) (eq. 7), seeded"""

    bl_idname = "ssm.random_shape"
    bl_label = "Random Shape"
    bl_options = {"REGISTER", "UNDO"}

    seed: IntProperty(name="Seed", default=0, min=0, options={"SKIP_SAVE"},
                      description="Seed of the shape (default: the panel's)")
    n_modes: IntProperty(name="Modes", description="Modes used (0: all)", default=0, min=0)
    sd_limit: FloatProperty(name="Limit (σ)", description="Clip each weight to ±limit standard deviations (default: "
                            "the panel's)", default=3.0, min=0.1, options={"SKIP_SAVE"})

    @classmethod
    def poll(cls, context):
        return _poll_model(cls, context)

    def execute(self, context):
        s = context.scene.ssm_model
        if not self.properties.is_property_set("seed"):
            self.seed = s.sample_seed
        if not self.properties.is_property_set("sd_limit"):
            self.sd_limit = s.sample_sd_limit
        try:
            obj = _require_model(context)
            model = model_from_object(obj)
        except InputError as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        k = self.n_modes or model.n_modes
        points = model.sample(1, k=k, seed=self.seed, sd_limit=self.sd_limit)[0]
        z = model.project(points, k=min(k, model.n_modes)) / model.standard_deviations[: min(k, model.n_modes)]
        name = f"SSM Sample {self.seed}"
        matrix = np.array(obj.matrix_world, dtype=float)
        width = float(np.ptp(np.asarray(model.mean, float) @ matrix[:3, :3].T, axis=0)[0]) if model.n_points else 0.0
        matrix[0, 3] += 1.3 * width  # beside the model, to its right as it is shown
        sample = bridge.new_mesh_object(context, name, points, model.faces, collection_name=MODEL_COLLECTION,
                                        matrix_world=matrix)
        bridge.colour_correspondence(sample, model.mean, context.scene.ssm_display.colouring)
        sample.ssm.role = "SAMPLE"
        sample["ssm_z"] = np.asarray(z, dtype=np.float64)
        sample["ssm_seed"] = int(self.seed)
        self.report({"INFO"}, f"{name}: z = {np.round(z[:3], 2).tolist()} ...")
        return {"FINISHED"}


class SSM_OT_reset_modes(bpy.types.Operator):
    """Set every mode value to 0 (the mean shape)"""

    bl_idname = "ssm.reset_modes"
    bl_label = "Reset Modes"
    bl_options = {"REGISTER", "UNDO"}

    clear_animation: BoolProperty(name="Clear animation", description="Also remove the mode keyframes (else the "
                                  "animation sets the values again on the next frame)", default=True)

    @classmethod
    def poll(cls, context):
        return _poll_model(cls, context)

    def execute(self, context):
        try:
            obj = _require_model(context)
        except InputError as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        if self.clear_animation:
            clear_mode_animation(obj)
        for slider in mode_sliders(obj):
            slider.value = 0.0
        if obj.type == "MESH":
            obj.data.update()
        return {"FINISHED"}


class SSM_OT_save_model(BackgroundJob, bpy.types.Operator):
    """Write the model's files and the build's report (report.json, report.html with the scene's findings) into a folder, as a headless build does"""

    bl_idname = "ssm.save_model"
    bl_label = "Save Model"
    bl_options = {"REGISTER"}

    directory: StringProperty(name="Directory", subtype="DIR_PATH")
    metrics: BoolProperty(name="Quality metrics", description="Generalization and specificity when the scene has "
                          "none yet (compactness always)", default=True)
    plots: BoolProperty(name="Plots", description="Spectrum and cumulative variance images (needs matplotlib)", default=True)
    n_samples: IntProperty(name="Specificity samples", default=500, min=1, options={"SKIP_SAVE"},
                           description="Random shapes of the specificity metric (default: the model settings')")
    force: BoolProperty(name="Write beside other files", default=False, options={"SKIP_SAVE"},
                        description="Write into a folder that holds files no SSM command wrote (they are kept, "
                                    "never overwritten)")

    @classmethod
    def poll(cls, context):
        return _poll_model(cls, context)

    def invoke(self, context, event):
        if not self.directory:
            self.directory = bpy.path.abspath(context.scene.ssm_model.last_directory) or ""
            context.window_manager.fileselect_add(self)
            return {"RUNNING_MODAL"}
        return BackgroundJob.invoke(self, context, event)

    def prepare(self, context):
        if not self.directory:
            raise InputError("Save Model: choose a directory")
        obj = _require_model(context)
        model = model_from_object(obj)
        out_dir = bpy.path.abspath(self.directory)
        samples = self.n_samples if self.properties.is_property_set("n_samples") else None
        with_metrics, plots, force, title = self.metrics, self.plots, self.force, f"SSM Builder: {obj.name}"
        output = scene_params(context, "ssm_output")
        extra = {"model_object": obj.name, "blend_file": bpy.data.filepath or ""}
        joint = None
        if model.structure_names:  # a joint model: its build's study, kept in the session and in the .blend
            joint, why = joint_study_of(context, obj, model)
            study = None
        else:
            study, why = saved_study(context, model)  # read here: the worker thread must not touch bpy
        mp = context.scene.ssm_model
        context_samples, seed, max_loo = mp.specificity_samples, mp.seed, mp.max_loo
        bpy_file = bpy.data.filepath
        self._metrics_result = None

        def work(progress, cancelled):
            if joint is not None:  # the joint build's writer, under the build's rules (never into an input's folder)
                save_joint_outputs(joint, out_dir, force=force, output=output, title=title, extra=extra,
                                   progress=progress, cancelled=cancelled, project=Absent(
                                       f"built interactively in Blender ({bpy_file or 'an unsaved .blend'})"))
                return out_dir, ""
            if study is None:  # a model on its own (opened from a file): its files and what it knows
                mets = core_metrics.evaluate(model, n_samples=samples or context_samples, seed=seed, max_loo=max_loo,
                                             progress=progress, cancelled=cancelled) if with_metrics else \
                    core_metrics.ModelMetrics(compactness=core_metrics.compactness(model))
                with owned_output_folder(out_dir, [], force=force, what="saving") as tmp:
                    written = write_outputs(model, tmp, metrics=mets, per_instance=dict(model.params.get("fit") or {}),
                                            extra=extra, plots=plots, why=why, statismo=output.statismo,
                                            tables=output.scores, gltf=output.gltf, vtk=output.vtk,
                                            exchange_modes=output.exchange_modes)
                    write_report_html(tmp, model, written["report_object"], title=title)
                return out_dir, written.get("plots_skipped", "")
            if study.metrics is None and with_metrics:
                self._metrics_result = metrics_stage(study, progress=sub_progress(progress, 0.0, 0.8),
                                                     cancelled=cancelled, specificity_samples=samples)
                apply_stage(study, self._metrics_result)
            unknown = {s: "not recorded in this scene (run in another session, or before the scene kept its "
                          "records)" for s in ("import", "template", "coating", "model") if s not in study.timings_s}
            folder, _files, _report = save_study_outputs(
                study, out_dir, force=force, output=output, title=title, plots=plots, extra=extra,
                project=Absent(f"built interactively in Blender ({bpy_file or 'an unsaved .blend'})"),
                timings_unknown=unknown, metrics_absent="not computed (Save Model with Quality metrics off)",
                progress=sub_progress(progress, 0.8, 1.0), cancelled=cancelled)
            return str(folder), ""

        return work

    def finish(self, context, outcome):
        folder, skipped = outcome
        if self._metrics_result is not None:
            record_stage(context, self._metrics_result)
        context.scene.ssm_model.last_directory = folder
        msg = f"saved {folder}: model.npz, model.h5, report.json, report.html"
        self.report({"WARNING"} if skipped else {"INFO"}, f"{msg}; {skipped}" if skipped else msg)
        return {"FINISHED"}


def saved_study(context, model: ShapeModel):
    """The scene's study for *Save Model*: its instances, template, coatings and records with
    ``model``, or ``(None, why)`` when the scene does not hold the study the model came from
    (a model opened from a file, or instances removed since)."""
    try:
        study = study_from_scene(context, records=True)
    except InputError as err:
        return None, f"a model without its study in this scene ({err})"
    names = [str(n) for n in model.instance_names]
    missing = [n for n in names if n not in study.coatings]
    if study.template is None or missing or not names:
        return None, ("a model without its study in this scene: " + (
            f"no coated instance {', '.join(missing[:3])}" if missing else "no template"))
    study.model = model
    if not study.outlier_scores:  # a model built before the scene kept its records
        study.outlier_scores = check_model(model, study.params.quality)[1]
    return study, ""


# ---------------------------------------------------------------------------------------
# panel
# ---------------------------------------------------------------------------------------
class SSM_PT_model(SSMPanel, bpy.types.Panel):
    """Model: build, per-mode variance bars and sliders, animation, sampling, files."""

    bl_idname = "SSM_PT_model"
    bl_label = "Model"
    bl_order = 40

    def draw(self, context):
        layout = self.layout
        settings = context.scene.ssm_model
        draw_params(layout, settings, ModelParams)
        structures = scene_structures(context)
        if structures:  # a joint study: its one build
            layout.operator("ssm.build_joint_model", text=f"Build Joint Model ({', '.join(structures)})",
                            icon="MOD_MESHDEFORM")
        else:
            n_coated = len(coated_objects(context))
            layout.operator("ssm.build_model", text=f"Build Model ({n_coated} coated)", icon="MOD_MESHDEFORM")
        obj = find_model_object(context)
        if obj is None:
            layout.label(text="No model yet", icon="INFO")
            return
        g = obj[MODEL_KEY]
        shp = json.loads(g["shape_json"])
        layout.label(text=f"{obj.name}: {shp['n']} instances, {shp['N']} points, {shp['K']} modes")
        parts = model_structures(obj)
        if parts:
            layout.label(text="joint model: " + ", ".join(parts) + " (one mesh each, one slider per mode)",
                         icon="GROUP_VERTEX")
        loc = obj.matrix_world.translation
        layout.label(text=f"at ({loc[0]:.0f}, {loc[1]:.0f}, {loc[2]:.0f}) mm, right of the instances",
                     icon="OBJECT_ORIGIN")
        fractions = np.asarray(g["fractions"])
        cum = np.cumsum(fractions)
        box = layout.box()
        keys = mode_sliders(obj)
        for i, slider in enumerate(keys[: settings.show_modes]):
            row = box.row(align=True)
            split = row.split(factor=0.45, align=True)
            pct = 100 * fractions[i] if i < len(fractions) else 0.0
            tot = 100 * cum[i] if i < len(cum) else 0.0
            split.progress(factor=float(fractions[i]) if i < len(fractions) else 0.0, type="BAR", text=f"{i + 1}: {pct:.1f} % (Σ {tot:.1f})")
            slider.draw(split)
        if len(keys) > settings.show_modes:
            box.label(text=f"… {len(keys) - settings.show_modes} more modes")
        box.prop(settings, "show_modes")
        row = layout.row(align=True)
        op = row.operator("ssm.reset_modes", text="Reset", icon="LOOP_BACK")
        op.clear_animation = True
        col = layout.column(align=True)
        col.prop(settings, "anim_modes")
        col.prop(settings, "anim_frames")
        col.prop(settings, "anim_amplitude")
        col.operator("ssm.animate_modes", icon="ANIM")
        row = layout.row(align=True)
        row.prop(settings, "sample_seed")
        row.operator("ssm.random_shape", icon="MOD_NOISE")
        layout.operator("ssm.save_model", icon="EXPORT")
        lines = [f"{f.instance or 'study'} [{f.gate}]: {f.message}" for f in scene_findings(context)]
        if structures:  # the last joint build's, by structure
            lines = json.loads(context.scene.get(JOINT_FINDINGS_KEY, "[]"))
        box = layout.box()
        box.label(text=f"Quality: {len(lines)} finding(s)" if lines else "Quality: every gate passed",
                  icon="ERROR" if lines else "CHECKMARK")
        for line in lines:
            box.label(text=line)


class SSM_PT_model_advanced(SSMPanel, bpy.types.Panel):
    bl_label = "Advanced"
    bl_idname = "SSM_PT_model_advanced"
    bl_parent_id = "SSM_PT_model"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        draw_params(self.layout, context.scene.ssm_model, ModelParams, advanced=True)
        self.layout.prop(context.scene.ssm_display, "colouring")


class SSM_OT_import_model(bpy.types.Operator, ImportHelper):
    """Open a shape model (model.npz of SSM Builder, or a statismo .h5 of ours or another tool's):
    the mean mesh with one shape key per mode and the Model panel, as for a built model"""

    bl_idname = "ssm.import_model"
    bl_label = "Import Shape Model"
    bl_options = {"REGISTER", "UNDO"}

    filter_glob: StringProperty(default=file_glob("model"), options={"HIDDEN"})

    def execute(self, context):
        try:
            notes = []
            model = load_model(self.filepath, say=notes.append)  # allow_pickle=False; errors name the file
        except SSMError as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        obj = create_model_object(context, model)
        obj[MODEL_FILE_PROP] = os.path.abspath(self.filepath)  # what a segmentation's segment.json names
        if store_appearance(obj, self.filepath, model.n_points):
            notes.append("with the boundary appearance learned from its training images (for Segment with Model)")
        self.report({"INFO"}, f"{os.path.basename(self.filepath)}: {model.n_modes} modes, {model.n_points} points"
                              f"{f', from {model.n_instances} instances' if model.n_instances else ''} as {obj.name!r}"
                              + (f"; structures {', '.join(model.structure_names)} (one mesh each)"
                                 if model.structure_names else "")
                              + "".join(f"; {n}" for n in notes))
        return {"FINISHED"}


def menu_func_import(self, context):
    self.layout.operator(SSM_OT_import_model.bl_idname, text="Shape Model (SSM: .npz, statismo .h5)")


def register_properties():
    bpy.types.TOPBAR_MT_file_import.append(menu_func_import)


def unregister_properties():
    bpy.types.TOPBAR_MT_file_import.remove(menu_func_import)


classes = (
    SSM_OT_import_model,
    SSM_OT_build_model,
    SSM_OT_animate_modes,
    SSM_OT_random_shape,
    SSM_OT_reset_modes,
    SSM_OT_save_model,
    SSM_PT_model,
    SSM_PT_model_advanced,
)
