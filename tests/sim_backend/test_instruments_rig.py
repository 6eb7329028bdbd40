"""The instruments rigs (config/benches/sim-*-instruments.toml): the bench gets what a lab's instruments give and no
simulator truth. Shaft speed only from the dynamometer's encoder (quantised, jittered, offset unknown), torque only
from the transducer (lagged, noisy), load only in the dynamometer's torque mode, injections only through the drive's
firmware; the record names the instrument behind each rig-truth signal."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from sim_backend.instruments import InstrumentedModel, InstrumentSpec
from sim_backend.rig import make_model

REPO = Path(__file__).resolve().parents[2]
RIGS = ("sim-pmsm-instruments", "sim-spim-instruments")
RIG_SCENARIO = REPO / "scenarios/rig/speed-step-20rads.toml"
CPR = 4096
GATE_S = 0.01
SPEED_LSB = 2 * math.pi / CPR / GATE_S          # one encoder count over the gate, rad/s
REGISTER_LSB = 0.01 * math.pi / 30              # the dyno's speed register: 0.01 rpm


def _telemetry(run_dir: Path) -> dict[str, np.ndarray]:
    return {k: np.asarray(v, dtype=float) for k, v in pq.read_table(run_dir / "telemetry.parquet").to_pydict().items()}


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bench", *args], capture_output=True, text=True, cwd=REPO)


@pytest.fixture(scope="module")
def rig_runs(tmp_path_factory):
    from bench.run.orchestrator import run_scenario

    out = tmp_path_factory.mktemp("instruments")
    return {rig: run_scenario(RIG_SCENARIO, REPO / f"config/benches/{rig}.toml", out_root=out / rig, rerun_mode="off")
            for rig in RIGS}


@pytest.mark.slow
@pytest.mark.parametrize("rig", RIGS)
def test_the_rig_scenario_passes_on_the_instruments_rig(rig_runs, rig):
    result = rig_runs[rig]
    record = result.record
    assert result.verdict == "pass", [(c["name"], c["value"], c["detail"]) for c in record["criteria"]]
    assert record["data_source"] == "trace"            # the drive's own recorder, the reference's readings beside it
    instruments = record["instruments"]
    assert "dyno encoder 4096 cpr" in instruments["speed_true_mech_rad_s"]
    assert "speed register 16" in instruments["speed_true_mech_rad_s"]
    assert "torque transducer" in instruments["torque_load_nm"]
    # measured by the rig's DAQ ([rig_truths], docs/instruments.md), judged on instruments/truths.parquet
    assert "DAQ record of the run" in instruments["pos_err_elec_rad"]
    assert ("DAQ record of the run" in instruments["flux_true_wb"]) == ("spim" in rig)
    assert (result.run_dir / "instruments" / "truths.parquet").exists()
    measured = set(record["measured_signals"])
    assert {"speed_true_mech_rad_s", "torque_load_nm", "speed_est_mech_rad_s"} <= measured
    assert not {"pos_err_elec_rad", "flux_true_wb"} & measured
    assert not {"speed_true_mech_rad_s", "pos_err_elec_rad", "flux_true_wb", "torque_load_nm"} & set(
        record["trace_signals"])                       # the drive is never asked for rig truth


@pytest.mark.slow
@pytest.mark.parametrize("rig", RIGS)
def test_the_true_speed_is_the_encoder_reading_not_the_plant_speed(rig_runs, rig):
    """At every reading (one per SYNC, 10 ms) speed_true is a whole number of encoder counts over the gate (to the
    register's 0.01 rpm); a plant speed would almost never be. Between readings the rows are interpolated."""
    t = _telemetry(rig_runs[rig].run_dir)
    speed = t["speed_true_mech_rad_s"]
    assert np.isfinite(speed).all()
    at_reading = np.abs(t["t_s"] / 0.01 - np.round(t["t_s"] / 0.01)) < 1e-6
    readings = speed[at_reading & (t["t_s"] > 0.5)]
    assert readings.size > 200
    counts = readings / SPEED_LSB
    off_grid = np.abs(counts - np.round(counts)) * SPEED_LSB
    assert off_grid.max() <= REGISTER_LSB / 2 + 1e-9, off_grid.max()
    assert np.unique(np.round(counts)).size < 40      # a handful of levels around 20 rad/s = 130 counts per gate
    for truth in ("pos_err_elec_rad", "flux_true_wb"):
        assert np.isnan(t[truth]).all()                # not measured: no instrument gives them


def test_the_drive_firmware_reports_no_rig_truth_and_the_dyno_reads_through_its_instruments():
    """The wrapped model: the drive's telemetry has NaN where rig truth was; the dyno's speed is the count difference
    over the gate (the plant's mean speed over it, quantised to one count); its torque lags a step with 100 Hz."""
    spec = InstrumentSpec(encoder_noise_counts=0.0, torque_noise_nm=0.0)
    plain = make_model(REPO / "config/motors/pmsm-paper.toml", 3)
    model = InstrumentedModel(make_model(REPO / "config/motors/pmsm-paper.toml", 3), spec, seed=3)
    for m in (plain, model):
        m.set_enabled(True)
        m.set_speed_ref(20.0)
    truth = plain.step(5000)                         # 0.5 s: the same drive, same seed, without instruments
    seen = model.step(5000)
    from drivers.contract.signals import SIGNAL_INDEX
    for name in ("speed_true_mech_rad_s", "pos_err_elec_rad", "flux_true_wb", "torque_load_nm"):
        assert np.isnan(seen[:, SIGNAL_INDEX[name]]).all(), name
    est = SIGNAL_INDEX["speed_est_mech_rad_s"]
    np.testing.assert_array_equal(seen[:, est], truth[:, est])      # the firmware is untouched
    speed, _ = model.load_feedback()
    plant = truth[-100:, SIGNAL_INDEX["speed_true_mech_rad_s"]].mean()
    assert abs(speed - plant) <= SPEED_LSB + 1e-9
    assert abs(speed / SPEED_LSB - round(speed / SPEED_LSB)) < 1e-9     # a whole number of counts
    model.set_load(0, 1.0, True)                     # 1 N*m torque step
    model.step(16)                                   # 1.6 ms = one time constant of 100 Hz
    _, torque = model.load_feedback()
    assert torque == pytest.approx(1 - math.exp(-2 * math.pi * 100 * 16 * model.control_period_s), abs=1e-3)
    model.step(200)
    assert model.load_feedback()[1] == pytest.approx(1.0, abs=1e-5)


def test_the_encoder_offset_is_seeded_and_the_readings_deterministic():
    a, b, c = (InstrumentedModel(make_model("toy", 0), InstrumentSpec(), seed) for seed in (1, 1, 2))
    assert a.offset_rad == b.offset_rad != c.offset_rad
    for m in (a, b):
        m.set_enabled(True)
        m.set_speed_ref(10.0)
    for _ in range(20):
        a.step(100)
        b.step(100)
        assert a.load_feedback() == b.load_feedback() and a.encoder_count() == b.encoder_count()


@pytest.mark.slow
def test_validate_refuses_plant_injections_and_dyno_modes_the_rig_lacks(tmp_path):
    """fig08 steps the plant's R_s: a lab cannot. A brake load needs a mode the instruments dyno does not have."""
    out = _cli("validate", str(REPO / "scenarios/pmsm/fig08-20rads-rs-step.toml"),
               "--bench", str(REPO / "config/benches/sim-pmsm-instruments.toml"))
    assert out.returncode == 2
    assert "simulator-only injection 'plant_rs'" in out.stderr and "plant_injections = false" in out.stderr
    brake = tmp_path / "brake.toml"
    brake.write_text(RIG_SCENARIO.read_text().replace('kind = "torque"\nstart_s = 1.5',
                                                      'kind = "brake"\nstart_s = 1.5'))
    out = _cli("validate", str(brake), "--bench", str(REPO / "config/benches/sim-pmsm-instruments.toml"))
    # the bench emulates the brake from the dyno encoder's speed (bench/run/load_emulation.py) and says so
    assert out.returncode == 0, out.stderr
    assert "load[0] (brake): emulated by the bench on 'sim-pmsm-instruments'" in out.stdout, out.stdout
    # without a measured shaft speed it cannot: refused
    blind = tmp_path / "blind.toml"
    blind.write_text((REPO / "config/benches/sim-pmsm-instruments.toml").read_text()
                     .replace('source = "load"', 'source = "none"'))
    out = _cli("validate", str(brake), "--bench", str(blind))
    assert out.returncode == 2 and "'brake' needs brake mode" in out.stderr, out.stderr
    assert "cannot emulate it without measuring the shaft speed" in out.stderr, out.stderr


@pytest.mark.slow
def test_validate_says_what_an_instruments_rig_measures():
    out = _cli("validate", str(REPO / "scenarios/pmsm/fig11-no-load-reversal.toml"),
               "--bench", str(REPO / "config/benches/sim-pmsm-instruments.toml"))
    assert out.returncode == 0, out.stderr
    flagged = [line for line in out.stdout.splitlines() if "not judged on bench" in line]
    # the DAQ and the alignment step measure the position error there now; the PMSM's true flux stays unmeasured
    assert not any("pos_err_elec_rad not measured" in line for line in flagged), flagged


def test_an_ordinary_simulated_bench_still_takes_rig_truth_from_the_drive():
    """Without [reference] (sim-pmsm, the fidelity suite) the drive's extension reports rig truth as before."""
    from bench.inputs.benchconfig import load_bench_config, measurable_signals

    cfg = load_bench_config(REPO / "config/benches/sim-pmsm.toml")
    assert {"pos_err_elec_rad", "flux_true_wb", "speed_true_mech_rad_s"} <= measurable_signals(cfg)
    cfg = load_bench_config(REPO / "config/benches/sim-pmsm-instruments.toml")
    assert "pos_err_elec_rad" in measurable_signals(cfg)          # [rig_truths]: the aligned encoder on a DAQ
    assert "flux_true_wb" not in measurable_signals(cfg)


@pytest.mark.slow
def test_same_seed_same_instrument_readings_through_the_bench(tmp_path):
    """Determinism holds through the instruments: two runs of the same scenario and seed record the same encoder and
    transducer readings bit for bit; another seed reads differently (jitter, offset)."""
    from bench.run.orchestrator import run_scenario

    bench = REPO / "config/benches/sim-pmsm-instruments.toml"
    runs = [run_scenario(RIG_SCENARIO, bench, out_root=tmp_path / str(i), seed=seed, rerun_mode="off")
            for i, seed in enumerate((3, 3, 4))]
    a, b, c = (_telemetry(r.run_dir) for r in runs)
    for name in ("speed_true_mech_rad_s", "torque_load_nm", "speed_est_mech_rad_s"):
        np.testing.assert_array_equal(a[name], b[name])
    assert not np.array_equal(a["torque_load_nm"], c["torque_load_nm"])


@pytest.mark.parametrize("table, needle", [
    ({"encoder_gate": 0.01}, "encoder_gate: unknown key"),
    ({"torque_noise_nm": -1.0}, "torque_noise_nm: must be a number >= 0"),
    ({"encoder_counts_per_rev": 1000.5}, "encoder_counts_per_rev: must be an integer"),
    ({"encoder_speed_gate_s": 0.0}, "must be > 0"),
])
def test_bad_instrument_settings_name_the_file_and_field(table, needle):
    from sim_backend.rig import spec_for_bench

    cfg = {"_path": "rig.toml", "simulator": {"motor": "toy", "instruments": table}, "drive": {}, "load": {}}
    with pytest.raises(RuntimeError, match="rig.toml: simulator.instruments") as err:
        spec_for_bench(cfg, 1)
    assert needle in str(err.value)


@pytest.mark.slow
def test_sim_serve_serves_the_instruments_rig_with_its_dyno_map(tmp_path):
    """Out of process too: `sim serve` of an instruments config serves its dynamometer's register map (torque only,
    integer registers) with the instruments' readings; the bench's load link talks to it by that map."""
    import os
    import re
    import threading

    from drivers.contract.load_map import LoadMode
    from drivers.modbus_load import ModbusLoadLink

    text = (REPO / "config/benches/sim-pmsm-instruments.toml").read_text()
    text = re.sub(r'"127\.0\.0\.1:\d+"', '"127.0.0.1:0"', text).replace('= "config/', f'= "{REPO}/config/')
    config = tmp_path / "bench.toml"
    config.write_text(text)
    proc = subprocess.Popen([sys.executable, "-m", "sim_backend.serve", "--config", str(config)], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    lines: list[str] = []
    try:
        def read():
            for line in proc.stdout:
                lines.append(line.strip())
                if line.startswith("ready"):
                    return
        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        reader.join(60)
        assert lines and lines[-1].startswith("ready"), (lines, proc.poll())
        port = int(re.search(r"modbus tcp://127\.0\.0\.1:(\d+)", "\n".join(lines)).group(1))
        dyno_map = str(REPO / "config/load-machines/instruments-dyno.toml")
        link = ModbusLoadLink({"transport": "modbus-tcp", "map": dyno_map, "host": "127.0.0.1", "port": port,
                               "timeout_s": 2.0}, REPO)
        try:
            link.open()
            assert link.modes == (LoadMode.TORQUE,)
            link.set_load(LoadMode.TORQUE, 1.234)
            link.enable(True)
            feedback = link.feedback()
            assert feedback.speed_mech_rad_s == 0.0                # shaft at rest: no counts
            assert feedback.torque_nm == 0.0                       # the transducer has not seen a control period yet
            link.zero_and_disable()
        finally:
            link.close()
    finally:
        proc.terminate()
        proc.wait(timeout=20)


def test_the_torque_transducer_sees_the_dynamometer_rotor_accelerate():
    """In line between motor and dynamometer the transducer reads T_L + J_dyno dw/dt: while the shaft accelerates with
    no load it reads J_dyno times the (lagged) acceleration of the plant; at steady speed the load torque alone."""
    from drivers.contract.signals import SIGNAL_INDEX

    spec = InstrumentSpec(encoder_noise_counts=0.0, torque_noise_nm=0.0, dyno_inertia_kgm2=5e-4)
    plain = make_model(REPO / "config/motors/pmsm-paper.toml", 3)
    model = InstrumentedModel(make_model(REPO / "config/motors/pmsm-paper.toml", 3), spec, seed=3)
    for m in (plain, model):
        m.set_enabled(True)
        m.set_speed_ref(20.0)
    truth = plain.step(100)[:, SIGNAL_INDEX["speed_true_mech_rad_s"]]
    model.step(100)
    dt = model.control_period_s
    acceleration = (truth[-1] - truth[-21]) / (20 * dt)          # the plant's, over the transducer's lag
    torque = model.load_feedback()[1]
    assert acceleration > 100 and torque == pytest.approx(5e-4 * acceleration, rel=0.3), (acceleration, torque)
    model.step(10_000)                                       # 1 s later: steady at 20 rad/s, no load
    assert abs(model.load_feedback()[1]) < 2e-3
