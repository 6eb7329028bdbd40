"""The truths a lab derives from its instruments, measured on the simulated rig through SCPI (the bench's drivers,
pyvisa over TCP) and compared with the simulator's own: the issue's agreement figures."""

from __future__ import annotations

import contextlib
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from bench.inputs.benchconfig import load_bench_config
from bench.run.rig_truths import align, power_flow, spim_field_flux, stator_flux, wrap
from drivers.instruments import open_instrument
from sim_backend.instruments import InstrumentSpec
from sim_backend.lab_rig import LabSpec
from sim_backend.rig import RigSpec, build

REPO = Path(__file__).resolve().parents[2]
NAMES = (("power_analyser", "analyser"), ("scope", "scope"))


@contextlib.contextmanager
def rig_of(kind: str, lab: LabSpec = LabSpec(), seed: int = 11):
    cfg = load_bench_config(REPO / f"config/benches/sim-{kind}-instruments.toml")
    spec = RigSpec(motor=REPO / f"config/motors/{kind}-paper.toml", seed=seed, instruments=InstrumentSpec(), lab=lab,
                   instrument_names=NAMES)
    with build(spec) as rig:
        truth = []
        rig.device.model.listeners.append(truth.append)
        yield rig, cfg.with_overrides({"instruments": rig.overrides["instruments"]}), truth


def _capture(rig, cfg, seconds: float, rate: float = 50_000.0, after: int | None = None):
    entry = next(i for i in cfg.instruments if i.name == "scope")
    scope = open_instrument(replace(entry, sample_rate_hz=rate))
    try:
        scope.arm(seconds, pretrigger=0.0)
        scope.force()
        with rig.device.lock:
            rig.device.advance(after or round(seconds / rig.device.model.control_period_s) + 10)
        scope.wait(2.0)
        return scope.fetch()
    finally:
        scope.close()


def _truth(blocks, name):
    return np.concatenate([b.t_s for b in blocks]), np.concatenate([getattr(b, name) for b in blocks])


@pytest.mark.parametrize("seed", [11, 12])
def test_encoder_alignment_and_magnet_flux_from_the_open_circuit_back_emf(seed):
    with rig_of("pmsm", seed=seed) as (rig, cfg, truth):
        model = rig.device.model
        with rig.device.lock:                      # drive disabled; the dynamometer spins the shaft, then lets it coast
            model.set_load(0, -0.25, True)
            rig.device.advance(4000)
            model.set_load(0, 0.0, False)
            rig.device.advance(100)
        t_start = model.time_s
        cap = _capture(rig, cfg, 0.25)
        index_true = [s for s in rig.servers[1].instrument._index_t if t_start <= s <= t_start + 0.25]
        t_true, angle_true = _truth(truth, "angle_elec_rad")
        flux_true = float(truth[-1].flux_wb[-1])
    result = align(cap.t_s, cap.signals["u_a_v"], cap.signals["encoder_index_v"])
    # the simulator's rotor angle at the instants the index passed
    unwrapped = np.unwrap(angle_true)                  # a row's true angle is at its period's start
    at_index = wrap(np.interp(index_true, t_true - 1e-4, unwrapped))
    expected = math.atan2(np.mean(np.sin(at_index)), np.mean(np.cos(at_index)))
    error = abs(float(wrap(result.theta_index_elec_rad - expected)))
    assert result.edges >= 2
    assert error < 0.05, (error, result)                # the position-error agreement
    assert error <= result.uncertainty_rad + 0.01       # and within what the step states
    assert result.flux_wb == pytest.approx(flux_true, rel=0.02)
    print(f"RESULT alignment_error_rad={error:.4f} stated_uncertainty_rad={result.uncertainty_rad:.4f} "
          f"flux_error_pct={100 * (result.flux_wb / flux_true - 1):.3f}")


def test_spim_stator_flux_from_measured_voltages_and_currents():
    with rig_of("spim") as (rig, cfg, truth):
        rig.device.model.set_load(0, 0.2, True)
        with rig.device.lock:
            for word in (0x06, 0x07, 0x0F):
                rig.device.write_controlword(word)
            rig.device.target_speed_mech_rad_s = 100.0
            rig.device.advance(15_000)
        cap = _capture(rig, cfg, 0.2)
        flux_true = truth[-1].flux_wb
    from sim_backend.drive import load_motor_config
    plant = load_motor_config(REPO / "config/motors/spim-paper.toml")["plant"]
    rs = {"main": plant["rsd_ohm"], "aux": plant["rsq_ohm"]}
    psi_d = stator_flux(cap.t_s, cap.signals["u_main_v"], cap.signals["i_main_a"], rs["main"])
    psi_q = stator_flux(cap.t_s, cap.signals["u_aux_v"], cap.signals["i_aux_a"], rs["aux"])
    field = spim_field_flux(psi_d, psi_q, cap.signals["i_aux_a"], plant["lsd_h"], plant["lsq_h"], plant["msrd_h"],
                            plant["msrq_h"])
    measured = float(np.mean(np.abs(field)))
    true = float(np.mean(flux_true))
    assert measured == pytest.approx(true, rel=0.02), (measured, true)
    print(f"RESULT spim_flux_error_pct={100 * (measured / true - 1):.3f}")


def test_efficiency_from_the_analyser_against_the_plants_power():
    with rig_of("pmsm") as (rig, cfg, truth):
        entry = next(i for i in cfg.instruments if i.name == "analyser")
        analyser = open_instrument(entry)
        try:
            with rig.device.lock:
                for word in (0x06, 0x07, 0x0F):
                    rig.device.write_controlword(word)
                rig.device.target_speed_mech_rad_s = 200.0
                rig.device.model.set_load(0, 3.0, True)
                rig.device.advance(20_000)
            r = analyser.poll().values
        finally:
            analyser.close()
        window = truth[-1:]
    # the plant's own powers over the analyser's last update interval (100 ms = the last 1000 periods)
    u = np.concatenate([b.u_v for b in truth])[-1000:]
    i = np.concatenate([b.i_a for b in truth])[-1000:]
    w = np.concatenate([b.speed_mech_rad_s for b in truth])[-1000:]
    tq = np.concatenate([b.torque_shaft_nm for b in truth])[-1000:]
    eff_true = 100 * float(np.mean(w * tq)) / float(np.mean(np.sum(u * i, axis=1)))
    flow = power_flow(r["p_dc_w"], r["p_a_w"] + r["p_b_w"] + r["p_c_w"], r["p_shaft_w"])
    assert abs(flow.motor_efficiency_pct - eff_true) < 0.5, (flow, eff_true)
    assert flow.motor_loss_w > 0
    assert window
    print(f"RESULT efficiency_error_points={flow.motor_efficiency_pct - eff_true:.3f} eff_true_pct={eff_true:.2f}")
