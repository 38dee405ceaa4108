"""Reach the Blender layer (``operators/``) from the core without importing ``bpy`` here.

``python -m ssm_addon build`` writes ``model.blend`` and the mode pictures when the
``bpy`` module is importable. The core stays Blender-free: this loader only finds the
extension package this core belongs to (the repo root, imported the way Blender imports
an extension) and hands the build result to ``operators.project.write_build_outputs``.
"""

from __future__ import annotations

import importlib
import importlib.util
import pkgutil
import sys
from pathlib import Path

PACKAGE_NAME = "ssm"


def bpy_available() -> bool:
    """True when the ``bpy`` module can be imported (Blender or ``pip install bpy``)."""
    return "bpy" in sys.modules or importlib.util.find_spec("bpy") is not None


def extension_package():
    """The extension package that contains this core (imported as ``ssm`` if needed)."""
    parent = __package__.rpartition(".")[0] if __package__ else ""
    if parent:  # inside Blender: bl_ext.<repo>.ssm.ssm_addon -> bl_ext.<repo>.ssm
        return importlib.import_module(parent)
    root = Path(__file__).resolve().parents[1]
    module = sys.modules.get(PACKAGE_NAME)
    if module is not None and Path(getattr(module, "__file__", "") or "").resolve() == root / "__init__.py":
        return module
    _alias_core(f"{PACKAGE_NAME}.ssm_addon")
    spec = importlib.util.spec_from_file_location(PACKAGE_NAME, root / "__init__.py", submodule_search_locations=[str(root)])
    module = importlib.util.module_from_spec(spec)
    sys.modules[PACKAGE_NAME] = module
    spec.loader.exec_module(module)
    return module


def _alias_core(alias: str) -> None:
    """Make ``<alias>.<module>`` the very modules of this core (one copy of every class).

    The operators import the core relatively (``from ..ssm_addon import volume``); without
    the alias the extension package would load a second copy whose classes differ from
    the ones the build produced (``isinstance`` and ``except`` would miss).
    """
    core = sys.modules[__package__]
    sys.modules.setdefault(alias, core)
    for info in pkgutil.iter_modules(core.__path__):
        if info.name == "__main__":
            continue
        module = importlib.import_module(f"{__package__}.{info.name}")
        sys.modules.setdefault(f"{alias}.{info.name}", module)


def write_blend_outputs(result, out_dir, log=print) -> dict:
    """Write ``model.blend`` and ``modes.png`` for a build into ``out_dir`` (needs bpy)."""
    pkg = extension_package()
    writer = importlib.import_module(f"{pkg.__name__}.operators.project")
    return writer.write_build_outputs(result, Path(out_dir), log=log)
