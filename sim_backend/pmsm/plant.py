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

from sim_backend.mechanics import apply_coulomb, coulomb_torque, smooth_load_torque

# state indices
X_ID, X_IQ, X_PSI_D, X_PSI_Q, X_W_MECH = 0, 1, 2, 3, 4
N_STATE = 5

# parameter indices (effective values: nominal * injected factor)
P_RS, P_LS, P_FLUX, P_INERTIA, P_VISCOUS, P_POLE_PAIRS = 0, 1, 2, 3, 4, 5
N_PARAMS = 6


@njit(cache=True)
def electromagnetic_torque(x: np.ndarray, p: np.ndarray) -> float:
    return 1.5 * p[P_POLE_PAIRS] * (x[X_PSI_D] * x[X_IQ] - x[X_PSI_Q] * x[X_ID])


@njit(cache=True)
def derivatives(x: np.ndarray, p: np.ndarray, u_d: float, u_q: float, load_mode: int, load_value: float,
                dx: np.ndarray) -> None:
    a1 = p[P_RS] / p[P_LS]
    a2 = 1.0 / p[P_LS]
    w_e = p[P_POLE_PAIRS] * x[X_W_MECH]
    # (1a): J w psi = w * [-psi_Q, psi_D]
    dx[X_PSI_D] = -w_e * x[X_PSI_Q]
    dx[X_PSI_Q] = w_e * x[X_PSI_D]
    # (1b): -J a2 w psi = a2 w * [psi_Q, -psi_D]
    dx[X_ID] = -a1 * x[X_ID] + a2 * w_e * x[X_PSI_Q] + a2 * u_d
    dx[X_IQ] = -a1 * x[X_IQ] - a2 * w_e * x[X_PSI_D] + a2 * u_q
    torque = electromagnetic_torque(x, p)
    w = x[X_W_MECH]
    dx[X_W_MECH] = (torque - smooth_load_torque(load_mode, load_value, w) - p[P_VISCOUS] * w) / p[P_INERTIA]


@njit(cache=True)
def rk4_step(x: np.ndarray, p: np.ndarray, u_d: float, u_q: float, load_mode: int, load_value: float,
             h: float, work: np.ndarray) -> None:
    """One classical Runge-Kutta step of length h, in place. work: (5, N_STATE) scratch."""
    k1, k2, k3, k4, tmp = work[0], work[1], work[2], work[3], work[4]
    derivatives(x, p, u_d, u_q, load_mode, load_value, k1)
    for j in range(N_STATE):
        tmp[j] = x[j] + 0.5 * h * k1[j]
    derivatives(tmp, p, u_d, u_q, load_mode, load_value, k2)
    for j in range(N_STATE):
        tmp[j] = x[j] + 0.5 * h * k2[j]
    derivatives(tmp, p, u_d, u_q, load_mode, load_value, k3)
    for j in range(N_STATE):
        tmp[j] = x[j] + h * k3[j]
    derivatives(tmp, p, u_d, u_q, load_mode, load_value, k4)
    for j in range(N_STATE):
        x[j] += h / 6.0 * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j])


@njit(cache=True)
def advance(x: np.ndarray, p: np.ndarray, u_d: float, u_q: float, load_mode: int, load_value: float,
            period: float, substeps: int, work: np.ndarray) -> None:
    """Advance the plant over one control period with the voltage held; Coulomb load after each substep."""
    h = period / substeps
    coulomb = coulomb_torque(load_mode, load_value)
    for _ in range(substeps):
        w_before = x[X_W_MECH]
        drive_torque = (electromagnetic_torque(x, p) - smooth_load_torque(load_mode, load_value, w_before)
                        - p[P_VISCOUS] * w_before)
        rk4_step(x, p, u_d, u_q, load_mode, load_value, h, work)
        x[X_W_MECH] = apply_coulomb(w_before, x[X_W_MECH], drive_torque, coulomb, p[P_INERTIA], h)
    # the magnet flux magnitude is a parameter: remove RK4's (tiny) amplitude drift of the rotation
    mag = math.hypot(x[X_PSI_D], x[X_PSI_Q])
    if mag > 0.0:
        x[X_PSI_D] *= p[P_FLUX] / mag
        x[X_PSI_Q] *= p[P_FLUX] / mag


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
