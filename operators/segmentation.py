"""Segmenting images in Blender: a CT as three slice planes, *Segment with Model*, *Save Segmentation*.

*Import Image* shows a grey-value image as three textured planes (sagittal, coronal, axial) in
world mm, with sliders that move them and a window/level; *Segment with Model* runs the core's
:func:`~ssm_addon.segmentation.segment.segment_image` from the 3D cursor (click on a slice with
Shift + right-click) with progress and Esc, and shows the result as a mesh with its posterior
SD as colours; *Save Segmentation* writes the files ``ssm segment`` writes. The numbers are the
command's: same model, image, point and parameters give the same surface.
"""

from __future__ import annotations

import dataclasses
import json
import os

import bpy
import numpy as np
from bpy.props import FloatProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from ssm_addon.base.errors import InputError
from ssm_addon.base.params import SegmentParams
from ssm_addon.formats.registry import file_glob
from ssm_addon.segmentation.appearance import appearance_from_arrays
from ssm_addon.segmentation.files import SEGMENT_FILES, SegmentationRecord, parse_labels, write_segmentation
from ssm_addon.segmentation.image import PLANES, read_image, window_values, world_slice
from ssm_addon.segmentation.segment import segment_image, start_pose, volume_centroid

from . import bridge
from .jobs import BackgroundJob
from .properties import SSMPanel, draw_params, scene_params
from .scene import APPEARANCE_KEY, MODEL_FILE_PROP, find_model_object, model_from_object, model_structures

IMAGE_COLLECTION = "SSM Image"
SEGMENT_COLLECTION = "SSM Segmentations"
_IMAGES: dict = {}  # path -> GreyImage, read once per session


def scene_image(context):
    """The scene's image (read again after the .blend was reopened), or None."""
    path = context.scene.ssm_image.filepath
    if not path:
        return None
    if path not in _IMAGES:
        _IMAGES[path] = read_image(path)
    return _IMAGES[path]


def _plane_name(axis: int) -> str:
    return f"SSM {PLANES[axis]} slice"


def update_slices(context, axes=(0, 1, 2)) -> None:
    """Draw the image on the slice planes at the scene's positions and window."""
    settings = context.scene.ssm_image
    image = scene_image(context)
    if image is None:
        return
    positions = (settings.position_x, settings.position_y, settings.position_z)
    for axis in axes:
        values, corners = world_slice(image, axis, positions[axis])
        grey = window_values(values, level=settings.level, width=settings.width)
        h, w = grey.shape
        name = _plane_name(axis)
        pixels = np.ones((h, w, 4), np.float32)
        pixels[..., :3] = grey[..., None]
        img = bpy.data.images.get(name)
        if img is None or tuple(img.size) != (w, h):
            if img is not None:
                bpy.data.images.remove(img)
            img = bpy.data.images.new(name, w, h, float_buffer=False)
        img.pixels.foreach_set(pixels.ravel())
        img.update()
        obj = bridge.new_mesh_object(context, name, corners, np.array([[0, 1, 2], [0, 2, 3]]),
                                     collection_name=IMAGE_COLLECTION, matrix_world=np.eye(4))
        uv = obj.data.uv_layers.get("UVMap") or obj.data.uv_layers.new(name="UVMap")
        corner_uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
        loops = np.zeros(len(obj.data.loops), np.int64)
        obj.data.loops.foreach_get("vertex_index", loops)
        uv.data.foreach_set("uv", corner_uv[loops].ravel())
        mat = _slice_material(name, img)
        if not obj.data.materials:
            obj.data.materials.append(mat)
        obj.hide_select = False


def _slice_material(name: str, img):
    mat = bpy.data.materials.get(name)
    if mat is None:
        mat = bpy.data.materials.new(name)
        if bpy.app.version < (5, 0, 0):
            mat.use_nodes = True
        nodes = mat.node_tree.nodes
        tex = nodes.new("ShaderNodeTexImage")
        bsdf = next((n for n in nodes if n.type == "BSDF_PRINCIPLED"), None)
        if bsdf is not None:
            mat.node_tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    tex = next(n for n in mat.node_tree.nodes if n.type == "TEX_IMAGE")
    tex.image = img
    return mat


