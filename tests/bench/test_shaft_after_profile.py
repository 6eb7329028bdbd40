"""The instruments rig's shaft speed after the profile: the rows the drive's trace recorder gives for the safe stop
(after the scenario's end) carry the dynamometer encoder's readings taken while the drive brakes, so
`speed_true_mech_rad_s` follows the shaft to standstill, with the drive's own speed, instead of holding the last
reading of the profile (it stayed at 50.0079 rad/s while the drive stopped, and `compare` saw a false difference)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
SCENARIO = REPO / "tests/data/coast-at-50rads-pmsm-instruments.toml"


def test_the_encoder_speed_follows_the_shaft_through_the_safe_stop(tmp_path):
    from bench.run.orchestrator import run_scenario

    result = run_scenario(SCENARIO, REPO / "config/benches/sim-pmsm-instruments.toml", out_root=tmp_path,
                          rerun_mode="off")
    assert result.verdict == "pass", result.record.get("abort_reason")
    columns = pq.read_table(result.run_dir / "telemetry.parquet").to_pydict()
    t = np.asarray(columns["t_s"])
    true = np.asarray(columns["speed_true_mech_rad_s"], dtype=float)
    est = np.asarray(columns["speed_est_mech_rad_s"], dtype=float)
    before = (t > 0.8) & (t <= 1.0)
    assert np.all(np.abs(true[before] - 50.0) < 0.5)                      # at speed to the end of the profile
    stop = t > 1.0
    assert stop.sum() >= 50, "the trace holds the safe stop's rows"
    assert abs(true[stop][-1]) < 2.0, true[stop][-5:]                     # at standstill at the end, not 50 rad/s
    assert len(np.unique(np.round(true[stop], 6))) > 10                   # read through the stop, not held
    # the encoder and the drive's own speed agree through the braking (encoder: 10 ms gate, half a gate late)
    assert np.nanmax(np.abs(true[stop] - est[stop])) < 15.0
    assert np.nanmean(np.abs(true[stop] - est[stop])) < 3.0
