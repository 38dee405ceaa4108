"""Coating in Blender (paper section 4): coat the template onto the instances.

``ssm.coat_template`` runs the core's :func:`~ssm_addon.pipeline.stages.coat_instances` on the
scene's study (the float64 template, each instance's landmarks in its file world and its
volume reloaded from source) and writes one mesh ``"<instance> coated"`` per instance:
the template's topology and correspondence colours, placed so it overlays the instance,
``obj.ssm.role == "COATED"``, ``obj.ssm.instance``, the float64 points in
``obj["ssm_coating"]`` and the fit figures in ``obj.ssm.fit_json``. Coating an instance
again replaces its coated mesh (found by the instance pointer, so renaming is safe).
"""

from __future__ import annotations

import time

import bpy
from bpy.props import BoolProperty, IntProperty

from ssm_addon.base.errors import InputError
from ssm_addon.base.params import CoatingParams, CorrespondenceParams
from ssm_addon.base.progress import sub_progress
from ssm_addon.coating import coating as core
from ssm_addon.pipeline.model_method import refine_correspondence
from ssm_addon.pipeline.runner import coating_stage
from ssm_addon.pipeline.sides import sides_first, with_sides_product
from ssm_addon.pipeline.stages import coating_result, import_result
from ssm_addon.pipeline.study import apply_stage
from ssm_addon.pipeline.template_refinement import with_template_refined

from .jobs import BackgroundJob
from .properties import SSMPanel, draw_params, scene_params
from .scene import (
    VolumeLoader,
    apply_sides,
    coated_object_of,
    coated_objects,
    find_template,
    finish_optimisation,
    instance_findings,
    prepare_optimisation,
    record_stage,
    report_stage,
    scene_instances,
    scene_optimisation,
    scene_records,
    study_from_scene,
    write_coated,
    write_template_object,
)


def fit_of(obj) -> core.FitFigures | None:
    """The fit figures stored on a coated object, or None."""
    if not obj.ssm.fit_json:
        return None
    try:
        return core.FitFigures.from_json(obj.ssm.fit_json)
    except (ValueError, TypeError):
        return None


class SSM_OT_coat_template(BackgroundJob, bpy.types.Operator):
    """Coat the template onto the instances: landmark warp, projection, mass-spring relaxation (paper 4). Esc keeps finished instances"""

    bl_idname = "ssm.coat_template"
    bl_label = "Coat Template"
    bl_options = {"REGISTER", "UNDO"}

    selected_only: BoolProperty(
        name="Selected only", default=False, description="Coat only the selected instances (or the panel's setting)"
    )
    cancel_after: IntProperty(
        default=-1, options={"HIDDEN", "SKIP_SAVE"}, description="Scripts/tests: act as if Esc was pressed after N instances"
    )

    @classmethod
    def poll(cls, context):
        if find_template(context) is None:
            cls.poll_message_set("Build the template first (Template panel)")
            return False
        return True

    def prepare(self, context):
        self._model_method = scene_params(context, "ssm_correspondence").method == "model"
        if self._model_method:  # the model method coats the whole study, as a build does
            return prepare_refinement(self, context, fresh=True)
        selected = self.selected_only or context.scene.ssm_coating.selected_only
        objs = scene_instances(context)
        if selected:
            objs = [o for o in objs if o.select_get()]
        if not objs:
            raise InputError("coat template: no instances to coat (select instances or switch off 'Selected only')")
        study = study_from_scene(context, coatings=False)
        if study.template is None:
            raise InputError("coat template: no template (build the template first)")
        names = [o.name for o in objs]
        template_obj = bpy.data.objects[study.template_instance]
        loader = VolumeLoader(context, list({o.name: o for o in [template_obj, *objs]}.values()))
        self._names, self._loader = names, loader
        self._faces, self._template_points = study.template.faces, study.template.points_object
        cancel_after = self.cancel_after
        done = [0]

        def count(_name):
            done[0] += 1

        def work(progress, cancelled):
            def stop():
                return bool(cancelled and cancelled()) or (cancel_after >= 0 and done[0] >= cancel_after)

            t0 = time.perf_counter()
            imported = import_result(study, loader.load(None, stop), time.perf_counter() - t0)
            apply_stage(study, imported)
            t0 = time.perf_counter()
            try:
                return imported, coating_stage(study, names=names, progress=progress, cancelled=stop,
                                                 on_coated=count), False
            except core.CoatingCancelled as err:  # Esc: keep the finished instances
                kept = {n: r for n, r in zip(names, err.results) if r is not None}
                return imported, coating_result(study, kept, {n: r.fit.start for n, r in kept.items()},
                                                time.perf_counter() - t0), True

        return work

    def _write(self, context, results: dict):
        written = []
        for name, result in results.items():
            inst = bpy.data.objects.get(name)
            if result is None or inst is None:
                continue
            written.append(write_coated(context, inst, result, self._faces, self._template_points))
        return written

    def finish(self, context, outcome):
        if self._model_method:
            return finish_refinement(self, context, outcome)
        self._loader.keep()
        imported, result, was_cancelled = outcome
        apply_sides(result.product.get("sides"))
        shown = show_template(context, result.product)  # from the medoid, or denser where coatings cut off parts
        if shown is not None:
            self._faces, self._template_points = shown.faces, shown.points_object
        written = self._write(context, result.product["coatings"])
        found = record_stage(context, imported) + record_stage(context, result)
        msg = f"coated {len(written)} instance(s)"
        check = result.product.get("correspondence_check")
        if check is not None:
            msg += f"; landmark transfer error {check.study_mm:.2f} mm"
        if was_cancelled:
            msg = f"cancelled: kept {len(written)} of {len(self._names)} coated instance(s)"
        report_stage(self, msg, found)
        return {"FINISHED"}

    def partial(self, context, state):
        """On an error after some instances finished, keep those (Esc is handled in ``work``)."""
        if self._model_method:
            return
        err = state.get("error")
        results = getattr(err, "results", None)
        if results:
            written = self._write(context, dict(zip(self._names, results)))
            self.report({"INFO"}, f"kept {len(written)} finished coated instance(s)")


