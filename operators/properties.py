"""Properties shared by every stage: what an object is to SSM Builder, and its metadata.

Stage-specific settings (template parameters, coating parameters, the landmark schema,
the model's numbers) live in the module of their stage as ``Scene.ssm_<stage>``.
"""

from __future__ import annotations

import bpy
from bpy.props import EnumProperty, FloatProperty, FloatVectorProperty, IntProperty, PointerProperty, StringProperty

ROLES = [
    ("NONE", "None", "Not part of an SSM build"),
    ("INSTANCE", "Instance", "A segmented object of the training set"),
    ("LANDMARK", "Landmark", "A landmark empty parented to an instance"),
    ("TEMPLATE", "Template", "The triangulated point-distribution template (paper 3)"),
    ("COATED", "Coated instance", "The template coated onto an instance (paper 4)"),
    ("MODEL", "Model", "The mean shape with one shape key per mode (paper 5)"),
    ("SAMPLE", "Model sample", "A shape generated from the model (eq. 7)"),
]

SOURCE_KINDS = [
    ("VOLUME", "Label map", "Imported from a label map file"),
    ("MESH_FILE", "Mesh file", "Voxelized from a closed surface mesh file"),
    ("BLENDER_MESH", "Blender mesh", "Voxelized from this object's own mesh data"),
]

FRAME_METHODS = [
    ("AUTO", "Auto", "Patient axes where the input has an orientation, else moments"),
    ("PATIENT", "Patient axes", "Pair each principal axis with the nearest patient axis (R, A, S)"),
    ("MOMENTS", "Moments", "Eigenvalue order and third-moment signs"),
]


class SSMObjectProperties(bpy.types.PropertyGroup):
    """Per-object SSM metadata (``obj.ssm``)."""

    role: EnumProperty(name="Role", items=ROLES, default="NONE")
    source_kind: EnumProperty(name="Source kind", items=SOURCE_KINDS, default="VOLUME")
    source: StringProperty(
        name="Source",
        description="Source file (relative to the .blend where possible, '//' prefix)", subtype="FILE_PATH",
        options={"PATH_SUPPORTS_BLEND_RELATIVE"},
    )
    label: IntProperty(name="Label", description="Label picked from the label map (-1: all non-zero)", default=-1)
    spacing_mm: FloatProperty(name="Spacing", description="Isotropic resampling spacing in mm", default=1.0, min=0.05, unit="NONE")
    frame_method: EnumProperty(name="Frame", items=FRAME_METHODS, default="AUTO")
    frame_origin: FloatVectorProperty(name="Frame origin", size=3, description="Centre of mass in world mm")
    frame_axes: FloatVectorProperty(name="Frame axes", size=9, description="Object axes (columns, row-major 3x3) in world")
    import_matrix: FloatVectorProperty(
        name="Import matrix",
        size=16,
        description="matrix_world at import (row-major); maps Blender world back to the file's world mm",
        default=(1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1),
    )
    volume_mm3: FloatProperty(name="Volume", description="Object volume in mm³", default=0.0)
    instance: PointerProperty(name="Instance", type=bpy.types.Object, description="The instance this object belongs to")
    fit_json: StringProperty(name="Fit", description="Fit figures of a coated instance (JSON)")


classes = (SSMObjectProperties,)


def register_properties():
    bpy.types.Object.ssm = PointerProperty(type=SSMObjectProperties)


def unregister_properties():
    del bpy.types.Object.ssm
