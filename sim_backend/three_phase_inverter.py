"""Averaged three-phase voltage source inverter and the drive's current/DC-link measurement (ADC).

Space vectors use the amplitude-invariant Clarke transform (alpha = phase a), as the PMSM paper does.
Everything here is a small numba function so the drive kernels can inline it; randomness is never drawn
here: callers pass pre-drawn standard-normal samples from their own seeded numpy Generator.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from sim_backend.numerics import smooth_sign

SQRT3 = math.sqrt(3.0)


@njit(cache=True, inline="always")
def clarke(i_a: float, i_b: float) -> tuple[float, float]:
    """(alpha, beta) from two phase quantities of a three-wire (zero-sum) system."""
    return i_a, (i_a + 2.0 * i_b) / SQRT3


@njit(cache=True, inline="always")
def inverse_clarke(x_alpha: float, x_beta: float) -> tuple[float, float, float]:
    """(a, b, c) phase quantities of an alpha-beta vector (no zero sequence)."""
    b = -0.5 * x_alpha + 0.5 * SQRT3 * x_beta
    c = -0.5 * x_alpha - 0.5 * SQRT3 * x_beta
    return x_alpha, b, c


@njit(cache=True, inline="always")
def limit_to_linear_range(u_alpha: float, u_beta: float, vdc: float) -> tuple[float, float]:
    """Clamp a voltage vector to the circle inscribed in the SVPWM hexagon, |u| <= vdc/sqrt(3)."""
    u_max = vdc / SQRT3
    mag = math.sqrt(u_alpha * u_alpha + u_beta * u_beta)
    if mag > u_max and mag > 0.0:
        scale = u_max / mag
        return u_alpha * scale, u_beta * scale
    return u_alpha, u_beta


@njit(cache=True, inline="always")
def switching_error_voltage(i_alpha: float, i_beta: float, vdc: float, dead_time_s: float, period_s: float,
                            device_drop_v: float, current_width_a: float) -> tuple[float, float]:
    """Average alpha-beta voltage lost to dead time and device drops: each phase loses
    (vdc * t_dead / T_pwm + V_drop) * sign(i_phase); the common mode does not reach a Y winding."""
    if dead_time_s <= 0.0 and device_drop_v <= 0.0:
        return 0.0, 0.0
    per_phase = vdc * dead_time_s / period_s + device_drop_v
    i_a, i_b, i_c = inverse_clarke(i_alpha, i_beta)
    e_a = -per_phase * smooth_sign(i_a, current_width_a)
    e_b = -per_phase * smooth_sign(i_b, current_width_a)
    e_c = -per_phase * smooth_sign(i_c, current_width_a)
    return (2.0 * e_a - e_b - e_c) / 3.0, (e_b - e_c) / SQRT3


def adc_lsb(bits: int, full_scale: float, bipolar: bool) -> float:
    """Size of one ADC step; 0.0 for bits <= 0 (ideal converter)."""
    if bits <= 0:
        return 0.0
    return (2.0 if bipolar else 1.0) * full_scale / 2 ** bits


@njit(cache=True, inline="always")
def adc_sample(value: float, noise_std: float, normal_draw: float, lsb: float, full_scale: float,
               bipolar: bool) -> float:
    """One ADC conversion: additive Gaussian noise, clipping to the range, rounding to the LSB.

    lsb <= 0 means an ideal converter (no quantisation, no clipping).
    """
    x = value + noise_std * normal_draw
    if lsb <= 0.0:
        return x
    low = -full_scale if bipolar else 0.0
    x = max(low, min(full_scale - lsb, x))
    return math.floor(x / lsb + 0.5) * lsb


def draw_measurement_noise(rng: np.random.Generator, n: int, channels: int) -> np.ndarray:
    """Pre-drawn standard normals for n control periods (one column per ADC channel)."""
    return rng.standard_normal((n, channels))