class SSM_OT_refine_correspondence(BackgroundJob, bpy.types.Operator):
    """Refine the correspondence with the model: the mean shape as template, each instance fitted by the model of the others and relaxed onto its surface (paper 3.3, 7). Instances not coated yet start from their landmarks or object frames. Esc keeps the scene as it was"""

    bl_idname = "ssm.refine_correspondence"
    bl_label = "Refine Correspondence"
    bl_options = {"REGISTER", "UNDO"}

    cancel_after: IntProperty(
        default=-1, options={"HIDDEN", "SKIP_SAVE"},
        description="Scripts/tests: act as if Esc was pressed after N instances were refined")

    @classmethod
    def poll(cls, context):
        if find_template(context) is None:
            cls.poll_message_set("Build the template first (Template panel)")
            return False
        if len(scene_instances(context)) < 3:
            cls.poll_message_set("Refinement needs at least 3 instances")
            return False
        return True

    def prepare(self, context):
        return prepare_refinement(self, context, fresh=False)

    def finish(self, context, outcome):
        return finish_refinement(self, context, outcome)


def prepare_refinement(op, context, *, fresh: bool):
    """The work of the model method on the scene's study (``fresh``: start every instance
    again, as a headless build does; else further rounds from the current coatings)."""
    study = study_from_scene(context, coatings=not fresh)
    if study.template is None:
        raise InputError("refine correspondence: no template (build the template first)")
    loader = VolumeLoader(context, scene_instances(context))
    op._loader, op._fresh = loader, fresh
    cancel_after = getattr(op, "cancel_after", -1)
    refined = [0]

    def count(_name):
        refined[0] += 1

    def work(progress, cancelled):
        def stop():
            return bool(cancelled and cancelled()) or 0 <= cancel_after <= refined[0]

        t0 = time.perf_counter()
        imported = import_result(study, loader.load(sub_progress(progress, 0.0, 0.1), stop), time.perf_counter() - t0)
        apply_stage(study, imported)

        def coat(s):
            return refine_correspondence(s, progress=sub_progress(progress, 0.1, 1.0), cancelled=stop, on_coated=count)

        # the sides first, as the build's coating stage decides them
        sided, decisions, seconds = sides_first(study, cancelled=stop)
        first = coat(sided)  # starting afresh, as a build does: the template refined where the coatings cut off parts
        result = with_template_refined(sided, first, coat, cancelled=stop) if fresh else first
        return imported, with_sides_product(sided, result, decisions, seconds)

    return work


