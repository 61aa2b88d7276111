"""Checks of config values shared by the simulator's configs (:mod:`.config`, :mod:`.rooms.config`,
:mod:`.raytrace.config`): each raises :class:`fruxel.errors.ConfigError` with one line naming the field."""

from __future__ import annotations

import math
from typing import Any

from fruxel.errors import ConfigError


def check_range(name: str, lo_hi: Any, low: float = -math.inf, high: float = math.inf) -> None:
    """Raise ConfigError unless ``lo_hi`` is a ``(lo, hi)`` pair of finite numbers with ``low <= lo <= hi <= high``."""
    try:
        lo, hi = (float(v) for v in lo_hi)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a (low, high) pair of numbers, got {lo_hi!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and low <= lo <= hi <= high):
        raise ConfigError(f"{name} must satisfy {low} <= low <= high <= {high}, got {lo_hi!r}")
