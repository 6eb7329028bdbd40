"""The protocol between the service and its run processes (bench/service/run_protocol.py): every message survives
its round trip; another version, an unknown type or field, a wrong type are refused with one line; a run process
refuses a request of another version on its protocol pipe; the service refuses a run process of another version and
marks the run failed with that reason; warm workers run the suite's runs and a SIGKILLed warm run is handled as a
cold one was."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from bench.service.run_protocol import (PROTOCOL_VERSION, Failed, Finished, Log, Progress, ProtocolError, RunRequest,
                                        Trip, decode, encode)

MESSAGES = [
    RunRequest(run_id=7, scenario_file="scenarios/pmsm/fig08-20rads-rs-step.toml", bench="config/benches/sim-pmsm.toml",
               out_dir="/data/runs/000007", seed=3, recording_name="run-7 · fig08", rerun_interval_s=0.5,
               recording_id="run-7", drill_proofs=({"key": "k", "monotonic_s": 1.5, "drilled_utc": "u",
                                                    "summary": {"verified": True}},)),
    RunRequest(run_id=8, scenario_file="a.toml", bench="b.toml", out_dir="o"),
    Progress(t_s=1.25, duration_s=5.0),
    Trip(reason="overcurrent", t_s=0.31, message="|i| 0.62 A > 0.5 A"),
    Trip(reason="drive_link", t_s=None, message="the drive went silent"),
    Log(line="warm worker: ready"),
    Finished(run_dir="/data/runs/000007/fig08", record_path="/data/runs/000007/fig08/record.json", verdict="pass"),
    Finished(run_dir="d", record_path="d/record.json", verdict="aborted", abort_reason="terminated (SIGTERM)",
             drill_proofs=({"key": "k"},)),
    Failed(reason="a.toml: duration_s: must be positive", exit_code=2),
    Failed(reason="no record"),
]


@pytest.mark.parametrize("message", MESSAGES, ids=lambda m: type(m).__name__)
def test_every_message_survives_its_round_trip(message):
    line = encode(message)
    assert line.endswith(b"\n") and line.count(b"\n") == 1
    data = json.loads(line)
    assert data["v"] == PROTOCOL_VERSION and data["type"]
    assert decode(line) == message
    assert decode(line.decode()) == message


@pytest.mark.parametrize("change, says", [
    ({"v": PROTOCOL_VERSION + 1}, f"version {PROTOCOL_VERSION + 1} refused"),
    ({"v": None}, "version None refused"),
    ({"type": "progres"}, "unknown message type 'progres'"),
    ({"extra": 1}, "progress: unknown field(s) extra"),
    ({"t_s": "1.0"}, "progress: t_s: str where float was expected"),
])
def test_a_message_the_reader_cannot_take_is_refused_with_one_line(change, says):
    data = {**json.loads(encode(Progress(t_s=1.0, duration_s=2.0))), **change}
    with pytest.raises(ProtocolError) as refused:
        decode(json.dumps(data))
    assert says in str(refused.value) and "\n" not in str(refused.value)
    with pytest.raises(ProtocolError, match="missing 1 required positional argument: 'duration_s'"):
        decode(json.dumps({"v": PROTOCOL_VERSION, "type": "progress", "t_s": 1.0}))
    with pytest.raises(ProtocolError, match="not a JSON message"):
        decode(b'{"progress_s": 0.5')
    with pytest.raises(ProtocolError, match="must be a JSON object"):
        decode(b"[1]")


def test_a_run_process_refuses_a_request_of_another_version_on_its_protocol_pipe():
    request = {**json.loads(encode(MESSAGES[1])), "v": 99}
    proc = subprocess.run([sys.executable, "-m", "bench.service.worker", "--parent", str(os.getpid())],
                          input=json.dumps(request).encode() + b"\n", capture_output=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stdout.splitlines()            # the protocol pipe carries protocol messages only
    assert len(lines) == 1, proc.stdout
    failed = decode(lines[0])
    assert isinstance(failed, Failed) and "version 99 refused" in failed.reason and failed.exit_code == 2


def test_a_cold_run_process_without_a_run_leaves_quietly():
    proc = subprocess.run([sys.executable, "-m", "bench.service.worker", "--parent", str(os.getpid())],
                          input=b"", capture_output=True, timeout=120)
    assert proc.returncode == 0 and proc.stdout == b"", proc.stderr


pytest.importorskip("fastapi", reason="the [service] extra is not installed")

from tests.service_fixtures import LONG, REPO, SHORT, Tokens, client_for, make_settings, wait_until  # noqa: E402

H = Tokens.header

OTHER_VERSION = f"""
import json, sys, time
sys.stdin.readline()
print(json.dumps({{"v": {PROTOCOL_VERSION + 41}, "type": "progress", "t_s": 0.1, "duration_s": 1.0}}), flush=True)
time.sleep(60)
"""


def test_a_run_process_of_another_version_is_refused_and_its_run_failed_with_that_reason(tmp_path):
    with client_for(make_settings(tmp_path, lease_ttl_s=3.0)) as api:
        api.service.runner.settings.run_start = "cold"                   # a new interpreter running this:
        api.service.runner.settings.worker = ("-c", OTHER_VERSION)
        op = api.tokens.operator
        t0 = time.monotonic()
        run_id = api.post("/api/runs", json={"scenario": SHORT, "rig": "real-a"}, headers=H(op)).json()["id"]
        run = wait_until(lambda: (r := api.get(f"/api/runs/{run_id}", headers=H(op)).json())["state"]
                         not in ("queued", "running") and r, 30, 0.1, "the run to end")
        assert run["state"] == "error", run
        assert f"version {PROTOCOL_VERSION + 41} refused" in run["reason"], run
        assert time.monotonic() - t0 < 20          # stopped (SIGTERM), not left to sleep its minute
        assert api.get("/api/rigs/real-a", headers=H(op)).json()["state"] == "free"


def test_forked_run_processes_pass_carry_the_drill_and_a_sigkilled_one_ends_aborted(tmp_path):
    with client_for(make_settings(tmp_path, lease_ttl_s=3.0)) as api:
        runner, op = api.service.runner, api.tokens.operator
        assert runner._forkserver_ready.wait(120), "the fork server's preload"
        assert api.get("/api/health").json()["run_processes"] == "warm"
        first = api.post("/api/runs", json={"scenario": SHORT, "rig": "sim-a"}, headers=H(op)).json()["id"]
        run = wait_until(lambda: (r := api.get(f"/api/runs/{first}", headers=H(op)).json())["state"]
                         not in ("queued", "running") and r, 60, 0.1, "the first run")
        assert run["state"] == "pass" and run["verdict"] == "pass", run
        assert runner.spawned == {"forked": 1, "cold": 0}
        assert runner.drill_proofs, "the passed drill is kept for the next runs"
        second = api.post("/api/runs", json={"scenario": SHORT, "rig": "sim-a"}, headers=H(op)).json()["id"]
        run = wait_until(lambda: (r := api.get(f"/api/runs/{second}", headers=H(op)).json())["state"]
                         not in ("queued", "running") and r, 60, 0.1, "the second run")
        record = api.get(run["record_url"], headers=H(op)).json()
        assert run["state"] == "pass" and record["comm_loss"]["reused"]["age_s"] > 0, record["comm_loss"]

        killed = api.post("/api/runs", json={"scenario": LONG, "rig": "sim-a"}, headers=H(op)).json()["id"]
        pid = wait_until(lambda: runner.children.get(killed) and runner.children[killed].proc.pid, 30, 0.05,
                         "the run process")
        assert runner.children[killed].warm and runner.children[killed].proc.process.pid == pid
        wait_until(lambda: (api.get(f"/api/runs/{killed}", headers=H(op)).json()["progress_s"] or 0) > 0.2, 60, 0.1,
                   "the run to be under way")
        os.kill(pid, signal.SIGKILL)
        run = wait_until(lambda: (r := api.get(f"/api/runs/{killed}", headers=H(op)).json())["state"] != "running"
                         and r, 10, 0.1, "reaped")
        assert run["state"] == "aborted" and "signal 9" in run["reason"]
        assert api.get("/api/rigs/sim-a", headers=H(op)).json()["state"] == "free"
        assert runner.spawned == {"forked": 3, "cold": 0}


def test_runs_wait_for_the_fork_servers_preload_a_minute_at_most_then_start_cold(tmp_path, monkeypatch):
    from bench.service.runner import FORKSERVER_WAIT_S, Runner

    def never_ready(self):                 # a preload that hangs, 3 s before the wait for it runs out
        self._forkserver_since = time.monotonic() - FORKSERVER_WAIT_S + 3.0

    monkeypatch.setattr(Runner, "_start_forkserver", never_ready)
    with client_for(make_settings(tmp_path, lease_ttl_s=3.0)) as api:
        runner, op = api.service.runner, api.tokens.operator
        assert api.get("/api/health").json()["run_processes"] == "warming"
        run_id = api.post("/api/runs", json={"scenario": SHORT, "rig": "sim-a"}, headers=H(op)).json()["id"]
        held = api.get(f"/api/runs/{run_id}", headers=H(op)).json()     # not started cold beside the preload
        assert held["state"] == "queued" and held["waiting"].startswith("run processes warming up"), held
        time.sleep(1.0)
        assert api.get(f"/api/runs/{run_id}", headers=H(op)).json()["state"] == "queued"
        run = wait_until(lambda: (r := api.get(f"/api/runs/{run_id}", headers=H(op)).json())["state"]
                         not in ("queued", "running") and r, 90, 0.1, "the run")
        assert run["state"] == "pass" and runner.spawned == {"forked": 0, "cold": 1}, (run, runner.spawned)
        assert api.get("/api/health").json()["run_processes"] == "cold"


WARM_CHECK = """
import gc, json, sys
import bench.service.fork_warm
from drivers.contract.eds import _od_snapshot
from sim_backend.pmsm.kernel import run_steps as pmsm_steps
from sim_backend.spim.kernel import run_steps as spim_steps
print(json.dumps({"frozen": gc.get_freeze_count(), "od": _od_snapshot.cache_info().currsize,
                  "pmsm": len(pmsm_steps.signatures), "spim": len(spim_steps.signatures),
                  "threads": __import__("threading").active_count()}))
