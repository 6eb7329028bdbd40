"""Averaged three-leg two-phase inverter (legs: a = main winding, b = auxiliary winding, c = common point)
and the ADCs that measure the winding currents and the DC-link voltage.

Leg x puts u_x = d_x * V_dc (to the negative rail) on its terminal, averaged over a PWM period; the winding
voltages are v_sd = u_a - u_c, v_sq = u_b - u_c. Dead time and device drop make each leg lose
(V_dc * t_dead * f_pwm + V_drop) against the sign of its output current (fading linearly within +-`i_band`, where the
ripple current crosses zero). With the gates off a leg's free-wheeling diodes clamp it to the rail the
current flows into: u_x = 0 for i_x > 0, u_x = V_dc for i_x < 0.
Leg currents (out of the leg): i_a = i_sd, i_b = i_sq, i_c = -(i_sd + i_sq).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

I_VDC, I_DEADTIME_S, I_FPWM, I_VDROP, I_IBAND, I_NOISE_I, I_LSB_I, I_NOISE_VDC, I_LSB_VDC = range(9)
N_INV_PARAMS = 9


@njit(cache=True, inline="always")
def _leg_loss(i, p):
    loss = p[I_VDC] * p[I_DEADTIME_S] * p[I_FPWM] + p[I_VDROP]
    if loss == 0.0:
        return 0.0
    return loss * min(max(i / p[I_IBAND], -1.0), 1.0)


@njit(cache=True, inline="always")
def winding_voltages(da, db, dc, isd, isq, gates_off, p):
    """Averaged (v_sd, v_sq) over the next control period from the duties and the currents at its start."""
    vdc = p[I_VDC]
    ic = -(isd + isq)
    if gates_off:
        ua = 0.0 if isd > 0.0 else vdc
        ub = 0.0 if isq > 0.0 else vdc
        uc = 0.0 if ic > 0.0 else vdc
        return ua - uc, ub - uc
    ua = da * vdc - _leg_loss(isd, p)
    ub = db * vdc - _leg_loss(isq, p)
    uc = dc * vdc - _leg_loss(ic, p)
    return ua - uc, ub - uc


@njit(cache=True, inline="always")
def adc(value, noise, sigma, lsb):
    """One ADC conversion: additive Gaussian noise (pre-drawn standard normal `noise`) and quantisation."""
    v = value + sigma * noise
    if lsb > 0.0:
        v = lsb * math.floor(v / lsb + 0.5)
    return v


def inverter_params(inv: dict, meas: dict) -> np.ndarray:
    p = np.zeros(N_INV_PARAMS)
    p[I_VDC] = inv["vdc_v"]
    p[I_DEADTIME_S] = inv["dead_time_s"]
    p[I_FPWM] = inv["pwm_frequency_hz"]
    p[I_VDROP] = inv["device_drop_v"]
    p[I_IBAND] = inv["zero_crossing_band_a"]
    p[I_NOISE_I] = meas["current_noise_a"]
    p[I_LSB_I] = meas["current_lsb_a"]
    p[I_NOISE_VDC] = meas["vdc_noise_v"]
    p[I_LSB_VDC] = meas["vdc_lsb_v"]
    return p
