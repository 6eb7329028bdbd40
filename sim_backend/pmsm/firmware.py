"""Sensorless IRFOC firmware of the PMSM paper, as the DSP runs it: one fixed-step function.

Inputs per step: two measured phase currents, the measured DC-link voltage, time, and this module's own
state (its previous voltage commands, the fieldbus speed reference and enable bit, test-hook flags).
Output: the PWM modulation command written into the state, and the firmware's telemetry columns.
This module imports nothing from the plant: it cannot see true speed, angle or flux.

Estimator (paper section III), in the frame (x, y) fixed to the estimated rotor flux:
    d i^_x/dt = -a1^ i^_x + w^ i^_y + a2 u_x                (5a)
    d i^_y/dt = -a1^ i^_y - w^ i^_x - a2 w^ psi^ + a2 u_y    (5b)
    w_e = w^,  rho^ = integral of w^ dt                       (5c)
    eps_w = -(i_y - i^_y) / (a2 psi^)                        (7a)
    eps_psi = -(i_x - i^_x) / (a2 w^2)                       (7b)
    w^ = (kp_w + ki_w/s) eps_w,  psi^ = (kp_psi + ki_psi/s) eps_psi   (8a), (8b)
(5) is discretised exactly for a voltage held over the period (complex form, i = i_x + j i_y):
    i^[k+1] = e^(lam T) i^[k] + (e^(lam T) - 1)/lam * a2 (u - j w^ psi^),  lam = -(a1^ + j w^).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from drivers.contract import signals
from drivers.contract.signals import SIGNAL_INDEX
import sim_backend.numerics as numerics
from sim_backend.numerics import smooth_sign
from sim_backend.pmsm.numba_cache import drop_stale_cache

drop_stale_cache(__file__, [signals.__file__, numerics.__file__])

SQRT3 = math.sqrt(3.0)

# ---- parameters (fw_params array) ----
F_PERIOD = 0               # control period T, s
F_POLE_PAIRS = 1
F_RS = 2                   # firmware's motor model: stator resistance, ohm
F_LS = 3                   # stator inductance, H
F_FLUX = 4                 # nominal magnet flux, Wb (start value of psi^; torque constant for tuning)
F_INERTIA = 5              # shaft inertia assumed by the speed-loop tuning, kg m^2
F_SPEED_EST_KP = 6         # kp_w (paper: 300)
F_SPEED_EST_KI_OVER_KP = 7  # ki_w / kp_w; <= 0 means a1^ = Rs^/Ls^ (paper)
F_FLUX_EST_KP = 8          # kp_psi (paper: 5000)
F_FLUX_EST_KI_OVER_KP = 9  # ki_psi / kp_psi (paper: 20)
F_FLUX_EST_MIN_SPEED = 10  # elec rad/s: below it psi^ is held; floor of w^2 in (7b)
F_FLUX_EST_MIN_FRACTION = 11  # psi^ kept >= this fraction of F_FLUX (guards (7a) division)
F_SPEED_BW = 12            # speed-loop crossover, rad/s
F_SPEED_ZERO_FRACTION = 13  # speed PI zero at this fraction of the crossover
F_CURRENT_BW = 14          # current-loop bandwidth, rad/s
F_I_MAX = 15               # torque-current limit, A (peak)
F_I_TRIP = 16              # overcurrent trip on any phase, A
F_RAMP = 17                # speed-reference ramp, mech rad/s^2
F_VOLTAGE_FRACTION = 18    # usable fraction of the linear range vdc/sqrt(3)
F_DELAY_COMP = 19          # angle advance of the inverse Park transform, in control periods
F_DEADTIME_COMP_V = 20     # per-phase dead-time/drop compensation voltage, V
F_DEADTIME_COMP_WIDTH = 21  # current below which the compensation fades linearly, A
F_ISX_REF = 22             # field-axis current reference, A (paper: 0)
F_FLUX_EST_MAX_FRACTION = 23  # psi^ kept <= this fraction of F_FLUX (a magnet cannot grow)
# derived values, recomputed by derive_gains() whenever a parameter is written (as the DSP does)
F_A1 = 24                  # a1^ = Rs^/Ls^
F_A2 = 25                  # a2 = 1/Ls^
F_DECAY = 26               # exp(-a1^ T)
F_KI_W = 27                # ki_w
F_KI_PSI = 28              # ki_psi
F_KP_SPEED = 29            # speed PI, A per mech rad/s
F_KI_SPEED = 30
F_KP_I = 31                # current PIs, V/A
F_KI_I = 32
F_INV_POLE_PAIRS = 33
F_FLUX_HOLD_RELAX_S = 34   # below F_FLUX_EST_MIN_SPEED psi^ relaxes to F_FLUX with this time constant; 0 = pure hold
F_RELAX_FACTOR = 35        # derived: T / F_FLUX_HOLD_RELAX_S per period (0 = pure hold)
N_PARAMS = 36

# ---- state (fw_state array) ----
S_ENABLE_CMD = 0           # fieldbus: 1 = operation enabled
S_SPEED_REF_CMD = 1        # fieldbus: speed reference, mech rad/s
S_FREEZE_SPEED = 2         # test hook flag
S_FREEZE_FLUX = 3          # test hook flag
S_RUNNING = 4              # gates on
S_FAULT = 5                # CiA 402 error code, 0 = none
S_THETA = 6                # rho^, elec rad, wrapped
S_OMEGA = 7                # w^, elec rad/s
S_PSI = 8                  # psi^, Wb
S_INT_OMEGA = 9            # integrator of (8a)
S_INT_PSI = 10             # integrator of (8b)
S_IHAT_X = 11              # model currents (5)
S_IHAT_Y = 12
S_U_ALPHA_LAST = 13        # command u[k-1] (being applied during this period), V
S_U_BETA_LAST = 14
S_U_ALPHA_PREV = 15        # command u[k-2] (was applied during the period that just ended), V
S_U_BETA_PREV = 16
S_SPEED_REF_RAMPED = 17    # mech rad/s
S_INT_SPEED = 18           # speed PI integrator, A
S_INT_IX = 19              # current PI integrators, V
S_INT_IY = 20
S_M_ALPHA = 21             # output: PWM modulation command (voltage / measured vdc)
S_M_BETA = 22
S_TO_FRAME_RE = 23         # e^(-j rho^) of this step, reused by the inverse Park transform
S_TO_FRAME_IM = 24
N_STATE = 25

FAULT_OVERCURRENT = 0x2310

# telemetry columns this module writes
C_SPEED_REF = SIGNAL_INDEX["speed_ref_mech_rad_s"]
C_SPEED_EST = SIGNAL_INDEX["speed_est_mech_rad_s"]
C_POS_EST = SIGNAL_INDEX["pos_est_elec_rad"]
C_FLUX_EST = SIGNAL_INDEX["flux_est_wb"]
C_I_SX = SIGNAL_INDEX["i_sx_a"]
C_I_SY = SIGNAL_INDEX["i_sy_a"]
C_I_SX_REF = SIGNAL_INDEX["i_sx_ref_a"]
C_I_SY_REF = SIGNAL_INDEX["i_sy_ref_a"]
C_U_SX = SIGNAL_INDEX["u_sx_v"]
C_U_SY = SIGNAL_INDEX["u_sy_v"]
C_TORQUE_EST = SIGNAL_INDEX["torque_est_nm"]
C_VDC = SIGNAL_INDEX["vdc_v"]


@njit(cache=True, inline="always")
def _wrap(angle: float) -> float:
    """Wrap to [-pi, pi) for an angle that moved by less than a turn."""
    if angle >= math.pi:
        return angle - 2.0 * math.pi
    if angle < -math.pi:
        return angle + 2.0 * math.pi
    return angle


@njit(cache=True, inline="always")
def _small_rotation(a: float) -> complex:
    """e^(j a) for the per-period angle steps (|a| < 0.1 at 3000 rpm): 5th-order Taylor, error < a^6/720."""
    if abs(a) > 0.3:
        return complex(math.cos(a), math.sin(a))
    a2 = a * a
    return complex(1.0 - a2 * (0.5 - a2 / 24.0), a * (1.0 - a2 * (1.0 / 6.0 - a2 / 120.0)))


@njit(cache=True, inline="always")
def _start(s: np.ndarray, p: np.ndarray, i_meas_xy: complex) -> None:
    """Gates on: estimators restart from w^ = 0 and psi^ = nominal; rho^ keeps its last value."""
    s[S_RUNNING] = 1.0
    s[S_OMEGA] = 0.0
    s[S_INT_OMEGA] = 0.0
    s[S_PSI] = p[F_FLUX]
    s[S_INT_PSI] = p[F_FLUX]
    s[S_IHAT_X] = i_meas_xy.real
    s[S_IHAT_Y] = i_meas_xy.imag
    for k in (S_U_ALPHA_LAST, S_U_BETA_LAST, S_U_ALPHA_PREV, S_U_BETA_PREV, S_SPEED_REF_RAMPED, S_INT_SPEED,
              S_INT_IX, S_INT_IY):
        s[k] = 0.0


@njit(cache=True, inline="always")
def _stop(s: np.ndarray) -> None:
    for k in (S_RUNNING, S_M_ALPHA, S_M_BETA, S_U_ALPHA_LAST, S_U_BETA_LAST):
        s[k] = 0.0


@njit(cache=True, inline="always")
def _update_estimators(s: np.ndarray, p: np.ndarray, i_alpha_beta: complex) -> complex:
    """Advance model (5) over the period that just ended, rotate the frame (5c), run (7)-(8).

    Returns the measured current in the new estimated frame.
    """
    T = p[F_PERIOD]
    a1 = p[F_A1]
    a2 = p[F_A2]
    w = s[S_OMEGA]
    psi = s[S_PSI]

    # voltage applied during the last period (own command u[k-2]) seen from the mid-period frame
    half_turn = _small_rotation(-0.5 * w * T)                               # e^(-j w T/2)
    to_mid_frame = complex(math.cos(s[S_THETA]), -math.sin(s[S_THETA])) * half_turn
    u_xy = complex(s[S_U_ALPHA_PREV], s[S_U_BETA_PREV]) * to_mid_frame
    lam = complex(-a1, -w)
    e = p[F_DECAY] * half_turn * half_turn                                   # e^(lam T)
    i_hat = complex(s[S_IHAT_X], s[S_IHAT_Y])
    i_hat = e * i_hat + (e - 1.0) / lam * a2 * (u_xy - 1j * w * psi)
    s[S_THETA] = _wrap(s[S_THETA] + w * T)                                   # (5c)
    to_frame = to_mid_frame * half_turn                                      # e^(-j rho^[k])
    i_xy = i_alpha_beta * to_frame
    s[S_IHAT_X] = i_hat.real
    s[S_IHAT_Y] = i_hat.imag
    s[S_TO_FRAME_RE] = to_frame.real
    s[S_TO_FRAME_IM] = to_frame.imag

    delta = i_xy - i_hat
    if s[S_FREEZE_SPEED] == 0.0:
        kp_w = p[F_SPEED_EST_KP]
        ki_w = p[F_KI_W]
        eps_w = -delta.imag / (a2 * psi)                                      # (7a)
        s[S_INT_OMEGA] += ki_w * T * eps_w
        s[S_OMEGA] = kp_w * eps_w + s[S_INT_OMEGA]                            # (8a)
    w_min = p[F_FLUX_EST_MIN_SPEED]
    if s[S_FREEZE_FLUX] == 0.0 and abs(w) < w_min:
        # (7b) has no information near standstill: relax towards the nominal flux, the best prior
        s[S_INT_PSI] += p[F_RELAX_FACTOR] * (p[F_FLUX] - s[S_INT_PSI])
        s[S_PSI] = s[S_INT_PSI]
    elif s[S_FREEZE_FLUX] == 0.0:
        kp_psi = p[F_FLUX_EST_KP]
        ki_psi = p[F_KI_PSI]
        eps_psi = -delta.real / (a2 * max(w * w, w_min * w_min))              # (7b)
        s[S_INT_PSI] += ki_psi * T * eps_psi
        psi_min = p[F_FLUX_EST_MIN_FRACTION] * p[F_FLUX]
        psi_max = p[F_FLUX_EST_MAX_FRACTION] * p[F_FLUX]
        s[S_INT_PSI] = min(max(s[S_INT_PSI], psi_min), psi_max)
        s[S_PSI] = min(max(kp_psi * eps_psi + s[S_INT_PSI], psi_min), psi_max)  # (8b)
    return i_xy


@njit(cache=True, inline="always")
def _speed_controller(s: np.ndarray, p: np.ndarray) -> float:
    """Ramped reference, PI on the estimated speed, torque-current limit with back-calculation."""
    T = p[F_PERIOD]
    step = p[F_RAMP] * T
    ref = s[S_SPEED_REF_RAMPED]
    ref += max(-step, min(step, s[S_SPEED_REF_CMD] - ref))
    s[S_SPEED_REF_RAMPED] = ref
    kp = p[F_KP_SPEED]
    ki = p[F_KI_SPEED]
    err = ref - s[S_OMEGA] * p[F_INV_POLE_PAIRS]
    s[S_INT_SPEED] += ki * T * err
    i_max = p[F_I_MAX]
    i_ref = kp * err + s[S_INT_SPEED]
    if i_ref > i_max or i_ref < -i_max:
        i_ref = max(-i_max, min(i_max, i_ref))
        s[S_INT_SPEED] = max(-i_max, min(i_max, i_ref - kp * err))
    return i_ref


@njit(cache=True, inline="always")
def _current_controller(s: np.ndarray, p: np.ndarray, i_xy: complex, i_ref: complex, vdc: float) -> complex:
    """PI per axis (zero cancels the winding pole), decoupling feed-forward, circle limit, anti-windup."""
    T = p[F_PERIOD]
    kp = p[F_KP_I]
    ki = p[F_KI_I]
    w = s[S_OMEGA]
    err = i_ref - i_xy
    int_x = s[S_INT_IX] + ki * T * err.real
    int_y = s[S_INT_IY] + ki * T * err.imag
    u_x = kp * err.real + int_x - w * p[F_LS] * i_ref.imag
    u_y = kp * err.imag + int_y + w * (p[F_LS] * i_ref.real + s[S_PSI])
    u_max = p[F_VOLTAGE_FRACTION] * vdc * (1.0 / SQRT3)
    mag = math.sqrt(u_x * u_x + u_y * u_y)
    if mag > u_max:
        u_x *= u_max / mag
        u_y *= u_max / mag
    else:                      # conditional integration: integrators move only while not saturated
        s[S_INT_IX] = int_x
        s[S_INT_IY] = int_y
    return complex(u_x, u_y)


@njit(cache=True, inline="always")
def firmware_step(s: np.ndarray, p: np.ndarray, i_a: float, i_b: float, vdc: float, t: float,
                  row: np.ndarray) -> None:
    """One control period. i_a, i_b: measured phase currents (A); vdc: measured DC link (V); t: drive
    clock (s, unused by the control law: it is time-invariant). Writes S_M_ALPHA/S_M_BETA and `row`."""
    i_c = -i_a - i_b
    i_ab = complex(i_a, (i_a + 2.0 * i_b) / SQRT3)
    trip = p[F_I_TRIP]
    if abs(i_a) > trip or abs(i_b) > trip or abs(i_c) > trip:
        s[S_FAULT] = FAULT_OVERCURRENT
    want_run = s[S_ENABLE_CMD] != 0.0 and s[S_FAULT] == 0.0
    if not want_run:
        if s[S_RUNNING] != 0.0:
            _stop(s)
        to_frame = complex(math.cos(s[S_THETA]), -math.sin(s[S_THETA]))
        s[S_TO_FRAME_RE] = to_frame.real
        s[S_TO_FRAME_IM] = to_frame.imag
        i_xy = i_ab * to_frame
        u_xy = complex(0.0, 0.0)
        i_ref = complex(0.0, 0.0)
    else:
        if s[S_RUNNING] == 0.0:
            _start(s, p, i_ab * complex(math.cos(s[S_THETA]), -math.sin(s[S_THETA])))
        i_xy = _update_estimators(s, p, i_ab)
        i_ref = complex(p[F_ISX_REF], _speed_controller(s, p))
        u_xy = _current_controller(s, p, i_xy, i_ref, vdc)
        # the command takes effect next period: rotate with the angle at the middle of that period
        advance = p[F_DELAY_COMP] * s[S_OMEGA] * p[F_PERIOD]
        from_frame = complex(s[S_TO_FRAME_RE], -s[S_TO_FRAME_IM]) * _small_rotation(advance)
        u_ab = u_xy * from_frame
        s[S_U_ALPHA_PREV] = s[S_U_ALPHA_LAST]
        s[S_U_BETA_PREV] = s[S_U_BETA_LAST]
        s[S_U_ALPHA_LAST] = u_ab.real
        s[S_U_BETA_LAST] = u_ab.imag
        comp = p[F_DEADTIME_COMP_V]
        if comp > 0.0:
            width = p[F_DEADTIME_COMP_WIDTH]
            e_a = comp * smooth_sign(i_a, width)
            e_b = comp * smooth_sign(i_b, width)
            e_c = comp * smooth_sign(i_c, width)
            u_ab += complex((2.0 * e_a - e_b - e_c) / 3.0, (e_b - e_c) / SQRT3)
        inv_vdc = 1.0 / max(vdc, 1.0)
        s[S_M_ALPHA] = u_ab.real * inv_vdc
        s[S_M_BETA] = u_ab.imag * inv_vdc

    row[C_SPEED_REF] = s[S_SPEED_REF_RAMPED] if want_run else 0.0
    row[C_SPEED_EST] = s[S_OMEGA] * p[F_INV_POLE_PAIRS]
    row[C_POS_EST] = s[S_THETA]
    row[C_FLUX_EST] = s[S_PSI]
    row[C_I_SX] = i_xy.real
    row[C_I_SY] = i_xy.imag
    row[C_I_SX_REF] = i_ref.real
    row[C_I_SY_REF] = i_ref.imag
    row[C_U_SX] = u_xy.real
    row[C_U_SY] = u_xy.imag
    row[C_TORQUE_EST] = 1.5 * p[F_POLE_PAIRS] * s[S_PSI] * i_xy.imag
    row[C_VDC] = vdc


def derive_gains(p: np.ndarray) -> None:
    """Recompute the derived slots from the model parameters and design targets.

    Speed PI: kp = J^ w_c / Kt^ (crossover w_c on the rigid shaft J^ s), Kt^ = 1.5 p psi_nominal, zero at
    a fraction of w_c. Current PIs: kp = Ls^ w_i, ki = Rs^ w_i, so the zero cancels the winding pole
    Rs/Ls and the closed current loop is first order with bandwidth w_i (plus the 1.5 T delay).
    """
    a1 = p[F_RS] / p[F_LS]
    p[F_A1] = a1
    p[F_A2] = 1.0 / p[F_LS]
    p[F_DECAY] = math.exp(-a1 * p[F_PERIOD])
    ratio = p[F_SPEED_EST_KI_OVER_KP]
    p[F_KI_W] = p[F_SPEED_EST_KP] * (ratio if ratio > 0.0 else a1)      # paper: ki_w / kp_w = a1
    p[F_KI_PSI] = p[F_FLUX_EST_KP] * p[F_FLUX_EST_KI_OVER_KP]
    torque_per_amp = 1.5 * p[F_POLE_PAIRS] * p[F_FLUX]
    p[F_KP_SPEED] = p[F_INERTIA] * p[F_SPEED_BW] / torque_per_amp
    p[F_KI_SPEED] = p[F_KP_SPEED] * p[F_SPEED_BW] * p[F_SPEED_ZERO_FRACTION]
    p[F_KP_I] = p[F_LS] * p[F_CURRENT_BW]
    p[F_KI_I] = p[F_RS] * p[F_CURRENT_BW]
    p[F_INV_POLE_PAIRS] = 1.0 / p[F_POLE_PAIRS]
    relax = p[F_FLUX_HOLD_RELAX_S]
    p[F_RELAX_FACTOR] = min(1.0, p[F_PERIOD] / relax) if relax > 0.0 else 0.0


# ---- test hooks (the lab firmware's debug objects) ----

def scale_flux_estimate(s: np.ndarray, factor: float) -> None:
    """psi^ <- factor * psi^ once; the integrator carries the step so the estimator must recover it."""
    psi = s[S_PSI]
    s[S_INT_PSI] += (factor - 1.0) * psi
    s[S_PSI] = factor * psi


def offset_angle_estimate(s: np.ndarray, offset_rad: float) -> None:
    """rho^ <- rho^ + offset once (initial position error)."""
    s[S_THETA] = (s[S_THETA] + offset_rad + math.pi) % (2.0 * math.pi) - math.pi


def new_state(initial_flux_wb: float) -> np.ndarray:
    s = np.zeros(N_STATE)
    s[S_PSI] = initial_flux_wb
    s[S_INT_PSI] = initial_flux_wb
    s[S_TO_FRAME_RE] = 1.0
    return s