def _moved(self, context):
    if context.scene.ssm_image.filepath:
        try:
            update_slices(context)
        except InputError as err:  # the file went away meanwhile: say so in the console, keep the planes
            print(f"SSM: {err}")


class SSMImageSettings(bpy.types.PropertyGroup):
    filepath: StringProperty(name="Image", subtype="FILE_PATH", description="The grey-value image shown and segmented")
    position_x: FloatProperty(name="Sagittal (x)", unit="LENGTH", update=_moved,
                              description="World x (mm, towards R) of the sagittal slice")
    position_y: FloatProperty(name="Coronal (y)", unit="LENGTH", update=_moved,
                              description="World y (mm, towards A) of the coronal slice")
    position_z: FloatProperty(name="Axial (z)", unit="LENGTH", update=_moved,
                              description="World z (mm, towards S) of the axial slice")
    level: FloatProperty(name="Level", default=400.0, update=_moved, description="Centre of the display window")
    width: FloatProperty(name="Window", default=1800.0, min=1.0, update=_moved,
                         description="Span of the display window (grey values)")


class SSM_OT_import_image(bpy.types.Operator, ImportHelper):
    """Show a grey-value image (CT; NIfTI, NRRD, MetaImage) as three slice planes in world mm (RAS)"""

    bl_idname = "ssm.import_image"
    bl_label = "Import Image"
    bl_options = {"REGISTER", "UNDO"}

    filter_glob: StringProperty(default=file_glob("image"), options={"HIDDEN"})

    def execute(self, context):
        try:
            image = read_image(self.filepath)
        except InputError as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        _IMAGES[self.filepath] = image
        bridge.ensure_mm_units(context.scene)
        settings = context.scene.ssm_image
        lo, hi = image.extent_world()
        centre = (lo + hi) / 2
        settings.filepath = self.filepath  # the sliders' updates draw once the path is set
        settings.position_x, settings.position_y, settings.position_z = (float(c) for c in centre)
        update_slices(context)
        self.report({"INFO"}, f"{os.path.basename(self.filepath)}: {' × '.join(str(s) for s in image.shape)} voxels "
                              f"of {' × '.join(f'{s:.3g}' for s in image.spacing_mm)} mm as three slice planes")
        return {"FINISHED"}


#: A joint model's start for one structure: an empty named this + the structure (*Place Start*).
START_PREFIX = "SSM start "


def structure_starts(context, model) -> dict:
    """{structure: (3,) world mm} of the scene's start empties for ``model``'s structures (a joint model)."""
    out = {}
    for name in model.structure_names:
        empty = context.scene.objects.get(START_PREFIX + name)
        if empty is not None and empty.type == "EMPTY":
            out[name] = np.array(empty.matrix_world.translation, float)
    return out


class SSM_OT_place_start(bpy.types.Operator):
    """Mark the 3D cursor as the start of one structure of the joint model (an empty named by the
    structure; segmenting then starts each marked structure at its own point, as `--at NAME=X,Y,Z`)"""

    bl_idname = "ssm.place_start"
    bl_label = "Place Start"
    bl_options = {"REGISTER", "UNDO"}

    structure: StringProperty(name="Structure", description="The joint model's structure this start is for")

    def execute(self, context):
        model_obj = find_model_object(context)
        names = model_structures(model_obj) if model_obj is not None else []
        if self.structure not in names:
            self.report({"ERROR"}, f"place start: the model has no structure {self.structure!r} (structures: "
                                   f"{', '.join(names) or 'none: the 3D cursor is the start'})")
            return {"CANCELLED"}
        name = START_PREFIX + self.structure
        empty = bpy.data.objects.get(name)
        if empty is None:
            empty = bpy.data.objects.new(name, None)
            empty.empty_display_type = "SPHERE"
            empty.empty_display_size = 3.0
            bridge.ensure_collection(context.scene, SEGMENT_COLLECTION).objects.link(empty)
        empty.location = context.scene.cursor.location
        self.report({"INFO"}, f"start of {self.structure}: {', '.join(f'{v:.1f}' for v in empty.location)} mm")
        return {"FINISHED"}


