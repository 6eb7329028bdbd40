"""The MDF4 export and the Rerun recording carry the lab instruments' records: a channel group per capture and per analyser, each with its
own master channel on the drive clock, read back with asammdf."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

REPO = Path(__file__).resolve().parents[2]
CAPTURE_RISE = """
[[criteria]]
name = "rise time on the capture"
kind = "rise_time"
signal = "scope:speed_scope_mech_rad_s"
window_s = [0.3, 0.49]
target = 20.0
from_value = 0.0
limit = 0.042
"""


def test_captures_and_analyser_readings_are_channel_groups_on_the_drive_clock(tmp_path):
    asammdf = pytest.importorskip("asammdf")
    from bench.outputs.export import export_run
    from bench.run.orchestrator import run_scenario

    scenario = tmp_path / "step.toml"
    scenario.write_text((REPO / "scenarios/rig/accept-speed-step.toml").read_text() + CAPTURE_RISE)
    result = run_scenario(scenario, REPO / "config/benches/sim-pmsm-instruments.toml", out_root=tmp_path / "r",
                          rerun_mode="save", seed=1)
    lab = json.loads((result.run_dir / "record.json").read_text())["lab_instruments"]
    path = export_run(result.run_dir, "mf4")
    mdf = asammdf.MDF(path)
    try:
        groups = {}
        for index, group in enumerate(mdf.groups):
            names = [ch.name for ch in group.channels]
            instrument = next((n.split(":")[0] for n in names if ":" in n), None)
            if instrument is not None:
                groups[instrument] = (index, names)
        assert set(groups) == {"analyser", "scope", "daq"}
        cap = pq.read_table(result.run_dir / lab["captures"]["scope"]["file"]).to_pydict()
        index, names = groups["scope"]
        speed = mdf.get("scope:speed_scope_mech_rad_s", group=index)
        assert np.array_equal(speed.timestamps, np.array(cap["t_s"]))            # the drive clock, as placed
        assert np.array_equal(speed.samples, np.array(cap["speed_scope_mech_rad_s"]))
        assert speed.unit == "rad/s" and len(speed.samples) == lab["captures"]["scope"]["samples"]
        power = mdf.get("analyser:p_dc_w", group=groups["analyser"][0])
        assert power.unit == "W" and len(power.timestamps) == lab["analysers"]["analyser"]["readings"]
        assert "placed by its trigger" in mdf.groups[index].channel_group.comment
        telemetry = mdf.get("speed_est_mech_rad_s")                               # the drive's group as before
        assert telemetry.timestamps[0] <= speed.timestamps[0]
    finally:
        mdf.close()


    # re-judged offline (drivebench evaluate): the criterion on the capture reads the stored record, same value
    from click.testing import CliRunner

    from bench.faces.cli import cli
    judged = next(c for c in result.record["criteria"] if c["signal"].startswith("scope:"))
    out = CliRunner().invoke(cli, ["evaluate", str(result.run_dir), "--scenario", str(scenario), "--json"])
    again = next(c for c in json.loads(out.output)["criteria"] if c["signal"].startswith("scope:"))
    assert judged["status"] == again["status"] == "pass" and again["value"] == judged["value"]


    # and in the run's Rerun recording, each instrument's record under instruments/<name>/
    from bench.outputs.rerun_view import rrd_entity_paths
    paths = rrd_entity_paths(result.run_dir / "run.rrd")
    assert {"/instruments/scope/speed_scope_mech_rad_s", "/instruments/analyser/p_dc_w",
            "/instruments/daq/encoder_angle_mech_rad"} <= paths, sorted(p for p in paths if "instr" in p)

    # and plotted: instruments/<name>.png per capture
    assert (result.run_dir / "instruments/scope.png").stat().st_size > 10_000
    assert (result.run_dir / "instruments/daq.png").is_file()
