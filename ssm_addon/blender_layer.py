"""Reach the Blender layer from the command line without importing ``bpy`` in the core.

``ssm build`` writes ``model.blend`` and the mode pictures when the ``bpy`` module is
importable and the Blender layer (the extension's ``operators`` package) can be found:
inside Blender the extension passes its writer itself (``operators/cli.py``); from a
source checkout the extension root next to this package is loaded as the package
``ssm``. The operators import the core as ``ssm_addon``, so the core exists once.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path

PACKAGE_NAME = "ssm"


def bpy_available() -> bool:
    """True when the ``bpy`` module can be imported (Blender or ``pip install bpy``)."""
    return "bpy" in sys.modules or importlib.util.find_spec("bpy") is not None


def extension_root() -> Path | None:
    """The extension folder of a source checkout (holding this core), or None."""
    root = Path(__file__).resolve().parents[1]
    if (root / "blender_manifest.toml").is_file() and (root / "operators" / "__init__.py").is_file():
        return root
    return None


def extension_package():
    """The extension package (the checkout's root imported as ``ssm``), or None."""
    root = extension_root()
    if root is None:
        return None
    module = sys.modules.get(PACKAGE_NAME)
    if module is not None and Path(getattr(module, "__file__", "") or "").resolve() == root / "__init__.py":
        return module
    spec = importlib.util.spec_from_file_location(PACKAGE_NAME, root / "__init__.py",
                                                  submodule_search_locations=[str(root)])
    module = importlib.util.module_from_spec(spec)
    sys.modules[PACKAGE_NAME] = module
    spec.loader.exec_module(module)
    return module


def blend_writer():
    """``write_build_outputs(result, out_dir, log)`` of the Blender layer, or None."""
    if not bpy_available():
        return None
    pkg = extension_package()
    if pkg is None:
        return None
    return importlib.import_module(f"{pkg.__name__}.operators.project").write_build_outputs
