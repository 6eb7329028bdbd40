"""Physics of the asymmetric single-phase induction machine plant (SPIM paper eqs. 1-9) and its integration."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from drivers.contract.signals import SIGNAL_INDEX as SI
from sim_backend.mechanics import LOAD_BRAKE
from sim_backend.spim import plant as pl
from sim_backend.spim.model import SpimDrive

CONFIG = Path(__file__).resolve().parents[2] / "config/motors/spim-paper.toml"
CFG = tomllib.loads(CONFIG.read_text())
W50 = 2 * math.pi * 50.0


def params(symmetric: bool = False, inertia: float | None = None, friction: float | None = None) -> np.ndarray:
    plant = dict(CFG["plant"], pole_pairs=CFG["motor"]["pole_pairs"])
    mech = dict(CFG["mechanics"])
    if symmetric:
        plant.update(rsq_ohm=plant["rsd_ohm"], lsq_h=plant["lsd_h"], msrq_h=plant["msrd_h"])
    if inertia is not None:
        mech["inertia_kgm2"] = inertia
    if friction is not None:
        mech["viscous_nm_s_rad"] = friction
    return pl.plant_params(plant, mech, {})


def simulate(p, voltage, t_end, dt=1e-4, substeps=2, x0=None):
    """Open-loop plant fed by voltage(t) held over each dt; returns times, states (before each step) and volts."""
    x = np.zeros(pl.N_PLANT_STATE) if x0 is None else x0.copy()
    n = int(round(t_end / dt))
    xs, vs = np.zeros((n + 1, pl.N_PLANT_STATE)), np.zeros((n, 2))
    xs[0] = x
    for k in range(n):
        vs[k] = voltage((k + 0.5) * dt)  # held over the step: sample its middle (no half-step lag)
        pl.advance(x, p, vs[k, 0], vs[k, 1], dt, substeps, False)
        xs[k + 1] = x
    return np.arange(n + 1) * dt, xs, vs


def currents_of(xs, p):
    return np.array([pl.currents(x[0], x[1], x[2], x[3], p, False, False) for x in xs])


def test_power_balance_on_the_asymmetric_plant():
    """Electrical input = copper losses + d/dt magnetic energy + mechanical power (here: into J and friction)."""
    p = params()
    dt = 2e-5
    t, xs, vs = simulate(p, lambda t: (200 * math.cos(W50 * t), 150 * math.sin(W50 * t + 0.3)), 0.3, dt, 4)
    i = currents_of(xs, p)
    p_cu = p[pl.P_RSD] * i[:, 0] ** 2 + p[pl.P_RSQ] * i[:, 1] ** 2 + p[pl.P_RR] * (i[:, 2] ** 2 + i[:, 3] ** 2)
    wm = xs[:, pl.X_WM]
    te = p[pl.P_NP] * (p[pl.P_MSRQ] * i[:, 1] * i[:, 2] - p[pl.P_MSRD] * i[:, 0] * i[:, 3])
    p_mech = te * wm
    w_mag = np.array([pl.magnetic_energy(x, p) for x in xs])

    def integral(y):  # trapezoid per step (voltage constant within a step, currents smooth)
        return np.sum(0.5 * (y[1:] + y[:-1])) * dt

    e_in = np.sum(vs[:, 0] * 0.5 * (i[1:, 0] + i[:-1, 0]) + vs[:, 1] * 0.5 * (i[1:, 1] + i[:-1, 1])) * dt
    e_out = integral(p_cu) + (w_mag[-1] - w_mag[0]) + integral(p_mech)
    assert wm[-1] > 10.0, "the machine should have started"
    assert abs(e_in - e_out) / e_in < 2e-4   # measured 1.4e-5
    # and the mechanical side: integral of T_e w = kinetic energy + friction losses
    e_kin = 0.5 * p[pl.P_J] * wm[-1] ** 2
    e_fric = integral(p[pl.P_FRICTION] * wm ** 2)
    assert abs(integral(p_mech) - e_kin - e_fric) / e_kin < 2e-3


def phasor(signal, t, w):
    """Complex amplitude of the w component of a steady periodic signal sampled over whole periods."""
    return 2.0 * np.mean(signal * np.exp(-1j * w * t))


@pytest.mark.parametrize("axis", ["d", "q"])
def test_locked_rotor_steady_state_matches_each_winding_phasor(axis):
    p = params(inertia=1e9)  # locked rotor: each winding is a transformer with a shorted secondary
    v_amp = 100.0
    _, xs, _ = simulate(p, lambda t: (v_amp * math.cos(W50 * t), v_amp * math.sin(W50 * t)), 0.4, 1e-4, 2)
    t = np.arange(len(xs)) * 1e-4
    last = slice(len(xs) - 2000, len(xs))  # last 0.2 s = 10 periods
    i = currents_of(xs[last], p)
    rs, ls, m = ((p[pl.P_RSD], p[pl.P_LSD], p[pl.P_MSRD]) if axis == "d" else (p[pl.P_RSQ], p[pl.P_LSQ], p[pl.P_MSRQ]))
    z = rs + 1j * W50 * ls + (W50 * m) ** 2 / (p[pl.P_RR] + 1j * W50 * p[pl.P_LR])
    v_ph = v_amp if axis == "d" else -1j * v_amp
    expected = v_ph / z
    got = phasor(i[:, 0 if axis == "d" else 1], t[last], W50)
    assert abs(got - expected) / abs(expected) < 2e-3
    assert abs(xs[-1, pl.X_WM]) < 1e-6


def test_no_load_runs_at_synchronous_speed():
    """Equal windings, balanced voltages, no load, no friction: the rotor reaches omega_s / n_p."""
    p = params(symmetric=True, friction=0.0)
    _, xs, _ = simulate(p, lambda t: (250 * math.cos(W50 * t), 250 * math.sin(W50 * t)), 1.5, 1e-4, 2)
    sync = W50 / p[pl.P_NP]
    assert abs(xs[-1, pl.X_WM] - sync) / sync < 1e-4


def test_no_load_asymmetric_machine_with_forward_field_voltages_runs_synchronously():
    """Asymmetric windings fed with the voltages of a pure forward field (balanced currents in the variables of
    eq. 10): at synchronous speed the rotor carries no current and no torque, and the rotor gets there."""
    p = params(friction=0.0)
    k = p[pl.P_MSRD] / p[pl.P_MSRQ]
    i_amp = 6.0
    i_d = i_amp                                    # i_sd = I cos(wt)
    i_q = -1j * i_amp * k                          # i_sq = k I sin(wt)
    # at synchronous speed, i_r = 0: v_s = (R_s + j w L_s) i_s on each axis
    v_d = (p[pl.P_RSD] + 1j * W50 * p[pl.P_LSD]) * i_d
    v_q = (p[pl.P_RSQ] + 1j * W50 * p[pl.P_LSQ]) * i_q

    def volts(t):
        e = np.exp(1j * W50 * t)
        return float((v_d * e).real), float((v_q * e).real)

    _, xs, _ = simulate(p, volts, 2.0, 1e-4, 2)
    sync = W50 / p[pl.P_NP]
    assert abs(xs[-1, pl.X_WM] - sync) / sync < 1e-4
    i = currents_of(xs[-200:], p)
    assert np.max(np.abs(i[:, 2:])) < 0.01 * i_amp


def torque_ripple_2ws(p):
    """Steady-state 2*omega_s torque amplitude and mean torque, rotor held at 1400 r/min, balanced voltages."""
    x0 = np.zeros(pl.N_PLANT_STATE)
    x0[pl.X_WM] = 1400 * 2 * math.pi / 60
    p = p.copy()
    p[pl.P_J] = 1e9
    _, xs, _ = simulate(p, lambda t: (200 * math.cos(W50 * t), 200 * math.sin(W50 * t)), 0.4, 1e-4, 2, x0)
    last = xs[-2000:]
    i = currents_of(last, p)
    te = p[pl.P_NP] * (p[pl.P_MSRQ] * i[:, 1] * i[:, 2] - p[pl.P_MSRD] * i[:, 0] * i[:, 3])
    t = np.arange(len(te)) * 1e-4
    return abs(phasor(te, t, 2 * W50)), float(te.mean())


def test_asymmetry_makes_torque_pulsate_at_twice_supply_frequency():
    ripple_asym, mean_asym = torque_ripple_2ws(params())
    ripple_sym, mean_sym = torque_ripple_2ws(params(symmetric=True))
    assert mean_asym > 1.0 and mean_sym > 1.0
    assert ripple_asym > 0.2 * mean_asym
    assert ripple_sym < 1e-3 * mean_sym


def closed_loop_metrics(substeps: int) -> dict[str, float]:
    cfg = tomllib.loads(CONFIG.read_text())
    cfg["plant"]["substeps"] = substeps
    d = SpimDrive.from_config(cfg, 3, noise=False)
    d.set_enabled(True)
    d.set_speed_ref(1500 * 2 * math.pi / 60)
    d.step(5000)
    d.set_load(LOAD_BRAKE, 4.0)
    out = d.step(5000)
    w = out[2500:]
    return {
        "speed_true": w[:, SI["speed_true_mech_rad_s"]].mean(),
        "speed_est": w[:, SI["speed_est_mech_rad_s"]].mean(),
        "flux_true": w[:, SI["flux_true_wb"]].mean(),
        "flux_est": w[:, SI["flux_est_wb"]].mean(),
        "i_sy": w[:, SI["i_sy_a"]].mean(),
        "i_sx": w[:, SI["i_sx_a"]].mean(),
        "torque_est": w[:, SI["torque_est_nm"]].mean(),
        "u_sy": w[:, SI["u_sy_v"]].mean(),
        "speed_true_rms": np.sqrt(np.mean(w[:, SI["speed_true_mech_rad_s"]] ** 2)),
    }


def test_halving_the_plant_step_changes_no_metric_by_more_than_0p1_percent():
    base = CFG["plant"]["substeps"]
    coarse, fine = closed_loop_metrics(base), closed_loop_metrics(2 * base)
    for name in coarse:
        assert abs(coarse[name] - fine[name]) <= 1e-3 * abs(fine[name]), (name, coarse[name], fine[name])
