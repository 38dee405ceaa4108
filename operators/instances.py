"""Instances in Blender: importing label maps and meshes, and turning meshes into instances.

An instance is a mesh object in the "SSM Instances" collection with ``obj.ssm.role ==
"INSTANCE"``. For an imported label map or mesh file its mesh is the display surface
(marching cubes, paper section 2) in *object* mm and ``obj.matrix_world`` is the object
frame's matrix, so it sits at its world position (1 Blender unit = 1 mm). Its metadata:
``source`` (relative to the .blend where possible), ``label``, ``spacing_mm``,
``frame_method``, ``frame_origin``/``frame_axes`` (the object frame in the file's world
mm), ``import_matrix`` (``matrix_world`` at import, row-major) and ``volume_mm3``.

Keeping the volume data: *reload from source*. Nothing but the metadata is stored in
the .blend; :func:`instance_object_volume` re-reads the source file (or, for an
instance made from a Blender mesh, re-voxelizes the object's current mesh) and resamples
it in the stored frame, caching the result in memory keyed by (object name, source,
label, spacing, file mtime or mesh digest). A saved and re-opened .blend therefore
continues the pipeline as long as the source files are where ``source`` points.

Coordinates: the file's world mm and Blender world agree at import; if the user moves
an instance afterwards, :func:`blender_to_file_world` / :func:`file_to_blender_world`
convert (file world = import_matrix @ inverse(matrix_world) @ Blender world).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, CollectionProperty, EnumProperty, FloatProperty, IntProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from ..ssm_addon import frame as FR
from ..ssm_addon import imageio as IO
from ..ssm_addon import resample as RS
from ..ssm_addon import volume as core
from ..ssm_addon import voxelize as VX
from ..ssm_addon.errors import InputError, check_cancelled
from ..ssm_addon.progress import report, sub_progress
from . import bridge
from .jobs import BackgroundJob
from .properties import FRAME_METHODS

VOXELS_PROP = "ssm_voxels"
"""Custom property of an instance: object voxel count in its input grid."""

FILE_GLOB = ";".join(f"*{ext}" for ext in IO.SUPPORTED_EXTENSIONS)

_CACHE: dict[tuple, core.ObjectVolume] = {}


# ------------------------------------------------------------------------------ helpers


def is_instance(obj) -> bool:
    """True for an SSM instance (a mesh object with role INSTANCE)."""
    return obj is not None and obj.type == "MESH" and obj.ssm.role == "INSTANCE"


def scene_instances(context) -> list:
    """The scene's instance objects, by name."""
    return sorted((o for o in context.scene.objects if is_instance(o)), key=lambda o: o.name)


def _import_matrix(obj) -> np.ndarray:
    return np.array(obj.ssm.import_matrix, dtype=float).reshape(4, 4)


def _apply(matrix: np.ndarray, points) -> np.ndarray:
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    return pts @ matrix[:3, :3].T + matrix[:3, 3]


def blender_to_file_world(obj, points_blender_world) -> np.ndarray:
    """(M, 3) Blender world mm -> the instance's file world mm.

    file world = import_matrix @ inverse(matrix_world) @ p, so moving an instance in the
    viewport after import does not change landmark coordinates in the file's frame.
    """
    m = _import_matrix(obj) @ np.linalg.inv(bridge.matrix_to_numpy(obj.matrix_world))
    return _apply(m, points_blender_world)


def file_to_blender_world(obj, points_file_world) -> np.ndarray:
    """(M, 3) file world mm -> Blender world mm (inverse of :func:`blender_to_file_world`)."""
    m = bridge.matrix_to_numpy(obj.matrix_world) @ np.linalg.inv(_import_matrix(obj))
    return _apply(m, points_file_world)


def stored_frame(obj) -> core.ObjectFrame | None:
    """The object frame stored on an instance (file world mm), or None if unset."""
    axes = np.array(obj.ssm.frame_axes, dtype=float).reshape(3, 3)
    if abs(np.linalg.det(axes) - 1.0) > 1e-4:
        return None
    return core.ObjectFrame(
        origin_world=np.array(obj.ssm.frame_origin, dtype=float),
        axes_world=axes,
        method=obj.ssm.frame_method.lower(),
    )


def absolute_source_path(obj) -> str:
    return os.path.normpath(bpy.path.abspath(obj.ssm.source))