"""


def test_the_fork_server_warms_each_rigs_run_and_freezes_what_it_loaded(tmp_path):
    """What bench.service.fork_warm does in the fork server, in a plain process: the rigs' drive models loaded (their
    compiled kernels), the drive's object dictionary parsed, everything frozen out of the collector, no thread left
    behind (the server forks); a bench config that cannot be read is one line, and the others are still warmed."""
    from bench.service.worker import WARM_BENCHES_ENV

    benches = [str(REPO / "config/benches/sim-pmsm.toml"), str(tmp_path / "missing.toml"),
               str(REPO / "config/benches/sim-spim.toml")]
    env = {**os.environ, WARM_BENCHES_ENV: json.dumps(benches)}
    done = subprocess.run([sys.executable, "-c", WARM_CHECK], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert got["pmsm"] >= 1 and got["spim"] >= 1 and got["od"] >= 1 and got["frozen"] > 10_000 and got["threads"] == 1
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "missing.toml" in lines[0] and "warm-up" in lines[0], done.stderr
    cold = subprocess.run([sys.executable, "-c", WARM_CHECK], cwd=REPO, capture_output=True, text=True, timeout=120,
                          env={k: v for k, v in os.environ.items() if k != WARM_BENCHES_ENV})
    assert json.loads(cold.stdout.strip().splitlines()[-1])["pmsm"] == 0     # imported elsewhere: it does nothing
