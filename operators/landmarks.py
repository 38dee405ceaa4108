"""Landmarks in Blender: the schema, placing by ray cast, snapping, files and the proposal.

A landmark is a sphere empty named ``"<instance> <landmark>"``, parented to its instance
(keeping its world position), with ``obj.ssm.role == "LANDMARK"``, ``obj.ssm.instance``
pointing at the instance and the custom property ``"ssm_landmark"`` holding the
landmark's name. The schema (the ordered landmark names shared by all instances, paper
4.1) is ``Scene.ssm_landmarks.names``.

Coordinates: Blender world is mm; landmark files are in the instance's file world mm.
The two agree for an instance at its import position; ``blender_to_file_world`` /
``file_to_blender_world`` (operators/instances.py) convert for moved instances.
"""

from __future__ import annotations

import bpy
import numpy as np
from bpy.props import (
    BoolProperty,
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)
from bpy_extras.io_utils import ExportHelper, ImportHelper
from bpy_extras.view3d_utils import location_3d_to_region_2d, region_2d_to_origin_3d, region_2d_to_vector_3d
from mathutils import Vector

from ssm_addon.base.errors import InputError, SSMError
from ssm_addon.base.progress import sub_progress
from ssm_addon.correspondence import proposal
from ssm_addon.formats import landmarks as core
from ssm_addon.formats.registry import file_glob

from . import bridge
from .jobs import BackgroundJob
from .properties import SSMPanel, scene_params
from .scene import (
    LANDMARK_PROP,
    ORDER_PROP,
    VolumeLoader,
    blender_to_file_world,
    find_model_object,
    find_template,
    instance_landmarks,
    is_instance,
    landmark_empties,
    model_from_object,
    scene_instances,
    schema_names,
    set_landmark,
    stored_frame,
    template_from_object,
)

PICK_RADIUS_PX = 12.0
FILE_GLOB = file_glob("landmarks")


# --------------------------------------------------------------------------- the scene
def active_instance(context):
    """The active instance, or the instance of the active landmark; None otherwise."""
    obj = context.active_object
    if obj is not None and obj.ssm.role == "LANDMARK" and is_instance(obj.ssm.instance):
        return obj.ssm.instance
    return obj if is_instance(obj) else None


def missing_names(context, instance) -> list[str]:
    """Schema names the instance has no landmark for, in schema order."""
    have = landmark_empties(instance)
    return [n for n in schema_names(context) if n not in have]


def _poll_instance(cls, context) -> bool:
    if active_instance(context) is None:
        cls.poll_message_set("Make an SSM instance (or one of its landmarks) active")
        return False
    return True


def ray_hit(instance, origin_world, direction_world, depsgraph=None):
    """First hit of a Blender-world ray on the instance's mesh: (3,) world point or None.

    The ray is cast in the instance's object space (``Object.ray_cast``).
    """
    inv = instance.matrix_world.inverted()
    origin = inv @ Vector([float(x) for x in origin_world])
    direction = inv.to_3x3() @ Vector([float(x) for x in direction_world])
    if direction.length == 0.0:
        return None
    kwargs = {"depsgraph": depsgraph} if depsgraph is not None else {}
    hit, loc, _normal, _index = instance.ray_cast(origin, direction.normalized(), **kwargs)
    return (instance.matrix_world @ loc) if hit else None


def pick_on_screen(screen_points: dict, mouse, radius_px: float = PICK_RADIUS_PX) -> str:
    """The landmark whose screen position (px; None if behind the view) is nearest the
    mouse within ``radius_px``; "" if none (then a click places a landmark)."""
    best, best_d = "", radius_px
    for name, p in screen_points.items():
        if p is not None:
            d = float(np.hypot(p[0] - mouse[0], p[1] - mouse[1]))
            if d < best_d:
                best, best_d = name, d
    return best


def place_landmark(context, instance, origin_world, direction_world, name: str = ""):
    """Ray-cast and place ``name`` (default: the next missing schema name). Returns (empty, name)."""
    if not name:
        missing = missing_names(context, instance)
        if not missing:
            raise InputError(f"{instance.name}: every landmark of the schema is placed (pick one to re-place it)")
        name = missing[0]
    hit = ray_hit(instance, origin_world, direction_world, context.evaluated_depsgraph_get())
    if hit is None:
        return None, name
    return set_landmark(context, instance, name, blender_world=hit), name


