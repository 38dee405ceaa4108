"""SSM Builder: point-based 3D statistical shape models from segmented volumes.

Extension entry point: ``register()`` / ``unregister()`` only. No module-level ``bpy``
import, so the tree imports under plain pytest. The Blender-free core is the package
``ssm_addon``, imported under that one name everywhere: the extension zip bundles it
as a wheel; in a source checkout it sits next to this file.
"""


def _ensure_core() -> None:
    """Make ``ssm_addon`` importable in a source checkout (the zip installs it as a wheel)."""
    import importlib.util
    import os
    import sys

    if importlib.util.find_spec("ssm_addon") is None:
        here = os.path.dirname(os.path.abspath(__file__))
        if os.path.isdir(os.path.join(here, "ssm_addon")) and here not in sys.path:
            sys.path.append(here)


def register():
    _ensure_core()
    from . import operators
    from .operators import cli

    operators.register()
    cli.register()


def unregister():
    from . import operators
    from .operators import cli

    cli.unregister()
    operators.unregister()
