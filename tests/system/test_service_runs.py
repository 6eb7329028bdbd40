"""The bench service with real run processes: a run from queue to verdict with its events, abort (the run's safe
stop, who aborted), a SIGKILLed lease holder freeing the rig within its TTL, a SIGKILLed service reconciled at
restart, and `drivebench submit` against a served instance."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("fastapi", reason="the [service] extra is not installed")

from tests.service_fixtures import (LONG, REPO, SCENARIOS, SHORT, Tokens, client_for, free_port,  # noqa: E402
                                    make_settings, make_tokens, serve_process, stop_process, wait_until)

H = Tokens.header


def _state(api, run_id, token):
    return api.get(f"/api/runs/{run_id}", headers=H(token)).json()


def submit_and_follow(api, events, body: dict, timeout_s: float = 60.0) -> tuple[int, list[dict]]:
    """Submit a run as the operator; its websocket events up to its final state."""
    t0 = time.monotonic()
    run_id = api.post("/api/runs", json=body, headers=H(api.tokens.operator)).json()["id"]
    seen: list[dict] = []
    while not seen or seen[-1].get("state") not in ("pass", "fail", "error", "aborted"):
        event = events.receive_json()
        assert time.monotonic() - t0 < timeout_s, seen
        if event["id"] == run_id:
            seen.append(event)
    return run_id, seen


def test_a_trip_is_pushed_as_it_happens(tmp_path):
    tripping = (SCENARIOS / SHORT).read_text().replace("overcurrent_a = 10.0", "overcurrent_a = 0.5")
    with client_for(make_settings(tmp_path, lease_ttl_s=3.0)) as api:
        with api.websocket_connect("/api/events", headers=H(api.tokens.viewer)) as events:
            _, seen = submit_and_follow(api, events, {"scenario_toml": tripping, "rig": "sim-a"})
    trips = [e for e in seen if e["type"] == "trip"]
    assert seen[-1]["state"] == "aborted" and trips, seen
    assert trips[0]["reason"] == "overcurrent" and 0 < trips[0]["t_s"] < 1.0 and "0.5" in trips[0]["message"]
    assert seen.index(trips[0]) < len(seen) - 1            # pushed while the run went on, before its final state


def test_a_run_goes_from_queue_to_verdict_with_events_and_its_record(tmp_path):
    with client_for(make_settings(tmp_path, lease_ttl_s=3.0)) as api:
        op = api.tokens.operator
        with api.websocket_connect("/api/events", headers=H(api.tokens.viewer)) as events:
            run_id, seen = submit_and_follow(api, events, {"scenario": SHORT, "rig": "sim-a"})
        states = [e["state"] for e in seen if e["type"] == "run"]
        assert states[0] == "running" and states[-1] == "pass", seen
        assert any(e["type"] == "progress" for e in seen)
        run = _state(api, run_id, op)
        assert run["verdict"] == "pass" and run["rig"] == "sim-a"
        assert run["criteria"][0]["name"] == "stable: position error within pi/4"
        assert run["scenario_sha256"] and run["seed"] == 1 and run["revision"]
        assert run["drive"]["device_name"] == "drivebench simulated PMSM drive"
        assert 0 < run["duration_s"] < 60
        record = api.get(run["record_url"], headers=H(op)).json()
        assert record["verdict"] == "pass" and record["rerun"]["sinks"]
        assert api.get(f"/api/runs/{run_id}/files/summary.png", headers=H(op)).content[:4] == b"\x89PNG"
        assert api.get(f"/api/runs/{run_id}/files/run.rrd", headers=H(op)).status_code == 200
        assert api.get(f"/api/runs/{run_id}/files/..%2Frecord.json", headers=H(op)).status_code == 404
        assert api.get("/api/rigs/sim-a", headers=H(op)).json()["state"] == "free"
        trend = api.get("/api/trend", params={"criterion": "stable: position error within pi/4"},
                        headers=H(op)).json()
        assert [p["run_id"] for p in trend] == [run_id] and trend[0]["passed"]


def test_abort_stops_the_run_safely_and_records_who(tmp_path):
    with client_for(make_settings(tmp_path, lease_ttl_s=3.0)) as api:
        op = api.tokens.operator
        run_id = api.post("/api/runs", json={"scenario": LONG, "rig": "real-a"}, headers=H(op)).json()["id"]
        wait_until(lambda: (_state(api, run_id, op)["progress_s"] or 0) > 0.5, 60, 0.1, "the run to be under way")
        queued = api.post("/api/runs", json={"scenario": SHORT, "rig": "real-a"}, headers=H(op)).json()["id"]
        assert api.get("/api/rigs/real-a", headers=H(op)).json()["state"] == "busy"
        assert api.post(f"/api/runs/{run_id}/abort", headers=H(api.tokens.operator2)).status_code == 403
        assert api.post(f"/api/runs/{run_id}/abort", headers=H(op)).status_code == 200
        run = wait_until(lambda: (r := _state(api, run_id, op))["state"] != "running" and r, 60, 0.1, "abort")
        assert run["state"] == "aborted" and run["aborted_by"] == "olga"
        assert run["verdict"] == "aborted" and "terminated (SIGTERM)" in run["reason"]
        record = api.get(run["record_url"], headers=H(op)).json()
        assert record["safe_stop"] and record["complete"]
        # a real rig runs one run at a time: the queued run starts once the aborted one released the rig
        assert wait_until(lambda: _state(api, queued, op)["state"] == "pass", 60, 0.1, "the next run")


def test_a_sigkilled_run_process_frees_the_rig_and_a_dead_lease_holder_within_its_ttl(tmp_path):
    ttl = 2.0
    with client_for(make_settings(tmp_path, lease_ttl_s=ttl)) as api:
        op = api.tokens.operator
        run_id = api.post("/api/runs", json={"scenario": LONG, "rig": "real-a"}, headers=H(op)).json()["id"]
        pid = wait_until(lambda: api.service.runner.children.get(run_id) and
                         api.service.runner.children[run_id].proc.pid, 30, 0.05, "the run process")
        wait_until(lambda: (_state(api, run_id, op)["progress_s"] or 0) > 0.2, 60, 0.1, "the run to be under way")
        os.kill(pid, signal.SIGKILL)
        killed = time.monotonic()
        wait_until(lambda: api.get("/api/rigs/real-a", headers=H(op)).json()["state"] == "free", ttl + 1, 0.05,
                   "the rig to be free")
        assert time.monotonic() - killed <= ttl + 1
        run = wait_until(lambda: (r := _state(api, run_id, op))["state"] != "running" and r, 10, 0.1, "reaped")
        assert run["state"] == "aborted" and "signal 9" in run["reason"]


def test_drivebench_submit_and_a_sigkilled_service_reconciled_at_restart(tmp_path):
    from bench.service.client import Client
    from bench.service.core import Service

    port = free_port()
    settings = make_settings(tmp_path, lease_ttl_s=2.0)
    service = Service(settings)                     # migrate and make tokens before the server starts
    tokens = make_tokens(service.db)
    service.db.dispose()
    server = serve_process(tmp_path, port, "--lease-ttl", "2")
    url = f"http://127.0.0.1:{port}"
    env = {**os.environ, "DRIVEBENCH_TOKEN": tokens.operator}
    try:
        junit = tmp_path / "junit.xml"
        ok = subprocess.run([sys.executable, "-m", "bench", "submit", "--server", url, str(SCENARIOS / SHORT),
                             "--tag", "pmsm", "--wait", "--junit", str(junit)], env=env, cwd=REPO,
                            capture_output=True, text=True, timeout=120)
        assert ok.returncode == 0, ok.stderr
        assert "service-short: pass" in ok.stdout and f"{url}/runs/1" in ok.stdout
        assert 'failures="0"' in junit.read_text()
        bad = subprocess.run([sys.executable, "-m", "bench", "submit", "--server", url, str(SCENARIOS / "bad.toml"),
                              "--rig", "sim-a", "--wait"], env=env, cwd=REPO, capture_output=True, text=True,
                             timeout=60)
        assert bad.returncode == 2 and "Traceback" not in bad.stderr
        assert bad.stderr.splitlines()[0].startswith(f"{SCENARIOS / 'bad.toml'}: ")
        no_token = subprocess.run([sys.executable, "-m", "bench", "submit", "--server", url, SHORT, "--rig",
                                   "sim-a", "--token", "dbt_wrong"], cwd=REPO, capture_output=True, text=True,
                                  timeout=60)
        assert no_token.returncode == 2 and "401" in no_token.stderr

        # a CI job holding the real rig through the API is SIGKILLed: nobody extends its lease, it expires
        holder = subprocess.Popen([sys.executable, "-c", f"""