# ----------------------------------------------------------------------------- schema


def _schema_renamed(self, context):
    """Update of a schema entry's name: rename the landmark empties that carry the old name."""
    old, new = self.previous, self.landmark.strip()
    if new == old:
        return
    settings = context.scene.ssm_landmarks
    if not new or any(item.name == new for item in settings.names if item != self):
        self.landmark = old  # refuse empty or duplicate names (re-enters with new == old)
        return
    if old:
        for obj in bpy.data.objects:
            if obj.ssm.role == "LANDMARK" and obj.get(LANDMARK_PROP) == old:
                obj[LANDMARK_PROP] = new
                if obj.ssm.instance is not None:
                    obj.name = f"{obj.ssm.instance.name} {new}"
    self.previous = new
    self.name = new


class SSMLandmarkName(bpy.types.PropertyGroup):
    """One landmark name of the schema (``name`` mirrors ``landmark``)."""

    landmark: StringProperty(name="Landmark", description="Landmark name (renaming renames the placed landmarks)", update=_schema_renamed)
    previous: StringProperty(options={"HIDDEN"})


def _instance_poll(self, obj):
    return is_instance(obj)


class SSMLandmarkSettings(bpy.types.PropertyGroup):
    """``Scene.ssm_landmarks``: the landmark schema and the landmark tools' settings."""

    names: CollectionProperty(type=SSMLandmarkName)
    active_index: IntProperty(name="Active landmark", default=0)
    proposal_source: PointerProperty(
        name="From", type=bpy.types.Object, poll=_instance_poll, description="Landmarked instance to propose landmarks from"
    )
    marker_size_mm: FloatProperty(name="Marker size", description="Landmark sphere radius in mm (0: 1.5 % of the instance size)", default=0.0, min=0.0)


def add_schema_name(settings, name: str, index: int | None = None) -> int:
    item = settings.names.add()
    item.previous = name
    item.landmark = name
    item.name = name
    last = len(settings.names) - 1
    if index is not None and 0 <= index < last:
        settings.names.move(last, index)
        return index
    return last


def set_schema(settings, names) -> None:
    settings.names.clear()
    for n in names:
        add_schema_name(settings, n)
    settings.active_index = 0


class SSM_UL_landmark_schema(bpy.types.UIList):
    """The schema list: double-click a name to rename it."""

    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index):
        inst = active_instance(context)
        placed = inst is not None and item.name in landmark_empties(inst)
        row = layout.row(align=True)
        row.label(text=f"{index + 1}", icon="CHECKMARK" if placed else "DOT")
        row.prop(item, "landmark", text="", emboss=False)


class SSM_OT_landmark_schema_add(bpy.types.Operator):
    """Add a landmark name to the schema after the active one"""

    bl_idname = "ssm.landmark_schema_add"
    bl_label = "Add Landmark Name"
    bl_options = {"REGISTER", "UNDO"}

    name: StringProperty(name="Name", description="New landmark name (empty: landmark-N)")

    def execute(self, context):
        settings = context.scene.ssm_landmarks
        existing = set(schema_names(context))
        name = self.name.strip()
        if not name:
            k = len(existing) + 1
            while f"landmark-{k}" in existing:
                k += 1
            name = f"landmark-{k}"
        if name in existing:
            self.report({"ERROR"}, f"landmark schema: {name!r} is already in the schema")
            return {"CANCELLED"}
        at = settings.active_index + 1 if len(settings.names) else 0
        settings.active_index = add_schema_name(settings, name, at)
        return {"FINISHED"}


class SSM_OT_landmark_schema_remove(bpy.types.Operator):
    """Remove the active landmark name from the schema (placed landmarks stay, as extra names)"""

    bl_idname = "ssm.landmark_schema_remove"
    bl_label = "Remove Landmark Name"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return len(context.scene.ssm_landmarks.names) > 0

    def execute(self, context):
        settings = context.scene.ssm_landmarks
        i = settings.active_index
        if not 0 <= i < len(settings.names):
            self.report({"ERROR"}, "landmark schema: no active name to remove")
            return {"CANCELLED"}
        settings.names.remove(i)
        settings.active_index = min(i, len(settings.names) - 1) if len(settings.names) else 0
        return {"FINISHED"}


