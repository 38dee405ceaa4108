"""Properties: what an object is to SSM Builder, and the parameters of every stage.

The stage parameters are not written here: each Blender property group is derived from
the core's parameter dataclass (:mod:`ssm_addon.base.params`, their one definition) by
:func:`param_group`, with the same names, defaults, ranges, choices and descriptions.
:func:`params_from_group` reads a group back into the dataclass (floats as the user
typed them, not with Blender's single-precision noise) and :func:`set_group` writes one
in; :func:`draw_params` draws the fields of a group, plain or advanced.
"""

from __future__ import annotations

import bpy
from bpy.props import (
    BoolProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)

from ssm_addon.base import params as P
from ssm_addon.base.errors import InputError

from . import bridge

ROLES = [
    ("NONE", "None", "Not part of an SSM build"),
    ("INSTANCE", "Instance", "A segmented object of the training set"),
    ("LANDMARK", "Landmark", "A landmark empty parented to an instance"),
    ("TEMPLATE", "Template", "The triangulated point-distribution template (paper 3)"),
    ("COATED", "Coated instance", "The template coated onto an instance (paper 4)"),
    ("MODEL", "Model", "The mean shape with one shape key per mode (paper 5)"),
    ("MODEL_PART", "Model structure", "One structure of a joint model: its shape keys follow the model's sliders"),
    ("SAMPLE", "Model sample", "A shape generated from the model (eq. 7)"),
]

SOURCE_KINDS = [
    ("VOLUME", "Label map", "Imported from a label map file"),
    ("MESH_FILE", "Mesh file", "Voxelized from a closed surface mesh file"),
    ("BLENDER_MESH", "Blender mesh", "Voxelized from this object's own mesh data"),
]

COLOURINGS = [
    ("POSITION", "Position on the template", "A smooth colour by each point's place on the template: corresponding "
                                             "places have the same colour on every instance and the model"),
    ("TRIANGLES", "Triangle index", "One colour per triangle, as the paper's figs. 6-7"),
]


class SSMObjectProperties(bpy.types.PropertyGroup):
    """Per-object SSM metadata (``obj.ssm``); the arrays live in ID properties (float64)."""

    role: EnumProperty(name="Role", items=ROLES, default="NONE")
    source_kind: EnumProperty(name="Source kind", items=SOURCE_KINDS, default="VOLUME")
    source: StringProperty(
        name="Source",
        description="Source file (relative to the .blend where possible, '//' prefix)", subtype="FILE_PATH",
        options={"PATH_SUPPORTS_BLEND_RELATIVE"},
    )
    label: IntProperty(name="Label", description="Label picked from the label map (-1: all non-zero)", default=-1)
    mesh_spacing_mm: FloatProperty(name="Mesh spacing", description="Voxelization step of a mesh instance in mm "
                                   "(0: the study's spacing)", default=0.0, min=0.0)
    order: IntProperty(name="Order", description="Position of the instance in the study", default=0)
    structure: StringProperty(name="Structure", description="The structure this instance is, in a joint study "
                              "(several structures per subject); empty in a study of one structure")
    subject: StringProperty(name="Subject", description="The subject this instance belongs to, in a joint study "
                            "(its name in the joint model)")
    volume_mm3: FloatProperty(name="Volume", description="Object volume in mm³", default=0.0)
    instance: PointerProperty(name="Instance", type=bpy.types.Object, description="The instance this object belongs to")
    fit_json: StringProperty(name="Fit", description="Fit figures of a coated instance (JSON)")


# ---------------------------------------------------------------------- parameter groups
def _auto_name(name: str) -> str:
    return f"{name}_auto"


