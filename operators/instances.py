"""Instances in Blender: importing label maps and meshes, and turning meshes into instances.

An instance is a mesh object in the "SSM Instances" collection with ``obj.ssm.role ==
"INSTANCE"`` (see ``operators/scene.py`` for what is stored where). For an imported
label map or mesh file its mesh is the display surface (marching cubes of the input
grid) in *object* mm and ``obj.matrix_world`` is the object frame, so it sits at its
world position (1 Blender unit = 1 mm). Every instance of a study is resampled at the
study's spacing with the study's frame method (``Scene.ssm_template``), as a project
file's ``[template] spacing`` and ``frame``.
"""

from __future__ import annotations

import os
from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, CollectionProperty, FloatProperty, IntProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from ssm_addon.base import params as P
from ssm_addon.base.errors import InputError, check_cancelled
from ssm_addon.base.progress import report, sub_progress
from ssm_addon.formats import label_maps as imageio
from ssm_addon.instances import importing as core
from ssm_addon.instances.importing import InstanceSpec
from ssm_addon.instances.volume import display_surface
from ssm_addon.instances.voxelize import voxelize_mesh

from . import bridge
from .jobs import BackgroundJob
from .properties import SSMPanel, scene_params
from .scene import (
    VolumeLoader,
    absolute_source_path,
    cache_volume,
    clear_volume_cache,
    is_instance,
    next_order,
    relative_source,
    scene_instances,
    set_side,
    write_frame,
)

VOXELS_PROP = "ssm_voxels"
"""Custom property of an instance: object voxel count in its input grid."""

FILE_GLOB = ";".join(f"*{ext}" for ext in imageio.SUPPORTED_EXTENSIONS)
DEFAULT_NAME_PATTERN = "{stem} label {label}"


def instance_name(pattern: str, path, label: int | None) -> str:
    """An instance's name from a pattern with ``{stem}`` (file name without extension) and ``{label}``.

    Without a label (a mesh, or all labels) the ``{label}`` part and the text between it
    and ``{stem}`` are dropped: "{stem} label {label}" gives "ball" for ball.stl.
    """
    stem = imageio.file_stem(path)
    if label is None:
        pattern = pattern.replace("label {label}", "").replace("{label}", "")
    try:
        name = pattern.format(stem=stem, label="" if label is None else label)
    except (KeyError, IndexError, ValueError):
        raise InputError(f"import: name pattern {pattern!r} may use only {{stem}} and {{label}}") from None
    return " ".join(name.split()) or stem


def write_instance(context, obj, spec: InstanceSpec, *, kind: str, frame, volume_mm3: float, voxels: int) -> None:
    """The metadata of an instance object (its matrix_world is the import matrix)."""
    ssm = obj.ssm
    ssm.role = "INSTANCE"
    ssm.source_kind = kind
    ssm.source = relative_source(str(spec.source)) if spec.source is not None else ""
    ssm.label = -1 if spec.label is None else int(spec.label)
    ssm.mesh_spacing_mm = float(spec.mesh_spacing_mm or 0.0)
    ssm.volume_mm3 = float(volume_mm3)
    write_frame(obj, frame, bridge.matrix_to_numpy(obj.matrix_world))
    set_side(obj, mirror=spec.mirror, side=spec.side)
    obj[VOXELS_PROP] = int(voxels)


def import_items(specs, *, spacing_mm: float, frame_method: str, space: str = "auto", label_maps: dict | None = None,
                 progress=None, cancelled=None) -> list[dict]:
    """Read, frame and resample instances with the core (no bpy: runs in a worker thread).

    Returns per instance what :func:`add_instance_objects` needs: the spec, the object
    volume, the display surface (object mm) and the input-grid volume and voxel count.
    """
    items = []
    for k, spec in enumerate(specs):
        check_cancelled(cancelled)
        prog = sub_progress(progress, k / len(specs), (k + 1) / len(specs), f"{spec.name}: ")
        report(prog, 0.0, "reading")
        label_map = (label_maps or {}).get(spec.volume_path)
        vol = core.read_instance(spec, spacing_mm=spacing_mm, label_map=label_map, space=space, cancelled=cancelled)
        report(prog, 0.3, "object frame and resampling")
        if spec.mesh_path is not None:  # the core's mesh import: voxelized on its object grid
            ov = core.mesh_instance(spec, spacing_mm=spacing_mm, frame_method=frame_method, space=space,
                                    cancelled=cancelled)
        else:
            ov = core.object_from_volume(vol, spacing_mm=spacing_mm, frame_method=frame_method, cancelled=cancelled)
        report(prog, 0.7, "surface")
        verts_world, faces = display_surface(vol)
        items.append({"spec": spec, "kind": "MESH_FILE" if spec.mesh_path is not None else "VOLUME", "object_volume": ov,
                      "vertices_object": ov.frame.to_object(verts_world), "faces": faces,
                      "volume_mm3": vol.volume_mm3, "voxels": int(np.count_nonzero(vol.mask))})
    return items


