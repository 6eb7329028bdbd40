"""Numeric helpers shared by firmware and plant models (neither owns them: firmware must not import a plant module)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def wrap_angle(angle: float) -> float:
    """Wrap to [-pi, pi)."""
    shifted = angle + np.pi
    if 0.0 <= shifted < 2.0 * np.pi:
        # already in range, where the modulo returns its operand unchanged: the same bits without the
        # out-of-line fmod call (an eighth of the SPIM drive's step time, twice per control period)
        return shifted - np.pi
    return shifted % (2.0 * np.pi) - np.pi


@njit(cache=True, inline="always")
def smooth_sign(x: float, width: float) -> float:
    """sign(x) made linear within +-width (a dead-time error, or its compensation, fades through zero current)."""
    if width <= 0.0:
        return float(np.sign(x))
    return max(-1.0, min(1.0, x / width))
