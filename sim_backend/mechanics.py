"""Shaft mechanics and load models shared by both simulated drives.

Sign convention (drivers.api.LoadMode): J*dw/dt = T_e - T_L - B*w, T_L opposes positive rotation.
"""

from __future__ import annotations

import numpy as np
from numba import njit

LOAD_TORQUE = 0   # active torque, keeps its sign (hanging mass)
LOAD_VISCOUS = 1  # T_L = value * w (DC generator into a resistor)
LOAD_BRAKE = 2    # T_L = value * sign(w), zero at standstill (passive brake)


@njit(cache=True, inline="always")
def smooth_load_torque_inline(mode: int, value: float, omega_mech: float) -> float:
    """smooth_load_torque, inlined into the caller at numba IR level (for RK4 stages in tight kernels)."""
    if mode == LOAD_TORQUE:
        return value
    if mode == LOAD_VISCOUS:
        return value * omega_mech
    return 0.0


@njit(cache=True)
def smooth_load_torque(mode: int, value: float, omega_mech: float) -> float:
    """The part of the load torque that is a smooth function of speed (passive brake excluded)."""
    return smooth_load_torque_inline(mode, value, omega_mech)


@njit(cache=True)
def coulomb_torque(mode: int, value: float) -> float:
    """Magnitude of the passive (Coulomb) load torque; it opposes motion and is zero at standstill."""
    if mode == LOAD_BRAKE:
        return abs(value)
    return 0.0


@njit(cache=True)
def apply_coulomb(omega_before: float, omega_free: float, drive_torque: float, coulomb: float,
                  inertia: float, dt: float) -> float:
    """Speed after one step of a shaft with Coulomb friction of magnitude `coulomb`.

    omega_free is the speed the step reached without Coulomb friction; drive_torque is the net smooth
    torque (T_e - smooth T_L - B*w). A shaft at rest stays at rest while |drive_torque| <= coulomb, and a
    moving shaft that the friction would push through zero stops at zero instead.
    """
    if coulomb <= 0.0:
        return omega_free
    if omega_before == 0.0:
        if abs(drive_torque) <= coulomb:
            return 0.0
        return omega_free - np.sign(drive_torque) * coulomb * dt / inertia
    omega = omega_free - np.sign(omega_before) * coulomb * dt / inertia
    if omega * omega_before < 0.0 and abs(drive_torque) <= coulomb:
        return 0.0
    return omega
