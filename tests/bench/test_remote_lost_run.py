"""Issue 32 item 1, the whole bench: a simulated e35 whose statusword bit 9 (remote) drops 1 s into the run and which
then ignores the controlword. The run trips `remote_lost`, the safe stop's controlword steps fail at once, and the
last resort lets the drive's comm-loss reaction stop it before the bench lets go of the rig: watched from the
simulator's side when the bench exits normally (the rig's services end after the links are closed)."""

from __future__ import annotations

import contextlib
from pathlib import Path

import sim_backend.rig as sim_rig
from bench.run.orchestrator import run_scenario

REPO = Path(__file__).resolve().parents[2]
SCENARIO = REPO / "scenarios/rig/speed-step-20rads.toml"


def test_remote_lost_mid_run_trips_and_the_drive_is_stopped_before_the_bench_exits(tmp_path, capsys, monkeypatch):
    text = (REPO / "config/benches/sim-generic-e35.toml").read_text()
    text = text.replace("consumer_time_ms = 2000", "consumer_time_ms = 300")
    text = text.replace("[simulator]\n", "[simulator]\nremote_drops_after_s = 1.0\n", 1)
    bench = tmp_path / "e35-remote.toml"
    bench.write_text(text)
    at_exit: dict = {}
    original = sim_rig.build

    @contextlib.contextmanager
    def watched(spec, device=None):
        with original(spec, device) as rig:
            yield rig
            dev = rig.device          # the bench has closed its links: what the drive is doing now
            at_exit.update(state=dev.device.state.name, powered=dev.device.power_enabled, remote=dev.device.remote,
                           speed=abs(float(dev.model.load_feedback()[0])), self_stops=list(dev.faults.self_stops))

    monkeypatch.setattr(sim_rig, "build", watched)
    result = run_scenario(SCENARIO, bench, out_root=tmp_path / "runs", rerun_mode="off")
    record = result.record
    assert result.verdict == "aborted", (result.verdict, record.get("abort_reason"))
    trips = record["trips"]
    assert trips[0]["reason"] == "remote_lost", trips
    assert "bit 9 (remote) dropped" in trips[0]["message"] and "ignores the controlword" in trips[0]["message"]
    assert 0.9 <= trips[0]["t_s"] <= 1.3, trips[0]
    assert at_exit["remote"] is False                                   # the quirk did act
    assert at_exit["powered"] is False and at_exit["speed"] < 5.0, at_exit
    assert any("0x6007 = 3 (quick stop)" in s for s in at_exit["self_stops"]), at_exit
    last = record["drive_settings"]["last_resort"]
    assert last["outcome"] == "stopped itself" and last["found_at_close"]["powered"] is True, last
    assert any(step.startswith("last resort: ") for step in record["safe_stop"]["steps"]), record["safe_stop"]
    assert "with the bench's heartbeat withheld it stopped itself" in capsys.readouterr().err