def _rel_source(path: str) -> str:
    """``//``-relative path when the .blend is saved (and on the same drive), else absolute."""
    path = os.path.abspath(path)
    if not bpy.data.filepath:
        return path
    try:
        return bpy.path.relpath(path)
    except ValueError:
        return path


def clear_instance_cache() -> None:
    """Forget every cached object volume (they are reloaded from source on demand)."""
    _CACHE.clear()


def mesh_file_world(obj) -> tuple[np.ndarray, np.ndarray]:
    """A Blender-mesh instance's current mesh in its file world mm, and its triangles."""
    verts = blender_to_file_world(obj, bridge.object_world_vertices(obj))
    return verts, bridge.mesh_triangles(obj.data)


def instance_object_volume(obj, progress=None, cancelled=None) -> core.ObjectVolume:
    """The resampled object volume of an instance (paper section 2), reloaded from source.

    Label-map and mesh-file instances re-read ``obj.ssm.source`` (resolved with
    ``bpy.path.abspath``); Blender-mesh instances re-voxelize the object's current mesh in
    its file world (import-matrix compensated). Resampled at ``obj.ssm.spacing_mm`` in
    the frame stored on the object (so landmarks placed in that frame stay valid).
    Cached in memory; works after saving and re-opening the .blend.

    Raises
    ------
    InputError
        Not an instance, source file missing, or any reader error.
    """
    if not is_instance(obj):
        raise InputError(f"{obj.name!r} is not an SSM instance (import it or use 'Add selected meshes as instances')")
    ssm = obj.ssm
    spacing = float(ssm.spacing_mm)
    label = None if ssm.label < 0 else int(ssm.label)
    method = ssm.frame_method.lower()
    if ssm.source_kind == "BLENDER_MESH":
        verts, faces = mesh_file_world(obj)
        digest = hashlib.sha1(verts.astype(np.float32).tobytes() + faces.astype(np.int32).tobytes()).hexdigest()
        key = (obj.name, "BLENDER_MESH", label, spacing, digest)
        if key in _CACHE:
            return _CACHE[key]
        report(progress, 0.0, f"voxelizing {obj.name}")
        vol = VX.voxelize_mesh(
            verts, faces, spacing, source=obj.name, patient_oriented=method == "patient", cancelled=cancelled
        )
    else:
        path = absolute_source_path(obj)
        if not os.path.isfile(path):
            raise InputError(f"instance {obj.name!r}: source file {path} not found (moved? set its Source path)")
        key = (obj.name, path, label, spacing, os.path.getmtime(path))
        if key in _CACHE:
            return _CACHE[key]
        report(progress, 0.0, f"reading {Path(path).name}")
        if ssm.source_kind == "MESH_FILE":
            vol = VX.load_mesh_volume(path, spacing, patient_oriented=method == "patient", cancelled=cancelled)
        else:
            vol = IO.load_volume(path, label)
    check_cancelled(cancelled)
    frame = _frame_for(obj, vol, method)
    ov = RS.resample(vol, frame, spacing, progress=sub_progress(progress, 0.3, 1.0), cancelled=cancelled)
    _CACHE[key] = ov
    return ov


def _frame_for(obj, vol: core.Volume, method: str) -> core.ObjectFrame:
    """The frame recomputed in double precision if it matches the stored (float32) one.

    The stored frame wins when they differ (e.g. the source changed since import), so
    landmarks placed in the instance's object frame stay valid.
    """
    computed = FR.object_frame(vol, method)
    stored = stored_frame(obj)
    if stored is None:
        return computed
    same = np.allclose(stored.origin_world, computed.origin_world, atol=1e-3) and np.allclose(
        stored.axes_world, computed.axes_world, atol=1e-5
    )
    return computed if same else stored


def _instance_name(path: str, label: int | None, n_labels: int) -> str:
    stem = IO.file_stem(path)
    return stem if label is None else f"{stem} L{label}"


