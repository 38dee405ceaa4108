"""Coating in Blender (paper section 4): coat the template onto the instances.

Inputs: the template object ``"SSM Template"`` (role TEMPLATE; its mesh vertices are the
template points in the object frame of its source instance ``obj.ssm.instance``), the
landmarks of every instance (``operators/landmarks.py``, file world mm, converted into
each instance's object frame) and each instance's object volume
(``operators/instances.instance_object_volume``).

Output per instance: a mesh ``"<instance> coated"`` with the template's topology and
per-triangle colours (paper figs. 6-8), placed so it overlays the instance, with
``obj.ssm.role == "COATED"``, ``obj.ssm.instance`` and the fit figures in
``obj.ssm.fit_json``.
"""

from __future__ import annotations

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty

from ..ssm_addon import coating as core
from ..ssm_addon import meshutil as mu
from ..ssm_addon.errors import InputError
from ..ssm_addon.landmarks import match_landmarks
from . import bridge
from .instances import instance_object_volume, scene_instances
from .jobs import BackgroundJob
from .landmarks import instance_frame, landmark_sets_by_instance
from .template import TEMPLATE_NAME, find_template

COATED_COLLECTION = "SSM Coated"
COATED_SUFFIX = " coated"

KERNEL_ITEMS = [
    ("biharmonic", "Biharmonic r", "3D biharmonic U(r) = r (paper's Duchon type for 3D)"),
    ("thin-plate", "r² ln r", "Thin-plate U(r) = r² ln r"),
    ("hardy", "Hardy", "Hardy multiquadric U(r) = (r² + s²)^a"),
]
REST_ITEMS = [
    ("warped", "Warped", "Rest lengths of the landmark-warped template (keeps the warp's stretch; best correspondence)"),
    ("template-scaled", "Template scaled", "Template edge lengths scaled to the instance's size (the paper)"),
]


class SSMCoatingSettings(bpy.types.PropertyGroup):
    """Coating parameters (``Scene.ssm_coating``), mirrors :class:`ssm_addon.coating.CoatingParams`."""

    kernel: EnumProperty(name="Kernel", items=KERNEL_ITEMS, default="biharmonic")
    hardy_a: FloatProperty(name="Hardy a", default=0.5, min=0.01, max=5.0)
    hardy_s_mm: FloatProperty(name="Hardy s (mm)", default=0.0, min=0.0, description="0: median landmark distance")
    k1: FloatProperty(name="k1 (edges)", default=core.CoatingParams.k1, min=0.0, soft_max=2.0)
    k2: FloatProperty(name="k2 (surface)", default=core.CoatingParams.k2, min=0.001, soft_max=5.0)
    k3: FloatProperty(name="k3 (smoothing)", default=core.CoatingParams.k3, min=0.0, soft_max=2.0)
    mass: FloatProperty(name="Mass", default=core.CoatingParams.mass, min=0.001)
    damping: FloatProperty(name="Damping", default=core.CoatingParams.damping, min=0.0)
    dt: FloatProperty(name="Step", default=core.CoatingParams.dt, min=0.001, max=2.0)
    max_iterations: IntProperty(name="Max iterations", default=core.CoatingParams.max_iterations, min=0, max=100000)
    velocity_tol_mm: FloatProperty(name="Velocity tolerance", default=core.CoatingParams.velocity_tol_mm, min=0.0)
    fold_angle_deg: FloatProperty(name="Fold angle (°)", default=core.CoatingParams.fold_angle_deg, min=1.0, max=180.0)
    rest_lengths: EnumProperty(name="Rest lengths", items=REST_ITEMS, default=core.CoatingParams.rest_lengths)
    use_registration: BoolProperty(
        name="Surface registration",
        default=True,
        description="Smooth coarse-to-fine surface registration between warp and projection (off: the paper's scheme)",
    )
    registration_sigma_mm: FloatProperty(
        name="Coarsest width (mm)",
        default=core.CoatingParams.registration_sigmas_mm[0],
        min=0.5,
        description="Gaussian width of the first registration level; each further level halves it",
    )
    registration_levels: IntProperty(
        name="Levels",
        default=len(core.CoatingParams.registration_sigmas_mm),
        min=1,
        max=8,
        description="Number of coarse-to-fine registration levels",
    )
    regularization: FloatProperty(
        name="Warp smoothing", default=0.0, min=0.0,
        description="λ of the landmark warp (0: exact at the landmarks; ~1000 tolerates inconsistent landmarks)",
    )  # fmt: skip
    fold_free_warp: BoolProperty(
        name="Fold-free warp", default=True,
        description="Smooth the warp just enough that inconsistent landmarks do not fold the template",
    )  # fmt: skip
    fold_smoothing: FloatProperty(
        name="Fold smoothing", default=core.CoatingParams.fold_smoothing, min=0.0, soft_max=2.0,
        description="Laplacian force on vertices of folded triangles (their surface force is off)",
    )  # fmt: skip
    selected_only: BoolProperty(name="Selected only", default=False, description="Coat only the selected instances")

    def params(self) -> core.CoatingParams:
        return core.CoatingParams(
            kernel=self.kernel,
            hardy_a=self.hardy_a,
            hardy_s_mm=self.hardy_s_mm if self.hardy_s_mm > 0 else None,
            k1=self.k1,
            k2=self.k2,
            k3=self.k3,
            mass=self.mass,
            damping=self.damping,
            dt=self.dt,
            max_iterations=self.max_iterations,
            velocity_tol_mm=self.velocity_tol_mm,
            fold_angle_deg=self.fold_angle_deg,
            rest_lengths=self.rest_lengths,
            regularization=self.regularization,
            fold_free_warp=self.fold_free_warp,
            fold_smoothing=self.fold_smoothing,
            registration_sigmas_mm=(
                tuple(self.registration_sigma_mm / 2**i for i in range(self.registration_levels))
                if self.use_registration
                else ()
            ),
        )


