"""Memory limits: refuse work that cannot fit, before allocating it.

Sizes that cannot fit in memory (a 0.01 mm spacing, a label map whose object spans a
1024³ grid, a tiny mesh spacing) are refused with the estimate and the limit, instead of
failing with MemoryError after minutes of work. The limit is half the machine's
physical memory, or ``SSM_MEMORY_LIMIT_GB`` when set.
"""

from __future__ import annotations

import os

from .errors import InputError

__all__ = ["BYTES_PER_OBJECT_VOXEL", "check_allocation", "memory_limit_bytes"]

#: Bytes per voxel of an object volume's grid over the later stages: the signed distance
#: map and its gradient (float64, 4 fields, twice during building), the EDTs and the
#: surface geometry of the template (measured peaks: ``docs/history.md``, Memory).
BYTES_PER_OBJECT_VOXEL = 80


def memory_limit_bytes() -> int:
    """``SSM_MEMORY_LIMIT_GB`` (GB), else half the physical memory."""
    env = os.environ.get("SSM_MEMORY_LIMIT_GB")
    if env:
        try:
            return int(float(env) * 2**30)
        except ValueError:
            raise InputError(f"SSM_MEMORY_LIMIT_GB={env!r} is not a number of GB") from None
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2)
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        return 8 * 2**30


def _size(n: float) -> str:
    for unit, scale in (("TB", 2**40), ("GB", 2**30), ("MB", 2**20)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n / 1024:.0f} kB"


def check_allocation(n_bytes: float, what: str, advice: str = "") -> None:
    """Raise InputError when ``n_bytes`` exceeds the memory limit.

    Parameters
    ----------
    n_bytes : float
        The estimate.
    what : str
        What needs it, naming the file or instance (starts the message).
    advice : str
        What to change.
    """
    limit = memory_limit_bytes()
    if n_bytes > limit:
        raise InputError(f"{what} would need about {_size(n_bytes)} of memory; the limit is {_size(limit)} (half this "
                         f"machine's memory, or SSM_MEMORY_LIMIT_GB){'; ' + advice if advice else ''}")