def _blender_property(s: P.Spec):
    """The bpy property of one parameter (see :class:`ssm_addon.base.params.Spec`)."""
    unit = f" ({s.unit})" if s.unit and s.unit != "deg" else (" (°)" if s.unit == "deg" else "")
    name = f"{s.label}{unit}"
    desc = s.help[:1].upper() + s.help[1:] + (f". {s.range_text().capitalize()}" if s.kind not in ("bool",) else "")
    if s.kind == "bool":
        return BoolProperty(name=name, description=desc, default=bool(s.default))
    if s.kind == "choice":
        items = [(c, c.replace("-", " ").capitalize(), f"{s.key} = {c!r}") for c in s.choices]
        return EnumProperty(name=name, description=desc, items=items, default=s.default)
    if s.kind == "int":
        kw = {}
        if s.minimum is not None:
            kw["min"] = int(s.minimum)
        if s.maximum is not None:
            kw["max"] = int(min(s.maximum, 2**31 - 1))
        default = s.default if s.default is not None else int(s.minimum or 0)
        return IntProperty(name=name, description=desc, default=int(default), **kw)
    if s.kind == "float":
        kw = {"precision": 3, "step": 10}
        if s.minimum is not None:
            kw["min"] = float(s.minimum)
        if s.maximum is not None:
            kw["max"] = float(s.maximum)
        default = s.default if s.default is not None else float(s.minimum or 0.0)
        return FloatProperty(name=name, description=desc, default=float(default), **kw)
    if s.kind == "floats" and s.size:
        kw = {}
        if s.minimum is not None:
            kw["min"] = float(s.minimum)
        if s.maximum is not None:
            kw["max"] = float(s.maximum)
        return FloatVectorProperty(name=name, description=desc, size=s.size, default=tuple(s.default), **kw)
    if s.kind == "floats":  # any length: typed as a list
        return StringProperty(name=name, description=desc + " (comma-separated)",
                              default=", ".join(f"{v:g}" for v in s.default))
    if s.kind == "strs":
        return StringProperty(name=name, description=desc + " (comma-separated)", default=", ".join(s.default))
    return StringProperty(name=name, description=desc, default=str(s.default or ""))


def param_group(cls, name: str, extra: dict | None = None) -> type:
    """A ``bpy.types.PropertyGroup`` subclass with one property per parameter of ``cls``.

    Optional parameters (None allowed) get a companion ``<name>_auto`` toggle ("Auto", or
    "Off" for a field whose default is a value and whose None is its ``off`` word); ``extra``
    adds further (UI-only) annotations.
    """
    annotations = {}
    implied = getattr(cls, "implied", None)
    for s in P.specs(cls):
        annotations[s.name] = _blender_property(s)
        chosen = tuple(implied(frozenset({s.name}))) if implied is not None else ()
        if chosen:
            # set in this version, a setting that would imply others in a scene of an older
            # version (eq. 1's radii: no tolerance) marks them as chosen too
            annotations[s.name].keywords["update"] = _marking_chosen(chosen)
        if s.optional:
            annotations[_auto_name(s.name)] = BoolProperty(
                name="Off" if s.off else "Auto", default=s.default is None,
                description=(f"Off: {s.none_means.removeprefix(s.off + ': ')}" if s.off else
                             f"Automatic: {s.none_means}"))
    annotations.update(extra or {})
    doc = f"{cls.__name__} as Blender properties (derived from ssm_addon.base.params)."
    return type(name, (bpy.types.PropertyGroup,), {"__annotations__": annotations, "__doc__": doc,
                                                    "params_class": cls})


def _marking_chosen(names: tuple):
    def update(group, _context):
        for name in names:
            setattr(group, name, getattr(group, name))
            if hasattr(group, _auto_name(name)):
                setattr(group, _auto_name(name), getattr(group, _auto_name(name)))
    return update


def _given(s: P.Spec, group) -> bool:
    return group.is_property_set(s.name) or (s.optional and group.is_property_set(_auto_name(s.name)))


def implied_by_an_older_scene(cls, group) -> dict:
    """``{name: value}`` a group of an older version's scene means where it differs from the
    defaults: the class's ``implied`` (see :func:`ssm_addon.base.params.from_table`) of the
    settings the scene holds, for those it does not hold. A ``[template]`` group whose eq. 1
    radii were set before the tolerance existed keeps eq. 1, as a project file does; in this
    version, setting a radius marks the tolerance as chosen (:func:`param_group`)."""
    implied = getattr(cls, "implied", None)
    if implied is None:
        return {}
    given = frozenset(s.name for s in P.specs(cls) if _given(s, group))
    return {name: value for name, value in implied(given).items() if name not in given}


def _read(s: P.Spec, group):
    if s.optional and getattr(group, _auto_name(s.name)):
        return None
    value = getattr(group, s.name)
    if s.kind == "float":
        return P.shortest_float32(value)
    if s.kind == "floats" and s.size:
        return tuple(P.shortest_float32(v) for v in value)
    if s.kind == "floats":
        text = str(value).replace(";", ",").strip()
        try:
            return tuple(float(v) for v in text.split(",") if v.strip())
        except ValueError:
            raise InputError(f"{s.label}: {text!r} is not a comma-separated list of numbers") from None
    if s.kind == "int":
        return int(value)
    if s.kind == "bool":
        return bool(value)
    return str(value)


