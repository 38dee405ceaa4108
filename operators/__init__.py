"""The Blender layer: thin operators, panels and properties over the ``ssm_addon`` core.

Each module in :data:`MODULES` exposes ``classes`` (registered in order, unregistered in
reverse) and optionally ``register_properties()`` / ``unregister_properties()`` which run
after its classes are registered / before they are unregistered.
"""

from __future__ import annotations

import importlib

import bpy

MODULES = (
    "properties",
    "instances",
    "landmarks",
    "template",
    "coating",
    "model",
    "fit",
    "segmentation",
    "analysis",
    "project",
)


def _modules():
    return [importlib.import_module(f"{__name__}.{name}") for name in MODULES]


def register():
    for module in _modules():
        for cls in getattr(module, "classes", ()):
            bpy.utils.register_class(cls)
        if hasattr(module, "register_properties"):
            module.register_properties()


def unregister():
    for module in reversed(_modules()):
        if hasattr(module, "unregister_properties"):
            module.unregister_properties()
        for cls in reversed(getattr(module, "classes", ())):
            bpy.utils.unregister_class(cls)
