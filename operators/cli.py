"""``blender -b --command ssm …``: the headless build inside Blender.

Registered with ``bpy.utils.register_cli_command``; the same arguments as
``python -m ssm_addon``.
"""

from __future__ import annotations

import bpy

from ssm_addon.__main__ import main

from .project import write_build_outputs

_handle = None


def command(argv):
    """Entry point Blender calls with the arguments after ``--command ssm``."""
    return main(list(argv), in_blender=True, blend_writer=write_build_outputs)


def register():
    global _handle
    if hasattr(bpy.utils, "register_cli_command"):
        _handle = bpy.utils.register_cli_command("ssm", command)


def unregister():
    global _handle
    if _handle is not None:
        bpy.utils.unregister_cli_command(_handle)
        _handle = None