def params_from_group(cls, group):
    """The parameter object of ``cls`` from a group made by :func:`param_group` (validated).

    Floats are read as the shortest decimal of their single-precision value, so 0.2
    typed in the sidebar is 0.2, the same number as 0.2 in a project file. A group of an
    older version's scene means what its project file would (:func:`implied_by_an_older_scene`).
    """
    older = implied_by_an_older_scene(cls, group)  # field names, as the class's implied gives them
    values = {s.key: older[s.name] if s.name in older else _read(s, group) for s in P.specs(cls)}
    values = {s.key: s.off if values[s.key] is None and s.off else values[s.key] for s in P.specs(cls)}
    return P.from_table(cls, {k: v for k, v in values.items() if v is not None},
                        where=f"{cls.__name__.removesuffix('Params')} settings:")


def set_group(group, params) -> None:
    """Write a parameter object into its property group."""
    for s in P.specs(type(params)):
        value = getattr(params, s.name)
        if s.optional:
            setattr(group, _auto_name(s.name), value is None)
            if value is None:
                continue
        if s.kind == "floats" and not s.size:
            setattr(group, s.name, ", ".join(repr(float(v)) for v in value))
        elif s.kind == "strs":
            setattr(group, s.name, ", ".join(value))
        elif s.kind == "floats":
            setattr(group, s.name, tuple(float(v) for v in value))
        else:
            setattr(group, s.name, value)


class SSMPanel:
    """Base of every SSM panel: the 3D viewport's sidebar (N), tab "SSM".

    Mixed in before ``bpy.types.Panel`` (``class SSM_PT_x(SSMPanel, bpy.types.Panel)``); a
    sub-panel sets ``bl_parent_id``, a panel closed at first ``bl_options``.
    """

    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "SSM"


def draw_params(layout, group, cls, *, advanced: bool = False, skip=()) -> None:
    """Draw the (plain or advanced) parameters of ``cls`` from its group; those the others leave
    unused (``cls.inactive``) greyed out."""
    col = layout.column(align=True)
    rule = getattr(cls, "inactive", None)
    unused = rule(lambda name: _read(P.spec(cls, name), group)) if rule is not None else frozenset()
    for s in P.specs(cls):
        if s.advanced != advanced or s.name in skip:
            continue
        if s.name in unused:
            row = col.row(align=True)
            row.active = False
            row.prop(group, s.name)
            continue
        if s.optional:
            row = col.row(align=True)
            row.prop(group, _auto_name(s.name), text="", icon="CANCEL" if s.off else "AUTO")
            sub = row.row(align=True)
            sub.enabled = not getattr(group, _auto_name(s.name))
            sub.prop(group, s.name)
        else:
            col.prop(group, s.name)


# ------------------------------------------------------------------------ scene settings
SSMTemplateSettings = param_group(P.TemplateParams, "SSMTemplateSettings")
SSMCoatingSettings = param_group(P.CoatingParams, "SSMCoatingSettings", extra={
    "selected_only": BoolProperty(name="Selected only", default=False, description="Coat only the selected instances"),
})
SSMModelSettings = param_group(P.ModelParams, "SSMModelSettings", extra={
    "show_modes": IntProperty(name="Shown modes", description="Modes listed in the panel", default=8, min=1, max=200),
    "anim_modes": IntProperty(name="Animated modes", description="Sweep the first modes in turn", default=3, min=1),
    "anim_frames": IntProperty(name="Frames per mode", default=48, min=6),
    "anim_amplitude": FloatProperty(name="Amplitude (σ)", description="Sweep amplitude in standard deviations",
                                    default=2.0, min=0.1, max=3.0),
    "sample_seed": IntProperty(name="Seed", description="Seed of the random shape", default=0, min=0),
    "sample_sd_limit": FloatProperty(name="Limit (σ)", description="Clip each mode weight to ±limit standard "
                                     "deviations", default=3.0, min=0.1),
    "last_directory": StringProperty(name="Last directory", subtype="DIR_PATH"),
})
SSMOutputSettings = param_group(P.OutputParams, "SSMOutputSettings")
SSMQualitySettings = param_group(P.QualityParams, "SSMQualitySettings")
SSMFitSettings = param_group(P.FitParams, "SSMFitSettings")
SSMSegmentSettings = param_group(P.SegmentParams, "SSMSegmentSettings")
SSMCorrespondenceSettings = param_group(P.CorrespondenceParams, "SSMCorrespondenceSettings")
SSMAnalysisSettings = param_group(P.AnalysisParams, "SSMAnalysisSettings")
SSMComputeSettings = param_group(P.ComputeParams, "SSMComputeSettings")  # kept for Save Project; no panel
SSMJointSettings = param_group(P.JointParams, "SSMJointSettings")  # kept for Save Project; no panel yet