class SSM_OT_landmark_schema_move(bpy.types.Operator):
    """Move the active landmark name up or down in the schema"""

    bl_idname = "ssm.landmark_schema_move"
    bl_label = "Move Landmark Name"
    bl_options = {"REGISTER", "UNDO"}

    direction: EnumProperty(items=[("UP", "Up", ""), ("DOWN", "Down", "")], default="UP")

    def execute(self, context):
        settings = context.scene.ssm_landmarks
        i = settings.active_index
        j = i - 1 if self.direction == "UP" else i + 1
        if not (0 <= i < len(settings.names) and 0 <= j < len(settings.names)):
            return {"CANCELLED"}
        settings.names.move(i, j)
        settings.active_index = j
        return {"FINISHED"}


class SSM_OT_landmark_schema_rename(bpy.types.Operator):
    """Rename a landmark of the schema and every placed landmark of that name"""

    bl_idname = "ssm.landmark_schema_rename"
    bl_label = "Rename Landmark"
    bl_options = {"REGISTER", "UNDO"}

    index: IntProperty(name="Index", default=-1, description="Schema position (-1: the active one)")
    new_name: StringProperty(name="New name")

    def execute(self, context):
        settings = context.scene.ssm_landmarks
        i = settings.active_index if self.index < 0 else self.index
        new = self.new_name.strip()
        if not 0 <= i < len(settings.names):
            self.report({"ERROR"}, f"landmark schema: no entry {i}")
            return {"CANCELLED"}
        if not new or (new in schema_names(context) and settings.names[i].name != new):
            self.report({"ERROR"}, f"landmark schema: cannot rename to {new!r} (empty or already in the schema)")
            return {"CANCELLED"}
        settings.names[i].landmark = new
        return {"FINISHED"}


class SSM_OT_landmark_schema_preset(bpy.types.Operator):
    """Replace the landmark schema by a preset"""

    bl_idname = "ssm.landmark_schema_preset"
    bl_label = "Landmark Preset"
    bl_options = {"REGISTER", "UNDO"}

    preset: EnumProperty(
        name="Preset",
        items=[(k, k, f"{len(v)} landmarks: {', '.join(v[:4])}, …") for k, v in core.LANDMARK_PRESETS.items()],
    )

    def execute(self, context):
        set_schema(context.scene.ssm_landmarks, core.LANDMARK_PRESETS[self.preset])
        return {"FINISHED"}


class SSM_OT_landmark_schema_from_instance(bpy.types.Operator):
    """Replace the landmark schema by the names of the active instance's landmarks"""

    bl_idname = "ssm.landmark_schema_from_instance"
    bl_label = "Schema from Instance"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return _poll_instance(cls, context)

    def execute(self, context):
        inst = active_instance(context)
        empties = landmark_empties(inst)
        if not empties:
            self.report({"ERROR"}, f"{inst.name}: no landmarks to take the schema from")
            return {"CANCELLED"}
        names = sorted(empties, key=lambda n: (empties[n].get(ORDER_PROP, 1 << 30), n))
        set_schema(context.scene.ssm_landmarks, names)
        return {"FINISHED"}


# -------------------------------------------------------------------------- placement


