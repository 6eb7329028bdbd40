"""`drivebench compare`: a changed limit and a changed scenario are shown (a limit change read "34.61 34.61 0 %,
fail / pass"), and a signal one run measured and the other did not is listed, not dropped."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from bench.inputs.benchconfig import BenchConfig, BenchSection
from bench.inputs.criteria import evaluate, verdict
from bench.inputs.scenario import load_scenario
from bench.outputs.recorder import RunRecorder
from drivers.contract.signals import SIGNAL_NAMES
import pytest

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
SOURCE = REPO / "scenarios/examples/pmsm-rs-step.toml"


def _run(tmp_path: Path, name: str, text: str, with_true_speed: bool) -> Path:
    path = tmp_path / f"{name}.toml"
    path.write_text(text.replace('"config/benches/', f'"{REPO}/config/benches/'))
    scenario = load_scenario(path)
    rec = RunRecorder(tmp_path / name, scenario, 1, BenchConfig(path="x", bench=BenchSection(name="sim-x"), drive={}))
    t = np.arange(1, 3001) * 1e-3
    cols = {n: np.full_like(t, np.nan) for n in SIGNAL_NAMES}
    cols.update(t_s=t, speed_ref_mech_rad_s=np.full_like(t, 20.0), speed_est_mech_rad_s=np.full_like(t, 20.0))
    if with_true_speed:
        cols["speed_true_mech_rad_s"] = np.full_like(t, 20.0)
    rec.append(cols)
    results = evaluate(scenario.criteria, t, cols)
    rec.finish(verdict(results, aborted=False), results, None)
    return rec.run_dir


def test_limits_scenario_keys_and_one_run_signals_are_shown(tmp_path):
    text = SOURCE.read_text()
    a = _run(tmp_path, "a", text, with_true_speed=True)
    changed = text.replace("overcurrent_a = 10.0", "overcurrent_a = 12.0").replace("limit = 1.0", "limit = 2.5", 1)
    b = _run(tmp_path, "b", changed, with_true_speed=False)
    out = subprocess.run([sys.executable, "-m", "bench", "compare", str(a), str(b), "--json"], capture_output=True,
                         text=True, cwd=REPO, timeout=120)
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    scenario = {row["key"]: (row["a"], row["b"]) for row in doc["scenario"]}
    assert scenario["limits.overcurrent_a"] == (10.0, 12.0)
    assert scenario["criteria[0].limit"] == (1.0, 2.5)
    first = doc["criteria"][0]
    assert (first["limit_a"], first["limit_b"], first["changed"]) == (1.0, 2.5, ["limit"])
    only = {row["signal"]: row["only_in"] for row in doc["signals"] if row.get("only_in")}
    assert only == {"speed_true_mech_rad_s": "a"}
    assert {row["signal"] for row in doc["signals"] if not row.get("only_in")} >= {"speed_est_mech_rad_s"}
    text_out = subprocess.run([sys.executable, "-m", "bench", "compare", str(a), str(b)], capture_output=True,
                              text=True, cwd=REPO, timeout=120, env={"COLUMNS": "250", "PATH": "/usr/bin:/bin"})
    assert "limits.overcurrent_a" in text_out.stdout and "limit changed" in text_out.stdout, text_out.stdout
    assert "measured in A only" in text_out.stdout