def write_instance_metadata(obj, *, kind, source, label, spacing, method, frame, import_matrix, volume_mm3, voxels):
    ssm = obj.ssm
    ssm.role = "INSTANCE"
    ssm.source_kind = kind
    ssm.source = source
    ssm.label = -1 if label is None else int(label)
    ssm.spacing_mm = float(spacing)
    ssm.frame_method = method
    ssm.frame_origin = [float(x) for x in frame.origin_world]
    ssm.frame_axes = [float(x) for x in np.asarray(frame.axes_world).ravel()]
    ssm.import_matrix = [float(x) for x in np.asarray(import_matrix).ravel()]
    ssm.volume_mm3 = float(volume_mm3)
    obj[VOXELS_PROP] = int(voxels)


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
    spacing_mm: FloatProperty(
        name="Spacing (mm)", default=1.0, min=0.05, soft_max=5.0, description="Isotropic resampling / voxelizing step"
    )
    frame_method: EnumProperty(name="Frame", items=FRAME_METHODS, default="AUTO")

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
                if IO.file_extension(n) in IO.SUPPORTED_EXTENSIONS
            )
            if found:
                return found
        raise InputError("no segmentation file selected")

    def prepare(self, context):
        paths = [os.path.abspath(bpy.path.abspath(p)) for p in self._paths()]
        label = None if self.label < 0 else int(self.label)
        split, spacing, method = bool(self.split_labels), float(self.spacing_mm), self.frame_method

        def work(progress, cancelled):
            items = []
            for n, path in enumerate(paths):
                prog = sub_progress(progress, n / len(paths), (n + 1) / len(paths), f"{Path(path).name}: ")
                report(prog, 0.0, "reading")
                if IO.is_mesh_file(path):
                    vols = [VX.load_mesh_volume(path, spacing, patient_oriented=method == "PATIENT")]
                    kind = "MESH_FILE"
                else:
                    lm = IO.read_label_map(path)
                    labels = sorted(IO.label_counts(lm)) if split else [label]
                    if not labels:
                        raise InputError(f"{path}: empty mask: the label map has no non-zero voxels")
                    vols = [IO.select_label(lm, lab) for lab in labels]
                    kind = "VOLUME"
                for k, vol in enumerate(vols):
                    check_cancelled(cancelled)
                    report(prog, (k + 0.2) / len(vols), f"label {vol.label}: object frame")
                    frame = FR.object_frame(vol, method.lower())
                    ov = RS.resample(vol, frame, spacing, cancelled=cancelled)
                    report(prog, (k + 0.7) / len(vols), f"label {vol.label}: surface")
                    verts_world, faces = core.display_surface(vol)
                    items.append(
                        {
                            "path": path,
                            "kind": kind,
                            "label": vol.label,
                            "name": _instance_name(path, vol.label, len(vols)),
                            "frame": frame,
                            "object_volume": ov,
                            "vertices_object": frame.to_object(verts_world),
                            "faces": faces,
                            "volume_mm3": vol.volume_mm3,
                            "voxels": int(np.count_nonzero(vol.mask)),
                        }
                    )
            report(progress, 1.0, "done")
            return items

        return work

    def finish(self, context, items):
        bridge.ensure_mm_units(context.scene)
        coll = bridge.ensure_collection(context.scene, bridge.INSTANCES_COLLECTION)
        created = []
        for item in items:
            source = _rel_source(item["path"])
            existing = bpy.data.objects.get(item["name"])
            replace = (
                existing is not None
                and is_instance(existing)
                and absolute_source_path(existing) == os.path.normpath(item["path"])
                and existing.ssm.label == (-1 if item["label"] is None else item["label"])
            )
            matrix = item["frame"].matrix_world
            obj = bridge.new_mesh_object(
                context,
                item["name"],
                item["vertices_object"],
                item["faces"],
                collection_name=coll.name,
                matrix_world=matrix,
                replace=replace,
            )
            write_instance_metadata(
                obj,
                kind=item["kind"],
                source=source,
                label=item["label"],
                spacing=self.spacing_mm,
                method=item["frame"].method.upper(),
                frame=item["frame"],
                import_matrix=matrix,
                volume_mm3=item["volume_mm3"],
                voxels=item["voxels"],
            )
            ov = item["object_volume"]
            label = None if obj.ssm.label < 0 else obj.ssm.label
            key = (obj.name, item["path"], label, float(obj.ssm.spacing_mm), os.path.getmtime(item["path"]))
            _CACHE[key] = ov
            created.append(obj)
        for obj in context.view_layer.objects:
            obj.select_set(obj in created)
        if created:
            context.view_layer.objects.active = created[-1]
        self.report({"INFO"}, f"Imported {len(created)} instance(s): {', '.join(o.name for o in created)}")
        return {"FINISHED"}

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "split_labels")
        row = layout.row()
        row.enabled = not self.split_labels
        row.prop(self, "label")
        layout.prop(self, "spacing_mm")
        layout.prop(self, "frame_method")