class SSM_OT_place_landmarks(bpy.types.Operator):
    """Click on the active instance to place the next missing landmark; click a landmark to re-place it. Esc or right-click ends"""

    bl_idname = "ssm.place_landmarks"
    bl_label = "Place Landmarks"
    bl_options = {"REGISTER", "UNDO"}

    landmark: StringProperty(name="Landmark", description="Landmark to place (empty: the next missing one)")
    ray_origin: FloatVectorProperty(name="Ray origin", size=3, description="Blender-world ray origin (mm), for scripts")
    ray_direction: FloatVectorProperty(name="Ray direction", size=3, description="Blender-world ray direction, for scripts")

    @classmethod
    def poll(cls, context):
        return _poll_instance(cls, context)

    # -- one placement (scripts, redo panel, and every click of the modal) --------
    def _place(self, context, instance, origin, direction, name):
        try:
            emp, name = place_landmark(context, instance, origin, direction, name)
        except SSMError as err:
            self.report({"ERROR"}, str(err))
            return None
        if emp is None:
            self.report({"WARNING"}, f"{instance.name}: the ray misses the surface; {name!r} not placed")
        return emp

    def execute(self, context):
        inst = active_instance(context)
        if Vector(self.ray_direction).length == 0.0:
            self.report({"ERROR"}, "place landmarks: give ray_origin and ray_direction (or invoke it in the 3D viewport)")
            return {"CANCELLED"}
        emp = self._place(context, inst, self.ray_origin, self.ray_direction, self.landmark.strip())
        if emp is None:
            return {"CANCELLED"}
        self.report({"INFO"}, f"placed {emp[LANDMARK_PROP]!r} on {inst.name}")
        return {"FINISHED"}

    # -- interactive -----------------------------------------------------------------
    def invoke(self, context, event):
        if Vector(self.ray_direction).length > 0.0:
            return self.execute(context)
        area = context.area
        if area is None or area.type != "VIEW_3D":
            self.report({"ERROR"}, "place landmarks: run it from a 3D viewport")
            return {"CANCELLED"}
        self._region = next((r for r in area.regions if r.type == "WINDOW"), None)
        self._rv3d = area.spaces.active.region_3d
        self._instance = active_instance(context)
        self._reselect = ""
        if not schema_names(context):
            self.report({"ERROR"}, "place landmarks: the landmark schema is empty (add names or pick a preset)")
            return {"CANCELLED"}
        self._update_header(context)
        context.window_manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def _next_name(self, context) -> str:
        if self._reselect:
            return self._reselect
        missing = missing_names(context, self._instance)
        return missing[0] if missing else ""

    def _update_header(self, context):
        inst = self._instance
        n_missing = len(missing_names(context, inst))
        nxt = self._next_name(context)
        if self._reselect:
            text = f"{inst.name}: click on the surface to re-place “{nxt}”"
        elif nxt:
            text = f"{inst.name}: click to place “{nxt}” ({n_missing} missing)"
        else:
            text = f"{inst.name}: all landmarks placed. Click a landmark to re-place it"
        text += " · Esc/right-click: done"
        context.area.header_text_set(text)
        context.workspace.status_text_set(text)

    def _end(self, context):
        context.area.header_text_set(None)
        context.workspace.status_text_set(None)

    def _mouse(self, event):
        r = self._region
        x, y = event.mouse_x - r.x, event.mouse_y - r.y
        return (x, y) if 0 <= x < r.width and 0 <= y < r.height else None

    def _landmark_under(self, coord):

        screen = {
            name: location_3d_to_region_2d(self._region, self._rv3d, emp.matrix_world.translation)
            for name, emp in landmark_empties(self._instance).items()
        }
        return pick_on_screen(screen, coord)

    def modal(self, context, event):

        if event.type in {"ESC", "RIGHTMOUSE"} and event.value == "PRESS":
            self._end(context)
            return {"FINISHED"}
        if event.type != "LEFTMOUSE" or event.value != "PRESS":
            return {"PASS_THROUGH"}  # navigation, sidebar, ...
        coord = self._mouse(event)
        if coord is None:
            return {"PASS_THROUGH"}
        picked = self._landmark_under(coord)
        if picked and picked != self._reselect:
            emp = landmark_empties(self._instance)[picked]
            bridge.select_only(context, [emp])
            self._reselect = picked
            self._update_header(context)
            return {"RUNNING_MODAL"}
        name = self._next_name(context)
        if not name:
            return {"RUNNING_MODAL"}
        origin = region_2d_to_origin_3d(self._region, self._rv3d, coord)
        direction = region_2d_to_vector_3d(self._region, self._rv3d, coord)
        emp = self._place(context, self._instance, origin, direction, name)
        if emp is not None:
            self._reselect = ""
            bpy.ops.ed.undo_push(message=f"Place landmark {name}")
        self._update_header(context)
        return {"RUNNING_MODAL"}