def add_instance_objects(context, items: list[dict]) -> list:
    """Create (or refresh) the instance objects of :func:`import_items` results (main thread).

    An instance of the same source and label is refreshed and keeps its name and place
    in the study; a new one gets the spec's name (made unique) and the next place.
    """
    bridge.ensure_mm_units(context.scene)
    coll = bridge.ensure_collection(context.scene, bridge.INSTANCES_COLLECTION)
    created = []
    for item in items:
        spec, ov = item["spec"], item["object_volume"]
        existing = next((o for o in scene_instances(context) if absolute_source_path(o) == os.path.normpath(
            str(spec.source)) and o.ssm.label == (-1 if spec.label is None else spec.label)), None)
        if existing is not None:
            obj = bridge.new_mesh_object(context, existing.name, item["vertices_object"], item["faces"],
                                         matrix_world=ov.frame.matrix_world)
        else:
            name, k = spec.name, 2
            while bpy.data.objects.get(name) is not None:
                name, k = f"{spec.name} {k}", k + 1
            obj = bridge.new_mesh_object(context, name, item["vertices_object"], item["faces"],
                                         collection_name=coll.name, matrix_world=ov.frame.matrix_world, replace=False)
            obj.ssm.order = next_order(context)
        write_instance(context, obj, spec, kind=item["kind"], frame=ov.frame, volume_mm3=item["volume_mm3"],
                       voxels=item["voxels"])
        cache_volume(context, obj, ov)
        created.append(obj)
    return created


def instance_object_volume(context, obj, progress=None, cancelled=None):
    """The resampled object volume of an instance (paper 2), reloaded from its source and cached."""
    loader = VolumeLoader(context, [obj])
    ov = loader.load(progress, cancelled)[obj.name]
    loader.keep()
    return ov


