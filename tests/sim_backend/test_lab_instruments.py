"""The simulated power analyser and scope, spoken to over SCPI on TCP through the bench's own drivers (pyvisa-py)."""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from bench.inputs.benchconfig import load_bench_config
from drivers.instruments import InstrumentError, open_instrument
from sim_backend.instruments import InstrumentSpec
from sim_backend.lab_rig import LabSpec
from sim_backend.rig import RigSpec, build, make_model
from sim_backend.terminals import TappedModel

REPO = Path(__file__).resolve().parents[2]
CFG = load_bench_config(REPO / "config/benches/sim-pmsm-instruments.toml")
NAMES = (("power_analyser", "analyser"), ("scope", "scope"))


@contextlib.contextmanager
def lab_rig(lab: LabSpec = LabSpec(reading_pct=0.0, range_pct=0.0), seed: int = 5):
    spec = RigSpec(motor=REPO / "config/motors/pmsm-paper.toml", seed=seed, instruments=InstrumentSpec(), lab=lab,
                   instrument_names=NAMES)
    with build(spec) as rig:
        yield rig, CFG.with_overrides({"instruments": rig.overrides["instruments"]})


def run_at(device, speed: float, load_nm: float, periods: int) -> None:
    with device.lock:
        for word in (0x06, 0x07, 0x0F):
            device.write_controlword(word)
        device.target_speed_mech_rad_s = speed
        device.model.set_load(0, load_nm, True)
        device.advance(periods)


def instrument(cfg, name, **changes):
    entry = next(i for i in cfg.instruments if i.name == name)
    return open_instrument(replace(entry, **changes))


def test_tapping_the_terminals_leaves_the_telemetry_bit_for_bit():
    plain, tapped = make_model(REPO / "config/motors/pmsm-paper.toml", 9), \
        TappedModel(make_model(REPO / "config/motors/pmsm-paper.toml", 9))
    seen = []
    tapped.listeners.append(seen.append)
    for m in (plain, tapped):
        m.set_enabled(True)
        m.set_speed_ref(120.0)
    a = np.concatenate([plain.step(100) for _ in range(20)])
    b = np.concatenate([tapped.step(100) for _ in range(20)])
    assert np.array_equal(a, b, equal_nan=True)
    assert sum(t.t_s.size for t in seen) == 2000


def test_analyser_power_balance_and_efficiency_over_scpi():
    with lab_rig() as (rig, cfg):
        analyser = instrument(cfg, "analyser")
        try:
            assert analyser.identity.startswith("YOKOGAWA,WT")
            run_at(rig.device, 150.0, 2.0, 12_000)
            r = analyser.poll()
        finally:
            analyser.close()
    v = r.values
    assert not r.not_judged
    p_motor = v["p_a_w"] + v["p_b_w"] + v["p_c_w"]
    # the simulated inverter is ideal (no dead time, no drops): DC-link power is the terminal power
    assert p_motor == pytest.approx(v["p_dc_w"], rel=2e-3)
    assert v["p_shaft_w"] == pytest.approx(v["speed_shaft_mech_rad_s"] * v["torque_shaft_nm"], rel=1e-4)
    assert v["torque_shaft_nm"] == pytest.approx(2.0, abs=0.02)
    assert v["eff_motor_pct"] == pytest.approx(100 * v["p_shaft_w"] / p_motor, abs=0.01)
    assert 80.0 < v["eff_motor_pct"] < 99.0            # copper losses of a 3.6 ohm winding at 2 N*m
    # f: three pole pairs at the shaft's speed
    assert v["f_elec_hz"] == pytest.approx(3 * v["speed_shaft_mech_rad_s"] / (2 * math.pi), rel=0.01), v
    assert v["u_dc_v"] == pytest.approx(540.0, abs=0.01)


def test_analyser_accuracy_is_within_its_stated_spec():
    readings = []
    for lab in (LabSpec(reading_pct=0.0, range_pct=0.0), LabSpec(reading_pct=0.05, range_pct=0.05)):
        with lab_rig(lab) as (rig, cfg):
            analyser = instrument(cfg, "analyser")
            run_at(rig.device, 150.0, 2.0, 12_000)
            readings.append(analyser.poll().values)
            analyser.close()
    exact, real = readings
    assert exact["p_a_w"] != real["p_a_w"]
    for signal, rng in (("p_a_w", 150.0 * 5.0), ("u_a_rms_v", 150.0), ("i_a_rms_a", 5.0)):
        assert abs(real[signal] - exact[signal]) <= 0.0005 * abs(exact[signal]) + 0.0005 * rng + 1e-6


