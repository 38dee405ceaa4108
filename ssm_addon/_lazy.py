"""Lazy re-exports for the stage subpackages (PEP 562).

A subpackage's ``__init__`` names its public API and the module that defines each name;
the module is imported on first access. So importing one module of a stage never runs
its siblings (the stages depend on each other only where their modules do, and the
import graph of the modules is the one that must have no cycles), and ``import
ssm_addon`` stays cheap for ``ssm --help`` and for worker processes.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping

__all__ = ["DEFERRED_IMPORTS", "DEFERRED_IN", "lazy_exports"]

#: The only imports that stand inside functions: every other import is at the top of its module
#: (``tests/test_structure.py`` holds it). Libraries the build needs only for one output, or only
#: when asked for, and that cost time to import or may be missing:
DEFERRED_IMPORTS = {
    "matplotlib": "the plots and pictures (0.4 s to import; optional: plots are skipped with a note)",
    "PIL": "the pictures of instances and fits (Pillow, which matplotlib brings)",
    "h5py": "statismo files, read or written only when a model file is",
    "dask": "the optional Dask scheduler (pip install \"ssm-builder[dask]\")",
    "distributed": "the optional Dask scheduler",
}
#: Modules whose functions import the core modules they run, and why.
DEFERRED_IN = {
    "ssm_addon/cli/command.py": "each subcommand imports the stages it runs, so `ssm --help`, `ssm params` and "
                                "`ssm info` import none of them",
}


def lazy_exports(package: str, modules: Mapping[str, tuple[str, ...]]) -> tuple[Callable, Callable, list[str]]:
    """``(__getattr__, __dir__, __all__)`` for ``package`` re-exporting ``modules``' names.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    modules : mapping module name -> names
        Submodule (relative to ``package``) and the public names it defines.
    """
    where = {name: module for module, names in modules.items() for name in names}

    def __getattr__(name: str):
        module = where.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{module}"), name)
        setattr(sys.modules[package], name, value)  # later look-ups skip this function
        return value

    def __dir__() -> list[str]:
        return sorted(set(where) | set(vars(sys.modules[package])))

    return __getattr__, __dir__, sorted(where)