# ---------------------------------------------------------------------------- operators
class SSM_OT_import_segmentation(BackgroundJob, bpy.types.Operator, ImportHelper):
    """Import label maps (NIfTI, NRRD, MetaImage, NumPy) or closed meshes (STL, PLY, OBJ) as SSM instances"""

    bl_idname = "ssm.import_segmentation"
    bl_label = "Import Segmentation (SSM)"
    bl_options = {"REGISTER", "UNDO"}

    filter_glob: StringProperty(default=FILE_GLOB, options={"HIDDEN"})
    files: CollectionProperty(type=bpy.types.OperatorFileListElement, options={"HIDDEN", "SKIP_SAVE"})
    directory: StringProperty(subtype="DIR_PATH", options={"HIDDEN", "SKIP_SAVE"})
    label: IntProperty(
        name="Label", default=-1, min=-1, description="Label to import from a label map (-1: all non-zero labels)"
    )
    split_labels: BoolProperty(
        name="Each label separately", default=False, description="Create one instance per label present in the map"
    )
    name_pattern: StringProperty(
        name="Name", default=DEFAULT_NAME_PATTERN,
        description="Instance name: {stem} is the file name without extension, {label} the label",
    )
    spacing_mm: FloatProperty(
        name="Spacing (mm)", default=0.0, min=0.0, soft_max=5.0, options={"SKIP_SAVE"},
        description="Sets the study's resampling spacing (every instance uses one; 0: keep the study's)",
    )

    def invoke(self, context, event):
        self._browser = True
        return ImportHelper.invoke(self, context, event)

    def execute(self, context):
        if getattr(self, "_browser", False) and context.window is not None and not bpy.app.background:
            self._browser = False
            return BackgroundJob.invoke(self, context, None)  # modal job with progress and Esc
        return BackgroundJob.execute(self, context)

    def _paths(self) -> list[str]:
        names = [f.name for f in self.files if f.name]
        if names and self.directory:
            return [os.path.join(self.directory, n) for n in names]
        if self.filepath and not os.path.isdir(self.filepath):
            return [self.filepath]
        if self.directory and os.path.isdir(self.directory) and not names:
            found = sorted(
                os.path.join(self.directory, n)
                for n in os.listdir(self.directory)
                if imageio.file_extension(n) in imageio.SUPPORTED_EXTENSIONS
            )
            if found:
                return found
        raise InputError("no segmentation file selected")

    def prepare(self, context):
        paths = [os.path.abspath(bpy.path.abspath(p)) for p in self._paths()]
        label = None if self.label < 0 else int(self.label)
        split, pattern = bool(self.split_labels), self.name_pattern
        tp = scene_params(context, "ssm_template")
        spacing = float(self.spacing_mm) if self.spacing_mm > 0 else tp.spacing_mm
        self._set_spacing = None
        if self.spacing_mm > 0:
            P.from_table(type(tp), {**P.to_table(tp), "spacing": P.shortest_float32(spacing)}, where="import:")
            self._set_spacing = spacing
        frame_method, space = tp.frame, tp.space

        def work(progress, cancelled):
            items = []
            for n, path in enumerate(paths):
                prog = sub_progress(progress, n / len(paths), (n + 1) / len(paths), f"{Path(path).name}: ")
                report(prog, 0.0, "reading")
                label_maps = {}
                if imageio.is_mesh_file(path):
                    specs = [InstanceSpec(name=instance_name(pattern, path, None), mesh_path=Path(path))]
                else:
                    label_maps[Path(path)] = label_map = imageio.read_label_map(path)
                    labels = sorted(imageio.label_counts(label_map)) if split else [label]
                    if not labels:
                        raise InputError(f"{path}: empty mask: the label map has no non-zero voxels")
                    specs = [InstanceSpec(name=instance_name(pattern, path, lab), volume_path=Path(path), label=lab)
                             for lab in labels]
                items += import_items(specs, spacing_mm=spacing, frame_method=frame_method, space=space, label_maps=label_maps,
                                      progress=sub_progress(prog, 0.2, 1.0), cancelled=cancelled)
            report(progress, 1.0, "done")
            return items

        return work

    def finish(self, context, items):
        if self._set_spacing is not None:
            context.scene.ssm_template.spacing_mm = self._set_spacing
        created = add_instance_objects(context, items)
        bridge.select_only(context, created, active=created[-1] if created else None)
        self.report({"INFO"}, f"Imported {len(created)} instance(s): {', '.join(o.name for o in created)}")
        return {"FINISHED"}

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "name_pattern")
        layout.prop(self, "split_labels")
        row = layout.row()
        row.enabled = not self.split_labels
        row.prop(self, "label")
        box = layout.box()
        box.label(text="Study (every instance)")
        box.prop(context.scene.ssm_template, "spacing_mm")
        box.prop(context.scene.ssm_template, "frame")