class SSM_OT_add_mesh_instances(BackgroundJob, bpy.types.Operator):
    """Turn the selected closed mesh objects into SSM instances (voxelized at the chosen spacing)"""

    bl_idname = "ssm.add_mesh_instances"
    bl_label = "Add Selected Meshes as Instances"
    bl_options = {"REGISTER", "UNDO"}

    spacing_mm: FloatProperty(name="Spacing (mm)", default=1.0, min=0.05, soft_max=5.0)
    frame_method: EnumProperty(
        name="Frame",
        items=FRAME_METHODS,
        default="MOMENTS",
        description="Moments unless the meshes are in patient coordinates (e.g. exported from 3D Slicer)",
    )

    @classmethod
    def poll(cls, context):
        return any(o.type == "MESH" for o in context.selected_objects)

    def prepare(self, context):
        objs = [o for o in context.selected_objects if o.type == "MESH"]
        if not objs:
            raise InputError("select one or more closed mesh objects")
        data = [(o.name, bridge.object_world_vertices(o), bridge.mesh_triangles(o.data)) for o in objs]
        spacing, method = float(self.spacing_mm), self.frame_method.lower()
        patient = method == "patient"

        def work(progress, cancelled):
            out = []
            for n, (name, verts, faces) in enumerate(data):
                report(progress, n / len(data), f"voxelizing {name}")
                vol = VX.voxelize_mesh(
                    verts, faces, spacing, source=name, patient_oriented=patient, cancelled=cancelled
                )
                frame = FR.object_frame(vol, method)
                ov = RS.resample(vol, frame, spacing, cancelled=cancelled)
                out.append((name, vol, frame, ov, verts, faces))
            report(progress, 1.0, "done")
            return out

        return work

    def finish(self, context, items):
        bridge.ensure_mm_units(context.scene)
        coll = bridge.ensure_collection(context.scene, bridge.INSTANCES_COLLECTION)
        for name, vol, frame, ov, verts, faces in items:
            obj = bpy.data.objects[name]
            if coll.objects.get(obj.name) is None:
                coll.objects.link(obj)
            write_instance_metadata(
                obj,
                kind="BLENDER_MESH",
                source="",
                label=None,
                spacing=self.spacing_mm,
                method=frame.method.upper(),
                frame=frame,
                import_matrix=bridge.matrix_to_numpy(obj.matrix_world),
                volume_mm3=vol.volume_mm3,
                voxels=int(np.count_nonzero(vol.mask)),
            )
            digest = hashlib.sha1(verts.astype(np.float32).tobytes() + faces.astype(np.int32).tobytes()).hexdigest()
            _CACHE[(obj.name, "BLENDER_MESH", None, float(obj.ssm.spacing_mm), digest)] = ov
        self.report({"INFO"}, f"Added {len(items)} instance(s)")
        return {"FINISHED"}


# ------------------------------------------------------------------------------- panel


class SSM_PT_instances(bpy.types.Panel):
    """Sidebar: the training instances and how to add them."""

    bl_idname = "SSM_PT_instances"
    bl_label = "Instances"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "SSM"
    bl_order = 0

    def draw(self, context):
        layout = self.layout
        row = layout.row(align=True)
        row.operator(SSM_OT_import_segmentation.bl_idname, text="Import", icon="IMPORT")
        row.operator(SSM_OT_add_mesh_instances.bl_idname, text="Add Selected", icon="ADD")
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
            row.label(text=f"L {label} | {voxels} vox | {obj.ssm.volume_mm3 / 1000.0:.1f} cm³")
        layout.label(text=f"{len(insts)} instance(s)")


def menu_func_import(self, context):
    self.layout.operator(SSM_OT_import_segmentation.bl_idname, text="Segmentation (SSM)")


classes = (SSM_OT_import_segmentation, SSM_OT_add_mesh_instances, SSM_PT_instances)


def register_properties():
    bpy.types.TOPBAR_MT_file_import.append(menu_func_import)


def unregister_properties():
    bpy.types.TOPBAR_MT_file_import.remove(menu_func_import)
    clear_instance_cache()