def show_template(context, product: dict):
    """The coating stage's template in the scene when the stage built it again: from the medoid
    (``product["template_instance"]``, another instance than the scene's template's: the template
    object moves to it) or denser where coatings cut off parts. Returns that template, or None."""
    template = product.get("template")
    if template is None:
        return None
    medoid = product.get("template_instance")
    current = context.scene.ssm_display.template_instance
    if current is None and find_template(context) is not None:
        current = find_template(context).ssm.instance
    if (medoid is not None and (current is None or current.name != medoid)
            and bpy.data.objects.get(medoid) is not None):  # the template built again from the medoid
        write_template_object(context, bpy.data.objects[medoid], template)
        return template
    if "refined_at" in (template.params or {}) and current is not None:  # built again, denser
        write_template_object(context, current, template)
        return template
    return None


def finish_refinement(op, context, outcome):
    """Write the refined coatings and the rounds' figures into the scene."""
    op._loader.keep()
    imported, result = outcome
    apply_sides(result.product.get("sides"))
    coatings, starts = result.product["coatings"], result.product["coating_start"]
    rounds = list(result.product.get("correspondence_rounds", ()))
    mean_points = result.product["template"].points_object
    show_template(context, result.product)
    written = []
    for name, coating in coatings.items():
        inst = bpy.data.objects.get(name)
        if inst is not None:
            obj = write_coated(context, inst, coating, result.product["template"].faces, mean_points)
            obj["ssm_coating_start"] = starts.get(name, coating.fit.start)
            written.append(obj)
    check = result.product.get("correspondence_check")
    folds = sum(c.fit.folded_after for c in coatings.values())
    last = rounds[-1] if rounds else None
    msg = (f"refined {len(written)} instance(s) in {len(rounds)} round(s)"
           + (f"; mean shape moved {last.mean_change_mm:.3f} mm in the last" if last else ""))
    if check is not None:
        kept = f"round {check.kept_round}'s coatings" if check.kept_round else "the start's coatings"
        msg += f"; {check.stop}: kept {kept}, landmark transfer error {check.study_mm:.2f} mm"
    found = record_stage(context, imported) + record_stage(context, result, fresh=op._fresh)
    report_stage(op, f"{msg}; {folds} folded triangle(s) left" if folds else msg, found)
    return {"FINISHED"}


class SSM_OT_optimise_correspondence(BackgroundJob, bpy.types.Operator):
    """Optimise the correspondence across the population: every instance's coated points slide along its own surface, the given landmarks held (the build's step after the coating). Progress per iteration with the objective; Esc keeps the last complete iteration"""

    bl_idname = "ssm.optimise_correspondence"
    bl_label = "Optimise Correspondence"
    bl_options = {"REGISTER", "UNDO"}

    cancel_after: IntProperty(
        default=-1, options={"HIDDEN", "SKIP_SAVE"},
        description="Scripts/tests: act as if Esc was pressed after N iterations")

    @classmethod
    def poll(cls, context):
        if find_template(context) is None:
            cls.poll_message_set("Build the template first (Template panel)")
            return False
        missing = [o.name for o in scene_instances(context) if coated_object_of(o) is None]
        if missing or not scene_instances(context):
            cls.poll_message_set("Coat every instance first" + (f" ({len(missing)} not coated)" if missing else ""))
            return False
        return True

    def prepare(self, context):
        return prepare_optimisation(self, context)

    def finish(self, context, outcome):
        imported, result, was_cancelled = outcome
        found = finish_optimisation(self, context, imported, result)
        opt = result.product["optimisation"]
        last = opt.steps[-1]
        msg = (f"optimised {len(result.product['coatings'])} instance(s): {opt.iterations} iteration(s), {opt.stop}; "
               f"objective {opt.steps[0].objective:.4f} -> {last.objective:.4f}")
        if was_cancelled:
            msg = f"cancelled: kept iteration {opt.iterations}; " + msg
        report_stage(self, msg, found)
        return {"FINISHED"}


def correspondence_check(context) -> dict:
    """The correspondence self-check of the coatings in this scene (empty when none was run)."""
    return scene_records(context).get("correspondence_check") or {}


def correspondence_rounds(context) -> list[dict]:
    """The refinement rounds of the coatings in this scene."""
    return list(scene_records(context).get("correspondence_rounds") or ())