# ------------------------------------------------------------------------------ helpers


def coated_objects(context) -> list:
    """Coated meshes of the scene, by name."""
    return sorted((o for o in context.scene.objects if o.type == "MESH" and o.ssm.role == "COATED"), key=lambda o: o.name)


def object_to_blender_matrix(instance) -> np.ndarray:
    """(4, 4) the instance's object frame (mm) -> Blender world (mm).

    Blender world = matrix_world @ inverse(import_matrix) @ frame.matrix_world, so the
    coated mesh overlays the instance even after the instance was moved.
    """
    imp = np.array(instance.ssm.import_matrix, dtype=float).reshape(4, 4)
    return bridge.matrix_to_numpy(instance.matrix_world) @ np.linalg.inv(imp) @ instance_frame(instance).matrix_world


def _coating_inputs(context, targets_selected_only: bool):
    """Read the template, landmarks and volumes from the scene (main thread)."""
    tpl = find_template(context)
    if tpl is None:
        raise InputError(f"coat template: no template object ({TEMPLATE_NAME!r} with role Template); build the template first")
    source = tpl.ssm.instance
    if source is None:
        raise InputError(f"coat template: {tpl.name!r} does not name its source instance (obj.ssm.instance)")
    instances = scene_instances(context)
    if targets_selected_only:
        instances = [o for o in instances if o.select_get()]
    if not instances:
        raise InputError("coat template: no instances to coat (select instances or switch off 'Selected only')")
    sets = landmark_sets_by_instance(context)
    if source.name not in sets:
        raise InputError(f"coat template: the template's instance {source.name!r} has no landmarks")
    missing = [o.name for o in instances if o.name not in sets]
    if missing:
        raise InputError(f"coat template: instance(s) without landmarks: {', '.join(missing)}")
    schema = [n for n in sets[source.name].names if all(n in sets[o.name].names for o in instances)]
    if len(schema) < 4:
        raise InputError(
            f"coat template: only {len(schema)} landmark name(s) shared by {source.name} and all instances; at least 4 needed"
        )
    matched = match_landmarks([sets[source.name]] + [sets[o.name] for o in instances], names=schema, allow_extra=True)
    src_lm = instance_frame(source).to_object(matched[0].points_world)
    targets, target_lms = [], []
    for obj, lm in zip(instances, matched[1:]):
        targets.append(instance_object_volume(obj))
        target_lms.append(instance_frame(obj).to_object(lm.points_world))
    points = bridge.mesh_vertices(tpl.data)
    faces = bridge.mesh_triangles(tpl.data)
    template = mu.Mesh(points, faces)
    return template, src_lm, targets, target_lms, [o.name for o in instances]


def write_coated(context, instance, result: core.CoatingResult, faces: np.ndarray):
    """Create or refresh ``"<instance> coated"`` for one coating result."""
    name = instance.name + COATED_SUFFIX
    obj = bridge.new_mesh_object(
        context, name, result.points_object, faces, collection_name=COATED_COLLECTION,
        matrix_world=object_to_blender_matrix(instance),
    )  # fmt: skip
    bridge.set_face_colors(obj.data, bridge.triangle_index_colors(len(faces)))
    mat = bridge.color_material()
    if not obj.data.materials:
        obj.data.materials.append(mat)
    else:
        obj.data.materials[0] = mat
    obj.ssm.role = "COATED"
    obj.ssm.instance = instance
    obj.ssm.fit_json = result.fit.to_json()
    return obj


