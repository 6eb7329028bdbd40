"""Honest verdicts: a criterion on a signal the bench does not measure, or over a window with missing rows, is not
judged — never a pass, never a silent fail — and the run's verdict says so ("incomplete", exit 1, a failing JUnit
case). For each transport: the fake link, the in-process CANopen drive, the serial drive."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from bench.inputs.criteria import CriterionSpec, TimeAxis, evaluate, time_axis, verdict
from tests.fakes import FakeRig, run_fake as run

REPO = Path(__file__).resolve().parents[2]


def spec(signal="speed_est_mech_rad_s", window=(0.0, 1.0), **params):
    return CriterionSpec("c", "peak_abs", signal, window, 10.0, params)


def test_a_criterion_on_an_unmeasured_signal_is_not_judged():
    t = np.arange(0, 1.0, 0.001)
    columns = {"speed_est_mech_rad_s": np.ones_like(t), "flux_true_wb": np.full_like(t, math.nan)}
    (r,) = evaluate([spec("flux_true_wb")], t, columns, measured=frozenset({"speed_est_mech_rad_s"}))
    assert r.status == "not_judged" and not r.passed and "flux_true_wb is not measured on this bench" in r.detail
    (r,) = evaluate([spec("flux_true_wb")], t, columns)           # NaN throughout, nobody said: not judged either
    assert r.status == "not_judged"
    assert verdict([r], aborted=False) == "incomplete"


def test_a_signal_the_drive_puts_out_as_nan_fails():
    t = np.arange(0, 1.0, 0.001)
    x = np.ones_like(t)
    x[500] = math.nan                                             # measured, and once NaN: the drive is broken
    (r,) = evaluate([spec()], t, {"speed_est_mech_rad_s": x}, measured=frozenset({"speed_est_mech_rad_s"}))
    assert r.status == "fail" and "NaN" in r.detail


def test_missing_rows_in_the_window_are_not_judged_whatever_the_values():
    t = np.arange(0, 1.0, 0.001)
    keep = (t < 0.40) | (t > 0.42)                                # 20 ms of rows lost in the middle
    columns = {"speed_est_mech_rad_s": np.zeros(keep.sum())}
    (r,) = evaluate([spec()], t[keep], columns, row_period_s=0.001)
    lost = int((~keep).sum())
    assert r.status == "not_judged" and f"{lost} rows missing in the window" in r.detail
    (r,) = evaluate([spec(window=(0.5, 1.0))], t[keep], columns, row_period_s=0.001)
    assert r.status == "pass"                                     # a window without the hole is judged
    holes = time_axis(t[keep], 0.001)
    assert (holes["gaps"], holes["missing_rows"], holes["duplicates"]) == (1, lost, 0)
    assert time_axis(np.array([0.0, 0.001, 0.001, 0.002]), 0.001)["duplicates"] == 1


def test_the_time_axis_checked_batch_by_batch_is_the_whole_axis_checked_at_once():
    rng = np.random.default_rng(3)
    t = np.cumsum(np.full(5000, 0.001))
    t = np.delete(t, np.r_[700:740, 2999, 4100:4103])                 # three holes, one of them one row
    t = np.insert(t, 1500, t[1500])                                   # a duplicated stamp
    t[3500] = t[3499] - 0.0005                                        # a stamp going back
    whole = time_axis(t, 0.001)
    # three holes (44 rows), the step after the backward stamp counted as one more (1 row); 2 non-increasing steps
    assert (whole["gaps"], whole["missing_rows"], whole["duplicates"]) == (4, 45, 2)
    for cuts in ([], [1500, 1501], sorted(rng.choice(t.size, 40, replace=False)), list(range(1, t.size))):
        axis = TimeAxis(0.001)
        for piece in np.split(t, cuts):
            axis.add(piece)
        assert axis.result() == whole, cuts[:5]


def test_verdict_order():
    def r(status, gap=None):
        from bench.inputs.criteria import CriterionResult
        return CriterionResult("c", "k", "s", (0, 1), 1.0, 1.0, status == "pass", gap, "", status)
    assert verdict([r("pass"), r("not_judged")], aborted=False) == "incomplete"
    assert verdict([r("fail"), r("not_judged")], aborted=False) == "fail"
    assert verdict([r("fail", gap="known")], aborted=False) == "pass"
    assert verdict([r("not_judged")], aborted=True) == "aborted"


class GappyRig(FakeRig):
    """A drive whose trace loses rows 0.40-0.45 s (a dropped upload)."""

    def __post_init__(self):
        super().__post_init__()
        real = self.drive.fetch_trace

        def fetch():
            block = real()
            if block is not None and len(block["t_s"]):
                t = block["t_s"]
                keep = (t < 0.40) | (t >= 0.45)
                block = {k: v[keep] for k, v in block.items()}
            return block

        self.drive.fetch_trace = fetch


def test_a_run_with_gaps_never_passes_fake_link(tmp_path):
    """The gap lies outside every criterion's window: each criterion is judged (and passes), but the run misses
    data, so it is not a pass."""
    result = run(tmp_path, GappyRig())
    record = result.record
    assert result.verdict == "incomplete", record["criteria"]
    assert record["time_axis"]["missing_rows"] >= 40 and record["time_axis"]["gaps"] == 1
    assert all(c["status"] == "pass" for c in record["criteria"])
    assert "telemetry misses" in record["abort_reason"]
    junit = ET.parse(result.run_dir / "junit.xml").getroot().find("testsuite")
    assert int(junit.get("failures")) >= 1                       # CI sees it as not passed


def _drop_rows(monkeypatch, link_cls, method="fetch_trace"):
    real = getattr(link_cls, method)

    def fetch(self):
        block = real(self)
        if block is not None and len(block.get("t_s", ())):
            keep = np.ones(len(block["t_s"]), dtype=bool)
            keep[len(keep) // 2:len(keep) // 2 + 30] = False        # 30 rows lost from the middle of one upload
            block = {k: v[keep] for k, v in block.items()}
        return block

    monkeypatch.setattr(link_cls, method, fetch)


@pytest.mark.slow
@pytest.mark.parametrize("bench", ["sim-pmsm.toml", "serial"])
def test_a_run_with_gaps_never_passes_real_transports(tmp_path, monkeypatch, bench):
    """The in-process CANopen drive and the serial drive (over a pty), trace rows lost in transport."""
    from bench.run.orchestrator import run_scenario
    from drivers.canopen.link import CanopenDriveLink
    from drivers.serial_link import SerialDriveLink

    _drop_rows(monkeypatch, CanopenDriveLink if bench == "sim-pmsm.toml" else SerialDriveLink)
    if bench == "serial":
        path = tmp_path / "serial.toml"
        path.write_text((REPO / "config/benches/sim-pmsm-serial.toml").read_text().replace(
            "[drive]", '[services]\nstart = "sim_backend.rig:start"\n\n[drive]', 1).replace(
            'motor = "config/motors/', f'motor = "{REPO}/config/motors/'))
        bench_path = path
    else:
        bench_path = REPO / "config/benches" / bench
    result = run_scenario(REPO / "scenarios/examples/pmsm-rs-step.toml", bench_path, out_root=tmp_path / "runs",
                          rerun_mode="off")
    assert result.verdict == "incomplete", [(c["name"], c["status"], c["detail"]) for c in result.record["criteria"]]
    assert result.record["time_axis"]["missing_rows"] >= 30
