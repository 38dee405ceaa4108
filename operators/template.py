"""Template in Blender (paper section 3): build the template from the active instance.

* ``Scene.ssm_template``: the :class:`~ssm_addon.template.TemplateParams` (lengths in mm);
* ``ssm.build_template``: a background job (modal progress bar, Esc to cancel; synchronous
  from scripts) that builds the template of the active instance and creates or replaces
  the mesh object ``"SSM Template"`` (collection "SSM Template"): vertices in the
  instance's object frame (mm) with ``matrix_world`` = object frame -> Blender world, so
  it overlays the instance; a colour attribute ``triangle_index`` (one colour per
  triangle index on its corners, :func:`bridge.set_face_colors`, as the paper's figs. 6-7
  show correspondence) shown by the triangle
  colour material; a POINT float attribute ``curvature`` (1/mm, paper fig. 3);
  ``obj.ssm.role = "TEMPLATE"`` and ``obj.ssm.instance`` = the source instance; the build
  parameters and figures as JSON in the ID property ``ssm_template_params``.
* Panel "Template" in the SSM sidebar.
"""

from __future__ import annotations

import json

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, FloatProperty, FloatVectorProperty, IntProperty, PointerProperty

from ..ssm_addon import template as core
from ..ssm_addon.errors import InputError
from . import bridge
from .jobs import BackgroundJob

TEMPLATE_NAME = "SSM Template"
TEMPLATE_COLLECTION = "SSM Template"
PARAMS_PROP = "ssm_template_params"
_D = core.TemplateParams()

SELECTION_ITEMS = [
    ("CURVATURE", "Curvature", "Highest curvature first: points on edges and tips (paper 3.1)"),
    ("RANDOM", "Random", "Seeded random order"),
]
RADIUS_ITEMS = [
    ("CURVATURE", "From curvature", "r from the curvature by eq. (1) between r min and r max"),
    ("CONSTANT", "Constant", "r = r max everywhere"),
]
FORM_ITEMS = [
    ("QUADRIC", "Quadric", "z = ax² + 2bxy + cy² + dx + ey + f with bias corrections (robust on voxels)"),
    ("PAPER", "Paper", "z = ax² + 2bxy + cy² as in paper 3.2"),
]


class SSMTemplateSettings(bpy.types.PropertyGroup):
    """Template parameters (``Scene.ssm_template``), mirrors :class:`ssm_addon.template.TemplateParams`."""

    spacing_mm: FloatProperty(name="Spacing (mm)", default=_D.spacing_mm, min=0.1, soft_max=3.0,
                              description="Isotropic resampling spacing of the template instance")
    normal_radius_mm: FloatProperty(name="Normal radius (mm)", default=_D.normal_radius_mm, min=0.5, soft_max=15.0,
                                    description="Sphere radius of the normal estimate (paper 3.2)")
    patch_radius_mm: FloatProperty(name="Patch radius (mm)", default=_D.patch_radius_mm, min=0.5, soft_max=20.0,
                                   description="Patch radius of the curvature fit (paper 3.2)")
    curvature_form: EnumProperty(name="Curvature fit", items=FORM_ITEMS, default=_D.curvature_form.upper())
    selection: EnumProperty(name="Selection", items=SELECTION_ITEMS, default=_D.selection.upper())
    radius: EnumProperty(name="Radius", items=RADIUS_ITEMS, default=_D.radius.upper())
    r_min_mm: FloatProperty(name="r min (mm)", default=_D.r_min_mm, min=0.5, soft_max=20.0,
                            description="Smallest reduction radius, surface distance (eq. 1)")
    r_max_mm: FloatProperty(name="r max (mm)", default=_D.r_max_mm, min=0.5, soft_max=40.0,
                            description="Largest reduction radius, surface distance (eq. 1)")
    p: FloatProperty(name="p", default=_D.p, min=0.1, soft_max=10.0,
                     description="Non-linearity of eq. (1): p > 1 gives more small radii")
    curvature_percentiles: FloatVectorProperty(name="c percentiles", size=2, default=_D.curvature_percentiles,
                                               min=0.0, max=100.0,
                                               description="Percentiles of c used as c min and c max in eq. (1)")
    seed: IntProperty(name="Seed", default=_D.seed, min=0)
    topology_auto: BoolProperty(name="Auto topology radius", default=True,
                                description="Closing radius = r min (fills tunnels below the point spacing)")
    topology_value_mm: FloatProperty(name="Topology radius (mm)", default=4.0, min=0.0, soft_max=10.0,
                                     description="Closing radius of the topology cleaning (0: none)")
    max_refinements: IntProperty(name="Max refinements", default=_D.max_refinements, min=0, max=1000,
                                 description="Rounds of seed insertion allowed to reach the closed-ball property")


def params_from_settings(s) -> core.TemplateParams:
    """A :class:`TemplateParams` from ``Scene.ssm_template`` (raises InputError on bad values)."""
    return core.TemplateParams(
        spacing_mm=float(s.spacing_mm), normal_radius_mm=float(s.normal_radius_mm),
        patch_radius_mm=float(s.patch_radius_mm), curvature_form=s.curvature_form.lower(),
        selection=s.selection.lower(), radius=s.radius.lower(), r_min_mm=float(s.r_min_mm),
        r_max_mm=float(s.r_max_mm), p=float(s.p), curvature_percentiles=tuple(float(x) for x in s.curvature_percentiles),
        seed=int(s.seed), topology_radius_mm=None if s.topology_auto else float(s.topology_value_mm),
        max_refinements=int(s.max_refinements),
    )