import time
from bench.service.client import Client
client = Client("{url}", "{tokens.operator2}")
lease = client.request("POST", "/api/rigs/real-a/lease", {{"ttl_s": 2, "reason": "ci job"}})
while True:
    time.sleep(0.3)
    client.request("POST", f"/api/leases/{{lease['id']}}/extend", {{"ttl_s": 2}})
"""], cwd=REPO)
        viewer = Client(url, tokens.viewer)
        wait_until(lambda: viewer.request("GET", "/api/rigs/real-a")["state"] == "reserved", 30, 0.05, "the hold")
        time.sleep(1.0)
        holder.kill()
        holder.wait(timeout=10)
        killed = time.monotonic()
        # TTL + 1 s on an idle machine (benchmarks/service.py: 2.00 s); the suite's own load on 2 cores adds to it
        wait_until(lambda: viewer.request("GET", "/api/rigs/real-a")["state"] == "free", 2.0 + 3, 0.05,
                   "the dead holder's lease to expire")
        assert time.monotonic() - killed <= 2.0 + 3

        # a long run on the real rig and one queued behind it; then the service is SIGKILLed
        long_run = subprocess.run([sys.executable, "-m", "bench", "submit", "--server", url, LONG, SHORT,
                                   "--rig", "real-a"], env=env, cwd=REPO, capture_output=True, text=True, timeout=60)
        assert long_run.returncode == 0, long_run.stderr
        long_id, short_id = (int(n) for n in re.findall(r": run (\d+) queued", long_run.stdout))
        from bench.service.db import Run, open_database
        db = open_database(service.db.url)
        wait_until(lambda: (r := db.sessions().get(Run, long_id)).state == "running" and r.pid, 30, 0.1,
                   "the long run to start")
        with db.session() as s:
            child_pid, out_dir = s.get(Run, long_id).pid, Path(s.get(Run, long_id).run_dir)
        # the run is under way (under load its imports alone can take seconds; a SIGTERM before the run's own
        # handler is installed, which comes after its first record.json is written, ends it without closing the
        # record): now the service dies
        wait_until(lambda: any(out_dir.glob("*/record.json")), 60, 0.1, "the long run's record")
        wait_until(lambda: (db.sessions().get(Run, long_id).progress_s or 0) > 0, 60, 0.1, "the long run's progress")
        time.sleep(0.5)
        server.kill()
        server.wait(timeout=10)
        killed, killed_wall = time.monotonic(), time.time()
        # the run process follows its service (SIGTERM: safe stop, record closed) ...
        wait_until(lambda: not _alive(child_pid), 30, 0.1, "the orphaned run process to stop")
        # ... and the real rig's lease, no longer extended, expires within its TTL of the kill (judged on the
        # lease's own expiry time: the wait for the run process above can take seconds on a loaded machine)
        from bench.service.db import Lease
        from bench.service.leases import active_leases
        wait_until(lambda: not active_leases(db.sessions(), "real-a"), max(0.0, killed + 2.0 + 3 - time.monotonic())
                   + 0.5, 0.05, "the lease to expire")
        with db.session() as s:
            lease = s.query(Lease).filter(Lease.run_id == long_id).one()
            assert lease.expires_ts <= killed_wall + 2.0 + 1.0, lease.expires_ts - killed_wall

        from bench.service.runner import Runner, RunnerSettings
        runner = Runner(db, RunnerSettings(data_dir=(tmp_path / "data").resolve()))
        assert runner.reconcile() == [long_id]
        with db.session() as s:
            aborted, queued = s.get(Run, long_id), s.get(Run, short_id)
            assert aborted.state == "aborted" and "the service stopped while the run was running" in aborted.reason
            assert "record says: aborted (terminated (SIGTERM))" in aborted.reason
            assert Path(aborted.run_dir, "record.json").is_file() and aborted.criteria
            assert queued.state == "queued"
        db.dispose()
        server = serve_process(tmp_path, port, "--lease-ttl", "2")      # the restarted service runs the queue
        waited = subprocess.run([sys.executable, "-c", f"""
import sys
from bench.service.client import Client
runs = Client("{url}", "{tokens.viewer}").wait([{short_id}], 60)
sys.exit(0 if runs[{short_id}]["state"] == "pass" else 1)
"""], cwd=REPO, timeout=90)
        assert waited.returncode == 0
    finally:
        stop_process(server)
    logs = "".join(p.read_text(errors="replace") for p in tmp_path.rglob("*.log"))
    for token in (tokens.operator, tokens.viewer):
        assert token not in logs          # tokens never logged


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:        # a zombie is dead: its parent (the killed service) is gone, init reaps it
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return False