class SSM_OT_segment_image(BackgroundJob, bpy.types.Operator):
    """Segment the scene's image with the model, starting from the 3D cursor (a point inside the structure,
    e.g. clicked on a slice with Shift + right-click)"""

    bl_idname = "ssm.segment_image"
    bl_label = "Segment with Model"
    bl_options = {"REGISTER", "UNDO"}

    evidence: StringProperty(name="Evidence", default="", options={"SKIP_SAVE"},
                             description="auto (the model's learned appearance when it has one), learned or "
                                         "gradient; empty: the sidebar's (Scene.ssm_segment)")

    @classmethod
    def poll(cls, context):
        if find_model_object(context) is None:
            cls.poll_message_set("Build or import a model first")
            return False
        if not context.scene.ssm_image.filepath:
            cls.poll_message_set("Import an image first")
            return False
        return True

    def prepare(self, context):
        model_obj = find_model_object(context)
        model = model_from_object(model_obj)
        image = scene_image(context)
        arrays = bridge.load_arrays(model_obj, APPEARANCE_KEY)
        appearance = appearance_from_arrays(arrays, model.n_points, model_obj.name) if arrays else None
        at = np.array(context.scene.cursor.location, float)
        params = scene_params(context, "ssm_segment")  # the sidebar's, as `ssm segment`'s options
        if self.evidence:
            params = dataclasses.replace(params, evidence=self.evidence)
        named = structure_starts(context, model)  # a joint model's starts per structure, if placed
        start = {"points": {n: p.tolist() for n, p in named.items()}} if named else {"at": at.tolist()}
        pose = start_pose(model, named=named) if named else None
        self._names = (model_obj.name, model_obj.get(MODEL_FILE_PROP, ""), image.path, start)

        def work(progress, cancelled):
            return segment_image(model, image, at=None if named else at, pose=pose, appearance=appearance,
                                 params=params, progress=progress, cancelled=cancelled)

        return work

    def finish(self, context, result):
        model_name, model_file, path, start = self._names
        # each segmentation its own object, named by image and model (a spine's vertebrae side by side)
        name = f"{os.path.basename(path).split('.')[0]} {model_name} segmented"
        obj = bridge.new_mesh_object(context, name, result.points, result.faces, collection_name=SEGMENT_COLLECTION,
                                     matrix_world=np.eye(4), replace=False)
        name = obj.name
        bridge.set_vertex_colors(obj.data, bridge.sd_colours(result.posterior_sd_mm), name="posterior_sd")
        bridge.set_point_attribute(obj.data, "posterior_sd_mm", result.posterior_sd_mm)
        bridge.set_point_attribute(obj.data, "deviation_mm", result.deviation_mm)
        mat = bridge.color_material("SSM Posterior SD", attribute="posterior_sd")
        if not obj.data.materials:
            obj.data.materials.append(mat)
        obj.ssm.role = "SAMPLE"
        bridge.sd_legend(context, result.points, SEGMENT_COLLECTION)
        obj["ssm_segment_json"] = json.dumps({**result.to_dict(), "image": path, "model": model_file or model_name,
                                              "model_object": model_name, "start_given": start})
        obj["ssm_segment_image"] = path
        # the slices move to the result: through its solid centroid (world mm), each plane drawn once
        settings = context.scene.ssm_image
        centre = volume_centroid(result.points, result.faces)
        for axis, key in enumerate(("position_x", "position_y", "position_z")):
            settings[key] = float(centre[axis])
        update_slices(context)
        findings = "".join(f"; {k}: {m}" for k, m in result.findings)
        self.report({"WARNING" if result.findings else "INFO"},
                    f"{name}: {result.evidence} evidence, {result.iterations} steps, Mahalanobis "
                    f"{result.mahalanobis:.2f}, posterior SD up to {result.posterior_sd_mm.max():.2f} mm{findings}")
        return {"FINISHED"}


def _segmentation_object(context):
    obj = context.active_object
    if obj is not None and "ssm_segment_json" in obj:
        return obj
    return next((o for o in context.scene.objects if "ssm_segment_json" in o), None)