def _is_instance(obj) -> bool:
    return obj is not None and obj.type == "MESH" and obj.ssm.role == "INSTANCE"


def _source_instance(context):
    """The active instance, or the instance of the active template/coated object."""
    obj = context.active_object
    if _is_instance(obj):
        return obj
    if obj is not None and obj.ssm.role in {"TEMPLATE", "COATED"} and _is_instance(obj.ssm.instance):
        return obj.ssm.instance
    return None


def find_template(context):
    """The template object ("SSM Template" with role TEMPLATE), or None."""
    obj = bpy.data.objects.get(TEMPLATE_NAME)
    if obj is not None and obj.type == "MESH" and obj.ssm.role == "TEMPLATE":
        return obj
    return next((o for o in context.scene.objects if o.type == "MESH" and o.ssm.role == "TEMPLATE"), None)


def write_template_object(context, instance, template: core.Template):
    """Create or replace ``"SSM Template"`` for ``template`` built from ``instance``."""
    from .coating import object_to_blender_matrix

    faces = np.asarray(template.faces)
    obj = bridge.new_mesh_object(context, TEMPLATE_NAME, template.points_object, faces,
                                 collection_name=TEMPLATE_COLLECTION, matrix_world=object_to_blender_matrix(instance))
    bridge.set_face_colors(obj.data, bridge.triangle_index_colors(len(faces)))
    bridge.set_point_attribute(obj.data, "curvature", np.asarray(template.curvature))
    mat = bridge.color_material()
    if not obj.data.materials:
        obj.data.materials.append(mat)
    else:
        obj.data.materials[0] = mat
    obj.ssm.role = "TEMPLATE"
    obj.ssm.instance = instance
    obj.ssm.spacing_mm = float(template.params.get("object_spacing_mm", instance.ssm.spacing_mm))
    obj[PARAMS_PROP] = json.dumps(template.params, default=str)
    return obj


def _prepare(self, context):
    from .instances import instance_object_volume

    instance = _source_instance(context)
    if instance is None:
        raise InputError("build template: make an SSM instance active (import one with File > Import > Segmentation)")
    params = params_from_settings(context.scene.ssm_template)
    ov = instance_object_volume(instance)
    self._instance_name = instance.name

    def work(progress, cancelled):
        vol = core.object_volume_at_spacing(ov, params.spacing_mm)
        return core.build_template(vol, params, progress=progress, cancelled=cancelled)

    return work


def _finish(self, context, template):
    instance = bpy.data.objects.get(self._instance_name)
    if instance is None:
        self.report({"ERROR"}, f"build template: instance {self._instance_name!r} was removed")
        return {"CANCELLED"}
    obj = write_template_object(context, instance, template)
    self.report({"INFO"}, f"template: {len(template.points_object)} points, {len(template.faces)} triangles, "
                          f"genus {template.params.get('genus')} from {instance.name}")
    for o in context.view_layer.objects:
        o.select_set(False)
    obj.select_set(True)
    return {"FINISHED"}


class SSM_OT_build_template(BackgroundJob, bpy.types.Operator):
    """Build the template from the active instance: point density reduction and triangulation (paper 3). Esc cancels"""

    bl_idname = "ssm.build_template"
    bl_label = "Build Template"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return _source_instance(context) is not None

    prepare = _prepare
    finish = _finish


class SSM_PT_template(bpy.types.Panel):
    bl_label = "Template"
    bl_idname = "SSM_PT_template"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "SSM"
    bl_order = 20
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        s = context.scene.ssm_template
        inst = _source_instance(context)
        layout.label(text=f"From: {inst.name}" if inst else "Make an instance active", icon="OBJECT_DATA")
        col = layout.column(align=True)
        col.prop(s, "spacing_mm")
        col.prop(s, "selection")
        col.prop(s, "radius")
        row = col.row(align=True)
        row.prop(s, "r_min_mm")
        row.prop(s, "r_max_mm")
        row = col.row(align=True)
        row.prop(s, "p")
        row.prop(s, "seed")
        col.prop(s, "curvature_percentiles")
        col = layout.column(align=True)
        col.prop(s, "curvature_form")
        row = col.row(align=True)
        row.prop(s, "normal_radius_mm")
        row.prop(s, "patch_radius_mm")
        col = layout.column(align=True)
        col.prop(s, "topology_auto")
        sub = col.row()
        sub.enabled = not s.topology_auto
        sub.prop(s, "topology_value_mm")
        col.prop(s, "max_refinements")
        layout.operator(SSM_OT_build_template.bl_idname, icon="MESH_ICOSPHERE")
        tpl = find_template(context)
        if tpl is not None:
            src = tpl.ssm.instance.name if tpl.ssm.instance else "?"
            layout.label(text=f"{tpl.name}: {len(tpl.data.vertices)} points, {len(tpl.data.polygons)} triangles",
                         icon="MESH_DATA")
            layout.label(text=f"from {src}")


classes = (SSMTemplateSettings, SSM_OT_build_template, SSM_PT_template)


def register_properties():
    bpy.types.Scene.ssm_template = PointerProperty(type=SSMTemplateSettings)


def unregister_properties():
    del bpy.types.Scene.ssm_template
