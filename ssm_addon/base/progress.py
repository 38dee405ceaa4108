"""Progress and cancellation conventions shared by every long step.

Long steps accept ``progress(fraction, message)`` with ``fraction`` in [0, 1] and
``cancelled()`` returning True when the user asked to stop. Both are optional.
:func:`sub_progress` maps a sub-step onto part of the parent's range.
"""

from __future__ import annotations

from collections.abc import Callable

ProgressFn = Callable[[float, str], None] | None
CancelledFn = Callable[[], bool] | None


def report(progress: ProgressFn, fraction: float, message: str) -> None:
    """Call ``progress`` if it is set, clamping ``fraction`` to [0, 1]."""
    if progress is not None:
        progress(min(max(float(fraction), 0.0), 1.0), message)


def sub_progress(progress: ProgressFn, start: float, stop: float, prefix: str = "") -> ProgressFn:
    """Return a progress callable that maps [0, 1] onto [start, stop] of ``progress``."""
    if progress is None:
        return None

    def inner(fraction: float, message: str) -> None:
        text = f"{prefix}{message}" if prefix else message
        report(progress, start + (stop - start) * float(fraction), text)

    return inner