def test_an_overloaded_element_is_not_judged_never_a_number():
    with lab_rig() as (rig, cfg):
        entry = next(i for i in cfg.instruments if i.name == "analyser")
        small = tuple(replace(c, range=0.5) if c.channel == "I1" else c for c in entry.channels)
        analyser = open_instrument(replace(entry, channels=small))
        try:
            run_at(rig.device, 150.0, 2.0, 12_000)
            r = analyser.poll()
        finally:
            analyser.close()
    for signal in ("i_a_rms_a", "p_a_w", "lambda_a"):
        assert math.isnan(r.values[signal]) and "over-range" in r.not_judged[signal]
    assert not math.isnan(r.values["p_b_w"])


def test_scope_capture_four_channels_at_50_khz_with_pretrigger():
    with lab_rig() as (rig, cfg):
        scope = instrument(cfg, "scope")
        try:
            run_at(rig.device, 150.0, 1.0, 10_000)
            scope.arm(0.05, pretrigger=0.2)
            t_force = rig.device.model.time_s
            scope.force()
            with rig.device.lock:
                rig.device.advance(600)
            scope.wait(2.0)
            cap = scope.fetch()
        finally:
            scope.close()
    assert cap.sample_rate_hz == pytest.approx(50_000.0)
    assert cap.t_s.size == 2500 and cap.t_s[0] == pytest.approx(-0.01)
    assert not cap.not_judged and len(cap.signals) >= 4
    ia, ib = cap.signals["i_a_a"], cap.signals["i_b_a"]
    # a balanced star: i_a + i_b + i_c = 0, and the phase currents are 120 degrees apart at f = 3 x 150 / 2 pi
    spectrum = np.abs(np.fft.rfft(ia * np.hanning(ia.size)))
    f = np.fft.rfftfreq(ia.size, 1 / cap.sample_rate_hz)[np.argmax(spectrum)]
    assert f == pytest.approx(3 * 150.0 / (2 * math.pi), abs=20.0)
    assert np.corrcoef(ia, ib)[0, 1] == pytest.approx(-0.5, abs=0.05)
    assert t_force == pytest.approx(1.0)


def test_a_clipped_scope_channel_is_not_judged():
    with lab_rig() as (rig, cfg):
        entry = next(i for i in cfg.instruments if i.name == "scope")
        small = tuple(replace(c, range=0.2) if c.channel == "CHAN3" else c for c in entry.channels)
        scope = open_instrument(replace(entry, channels=small))
        try:
            run_at(rig.device, 150.0, 2.0, 10_000)
            scope.arm(0.02)
            scope.force()
            with rig.device.lock:
                rig.device.advance(300)
            scope.wait(2.0)
            cap = scope.fetch()
        finally:
            scope.close()
    assert "over-range" in cap.not_judged["i_a_a"] and np.isnan(cap.signals["i_a_a"]).any()
    assert "i_b_a" not in cap.not_judged


# ---- faults: one clear line, bounded in time, never a number ----

def _timed(fn):
    t0 = time.monotonic()
    with pytest.raises(InstrumentError) as err:
        fn()
    return str(err.value), time.monotonic() - t0


def test_a_silent_instrument_is_one_line_within_its_timeout():
    with lab_rig() as (rig, cfg):
        rig.servers[0].quirks.silent = True
        line, took = _timed(lambda: instrument(cfg, "analyser", timeout_s=0.3))
    assert "'analyser'" in line and "no answer within 0.3 s" in line and "\n" not in line
    assert took < 2.0


def test_an_instrument_answering_garbage_is_one_line():
    with lab_rig() as (rig, cfg):
        analyser = instrument(cfg, "analyser")
        rig.servers[0].quirks.garbage = True
        line, _ = _timed(analyser.poll)
        analyser.close()
    assert "garbage" in line and "'analyser'" in line


def test_an_error_left_in_the_queue_refuses_the_configuration():
    with lab_rig() as (rig, cfg):
        rig.servers[1].instrument.errors.append('-310,"System error: calibration lost"')
        # *CLS clears the queue first: the error must come from the configuration itself
        entry = next(i for i in cfg.instruments if i.name == "scope")
        bad = replace(entry, sample_rate_hz=5e6)          # beyond the scope's 1 MS/s
        line, _ = _timed(lambda: open_instrument(bad))
    assert "error after configuration" in line and "sample rate" in line


def test_a_connection_dropped_mid_run_is_one_line():
    with lab_rig() as (rig, cfg):
        analyser = instrument(cfg, "analyser", timeout_s=0.5)
        run_at(rig.device, 100.0, 0.0, 2000)
        analyser.poll()
        rig.servers[0].quirks.drop_after = 0
        line, took = _timed(analyser.poll)
        analyser.close()
    assert "'analyser'" in line and took < 2.0


def test_slow_answers_are_waited_for_within_the_timeout():
    with lab_rig(LabSpec(reading_pct=0.0, range_pct=0.0, slow_s=0.05)) as (rig, cfg):
        analyser = instrument(cfg, "analyser", timeout_s=1.0)
        run_at(rig.device, 100.0, 0.0, 2000)
        assert analyser.poll().values["u_dc_v"] == pytest.approx(540.0)
        analyser.close()