class SSM_OT_snap_landmarks(bpy.types.Operator):
    """Move the active instance's landmarks (selected ones, or all) to the nearest surface point"""

    bl_idname = "ssm.snap_landmarks"
    bl_label = "Snap Landmarks to Surface"
    bl_options = {"REGISTER", "UNDO"}

    selected_only: BoolProperty(name="Selected only", default=False)

    @classmethod
    def poll(cls, context):
        return _poll_instance(cls, context)

    def execute(self, context):
        inst = active_instance(context)
        empties = [e for e in landmark_empties(inst).values() if e.select_get() or not self.selected_only]
        if not empties:
            self.report({"WARNING"}, f"{inst.name}: no {'selected ' if self.selected_only else ''}landmarks to snap")
            return {"CANCELLED"}
        depsgraph = context.evaluated_depsgraph_get()
        inv = inst.matrix_world.inverted()
        for emp in empties:
            found, loc, _n, _i = inst.closest_point_on_mesh(inv @ emp.matrix_world.translation, depsgraph=depsgraph)
            if found:
                set_landmark(context, inst, str(emp[LANDMARK_PROP]), blender_world=np.array(inst.matrix_world @ loc))
        self.report({"INFO"}, f"{inst.name}: snapped {len(empties)} landmark(s)")
        return {"FINISHED"}


# ------------------------------------------------------------------------------ files


class SSM_OT_import_landmarks(bpy.types.Operator, ImportHelper):
    """Import landmarks for the active instance (.fcsv, .mrk.json, .csv, .json; world mm)"""

    bl_idname = "ssm.import_landmarks"
    bl_label = "Import Landmarks"
    bl_options = {"REGISTER", "UNDO"}

    filter_glob: StringProperty(default=FILE_GLOB, options={"HIDDEN"})
    add_to_schema: BoolProperty(name="Add unknown names to the schema", default=False)

    @classmethod
    def poll(cls, context):
        return _poll_instance(cls, context)

    def execute(self, context):
        inst = active_instance(context)
        settings = context.scene.ssm_landmarks
        try:
            lm = core.read_landmarks(self.filepath)
            if not len(settings.names):
                set_schema(settings, lm.names)
            lm = core.order_by_schema(lm, schema_names(context), allow_missing=True, allow_extra=self.add_to_schema)
        except SSMError as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        for n in lm.names:
            if n not in schema_names(context):
                add_schema_name(settings, n)
        for i, (name, p) in enumerate(zip(lm.names, lm.points_world)):
            set_landmark(context, inst, name, file_world=p, order=i)
        missing = missing_names(context, inst)
        msg = f"{inst.name}: imported {len(lm)} landmark(s)" + (f"; missing {', '.join(missing)}" if missing else "")
        self.report({"INFO"}, msg)
        return {"FINISHED"}


class SSM_OT_export_landmarks(bpy.types.Operator, ExportHelper):
    """Export the active instance's landmarks (format by extension: .fcsv, .mrk.json, .csv, .json; world mm)"""

    bl_idname = "ssm.export_landmarks"
    bl_label = "Export Landmarks"
    bl_options = {"REGISTER"}

    filename_ext = ".fcsv"
    check_extension = None
    filter_glob: StringProperty(default=FILE_GLOB, options={"HIDDEN"})
    coordinate_system: EnumProperty(
        name="Slicer coordinates",
        items=[("LPS", "LPS", "3D Slicer's default"), ("RAS", "RAS", "World RAS as in NIfTI")],
        default="LPS",
        description="Coordinate system written into .fcsv / .mrk.json (CSV and JSON are always world RAS)",
    )

    @classmethod
    def poll(cls, context):
        return _poll_instance(cls, context)

    def execute(self, context):
        inst = active_instance(context)
        try:
            lm = instance_landmarks(context, inst)
            if not len(lm):
                raise InputError(f"{inst.name}: no landmarks to export")
            fmt = core.landmark_format(self.filepath)
            system = self.coordinate_system if fmt in ("fcsv", "mrk.json") else None
            core.write_landmarks(self.filepath, lm, coordinate_system=system)
        except SSMError as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        self.report({"INFO"}, f"{inst.name}: wrote {len(lm)} landmark(s) to {self.filepath}")
        return {"FINISHED"}


# --------------------------------------------------------------------------- proposal


