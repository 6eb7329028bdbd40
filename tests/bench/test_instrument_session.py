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

REPO = Path(__file__).resolve().parents[2]
STEP = REPO / "scenarios/rig/accept-speed-step.toml"


def _rise_time(t, x, t0, target, lo=0.1, hi=0.9):
    after = t >= t0
    t, x = t[after], x[after]
    t_lo = t[np.argmax(x >= lo * target)]
    t_hi = t[np.argmax(x >= hi * target)]
    return float(t_hi - t_lo)


@pytest.mark.parametrize("rig", ["pmsm", "spim"])
def test_a_run_records_the_analyser_and_a_capture_on_the_drive_clock(tmp_path, rig):
    result = run_scenario(STEP, REPO / f"config/benches/sim-{rig}-instruments.toml", out_root=tmp_path / "i",
                          rerun_mode="off", seed=1)
    lab = json.loads((result.run_dir / "record.json").read_text())["lab_instruments"]
    assert lab["errors"] == [] and set(lab["identities"]) == {"analyser", "scope"}
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
    print(f"RESULT {rig}_rise_time_capture_s={rise_capture:.5f} plain_s={rise_truth:.5f} "
          f"analyser_rate_hz={a['rate_hz_drive_clock']}")
