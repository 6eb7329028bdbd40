"""IEC 61800-9-2's eight operating points on the simulated PMSM instruments rig: losses and efficiency judged on the
power analyser's readings with the uncertainty of its stated accuracy; without an analyser, never a pass."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from bench.run.orchestrator import run_scenario

REPO = Path(__file__).resolve().parents[2]
SCENARIO = REPO / "scenarios/rig/accept-efficiency-pmsm.toml"


@pytest.mark.slow
def test_the_eight_points_are_judged_on_the_analyser_with_their_uncertainty(tmp_path):
    result = run_scenario(SCENARIO, REPO / "config/benches/sim-pmsm-instruments.toml", out_root=tmp_path / "i",
                          rerun_mode="off", seed=1)
    record = json.loads((result.run_dir / "record.json").read_text())
    assert result.verdict == "pass", [c["detail"] for c in record["criteria"] if c["status"] != "pass"]
    points = {c["name"].split(" ")[0] for c in record["criteria"]}
    assert points == {"(0,25)", "(0,50)", "(0,100)", "(50,25)", "(50,50)", "(50,100)", "(90,50)", "(90,100)"}
    assert all("±" in c["detail"] and "upper bound judged" in c["detail"] for c in record["criteria"])
    # the analyser's shaft power is the shaft's: speed x torque of the rig's reference sensors, window by window
    a = pq.read_table(result.run_dir / record["lab_instruments"]["analysers"]["analyser"]["file"]).to_pydict()
    tel = pq.read_table(result.run_dir / "telemetry.parquet").to_pydict()
    t_a, t = np.array(a["t_s"]), np.array(tel["t_s"])
    shaft = np.array(tel["speed_true_mech_rad_s"]) * np.array(tel["torque_load_nm"])
    for c in record["criteria"]:
        lo, hi = c["window_s"]
        p_an = np.mean(np.array(a["p_shaft_w"])[(t_a >= lo) & (t_a <= hi)])
        p_ref = np.mean(shaft[(t >= lo) & (t <= hi)])
        assert abs(p_an - p_ref) <= 0.01 * abs(p_ref) + 2.5, (c["name"], p_an, p_ref)
    plain = run_scenario(SCENARIO, REPO / "config/benches/sim-pmsm.toml", out_root=tmp_path / "p",
                         rerun_mode="off", seed=1)
    assert plain.verdict == "incomplete"
    assert all(c.status == "not_judged" and "no record from instrument 'analyser'" in c.detail
               for c in plain.criteria)