def _recolour(self, context):
    bridge.recolour_scene(context)


def _instance_poll(self, obj):
    return obj.type == "MESH" and obj.ssm.role == "INSTANCE"


class SSMStudySettings(bpy.types.PropertyGroup):
    """``Scene.ssm_display``: the study's template instance and how correspondence is shown."""

    colouring: EnumProperty(name="Correspondence colours", items=COLOURINGS, default="POSITION", update=_recolour)
    template_instance: PointerProperty(name="Template instance", type=bpy.types.Object, poll=_instance_poll,
                                       description="The instance the template is built from ([template] instance)")


_GROUPS = {"template": SSMTemplateSettings, "coating": SSMCoatingSettings, "model": SSMModelSettings,
           "output": SSMOutputSettings, "quality": SSMQualitySettings, "correspondence": SSMCorrespondenceSettings,
           "analysis": SSMAnalysisSettings, "compute": SSMComputeSettings, "joint": SSMJointSettings}
#: Scene property name -> (group class, parameter class): ``Scene.ssm_<table>`` for every table of
#: :class:`ssm_addon.base.params.StudyParams`, ``Scene.ssm_fit`` (Fit Model's own) and ``Scene.ssm_segment``
#: (Segment with Model's own).
SCENE_GROUPS = {**{f"ssm_{section}": (_GROUPS[section], cls) for section, cls in P.SECTIONS.items()},
                "ssm_fit": (SSMFitSettings, P.FitParams), "ssm_segment": (SSMSegmentSettings, P.SegmentParams)}


def scene_params(context, key: str):
    """The parameter object held by ``Scene.<key>`` (e.g. ``"ssm_coating"``)."""
    group_cls, cls = SCENE_GROUPS[key]
    return params_from_group(cls, getattr(context.scene, key))


def scene_study_params(context) -> P.StudyParams:
    """Every table's parameters as the scene holds them (the bundle a project file holds)."""
    return P.StudyParams(**{section: scene_params(context, f"ssm_{section}") for section in P.SECTIONS})


def set_scene_study_params(scene, params: P.StudyParams) -> None:
    """Write every table of ``params`` into the scene's property groups."""
    for section, value in params.tables():
        set_group(getattr(scene, f"ssm_{section}"), value)


classes = (SSMObjectProperties, SSMTemplateSettings, SSMCoatingSettings, SSMModelSettings, SSMOutputSettings,
           SSMQualitySettings, SSMFitSettings, SSMSegmentSettings, SSMCorrespondenceSettings, SSMAnalysisSettings, SSMComputeSettings,
           SSMJointSettings, SSMStudySettings)


def keep_older_scene_settings(scene) -> None:
    """Write into ``scene``'s groups what an older version's settings mean
    (:func:`implied_by_an_older_scene`), so the panels show what a build uses (a scene
    appended later, which no load handler sees, is read the same way by
    :func:`params_from_group`)."""
    for key, (_group_cls, cls) in SCENE_GROUPS.items():
        group = getattr(scene, key)
        for name, value in implied_by_an_older_scene(cls, group).items():
            if value is None:
                setattr(group, _auto_name(name), True)
            else:
                setattr(group, name, value)


@bpy.app.handlers.persistent
def _older_scenes_on_load(_path=None):
    for scene in bpy.data.scenes:
        keep_older_scene_settings(scene)


def register_properties():
    bpy.types.Object.ssm = PointerProperty(type=SSMObjectProperties)
    for key, (group_cls, _cls) in SCENE_GROUPS.items():
        setattr(bpy.types.Scene, key, PointerProperty(type=group_cls))
    bpy.types.Scene.ssm_display = PointerProperty(type=SSMStudySettings)
    bpy.app.handlers.load_post.append(_older_scenes_on_load)


def unregister_properties():
    if _older_scenes_on_load in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_older_scenes_on_load)
    del bpy.types.Scene.ssm_display
    for key in reversed(SCENE_GROUPS):
        delattr(bpy.types.Scene, key)
    del bpy.types.Object.ssm
