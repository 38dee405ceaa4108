"""SSM Builder: point-based 3D statistical shape models from segmented volumes.

Extension entry point: ``register()`` / ``unregister()`` only. No module-level ``bpy``
import, so the tree (and the Blender-free core ``ssm_addon``) imports under plain pytest.
"""


def register():
    from . import operators
    from .operators import cli

    operators.register()
    cli.register()


def unregister():
    from . import operators
    from .operators import cli

    cli.unregister()
    operators.unregister()
