"""MDF4's measurement start is the run's start (record.json's started_utc), not the moment of the export."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import numpy as np
import pytest

from bench.inputs.benchconfig import BenchConfig, BenchSection
from bench.inputs.criteria import evaluate, verdict
from bench.inputs.scenario import load_scenario
from bench.outputs.recorder import RunRecorder
from drivers.contract.signals import SIGNAL_NAMES

REPO = Path(__file__).resolve().parents[2]


def test_the_mf4_start_time_is_the_runs_start(tmp_path: Path):
    pytest.importorskip("asammdf")
    from asammdf import MDF

    from bench.outputs.export import export_run

    scenario = load_scenario(REPO / "scenarios/examples/pmsm-rs-step.toml")
    rec = RunRecorder(tmp_path / "runs", scenario, 5, BenchConfig(path="x", bench=BenchSection(name="sim-x"), drive={}))
    t = np.arange(1, 101) * 1e-3
    cols = {name: np.full_like(t, np.nan) for name in SIGNAL_NAMES}
    cols.update(t_s=t, speed_est_mech_rad_s=np.sin(t))
    rec.append(cols)
    results = evaluate(scenario.criteria, t, cols)
    rec.finish(verdict(results, aborted=False), results, None)
    record_path = rec.run_dir / "record.json"
    record = json.loads(record_path.read_text())
    record["started_utc"] = "2020-01-02T03:04:05.678Z"        # a run of long ago, exported now
    record_path.write_text(json.dumps(record))
    out = export_run(rec.run_dir, "mf4", tmp_path / "run.mf4")
    mdf = MDF(out)
    try:
        assert mdf.header.start_time == dt.datetime(2020, 1, 2, 3, 4, 5, 678000, tzinfo=dt.timezone.utc)
    finally:
        mdf.close()
