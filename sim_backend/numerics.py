"""Numeric helpers shared by firmware and plant models (neither owns them: firmware must not import a plant module)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def wrap_angle(angle: float) -> float:
    """Wrap to [-pi, pi)."""
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


@njit(cache=True, inline="always")
def smooth_sign(x: float, width: float) -> float:
    """sign(x) made linear within +-width (a dead-time error, or its compensation, fades through zero current)."""
    if width <= 0.0:
        return float(np.sign(x))
    return max(-1.0, min(1.0, x / width))
