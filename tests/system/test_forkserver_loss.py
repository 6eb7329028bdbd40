"""SIGKILL of the service's fork server (the OOM killer's likely pick: the largest process) loses no run: the run it
forked goes on and ends by its own verdict, the runner does not stall, the next queued run runs, and /api/health
says what happened and that a new fork server was started."""

from __future__ import annotations

import os
import signal
from multiprocessing import forkserver

from tests.service_fixtures import LONG, SHORT, client_for, make_settings, wait_until


def test_a_sigkilled_fork_server_loses_no_run_and_health_says_so(tmp_path):
    with client_for(make_settings(tmp_path, lease_ttl_s=3.0)) as api:
        runner, op = api.service.runner, {"Authorization": f"Bearer {api.tokens.operator}"}
        assert runner._forkserver_ready.wait(120), "the fork server's preload"
        first = api.post("/api/runs", json={"scenario": LONG, "rig": "real-a"}, headers=op).json()["id"]
        second = api.post("/api/runs", json={"scenario": SHORT, "rig": "real-a"}, headers=op).json()["id"]
        wait_until(lambda: (api.get(f"/api/runs/{first}", headers=op).json()["progress_s"] or 0) > 0.5, 90, 0.1,
                   "the first run to be under way")
        assert runner.children[first].warm
        server = forkserver._forkserver._forkserver_pid
        os.kill(server, signal.SIGKILL)
        health = wait_until(lambda: (h := api.get("/api/health").json()).get("fork_server", {}).get("lost") and h, 5,
                            0.05, "/api/health to say the fork server was lost")
        assert health["fork_server"]["last_lost"]["pid"] == server, health
        assert health["fork_server"]["last_lost"]["how"] == "killed by signal 9", health
        assert health["run_processes"] in ("warming", "warm"), health        # a new one is preloading
        assert api.get(f"/api/runs/{first}", headers=op).json()["state"] == "running"
        run = wait_until(lambda: (r := api.get(f"/api/runs/{first}", headers=op).json())["state"]
                         not in ("queued", "running") and r, 180, 0.2, "the first run to end")
        assert run["state"] == "pass" and run["verdict"] == "pass", run      # its own verdict: not killed with it
        run = wait_until(lambda: (r := api.get(f"/api/runs/{second}", headers=op).json())["state"]
                         not in ("queued", "running") and r, 180, 0.2, "the queued run to run")
        assert run["state"] == "pass", run
        assert runner.fenced is None, runner.fenced                           # the runner never stalled
        wait_until(lambda: api.get("/api/health").json()["run_processes"] == "warm", 120, 0.2, "a new fork server")
        health = api.get("/api/health").json()
        assert health["fork_server"]["pid"] not in (None, server), health
