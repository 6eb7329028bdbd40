"""Criteria naming an instrument's record (`<instrument>:<signal>`), judged at its rate; the harmonic kinds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.inputs.capture_criteria import evaluate_on_records, judge_with_records
from bench.inputs.criteria import CriterionSpec, evaluate, parse_criteria
from drivers.contract.checks import Problems

FS = 50_000.0


def _record(seconds=0.2, t0=1.0):
    t = t0 + np.arange(int(seconds * FS)) / FS
    f_e = 50.0
    torque = 2.0 + 0.04 * np.sin(2 * np.pi * 6 * f_e * t + 0.3) + 0.01 * np.sin(2 * np.pi * 12 * f_e * t)
    current = 5.0 * np.sin(2 * np.pi * f_e * t) + 0.25 * np.sin(2 * np.pi * 5 * f_e * t) \
        + 0.15 * np.sin(2 * np.pi * 7 * f_e * t)
    return {"t_s": t, "torque_shaft_nm": torque, "i_a_a": current}


def _spec(kind, signal, window=(1.0, 1.2), limit=1.0, **params):
    return CriterionSpec(f"{kind} {signal}", kind, signal, window, limit, params)


def test_torque_ripple_per_order_and_current_thd_on_a_capture():
    records = {"scope": _record()}
    r6, r12, thd, factor, i5 = evaluate_on_records([
        _spec("harmonic_pct", "scope:torque_shaft_nm", fundamental_hz=50.0, order=6.0),
        _spec("harmonic_pct", "scope:torque_shaft_nm", fundamental_hz=50.0, order=12.0),
        _spec("thd_pct", "scope:i_a_a", fundamental_hz=50.0, limit=10.0),
        _spec("ripple_rms_pct", "scope:torque_shaft_nm", limit=2.0),
        _spec("harmonic_pct", "scope:i_a_a", fundamental_hz=50.0, order=5.0, of_fundamental=True, limit=4.0),
    ], records)
    assert r6.value == pytest.approx(2.0, rel=1e-3) and r6.status == "fail" and r6.unit == "%"
    assert r12.value == pytest.approx(0.5, rel=1e-3) and r12.status == "pass"
    assert thd.value == pytest.approx(100 * math.hypot(0.25, 0.15) / 5.0, rel=1e-3)
    assert factor.value == pytest.approx(100 * math.hypot(0.04, 0.01) / math.sqrt(2) / 2.0, rel=1e-3)
    assert i5.value == pytest.approx(5.0, rel=1e-3) and i5.status == "fail"
    assert "50000 S/s" in r6.detail


def test_a_rise_time_on_a_capture_is_resolved_to_its_samples():
    t = 0.25 + np.arange(12_500) / FS
    speed = np.clip((t - 0.3) / 0.02, 0.0, 1.0) * 20.0           # 0 -> 20 in 20 ms: 10-90 % in 16 ms
    [r] = evaluate_on_records([_spec("rise_time", "scope:speed", (0.3, 0.49), 0.042, target=20.0, from_value=0.0)],
                              {"scope": {"t_s": t, "speed": speed}})
    assert r.status == "pass" and r.value == pytest.approx(0.016, abs=2 / FS)


def test_what_the_record_does_not_give_is_not_judged_never_a_number():
    rec = _record()
    rec["i_a_a"][3000] = np.nan                                     # one clipped sample
    specs = [_spec("thd_pct", "scope:i_a_a", fundamental_hz=50.0),
             _spec("ripple_rms_pct", "daq:torque_shaft_nm"),
             _spec("ripple_rms_pct", "scope:flux_wb"),
             _spec("ripple_rms_pct", "scope:torque_shaft_nm", window=(0.5, 1.1))]
    results = evaluate_on_records(specs, {"scope": rec})
    assert [r.status for r in results] == ["not_judged"] * 4
    assert "1 samples over-range or clipped" in results[0].detail
    assert "no record from instrument 'daq'" in results[1].detail
    assert "records no such signal" in results[2].detail
    assert "starts at" in results[3].detail                       # the capture does not cover the window
    assert all(math.isnan(r.value) for r in results)


def test_the_scenario_order_is_kept_when_both_kinds_of_criteria_are_judged():
    t = np.arange(0, 2.0, 0.01)
    plain = _spec("mean", "speed_true_mech_rad_s", (0.5, 1.5), 0.1, expected=0.0)
    capture = _spec("ripple_rms_pct", "scope:torque_shaft_nm", limit=2.0)
    results = judge_with_records([capture, plain], lambda s: evaluate(s, t, {"speed_true_mech_rad_s": 0 * t}),
                                 {"scope": _record()})
    assert [r.name for r in results] == [capture.name, plain.name] and all(r.status == "pass" for r in results)


def test_a_scenario_may_name_an_instrument_signal_and_bad_names_are_one_line():
    p = Problems("s.toml")
    ok = parse_criteria(p, [("criteria[0]", {"name": "a", "kind": "harmonic_pct", "signal": "scope:torque_shaft_nm",
                                             "window_s": [1.0, 1.2], "limit": 1.0, "fundamental_hz": 50.0,
                                             "order": 6})], 2.0)
    assert ok and ok[0].signal == "scope:torque_shaft_nm" and not p.lines
    bad = Problems("s.toml")
    parse_criteria(bad, [("criteria[0]", {"name": "b", "kind": "harmonic_pct", "signal": "Scope:x y",
                                          "window_s": [1.0, 1.2], "limit": 1.0, "order": 6})], 2.0)
    lines = bad.lines
    assert any("criteria[0].signal: unknown signal" in line for line in lines)
    assert any("criteria[0].fundamental_hz: missing" in line for line in lines)


def _analyser(p_in=1000.0, p_out=900.0, n=6):
    return {"t_s": 2.0 + 0.1 * np.arange(n), "p_dc_w": np.full(n, p_in), "p_shaft_w": np.full(n, p_out)}


class _Ch:
    def __init__(self, signal, rng):
        self.signal, self.unit, self.range, self.scale, self.channel = signal, "W", rng, 1.0, signal


class _Analyser:
    name, kind, accuracy_reading_pct, accuracy_range_pct = "analyser", "power_analyser", 0.1, 0.1
    channels = (_Ch("p_dc_w", 3000.0), _Ch("p_shaft_w", 4000.0))


def test_losses_and_efficiency_with_the_analysers_uncertainty_budget_and_an_indicative_class():
    window = (2.0, 2.5)
    loss, eff, unstated = evaluate_on_records([
        _spec("loss_w", "analyser:p_dc_w", window, 110.0, output="analyser:p_shaft_w", reference_loss_w=120.0),
        _spec("loss_pct", "analyser:p_dc_w", window, 10.5, output="analyser:p_shaft_w"),
        _spec("loss_w", "analyser:p_dc_w", window, 110.0, output="analyser:p_shaft_w"),
    ], {"analyser": _analyser()}, [_Analyser()])
    u_in, u_out = 0.001 * 1000 + 0.001 * 3000, 0.001 * 900 + 0.001 * 4000     # 4.0 W and 4.9 W
    assert loss.value == pytest.approx(100 + u_in + u_out) and loss.unit == "W" and loss.status == "pass"
    assert "±8.9 W" in loss.detail and "IES1 indicative" in loss.detail and "not a certification" in loss.detail
    assert eff.value == pytest.approx(10 + 100 * 0.9 * (u_in / 1000 + u_out / 900))
    assert eff.status == "fail"          # 10 % measured, below 10.5 %, but not shown to be: +0.85 points of budget
    [bare] = evaluate_on_records([_spec("loss_w", "analyser:p_dc_w", window, 110.0, output="analyser:p_shaft_w")],
                                 {"analyser": _analyser()}, [])
    assert bare.status == "not_judged" and "accuracy_reading_pct" in bare.detail


def test_thd_measures_its_fundamental_when_none_is_given():
    [r] = evaluate_on_records([_spec("thd_pct", "scope:i_a_a", limit=10.0)], {"scope": _record()})
    assert r.value == pytest.approx(100 * math.hypot(0.25, 0.15) / 5.0, rel=2e-3) and "of 50 Hz" in r.detail


def test_a_cdms_losses_sum_the_output_elements_and_their_uncertainty():
    rec = _analyser()
    rec["p_a_w"], rec["p_b_w"] = rec["p_shaft_w"] / 2, rec["p_shaft_w"] / 2
    chans = (_Ch("p_dc_w", 3000.0), _Ch("p_a_w", 750.0), _Ch("p_b_w", 750.0))
    inst = type("A", (), {"name": "analyser", "kind": "power_analyser", "accuracy_reading_pct": 0.1,
                          "accuracy_range_pct": 0.1, "channels": chans})()
    [r] = evaluate_on_records([_spec("loss_w", "analyser:p_dc_w", (2.0, 2.5), 200.0, output="analyser:p_a_w",
                                     output_2="analyser:p_b_w")], {"analyser": rec}, [inst])
    u = (0.001 * 1000 + 3.0) + 2 * (0.001 * 450 + 0.75)
    assert r.value == pytest.approx(100 + u) and "(2 elements)" in r.detail
