"""PMSM plant physics: power balance, locked-rotor and short-circuit steady states, closed-loop no-load state."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.contract.signals import SIGNAL_INDEX as COL
from sim_backend.drive import load_motor_config, make_drive
from sim_backend.pmsm import plant as pl

CONFIG = "config/motors/pmsm-paper.toml"
RS, LS, PSI, P = 3.58356, 0.02, 0.2592772, 3


def plant_params(inertia: float = 1e-3, viscous: float = 2e-4) -> np.ndarray:
    p = np.zeros(pl.N_PARAMS)
    p[pl.P_RS], p[pl.P_LS], p[pl.P_FLUX] = RS, LS, PSI
    p[pl.P_INERTIA], p[pl.P_VISCOUS], p[pl.P_POLE_PAIRS] = inertia, viscous, P
    return p


def test_instantaneous_power_balance():
    """1.5 u.i = 1.5 Rs |i|^2 + d/dt(0.75 Ls |i|^2) + T_e w_mech, at random states."""
    rng = np.random.default_rng(5)
    a1, a2 = RS / LS, 1.0 / LS
    for _ in range(50):
        i_d, i_q, w = rng.normal(0, 3), rng.normal(0, 3), rng.normal(0, 100)
        angle = rng.uniform(-math.pi, math.pi)
        u_d, u_q = rng.normal(0, 200), rng.normal(0, 200)
        d = pl.derivatives((i_d, i_q, PSI * math.cos(angle), PSI * math.sin(angle), w), u_d, u_q,
                           (a1, a2, float(P), 1e3, 0.0, 0, 0.0))
        p_in = 1.5 * (u_d * i_d + u_q * i_q)
        copper = 1.5 * RS * (i_d ** 2 + i_q ** 2)
        magnetic = 1.5 * LS * (i_d * d[0] + i_q * d[1])
        torque = 1.5 * P * (PSI * math.cos(angle) * i_q - PSI * math.sin(angle) * i_d)
        assert p_in == pytest.approx(copper + magnetic + torque * w, rel=1e-9, abs=1e-9)


@pytest.mark.slow
def test_integrated_energy_balance():
    """Energy over 0.2 s of a run with a rotating voltage: input = copper + magnetic + kinetic + friction + load."""
    p = plant_params()
    x = pl.initial_state(PSI, 0.3)
    h, n = 1e-5, 20000
    load = 0.5
    e_in = copper = friction = load_work = 0.0
    w_mag0 = 0.75 * LS * (x[0] ** 2 + x[1] ** 2)
    e_kin0 = 0.5 * p[pl.P_INERTIA] * x[pl.X_W_MECH] ** 2
    for k in range(n):
        t = k * h
        u_d, u_q = 60.0 * math.cos(120.0 * t), 60.0 * math.sin(120.0 * t)
        before = x.copy()
        pl.advance(x, p, u_d, u_q, 0, load, h, 1)
        i2 = 0.5 * (before[0] ** 2 + before[1] ** 2 + x[0] ** 2 + x[1] ** 2)
        e_in += 1.5 * h * 0.5 * (u_d * (before[0] + x[0]) + u_q * (before[1] + x[1]))
        copper += 1.5 * RS * h * i2
        w2 = 0.5 * (before[4] ** 2 + x[4] ** 2)
        friction += p[pl.P_VISCOUS] * w2 * h
        load_work += load * 0.5 * (before[4] + x[4]) * h
    magnetic = 0.75 * LS * (x[0] ** 2 + x[1] ** 2) - w_mag0
    kinetic = 0.5 * p[pl.P_INERTIA] * x[pl.X_W_MECH] ** 2 - e_kin0
    assert x[pl.X_W_MECH] > 10.0  # the machine really ran as a motor
    out = copper + magnetic + kinetic + friction + load_work
    assert e_in == pytest.approx(out, rel=2e-4)


def test_locked_rotor_step_response():
    """w = 0: i_D(t) = U/Rs (1 - exp(-t Rs/Ls)) exactly; the rotor flux does not move."""
    p = plant_params(inertia=1e12)
    x = pl.initial_state(PSI, 0.0)
    u = 10.0
    period = 1e-4
    for k in range(1, 601):
        pl.advance(x, p, u, 0.0, 0, 0.0, period, 1)
        expected = u / RS * (1.0 - math.exp(-k * period * RS / LS))
        assert x[pl.X_ID] == pytest.approx(expected, rel=1e-6)
    assert abs(x[pl.X_IQ]) < 1e-12
    assert x[pl.X_ID] == pytest.approx(u / RS, rel=1e-4)  # 60 ms = 10.7 time constants
    assert x[pl.X_PSI_D] == pytest.approx(PSI) and abs(x[pl.X_PSI_Q]) < 1e-12


def test_short_circuit_steady_state():
    """Shorted winding at constant speed: |i| = w_e psi / |Rs + j w_e Ls|, braking torque closed form."""
    p = plant_params(inertia=1e12, viscous=0.0)
    w_mech = 50.0
    x = pl.initial_state(PSI, 0.0)
    x[pl.X_W_MECH] = w_mech
    for _ in range(2000):  # 0.2 s = 36 electrical time constants
        pl.advance(x, p, 0.0, 0.0, 0, 0.0, 1e-4, 1)
    w_e = P * w_mech
    z = complex(RS, w_e * LS)
    i_mag = w_e * PSI / abs(z)
    assert math.hypot(x[pl.X_ID], x[pl.X_IQ]) == pytest.approx(i_mag, rel=1e-6)
    torque = float(pl.electromagnetic_torque(x, p))
    assert torque == pytest.approx(-1.5 * P * PSI * i_mag ** 2 * RS / (w_e * PSI), rel=1e-6)
    assert x[pl.X_W_MECH] == pytest.approx(w_mech, rel=1e-9)


def test_closed_loop_no_load_steady_state():
    """Drive at 100 mech rad/s, no load: i_sy = B w / Kt, u_sy = Rs i_sy + w_e psi, u_sx = -w_e Ls i_sy.

    10 s of settling: at w_e = 300 rad/s the flux estimator's slowest pole is about -1.1 1/s (design check).
    """
    cfg = load_motor_config(CONFIG)
    drive = make_drive(cfg, seed=0, noise=False)
    drive.set_enabled(True)
    drive.set_speed_ref(100.0)
    drive.step(100000)
    tail = drive.step(5000)
    b = cfg["mechanics"]["viscous_nm_s_rad"]
    w = tail[:, COL["speed_true_mech_rad_s"]].mean()
    assert w == pytest.approx(100.0, rel=1e-4)
    i_sy = tail[:, COL["i_sy_a"]].mean()
    assert i_sy == pytest.approx(b * w / (1.5 * P * PSI), rel=0.01)
    w_e = P * w
    assert tail[:, COL["u_sy_v"]].mean() == pytest.approx(RS * i_sy + w_e * PSI, rel=1e-3)
    assert tail[:, COL["u_sx_v"]].mean() == pytest.approx(-w_e * LS * i_sy, rel=0.02)
    assert abs(tail[:, COL["pos_err_elec_rad"]]).max() < 2e-4
    assert tail[:, COL["flux_est_wb"]].mean() == pytest.approx(PSI, rel=1e-4)


def test_noise_free_drive_is_mirror_symmetric():
    """Reflecting beta (speed, load torque and angle error change sign) mirrors every trajectory."""
    def run(sign: float) -> np.ndarray:
        drive = make_drive(CONFIG, seed=0, noise=False)
        drive.set_load(0, sign * 1.0)
        drive.set_hook("pos_est_offset_rad", sign * 0.7)
        drive.set_enabled(True)
        drive.set_speed_ref(sign * 15.0)
        return drive.step(5000)
    plus, minus = run(1.0), run(-1.0)
    for name in ("speed_true_mech_rad_s", "speed_est_mech_rad_s", "pos_err_elec_rad", "i_sy_a", "u_sy_v"):
        assert np.allclose(plus[:, COL[name]], -minus[:, COL[name]], rtol=1e-9, atol=1e-9), name
    for name in ("flux_est_wb", "i_sx_a", "u_sx_v"):
        assert np.allclose(plus[:, COL[name]], minus[:, COL[name]], rtol=1e-9, atol=1e-9), name
