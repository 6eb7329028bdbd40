"""Angle arithmetic shared by firmware and plant models (neither owns it: firmware must not import a plant module)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def wrap_angle(angle: float) -> float:
    """Wrap to [-pi, pi)."""
    return (angle + np.pi) % (2.0 * np.pi) - np.pi
