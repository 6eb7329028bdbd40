"""A run on the instruments rig with its SCPI instruments: the analyser polled at its own rate on the drive clock,
the scope captured around the scenario's step and placed on the drive clock, faults one line and a safe stop."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from bench.run.orchestrator import run_scenario

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
STEP = REPO / "scenarios/rig/accept-speed-step.toml"
CAPTURE_RISE = """
[[criteria]]
name = "rise time 10-90 % of the step, judged on the scope's capture"
kind = "rise_time"
signal = "scope:speed_scope_mech_rad_s"
window_s = [0.3, 0.49]
target = 20.0
from_value = 0.0
limit = 0.042
"""


def _rise_time(t, x, t0, target, lo=0.1, hi=0.9):
    after = t >= t0
    t, x = t[after], x[after]
    t_lo = t[np.argmax(x >= lo * target)]
    t_hi = t[np.argmax(x >= hi * target)]
    return float(t_hi - t_lo)


@pytest.mark.parametrize("rig", ["pmsm", pytest.param("spim", marks=pytest.mark.slow)])
def test_a_run_records_the_analyser_and_a_capture_on_the_drive_clock(tmp_path, rig):
    scenario = tmp_path / "step.toml"
    scenario.write_text(STEP.read_text() + CAPTURE_RISE)
    result = run_scenario(scenario, REPO / f"config/benches/sim-{rig}-instruments.toml", out_root=tmp_path / "i",
                          rerun_mode="off", seed=1)
    record = json.loads((result.run_dir / "record.json").read_text())
    lab = record["lab_instruments"]
    assert lab["errors"] == [] and set(lab["identities"]) == {"analyser", "scope", "daq"}
    a = lab["analysers"]["analyser"]
    assert a["rate_hz_drive_clock"] >= 9.9 and not a["not_judged"]
    table = pq.read_table(result.run_dir / a["file"]).to_pydict()
    assert min(np.diff(table["t_s"])) > 0.09 and max(table["eff_motor_pct"][5:]) < 100
    c = lab["captures"]["scope"]
    assert c["sample_rate_hz"] == pytest.approx(50_000.0) and c["marked_moment_s"] == pytest.approx(0.3)
    assert c["forced_at_drive_s"] - 0.3 < 0.0101 and c["placement_uncertainty_s"] <= 1e-4
    cap = pq.read_table(result.run_dir / c["file"]).to_pydict()
    t = np.array(cap["t_s"])
    assert t[0] == pytest.approx(c["forced_at_drive_s"] - 0.2 * 0.25, abs=1e-9) and len(cap) >= 6
    # the shaft's rise time judged at the capture's rate, against the plain simulated run of the same seed
    plain = run_scenario(STEP, REPO / f"config/benches/sim-{rig}.toml", out_root=tmp_path / "p", rerun_mode="off",
                         seed=1)
    tel = pq.read_table(plain.run_dir / "telemetry.parquet").to_pydict()
    rise_truth = _rise_time(np.array(tel["t_s"]), np.array(tel["speed_true_mech_rad_s"]), 0.3, 20.0)
    rise_capture = _rise_time(t, np.array(cap["speed_scope_mech_rad_s"]), 0.3, 20.0)
    assert abs(rise_capture - rise_truth) < 1e-3, (rise_capture, rise_truth)
    # the same rise time judged by the bench's criterion on the capture, at its 50 kS/s
    judged = next(c for c in record["criteria"] if c["signal"] == "scope:speed_scope_mech_rad_s")
    assert judged["status"] == "pass" and judged["unit"] == "s" and "50000 S/s" in judged["detail"], judged
    assert judged["value"] == pytest.approx(rise_capture, abs=2.1e-5)
    assert abs(judged["value"] - rise_truth) < 1e-3, (judged["value"], rise_truth)
    print(f"RESULT {rig}_rise_time_capture_criterion_s={judged['value']:.5f} test_s={rise_capture:.5f} "
          f"plain_s={rise_truth:.5f} analyser_rate_hz={a['rate_hz_drive_clock']}")


@pytest.mark.slow
@pytest.mark.parametrize("rig,scenario", [("pmsm", "scenarios/pmsm-rig/fig11-no-load-reversal.toml"),
                                          ("spim", "scenarios/rig/accept-reversal.toml")])
def test_the_measured_position_error_and_flux_agree_with_the_simulators_truth(tmp_path, rig, scenario):
    """pos_err_elec_rad measured on the instruments rig (PMSM: aligned encoder; SPIM: stator flux from v and i)
    against the plain simulated rig's truth, same scenario and seed (and the same physical load): the issue's
    0.05 rad and 2 %."""
    from bench.inputs.prepared import prepare_run

    runs = {}
    for name, bench in (("i", f"sim-{rig}-instruments"), ("p", f"sim-{rig}")):
        runs[name] = run_scenario(prepare_run(REPO / scenario, REPO / f"config/benches/{bench}.toml", seed=1),
                                  out_root=tmp_path / name, rerun_mode="off")
    measured, plain = runs["i"], runs["p"]
    truths = pq.read_table(measured.run_dir / "instruments/truths.parquet").to_pydict()
    tel = pq.read_table(plain.run_dir / "telemetry.parquet").to_pydict()
    t, t_plain = np.array(truths["t_s"]), np.array(tel["t_s"])
    on = t <= 0.999 * t[-1]
    diff = np.angle(np.exp(1j * (np.array(truths["pos_err_elec_rad"])
                                 - np.interp(t, t_plain, np.array(tel["pos_err_elec_rad"])))))[on]
    assert np.isfinite(diff).mean() > 0.99
    assert np.nanmax(np.abs(diff)) < 0.05, np.nanmax(np.abs(diff))
    line = f"RESULT {rig}_pos_err_max_diff_rad={np.nanmax(np.abs(diff)):.4f}"
    if rig == "spim":
        flux = np.array(truths["flux_true_wb"])[on]
        ref = np.interp(t, t_plain, np.array(tel["flux_true_wb"]))[on]
        built = ref > 0.5 * np.nanmax(ref)          # the first 50 ms magnetise the machine: a ms of skew is % there
        rel = (np.abs(flux - ref) / ref)[built]
        assert np.nanmax(rel) < 0.02, np.nanmax(rel)
        line += f" spim_flux_max_diff_pct={100 * np.nanmax(rel):.3f}"
    print(line)


def _faulty_bench(tmp_path: Path, lab_lines: str, timeout_s: float | None = None) -> Path:
    text = (REPO / "config/benches/sim-pmsm-instruments.toml").read_text().replace('"config/', f'"{REPO}/config/')
    head, tail = text.rsplit("\n[simulator.lab_instruments]", 1)
    text = f"{head}\n[simulator.lab_instruments]\n{lab_lines}{tail}"
    if timeout_s is not None:
        text = text.replace("timeout_s = 2.0\npoll_hz", f"timeout_s = {timeout_s}\npoll_hz")
        text = text.replace("timeout_s = 2.0\nsample_rate_hz", f"timeout_s = {timeout_s}\nsample_rate_hz")
        text = text.replace("timeout_s = 5.0\nsample_rate_hz", f"timeout_s = {timeout_s}\nsample_rate_hz")
    path = tmp_path / "faulty.toml"
    path.write_text(text)
    return path


def test_silent_instruments_give_lines_and_not_judged_never_a_pass_and_the_drive_stops(tmp_path):
    from bench.inputs.prepared import prepare_run

    bench = _faulty_bench(tmp_path, "slow_s = 1.0", timeout_s=0.2)
    result = run_scenario(prepare_run(REPO / "scenarios/pmsm-rig/fig10-startup-position-error.toml", bench, seed=1),
                          out_root=tmp_path / "r", rerun_mode="off")
    record = json.loads((result.run_dir / "record.json").read_text())
    errors = record["lab_instruments"]["errors"]
    assert len(errors) == 3 and all("\n" not in e and "no answer within 0.2 s" in e for e in errors), errors
    position = [c for c in record["criteria"] if c["signal"] == "pos_err_elec_rad"]
    assert position and all(c["status"] == "not_judged" for c in position)
    assert result.verdict != "pass"
    assert [c for c in record["criteria"] if c["signal"] != "pos_err_elec_rad" and c["status"] == "pass"]
    assert not record["safe_stop"]["errors"]                  # the drive disabled, the load at zero, as always


def test_an_analyser_dropping_its_connection_mid_run_ends_its_data_there(tmp_path):
    from bench.inputs.prepared import prepare_run

    bench = _faulty_bench(tmp_path, "drop_after = 10", timeout_s=0.5)
    result = run_scenario(prepare_run(REPO / "scenarios/pmsm-rig/fig10-startup-position-error.toml", bench, seed=1),
                          out_root=tmp_path / "r", rerun_mode="off")
    record = json.loads((result.run_dir / "record.json").read_text())
    lab = record["lab_instruments"]
    assert len(lab["errors"]) == 1 and "'analyser'" in lab["errors"][0] and "its data ends at" in lab["errors"][0]
    assert 0 < lab["analysers"]["analyser"]["readings"] < 15
    assert result.verdict == "pass"                            # the DAQ's position error is judged as before
    assert not record["safe_stop"]["errors"]


@pytest.mark.slow
def test_a_capture_is_placed_by_its_trigger_not_by_the_instruments_clock(tmp_path):
    """The scope's clock shifted by 37 ms: the capture lands at the same drive time, and against the plain simulated
    run's shaft speed (same scenario and seed) its best-fitting shift is within the stated placement uncertainty."""
    from bench.inputs.prepared import prepare_run

    captures = []
    for offset in (0.0, 0.037):
        bench = _faulty_bench(tmp_path, f"scope_clock_offset_s = {offset}")
        result = run_scenario(prepare_run(STEP, bench, seed=1), out_root=tmp_path / str(offset), rerun_mode="off")
        c = json.loads((result.run_dir / "record.json").read_text())["lab_instruments"]["captures"]["scope"]
        captures.append((c, pq.read_table(result.run_dir / c["file"]).to_pydict()))
    (c0, cap0), (c1, cap1) = captures
    assert cap0["t_s"] == cap1["t_s"] and cap0["speed_scope_mech_rad_s"] == cap1["speed_scope_mech_rad_s"]
    plain = run_scenario(prepare_run(STEP, REPO / "config/benches/sim-pmsm.toml", seed=1), out_root=tmp_path / "p",
                         rerun_mode="off")
    tel = pq.read_table(plain.run_dir / "telemetry.parquet").to_pydict()
    t, speed = np.array(cap0["t_s"]), np.array(cap0["speed_scope_mech_rad_s"])
    rows = (np.array(tel["t_s"]) >= t[0]) & (np.array(tel["t_s"]) <= t[-1])
    t_rows, truth = np.array(tel["t_s"])[rows], np.array(tel["speed_true_mech_rad_s"])[rows]
    shifts = np.arange(-2e-3, 2e-3 + 1e-9, 1e-5)
    cost = [float(np.mean((np.interp(t_rows, t + s, speed) - truth) ** 2)) for s in shifts]
    best = float(shifts[int(np.argmin(cost))])
    assert abs(best) <= c0["placement_uncertainty_s"] + 1e-5, best
    print(f"RESULT capture_best_shift_s={best:.6f} stated_s={c0['placement_uncertainty_s']}")