class SSM_OT_propose_landmarks(BackgroundJob, bpy.types.Operator):
    """Propose the active instance's missing landmarks: from the scene's model (fitted to it) when one exists, else from a landmarked instance (object frames aligned; then nearest surface point, or coating)"""

    bl_idname = "ssm.propose_landmarks"
    bl_label = "Propose Landmarks"
    bl_options = {"REGISTER", "UNDO"}

    source: StringProperty(name="From", description="Landmarked instance (empty: the panel's choice)")
    method: EnumProperty(
        name="Method",
        items=[
            ("auto", "Automatic", "The model when the scene has one with landmarks, else object frames"),
            ("model", "Model", "Fit the scene's model to the instance (its placed landmarks as soft constraints) "
             "and read the landmarks off the fit (paper 7; a second or so)"),
            ("frame", "Object frames", "Align by object frames, take the nearest surface point (instant)"),
            ("coating", "Coating", "Coat the source's surface onto the target (paper 4) and read the landmarks off it (tens of seconds)"),
        ],
        default="auto",
    )
    spacing_mm: FloatProperty(name="Spacing", description="Voxel size for coating (target volume), mm", default=1.0, min=0.1)

    @classmethod
    def poll(cls, context):
        return _poll_instance(cls, context)

    def _model(self, context):
        """The scene's model if it carries landmarks (``method`` auto or model), else None."""
        if self.method not in ("auto", "model"):
            return None

        obj = find_model_object(context)
        model = model_from_object(obj) if obj is not None else None
        if model is not None and len(model.landmark_locations):
            return model
        if self.method == "model":
            raise InputError("propose landmarks: no model with landmarks in the scene (build the model from a "
                             "landmarked template first, or propose from an instance)")
        return None

    def _prepare_model(self, context, target, model):
        frame = stored_frame(target)
        if frame is None:
            raise InputError(f"propose landmarks: {target.name} has no object frame (import it with SSM)")
        have = landmark_empties(target)
        known = instance_landmarks(context, target) if have else None
        names = [n for n in model.landmark_locations.names if n not in have]
        if not names:
            raise InputError(f"propose landmarks: {target.name} already has every landmark the model knows")
        mesh = (blender_to_file_world(target, bridge.object_world_vertices(target)), bridge.mesh_triangles(target.data))
        params = scene_params(context, "ssm_fit")
        self._target_name, self._source_name, self._loader = target.name, "the model", None

        def work(progress, cancelled):
            return proposal.propose_by_model(model, frame, mesh, known=known, names=names, params=params,
                                             source=target.name, progress=progress, cancelled=cancelled)

        return work

    def prepare(self, context):
        target = active_instance(context)
        model = self._model(context)
        if model is not None:
            return self._prepare_model(context, target, model)
        src = bpy.data.objects.get(self.source) if self.source else context.scene.ssm_landmarks.proposal_source
        if not is_instance(src) or src == target:
            raise InputError("propose landmarks: choose another, landmarked instance to propose from")
        lm = instance_landmarks(context, src)
        schema = schema_names(context)
        have = set(landmark_empties(target))
        names = [n for n in lm.names if n not in have and (n in schema or not schema)]
        if not names:
            raise InputError(f"propose landmarks: {src.name} has none of {target.name}'s missing landmarks")
        meshes = [(blender_to_file_world(obj, bridge.object_world_vertices(obj)), bridge.mesh_triangles(obj.data))
                  for obj in (src, target)]
        frames = stored_frame(src), stored_frame(target)
        if None in frames:
            raise InputError("propose landmarks: both instances need their object frame (import them with SSM)")
        self._target_name, self._source_name = target.name, src.name
        method, spacing, subset = ("frame" if self.method == "auto" else self.method), self.spacing_mm, lm.subset(names)
        loader, template = None, None
        if method == "coating":
            # the instances' own resampled masks (reloaded from source, cached) and, when
            # the scene's template was built from the source, that template
            try:
                loader = VolumeLoader(context, [src, target])
            except SSMError as err:  # no reachable source: the core voxelizes the meshes instead
                self.report({"INFO"}, f"{err}; using the meshes")
            tpl = find_template(context)
            if tpl is not None and tpl.ssm.instance == src:
                template = template_from_object(tpl)
        self._loader = loader

        def work(progress, cancelled):
            extra = {}
            if loader is not None:
                vols = loader.load(sub_progress(progress, 0.0, 0.2), cancelled)
                extra = {"source_volume": vols[src.name], "target_volume": vols[target.name]}
            return proposal.propose_from_meshes(
                subset, frames[0], meshes[0], frames[1], meshes[1], method=method, spacing_mm=spacing,
                source=target.name, progress=sub_progress(progress, 0.2, 1.0), cancelled=cancelled,
                template=template, **extra,
            )  # fmt: skip

        return work

    def finish(self, context, result):
        if self._loader is not None:
            self._loader.keep()
        target = bpy.data.objects.get(self._target_name)
        if target is None:
            self.report({"ERROR"}, f"propose landmarks: instance {self._target_name!r} is gone")
            return {"CANCELLED"}
        for name, p in zip(result.names, result.points_world):
            set_landmark(context, target, name, file_world=p)
        self.report({"INFO"}, f"{target.name}: proposed {len(result)} landmark(s) from {self._source_name}; "
                              "check and correct them")
        return {"FINISHED"}


