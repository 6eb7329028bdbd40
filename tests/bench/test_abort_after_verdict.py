"""An abort of a run whose process has already sent its verdict is 409 (docs/service.md: "409 if already final"),
not a 200 that turned the finished run into `aborted` with `verdict = pass`; the verdict stands."""

from __future__ import annotations

import threading

from tests.service_fixtures import SHORT, client_for, make_settings, wait_until
import pytest

pytestmark = pytest.mark.slow


def test_abort_after_the_run_sent_its_verdict_is_409_and_the_verdict_stands(tmp_path, monkeypatch):
    from bench.service.runner import Runner

    hold = threading.Event()            # the runner indexes the finished run only once the abort was tried
    reap = Runner._reap
    monkeypatch.setattr(Runner, "_reap", lambda self: reap(self) if hold.is_set() else None)
    with client_for(make_settings(tmp_path, lease_ttl_s=3.0)) as api:
        op = {"Authorization": f"Bearer {api.tokens.operator}"}
        runner = api.service.runner
        run_id = api.post("/api/runs", json={"scenario": SHORT, "rig": "sim-a"}, headers=op).json()["id"]
        wait_until(lambda: runner.children.get(run_id) and runner.children[run_id].result is not None, 120, 0.05,
                   "the run process's verdict")
        answer = api.post(f"/api/runs/{run_id}/abort", headers=op)
        assert answer.status_code == 409, answer.text
        assert "already finished (pass)" in str(answer.json()["detail"]), answer.text
        hold.set()
        run = wait_until(lambda: (r := api.get(f"/api/runs/{run_id}", headers=op).json())["state"]
                         not in ("queued", "running") and r, 30, 0.1, "the run to be indexed")
        assert run["state"] == "pass" and run["verdict"] == "pass" and not run.get("aborted_by"), run
        again = api.post(f"/api/runs/{run_id}/abort", headers=op)
        assert again.status_code == 409 and "already pass" in str(again.json()["detail"]), again.text