def fit_of(obj) -> core.FitFigures | None:
    """The fit figures stored on a coated object, or None."""
    if not obj.ssm.fit_json:
        return None
    try:
        return core.FitFigures.from_json(obj.ssm.fit_json)
    except (ValueError, TypeError):
        return None


# ---------------------------------------------------------------------------- operator


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
        return find_template(context) is not None

    def prepare(self, context):
        settings = context.scene.ssm_coating
        selected = self.selected_only or settings.selected_only
        template, src_lm, targets, target_lms, names = _coating_inputs(context, selected)
        params = settings.params()
        params.validate()
        self._names = names
        self._faces = template.faces
        cancel_after = self.cancel_after
        done = [0]

        def counting(progress):
            def inner(fraction, message):
                if message.startswith("coated "):
                    done[0] += 1
                if progress is not None:
                    progress(fraction, message)

            return inner

        def work(progress, cancelled):
            def stop():
                return bool(cancelled and cancelled()) or (cancel_after >= 0 and done[0] >= cancel_after)

            try:
                results = core.coat_all(template, src_lm, targets, target_lms, params, jobs=1,
                                        progress=counting(progress), cancelled=stop, names=names)  # fmt: skip
            except core.CoatingCancelled as err:  # Esc: keep the finished instances
                return err.results, True
            return results, False

        return work

    def _write(self, context, results):
        written = []
        for name, result in zip(self._names, results):
            inst = bpy.data.objects.get(name)
            if result is None or inst is None:
                continue
            written.append(write_coated(context, inst, result, self._faces))
        return written

    def finish(self, context, outcome):
        results, was_cancelled = outcome
        written = self._write(context, results)
        poor = [o.name for o in written if fit_of(o).poor]
        msg = f"coated {len(written)} instance(s)"
        if was_cancelled:
            msg = f"cancelled: kept {len(written)} of {len(results)} coated instance(s)"
        if poor:
            self.report({"WARNING"}, f"{msg}; poor fit (folds or > 1 voxel): {', '.join(poor)}")
        else:
            self.report({"INFO"}, msg)
        return {"FINISHED"}

    def partial(self, context, state):
        """On an error after some instances finished, keep those (Esc is handled in ``work``)."""
        err = state.get("error")
        results = getattr(err, "results", None)
        if results:
            written = self._write(context, results)
            self.report({"INFO"}, f"kept {len(written)} finished coated instance(s)")


# ------------------------------------------------------------------------------- panel


class SSM_PT_coating(bpy.types.Panel):
    bl_label = "Coating"
    bl_idname = "SSM_PT_coating"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "SSM"
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
        col = layout.column(align=True)
        col.prop(s, "kernel")
        if s.kernel == "hardy":
            row = col.row(align=True)
            row.prop(s, "hardy_a")
            row.prop(s, "hardy_s_mm")
        col.prop(s, "regularization")
        col.prop(s, "fold_free_warp")
        col = layout.column(align=True)
        col.prop(s, "use_registration")
        if s.use_registration:
            row = col.row(align=True)
            row.prop(s, "registration_sigma_mm")
            row.prop(s, "registration_levels")
        col = layout.column(align=True)
        col.prop(s, "rest_lengths")
        row = col.row(align=True)
        row.prop(s, "k1")
        row.prop(s, "k2")
        col.prop(s, "k3")
        row = col.row(align=True)
        row.prop(s, "mass")
        row.prop(s, "damping")
        row = col.row(align=True)
        row.prop(s, "dt")
        row.prop(s, "max_iterations")
        row = col.row(align=True)
        row.prop(s, "velocity_tol_mm")
        row.prop(s, "fold_angle_deg")
        col.prop(s, "fold_smoothing")
        layout.prop(s, "selected_only")
        layout.operator(SSM_OT_coat_template.bl_idname, icon="MOD_SHRINKWRAP")
        coated = coated_objects(context)
        if coated:
            box = layout.box()
            box.label(text="Fit (mean / max mm, folds, start)")
            for obj in coated:
                fit = fit_of(obj)
                if fit is None:
                    continue
                row = box.row()
                row.label(
                    text=f"{obj.name.removesuffix(COATED_SUFFIX)}: {fit.mean_distance_mm:.2f} / {fit.max_distance_mm:.2f}, "
                    f"{fit.folded_after}, {fit.start}",
                    icon="ERROR" if fit.poor else "CHECKMARK",
                )


classes = (SSMCoatingSettings, SSM_OT_coat_template, SSM_PT_coating)


def register_properties():
    bpy.types.Scene.ssm_coating = PointerProperty(type=SSMCoatingSettings)


def unregister_properties():
    del bpy.types.Scene.ssm_coating
