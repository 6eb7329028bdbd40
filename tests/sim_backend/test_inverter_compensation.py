"""A non-ideal inverter (campaigns/inverter-*.toml): the paper suite's scenarios with the inverter's dead time and
drop set by injection and the firmware's compensation exact or off by 5 %. What still works and what is lost, as
docs/firmware.md and docs/firmware-pmsm.md state it, checked on the shaft (true speed), not only on the verdict."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from bench.run.orchestrator import run_scenario
from bench.inputs.prepared import prepare_run

ROOT = Path(__file__).resolve().parents[2]
SPIM_15RPM = ROOT / "scenarios/spim/fig08-low-speed-15rpm.toml"
PMSM_FIG08 = ROOT / "scenarios/pmsm/fig08-20rads-rs-step.toml"
PMSM_IGBT = (("inverter_dead_time_s", 2e-6), ("inverter_device_drop_v", 1.5))


def run_with(scenario: Path, axes, tmp_path: Path):
    prepared = prepare_run(scenario, seed=1, injections=tuple(axes))      # what a campaign point with these axes runs
    result = run_scenario(prepared, out_root=tmp_path / "runs", rerun_mode="off")
    columns = pq.read_table(result.run_dir / "telemetry.parquet").to_pydict()
    return result, {k: np.asarray(v) for k, v in columns.items()}


def mean_in(columns, name, window):
    t = columns["t_s"]
    return float(np.mean(columns[name][(t >= window[0]) & (t <= window[1])]))


def rpm(rad_s: float) -> float:
    return rad_s * 60.0 / (2.0 * np.pi)


@pytest.mark.slow
@pytest.mark.parametrize("comp_v, shaft_rpm, verdict", [(7.2, (13.5, 16.5), "pass"), (6.84, (25.0, 31.0), "fail")])
def test_spim_low_speed_rests_on_exact_dead_time_compensation(tmp_path, comp_v, shaft_rpm, verdict):
    """5 % too little compensation: the estimate still reads 15 r/min while the shaft turns at ~28 r/min; the
    true-speed criteria catch it."""
    result, cols = run_with(SPIM_15RPM, [("fw_deadtime_comp_v", comp_v)], tmp_path)
    shaft = rpm(mean_in(cols, "speed_true_mech_rad_s", (2.0, 4.0)))
    estimate = rpm(mean_in(cols, "speed_est_mech_rad_s", (2.0, 4.0)))
    assert shaft_rpm[0] < shaft < shaft_rpm[1], shaft
    assert 14.0 < estimate < 16.0, estimate
    assert result.verdict == verdict
    failed = {c.name for c in result.criteria if c.status == "fail" and not c.known_gap}
    assert ("true speed holds +15 r/min" in failed) == (verdict == "fail")


@pytest.mark.slow
def test_pmsm_on_an_igbt_stage_needs_its_compensation_within_5_percent(tmp_path):
    """2 us dead time and 1.5 V drop (12.3 V of error per phase, about the back-EMF at 20 rad/s): exactly compensated
    Fig. 8 still passes; 5 % low, the flux estimate misses eq. (15b)."""
    exact, _ = run_with(PMSM_FIG08, [*PMSM_IGBT, ("fw_deadtime_comp_v", 12.3)], tmp_path / "exact")
    low, cols = run_with(PMSM_FIG08, [*PMSM_IGBT, ("fw_deadtime_comp_v", 11.685)], tmp_path / "low")
    assert exact.verdict == "pass"
    failed = {c.name for c in low.criteria if c.status == "fail"}
    assert {"flux estimate accurate before the R_s step", "flux offset after the R_s step = eq. (15b)"} <= failed
    assert abs(mean_in(cols, "speed_true_mech_rad_s", (3.5, 5.0)) - 20.0) < 0.2     # the shaft still holds 20 rad/s