# ------------------------------------------------------------------------------ panel


class SSM_PT_landmarks(SSMPanel, bpy.types.Panel):
    bl_label = "Landmarks"
    bl_idname = "SSM_PT_landmarks"
    bl_order = 10

    def draw(self, context):
        layout = self.layout
        settings = context.scene.ssm_landmarks
        n_schema = len(settings.names)

        layout.label(text=f"Schema ({n_schema} names)")
        row = layout.row()
        row.template_list("SSM_UL_landmark_schema", "", settings, "names", settings, "active_index", rows=5)
        col = row.column(align=True)
        col.operator("ssm.landmark_schema_add", icon="ADD", text="")
        col.operator("ssm.landmark_schema_remove", icon="REMOVE", text="")
        col.separator()
        col.operator("ssm.landmark_schema_move", icon="TRIA_UP", text="").direction = "UP"
        col.operator("ssm.landmark_schema_move", icon="TRIA_DOWN", text="").direction = "DOWN"
        row = layout.row(align=True)
        row.operator_menu_enum("ssm.landmark_schema_preset", "preset", text="Preset", icon="PRESET")
        row.operator("ssm.landmark_schema_from_instance", text="From Instance", icon="EMPTY_DATA")

        inst = active_instance(context)
        box = layout.box()
        if inst is None:
            box.label(text="Select an instance", icon="INFO")
        else:
            missing = missing_names(context, inst)
            box.label(text=f"{inst.name}: {n_schema - len(missing)}/{n_schema} placed", icon="OBJECT_DATA")
            if missing:
                col = box.column(align=True)
                col.scale_y = 0.8
                for name in missing[:8]:
                    col.label(text=f"  missing: {name}")
                if len(missing) > 8:
                    col.label(text=f"  … and {len(missing) - 8} more")
            box.operator("ssm.place_landmarks", icon="RESTRICT_SELECT_OFF")
            row = box.row(align=True)
            row.operator("ssm.snap_landmarks", text="Snap All", icon="SNAP_ON").selected_only = False
            row.operator("ssm.snap_landmarks", text="Snap Selected").selected_only = True
            row = box.row(align=True)
            row.operator("ssm.import_landmarks", text="Import", icon="IMPORT")
            row.operator("ssm.export_landmarks", text="Export", icon="EXPORT")
            row = box.row(align=True)
            row.prop(settings, "proposal_source", text="From")
            row.operator("ssm.propose_landmarks", text="Propose", icon="SHADERFX")
        layout.prop(settings, "marker_size_mm")

        all_instances = scene_instances(context)
        if all_instances:
            col = layout.column(align=True)
            col.label(text="Instances")
            schema = set(schema_names(context))
            for obj in all_instances:
                have = set(landmark_empties(obj))
                placed = len(have & schema)
                icon = "CHECKMARK" if placed == n_schema and n_schema else "ERROR"
                col.label(text=f"{obj.name}: {placed} placed, {n_schema - placed} missing", icon=icon)


classes = (
    SSMLandmarkName,
    SSMLandmarkSettings,
    SSM_UL_landmark_schema,
    SSM_OT_landmark_schema_add,
    SSM_OT_landmark_schema_remove,
    SSM_OT_landmark_schema_move,
    SSM_OT_landmark_schema_rename,
    SSM_OT_landmark_schema_preset,
    SSM_OT_landmark_schema_from_instance,
    SSM_OT_place_landmarks,
    SSM_OT_snap_landmarks,
    SSM_OT_import_landmarks,
    SSM_OT_export_landmarks,
    SSM_OT_propose_landmarks,
    SSM_PT_landmarks,
)


def register_properties():
    bpy.types.Scene.ssm_landmarks = PointerProperty(type=SSMLandmarkSettings)


def unregister_properties():
    del bpy.types.Scene.ssm_landmarks
