"""`drivebench compare`: the identity fields that differ, each criterion's delta, each signal's difference on the
drive clock (B interpolated onto A's samples; angles the short way round), and the overlay plot."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench.inputs.benchconfig import BenchConfig, BenchSection
from bench.outputs.compare import compare_runs
from bench.inputs.criteria import evaluate, verdict
from bench.outputs.recorder import RunRecorder
from bench.inputs.scenario import load_scenario
from drivers.contract.signals import SIGNAL_NAMES

REPO = Path(__file__).resolve().parents[2]


def make_run(root: Path, seed: int, speed_offset: float, angle_offset: float, dt: float) -> Path:
    scenario = load_scenario(REPO / "scenarios/examples/pmsm-rs-step.toml")
    rec = RunRecorder(root, scenario, seed, BenchConfig(path="x", bench=BenchSection(name="sim-x"), drive={}))
    t = np.arange(1, int(round(6.0 / dt)) + 1) * dt
    cols = {name: np.full_like(t, np.nan) for name in SIGNAL_NAMES}
    cols.update(t_s=t, speed_ref_mech_rad_s=np.full_like(t, 20.0), speed_est_mech_rad_s=20.0 + speed_offset + 0 * t,
                speed_true_mech_rad_s=20.0 + speed_offset + 0 * t, i_sx_a=np.zeros_like(t),
                pos_est_elec_rad=((3.1 + angle_offset) + np.pi) % (2 * np.pi) - np.pi + 0 * t)
    rec.append(cols)
    results = evaluate(scenario.criteria, t, cols)
    rec.finish(verdict(results, aborted=False), results, None)
    return rec.run_dir


def test_deltas_signals_and_identity(tmp_path: Path):
    a = make_run(tmp_path / "a", seed=1, speed_offset=0.0, angle_offset=0.0, dt=1e-3)
    b = make_run(tmp_path / "b", seed=2, speed_offset=0.25, angle_offset=0.1, dt=2e-3)   # other rate, wraps past pi
    result = compare_runs(a, b)
    ident = {row["field"]: row for row in result["identity"]}
    assert not ident["seed"]["same"] and (ident["seed"]["a"], ident["seed"]["b"]) == (1, 2)
    assert ident["scenario sha256"]["same"] and ident["bench"]["same"]
    signals = {row["signal"]: row for row in result["signals"]}
    assert abs(signals["speed_est_mech_rad_s"]["rms_diff"] - 0.25) < 1e-9
    assert abs(signals["speed_true_mech_rad_s"]["max_abs_diff"] - 0.25) < 1e-9
    assert signals["i_sx_a"]["max_abs_diff"] == 0.0
    assert abs(signals["pos_est_elec_rad"]["max_abs_diff"] - 0.1) < 1e-6         # not 2 pi - 0.1
    assert "flux_est_wb" not in signals                                          # measured in neither
    assert signals["speed_est_mech_rad_s"]["span_s"] == [0.002, 6.0]             # what both cover
    by_name = {row["name"]: row for row in result["criteria"]}
    steady = by_name["steady-state speed error"]
    assert steady["unit"] and abs(steady["delta"] - (steady["value_b"] - steady["value_a"])) < 1e-12
    assert steady["unit"] == "%" and steady["value_a"] == 0.0 and abs(steady["value_b"] - 1.25) < 1e-9


@pytest.mark.slow
def test_cli_json_and_plot(tmp_path: Path):
    a = make_run(tmp_path / "a", seed=1, speed_offset=0.0, angle_offset=0.0, dt=1e-3)
    b = make_run(tmp_path / "b", seed=1, speed_offset=0.5, angle_offset=0.0, dt=1e-3)
    plot = tmp_path / "cmp.png"
    proc = subprocess.run([sys.executable, "-m", "bench", "compare", str(a), str(b), "--json", "--plot", str(plot)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    assert doc["plot"] == str(plot) and plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert all(row["same"] for row in doc["identity"] if row["field"] != "verdict")
    proc = subprocess.run([sys.executable, "-m", "bench", "compare", str(a), str(tmp_path / "nope")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