class SSM_PT_coating(SSMPanel, bpy.types.Panel):
    bl_label = "Coating"
    bl_idname = "SSM_PT_coating"
    bl_order = 30
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        s = context.scene.ssm_coating
        tpl = find_template(context)
        if tpl is None:
            layout.label(text="No template yet", icon="INFO")
        else:
            src = tpl.ssm.instance.name if tpl.ssm.instance else "?"
            layout.label(text=f"{tpl.name}: {len(tpl.data.vertices)} points, from {src}", icon="MESH_ICOSPHERE")
        draw_params(layout, s, CoatingParams)
        layout.prop(s, "selected_only")
        layout.operator(SSM_OT_coat_template.bl_idname, icon="MOD_SHRINKWRAP")
        box = layout.box()
        box.label(text="Model-guided correspondence", icon="MOD_MESHDEFORM")
        draw_params(box, context.scene.ssm_correspondence, CorrespondenceParams)
        box.operator(SSM_OT_refine_correspondence.bl_idname, icon="FILE_REFRESH")
        box.operator(SSM_OT_optimise_correspondence.bl_idname, icon="MOD_SMOOTH")
        opt = scene_optimisation(context)
        if opt.get("steps"):
            first, last = opt["steps"][0], opt["steps"][-1]
            box.label(text=f"optimised: {opt['iterations']} iteration(s), {opt['stop']}; objective "
                      f"{first['objective']:.4f} -> {last['objective']:.4f}; moved ≤ "
                      f"{max(opt['instance_movement_mm'].values(), default=0.0):.3f} mm", icon="CHECKMARK")
        elif context.scene.ssm_correspondence.optimise and coated_objects(context):
            box.label(text="coatings not optimised yet (Build Model optimises them first)", icon="INFO")
        for r in correspondence_rounds(context)[-6:]:
            moved = max(r["instance_change_mm"].values(), default=0.0)
            shift = max(r.get("landmark_shift_mm", {}).values(), default=0.0)
            kept = "kept" if r.get("kept", True) else "dropped"
            transfer = r.get("transfer_after_mm")
            judged = f", transfer {transfer:.2f} mm" if isinstance(transfer, float) and transfer == transfer else ""
            noise = r.get("landmark_noise") or {}
            box.label(text=f"round {r['round']} {kept}: mean {r['mean_change_mm']:.3f} mm, instances ≤ {moved:.2f} "
                      f"mm, landmarks ≤ {shift:.2f} mm, folds {sum(r['folds'].values())}{judged}, "
                      f"{r['seconds']:.0f} s")
            if noise.get("shrink"):
                box.label(text=f"    landmarks {noise['click_mm']:.2f} mm off, model {noise['model_mm']:.2f} mm: "
                          f"moved {noise['shrink']:.0%} to the prediction")
        check = correspondence_check(context)
        if check.get("instance_mm"):
            worst = max(check["instance_mm"], key=check["instance_mm"].get)
            stop = {"converged": "rounds converged", "criterion": "stopped by the self-check",
                    "limit": "round limit reached"}.get(check.get("stop", ""), "single pass")
            box.label(text=f"self-check: landmark transfer {check['study_mm']:.2f} mm (largest {worst} "
                      f"{check['instance_mm'][worst]:.2f} mm); {stop}",
                      icon="ERROR" if check.get("stop") == "limit" else "CHECKMARK")
        layout.prop(context.scene.ssm_display, "colouring")
        coated = coated_objects(context)
        if coated:
            box = layout.box()
            box.label(text="Fit (mean / max mm, folds, start)")
            for obj in coated:
                fit = fit_of(obj)
                if fit is None:
                    continue
                findings = instance_findings(context, obj.ssm.instance.name, "coating")
                row = box.row()
                row.label(
                    text=f"{obj.ssm.instance.name}: {fit.mean_distance_mm:.2f} / {fit.max_distance_mm:.2f}, "
                    f"{fit.folded_after}, {obj.get('ssm_coating_start', fit.start)}",
                    icon="ERROR" if findings else "CHECKMARK",
                )
                for f in findings:
                    box.label(text=f"    {f.gate}: {f.message}", icon="BLANK1")


class SSM_PT_coating_advanced(SSMPanel, bpy.types.Panel):
    bl_label = "Advanced"
    bl_idname = "SSM_PT_coating_advanced"
    bl_parent_id = "SSM_PT_coating"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        draw_params(self.layout, context.scene.ssm_coating, CoatingParams, advanced=True)


classes = (SSM_OT_coat_template, SSM_OT_refine_correspondence, SSM_OT_optimise_correspondence, SSM_PT_coating,
           SSM_PT_coating_advanced)
