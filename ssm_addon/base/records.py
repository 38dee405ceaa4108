"""What a build records: the library versions and JSON-ready values of its parameters."""

from __future__ import annotations

import platform
from pathlib import Path

import numpy as np
import scipy
import skimage

from ..version import __version__

__all__ = ["jsonable", "versions"]


def versions() -> dict:
    """The versions of this package, Python and the numeric libraries (recorded in ``params_json``)."""
    return {"ssm_builder": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__, "scikit-image": skimage.__version__}


def jsonable(obj):
    """``obj`` with numpy scalars and arrays, tuples, paths and non-finite floats as plain JSON types.

    Non-finite floats become ``None`` (JSON has no NaN).

    >>> jsonable({"a": np.float64(1.5), "b": (1, np.arange(2)), "c": float("nan")})
    {'a': 1.5, 'b': [1, [0, 1]], 'c': None}
    """
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    if isinstance(obj, Path):
        return str(obj)
    return obj