class SSM_OT_save_segmentation(bpy.types.Operator):
    """Write the segmentation's files as `ssm segment` does: segmentation.nii.gz on the image's grid,
    segmented.ply, segment.json and segment.png"""

    bl_idname = "ssm.save_segmentation"
    bl_label = "Save Segmentation"
    bl_options = {"REGISTER"}

    directory: StringProperty(name="Folder", subtype="DIR_PATH")
    labels: StringProperty(name="Labels", default="",
                           description="a joint model's label numbers, STRUCTURE=N separated by commas (as ssm "
                                       "segment --labels); empty: VerSe's for vertebrae, else 1, 2, … in the "
                                       "model's order")

    @classmethod
    def poll(cls, context):
        if _segmentation_object(context) is None:
            cls.poll_message_set("Segment an image first")
            return False
        return True

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        obj = _segmentation_object(context)
        try:
            if not self.directory:
                raise InputError("save segmentation: choose a folder")
            image = _IMAGES.get(obj["ssm_segment_image"]) or read_image(obj["ssm_segment_image"])
            mesh = obj.data
            record = SegmentationRecord(points=bridge.object_world_vertices(obj), faces=bridge.mesh_triangles(mesh),
                                        posterior_sd_mm=bridge.get_point_attribute(mesh, "posterior_sd_mm"),
                                        deviation_mm=bridge.get_point_attribute(mesh, "deviation_mm"),
                                        record=json.loads(obj["ssm_segment_json"]))
            write_segmentation(record, image, self.directory, model_source=record.record.get("model", ""),
                               labels=parse_labels([self.labels]))
        except InputError as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        self.report({"INFO"}, f"written: {', '.join(SEGMENT_FILES)} in {self.directory}")
        return {"FINISHED"}


class SSM_PT_segment(SSMPanel, bpy.types.Panel):
    bl_label = "Segment"
    bl_idname = "SSM_PT_segment"
    bl_order = 47
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        settings = context.scene.ssm_image
        layout.operator(SSM_OT_import_image.bl_idname, icon="IMAGE_DATA")
        if settings.filepath:
            layout.label(text=os.path.basename(settings.filepath), icon="FILE_IMAGE")
            col = layout.column(align=True)
            for key in ("position_x", "position_y", "position_z"):
                col.prop(settings, key)
            row = layout.row(align=True)
            row.prop(settings, "level")
            row.prop(settings, "width")
            layout.label(text="Start: the 3D cursor (Shift + right-click on a slice)", icon="PIVOT_CURSOR")
            model_obj = find_model_object(context)
            names = model_structures(model_obj) if model_obj is not None else []
            if names:  # a joint model: a start per structure, each at the cursor when placed
                row = layout.row(align=True)
                for name in names:
                    placed = context.scene.objects.get(START_PREFIX + name) is not None
                    row.operator(SSM_OT_place_start.bl_idname, text=name,
                                 icon="CHECKMARK" if placed else "EMPTY_AXIS").structure = name
        draw_params(layout, context.scene.ssm_segment, SegmentParams)
        layout.operator(SSM_OT_segment_image.bl_idname, icon="MOD_SHRINKWRAP")
        obj = _segmentation_object(context)
        if obj is not None:
            d = json.loads(obj["ssm_segment_json"])
            layout.label(text=f"{obj.name}: {d['evidence']} evidence, SD up to {d['posterior_sd_mm']['max']:.2f} mm")
            for f in d["verdict"]["findings"]:
                layout.label(text=f"{f['kind']}: {f['message'][:60]}", icon="ERROR")
            layout.operator(SSM_OT_save_segmentation.bl_idname, icon="EXPORT")


classes = (SSMImageSettings, SSM_OT_import_image, SSM_OT_place_start, SSM_OT_segment_image, SSM_OT_save_segmentation,
           SSM_PT_segment)


def register_properties():
    bpy.types.Scene.ssm_image = bpy.props.PointerProperty(type=SSMImageSettings)


def unregister_properties():
    del bpy.types.Scene.ssm_image
