"""Exposure limits shared by every trigger: checked before anything is sent (``LimitError``)."""
from __future__ import annotations

import math
import numbers

from ..errors import LimitError


def check_exposure_range(min_exposure_s: float, max_exposure_s: float) -> None:
    """Validate a driver's configured exposure range (a programming or config error: ValueError)."""
    if not 0 < min_exposure_s <= max_exposure_s:
        raise ValueError(f"need 0 < min_exposure_s <= max_exposure_s, got {min_exposure_s}, {max_exposure_s}")


def exposure_ms(exposure_s: float, *, min_exposure_s: float, max_exposure_s: float) -> int:
    """Whole milliseconds (>= 1) for ``exposure_s``; :class:`LimitError` when it is not a finite number of
    seconds inside ``[min_exposure_s, max_exposure_s]``."""
    if not isinstance(exposure_s, numbers.Real) or isinstance(exposure_s, bool):
        raise LimitError(f"exposure must be a number of seconds, got {exposure_s!r}")
    exposure_s = float(exposure_s)
    if not math.isfinite(exposure_s):
        raise LimitError(f"exposure must be a finite number of seconds, got {exposure_s!r}")
    if not min_exposure_s <= exposure_s <= max_exposure_s:
        raise LimitError(f"exposure {exposure_s:g} s outside the trigger's range "
                         f"[{min_exposure_s:g}, {max_exposure_s:g}] s")
    ms = round(exposure_s * 1000.0)
    if ms < 1:
        raise LimitError(f"exposure {exposure_s:g} s rounds to {ms} ms; the minimum is 1 ms")
    return ms