class SSM_OT_add_mesh_instances(BackgroundJob, bpy.types.Operator):
    """Turn the selected closed mesh objects into SSM instances (voxelized at the study's spacing)"""

    bl_idname = "ssm.add_mesh_instances"
    bl_label = "Add Selected Meshes as Instances"
    bl_options = {"REGISTER", "UNDO"}

    spacing_mm: FloatProperty(name="Mesh spacing (mm)", default=0.0, min=0.0, soft_max=5.0,
                              description="Voxel size of the meshes' input volumes shown and measured beside them "
                                          "(0: the study's spacing)")

    @classmethod
    def poll(cls, context):
        if not any(o.type == "MESH" and not is_instance(o) for o in context.selected_objects):
            cls.poll_message_set("Select one or more closed mesh objects that are not instances yet")
            return False
        return True

    def prepare(self, context):
        objs = [o for o in context.selected_objects if o.type == "MESH" and not is_instance(o)]
        if not objs:
            raise InputError("select one or more closed mesh objects")
        data = [(o.name, bridge.object_world_vertices(o), bridge.mesh_triangles(o.data)) for o in objs]
        tp = scene_params(context, "ssm_template")
        mesh_spacing = float(self.spacing_mm) or None
        method = tp.frame

        def work(progress, cancelled):
            out = []
            for n, (name, verts, faces) in enumerate(data):
                report(progress, n / len(data), f"voxelizing {name}")
                vol = voxelize_mesh(verts, faces, mesh_spacing or tp.spacing_mm, source=name, cancelled=cancelled)
                ov = core.object_from_mesh(verts, faces, spacing_mm=tp.spacing_mm, mesh_spacing_mm=mesh_spacing,
                                           frame_method=method, source=name, cancelled=cancelled)
                out.append((name, vol, ov))
            report(progress, 1.0, "done")
            return out

        return work

    def finish(self, context, items):
        bridge.ensure_mm_units(context.scene)
        coll = bridge.ensure_collection(context.scene, bridge.INSTANCES_COLLECTION)
        for name, vol, ov in items:
            obj = bpy.data.objects[name]
            if coll.objects.get(obj.name) is None:
                coll.objects.link(obj)
            if not is_instance(obj):
                obj.ssm.order = next_order(context)
            write_instance(context, obj, InstanceSpec(name=name, mesh_spacing_mm=float(self.spacing_mm) or None),
                           kind="BLENDER_MESH", frame=ov.frame, volume_mm3=vol.volume_mm3,
                           voxels=int(np.count_nonzero(vol.mask)))
            cache_volume(context, obj, ov)
        self.report({"INFO"}, f"Added {len(items)} instance(s)")
        return {"FINISHED"}


# ------------------------------------------------------------------------------- panel
class SSM_PT_instances(SSMPanel, bpy.types.Panel):
    """Sidebar: the training instances and how to add them."""

    bl_idname = "SSM_PT_instances"
    bl_label = "Instances"
    bl_order = 0

    def draw(self, context):
        layout = self.layout
        row = layout.row(align=True)
        row.operator(SSM_OT_import_segmentation.bl_idname, text="Import", icon="IMPORT")
        row.operator(SSM_OT_add_mesh_instances.bl_idname, text="Add Selected", icon="ADD")
        col = layout.column(align=True)
        col.prop(context.scene.ssm_template, "spacing_mm")
        col.prop(context.scene.ssm_template, "frame")
        insts = scene_instances(context)
        if not insts:
            layout.label(text="No instances yet", icon="INFO")
            return
        col = layout.column(align=True)
        for obj in insts:
            row = col.row(align=True)
            icon = "RESTRICT_SELECT_OFF" if obj.select_get() else "MESH_DATA"
            row.label(text=obj.name, icon=icon)
            label = "all" if obj.ssm.label < 0 else str(obj.ssm.label)
            voxels = obj.get(VOXELS_PROP, 0)
            row.label(text=f"label {label} | {voxels} vox | {obj.ssm.volume_mm3 / 1000.0:.1f} cm³")
        layout.label(text=f"{len(insts)} instance(s)")
        active = context.active_object
        if is_instance(active) and active.ssm.source_kind != "BLENDER_MESH":
            layout.prop(active.ssm, "source", text="Source")


def menu_func_import(self, context):
    self.layout.operator(SSM_OT_import_segmentation.bl_idname, text="Segmentation (SSM)")


classes = (SSM_OT_import_segmentation, SSM_OT_add_mesh_instances, SSM_PT_instances)


@bpy.app.handlers.persistent
def _relative_sources_on_save(filepath, *_args):
    """Make instance sources relative to the .blend when it is saved (also the first save)."""
    folder = os.path.dirname(bpy.path.abspath(filepath or bpy.data.filepath))
    if not folder:
        return
    for obj in bpy.data.objects:
        if obj.ssm.role == "INSTANCE" and obj.ssm.source and not obj.ssm.source.startswith("//"):
            try:
                obj.ssm.source = bpy.path.relpath(obj.ssm.source, start=folder)
            except ValueError:  # another drive on Windows: stays absolute
                pass


def register_properties():
    bpy.types.TOPBAR_MT_file_import.append(menu_func_import)
    bpy.app.handlers.save_pre.append(_relative_sources_on_save)


def unregister_properties():
    if _relative_sources_on_save in bpy.app.handlers.save_pre:
        bpy.app.handlers.save_pre.remove(_relative_sources_on_save)
    bpy.types.TOPBAR_MT_file_import.remove(menu_func_import)
    clear_volume_cache()
