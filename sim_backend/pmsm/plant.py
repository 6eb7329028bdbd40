"""Surface PMSM plant, PMSM paper eq. (1), stationary frame (sD, sQ), amplitude-invariant space vectors.

    d psi_r / dt = J w_e psi_r                       (1a)   w_e = p * w_mech
    d i_s  / dt = -a1 i_s - J a2 w_e psi_r + a2 u_s   (1b)   a1 = Rs/Ls, a2 = 1/Ls
    T_e = 1.5 p (psi_rD i_sQ - psi_rQ i_sD)
    J_m d w_mech / dt = T_e - T_L(w_mech) - B w_mech  (sim_backend.mechanics sign convention)

State x = [i_sD, i_sQ, psi_rD, psi_rQ, w_mech]; the rotor electrical angle is atan2(psi_rQ, psi_rD).
Integrated with classical RK4, the inverter voltage held over the control period (zero-order hold).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from sim_backend import mechanics
from sim_backend.mechanics import apply_coulomb, coulomb_torque, smooth_load_torque, smooth_load_torque_inline
from sim_backend.pmsm.numba_cache import drop_stale_cache

drop_stale_cache(__file__, [mechanics.__file__])

# state indices
X_ID, X_IQ, X_PSI_D, X_PSI_Q, X_W_MECH = 0, 1, 2, 3, 4
N_STATE = 5

# parameter indices (effective values: nominal * injected factor)
P_RS, P_LS, P_FLUX, P_INERTIA, P_VISCOUS, P_POLE_PAIRS = 0, 1, 2, 3, 4, 5
N_PARAMS = 6


@njit(cache=True, inline="always")
def electromagnetic_torque(x: np.ndarray, p: np.ndarray) -> float:
    return 1.5 * p[P_POLE_PAIRS] * (x[X_PSI_D] * x[X_IQ] - x[X_PSI_Q] * x[X_ID])


@njit(cache=True, inline="always")
def derivatives(y: tuple, u_d: float, u_q: float, c: tuple) -> tuple[float, float, float, float, float]:
    """d/dt of y = (i_sD, i_sQ, psi_rD, psi_rQ, w_mech); c = (a1, a2, p, 1/J, B, load_mode, load_value)."""
    i_d, i_q, psi_d, psi_q, w = y
    a1, a2, pole_pairs, inv_inertia, viscous, load_mode, load_value = c
    w_e = pole_pairs * w
    d_psi_d = -w_e * psi_q                                # (1a): J w psi = w [-psi_Q, psi_D]
    d_psi_q = w_e * psi_d
    d_i_d = -a1 * i_d + a2 * w_e * psi_q + a2 * u_d       # (1b): -J a2 w psi = a2 w [psi_Q, -psi_D]
    d_i_q = -a1 * i_q - a2 * w_e * psi_d + a2 * u_q
    torque = 1.5 * pole_pairs * (psi_d * i_q - psi_q * i_d)
    d_w = (torque - smooth_load_torque_inline(load_mode, load_value, w) - viscous * w) * inv_inertia
    return d_i_d, d_i_q, d_psi_d, d_psi_q, d_w


@njit(cache=True, inline="always")
def _axpy(y: tuple, h: float, k: tuple) -> tuple[float, float, float, float, float]:
    return (y[0] + h * k[0], y[1] + h * k[1], y[2] + h * k[2], y[3] + h * k[3], y[4] + h * k[4])


@njit(cache=True, inline="always")
def rk4_step(x: np.ndarray, p: np.ndarray, u_d: float, u_q: float, load_mode: int, load_value: float,
             h: float) -> None:
    """One classical Runge-Kutta step of length h, in place."""
    a2 = 1.0 / p[P_LS]
    c = (p[P_RS] * a2, a2, p[P_POLE_PAIRS], 1.0 / p[P_INERTIA], p[P_VISCOUS], load_mode, load_value)
    y0 = (x[X_ID], x[X_IQ], x[X_PSI_D], x[X_PSI_Q], x[X_W_MECH])
    k1 = derivatives(y0, u_d, u_q, c)
    k2 = derivatives(_axpy(y0, 0.5 * h, k1), u_d, u_q, c)
    k3 = derivatives(_axpy(y0, 0.5 * h, k2), u_d, u_q, c)
    k4 = derivatives(_axpy(y0, h, k3), u_d, u_q, c)
    for j in range(N_STATE):
        x[j] = y0[j] + h / 6.0 * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j])


@njit(cache=True, inline="always")
def advance(x: np.ndarray, p: np.ndarray, u_d: float, u_q: float, load_mode: int, load_value: float,
            period: float, substeps: int) -> None:
    """Advance the plant over one control period with the voltage held; Coulomb load after each substep."""
    h = period / substeps
    coulomb = coulomb_torque(load_mode, load_value)
    for _ in range(substeps):
        if coulomb > 0.0:
            w_before = x[X_W_MECH]
            drive_torque = (electromagnetic_torque(x, p) - smooth_load_torque(load_mode, load_value, w_before)
                            - p[P_VISCOUS] * w_before)
            rk4_step(x, p, u_d, u_q, load_mode, load_value, h)
            x[X_W_MECH] = apply_coulomb(w_before, x[X_W_MECH], drive_torque, coulomb, p[P_INERTIA], h)
        else:
            rk4_step(x, p, u_d, u_q, load_mode, load_value, h)
    # the magnet flux magnitude is a parameter: remove RK4's (tiny) amplitude drift of the rotation
    scale = p[P_FLUX] / math.sqrt(x[X_PSI_D] * x[X_PSI_D] + x[X_PSI_Q] * x[X_PSI_Q])
    x[X_PSI_D] *= scale
    x[X_PSI_Q] *= scale


@njit(cache=True)
def rotor_angle_elec(x: np.ndarray) -> float:
    return math.atan2(x[X_PSI_Q], x[X_PSI_D])


@njit(cache=True)
def load_torque(x: np.ndarray, load_mode: int, load_value: float) -> float:
    """Shaft load torque as the rig's torque transducer reads it (brake: zero at standstill)."""
    w = x[X_W_MECH]
    t = smooth_load_torque(load_mode, load_value, w)
    if w != 0.0:
        t += coulomb_torque(load_mode, load_value) * np.sign(w)
    return t


def initial_state(flux_wb: float, angle_elec_rad: float) -> np.ndarray:
    x = np.zeros(N_STATE)
    x[X_PSI_D] = flux_wb * math.cos(angle_elec_rad)
    x[X_PSI_Q] = flux_wb * math.sin(angle_elec_rad)
    return x
