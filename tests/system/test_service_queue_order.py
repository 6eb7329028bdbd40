"""Queue order (docs/service.md, "Queue order"): a run that can start starts within a second whatever is queued
for rigs that cannot take one (disabled, reserved by someone else), FIFO per rig, and a reservation holder's own
runs go first on the reserved rig. Real run processes, the service's own database."""

from __future__ import annotations

import time

import pytest

pytest.importorskip("fastapi", reason="the [service] extra is not installed")

from tests.service_fixtures import SCENARIOS, SHORT, Tokens, client_for, make_settings, wait_until  # noqa: E402

H = Tokens.header


def _queue(db, rig: str | None, n: int, owner: str = "carl", tag: str | None = None,
           candidates: list[str] | None = None) -> list[int]:
    """`n` queued runs straight into the database (as submit leaves them), without validating each."""
    from bench.service.db import Run, RunCandidate

    ids = []
    with db.session() as s:
        for _ in range(n):
            run = Run(state="queued", rig=rig, tag=tag, candidates=candidates, scenario=SHORT,
                      scenario_file=str(SCENARIOS / SHORT), scenario_name="service-short", owner=owner)
            s.add(run)
            s.flush()
            s.add_all(RunCandidate(run_id=run.id, rig=c) for c in candidates or [])
            ids.append(run.id)
    return ids


def test_a_run_for_a_free_rig_starts_within_a_second_behind_150_that_cannot(tmp_path):
    with client_for(make_settings(tmp_path, lease_ttl_s=3.0, max_parallel=2)) as api:
        db, op = api.service.db, api.tokens.operator
        assert api.patch("/api/rigs/spim-a", json={"enabled": False}, headers=H(api.tokens.admin)).status_code == 200
        assert api.post("/api/rigs/real-a/lease", json={"ttl_s": 300, "reason": "manual work"},
                        headers=H(api.tokens.operator2)).status_code == 201
        starving = (_queue(db, "spim-a", 100) + _queue(db, "real-a", 25)
                    + _queue(db, None, 25, tag="lab", candidates=["real-a"]))
        latencies = {}
        for body in ({"scenario": SHORT, "rig": "sim-a"}, {"scenario": SHORT, "tag": "pmsm"}):
            run_id = api.post("/api/runs", json=body, headers=H(op)).json()["id"]
            sent = time.monotonic()          # queued (validation, which the submit does first, is not queueing)
            run = wait_until(lambda: (r := api.get(f"/api/runs/{run_id}", headers=H(op)).json())["state"] != "queued"
                             and r, 10, 0.02, f"run {run_id} to start")
            latencies[run_id] = time.monotonic() - sent
            assert run["state"] == "running" and run["rig"] == "sim-a", run
        waited = wait_until(lambda: all(api.get(f"/api/runs/{i}", headers=H(op)).json()["state"] == "pass"
                                        for i in latencies), 60, 0.2, "both runs to pass")
        assert waited
        from bench.service.db import Run
        with db.session() as s:
            recorded = {i: s.get(Run, i).started_ts - s.get(Run, i).submitted_ts for i in latencies}
            assert all(s.get(Run, i).state == "queued" for i in starving)
    print(f"\nQUEUE 150 runs that cannot start ahead: submit -> running seen by the client "
          f"{', '.join(f'{v * 1000:.0f} ms' for v in latencies.values())}; submitted -> started in the database "
          f"{', '.join(f'{v * 1000:.0f} ms' for v in recorded.values())}")
    assert all(v < 1.0 for v in latencies.values()) and all(v < 1.0 for v in recorded.values()), (latencies, recorded)


def test_fifo_per_rig_and_a_reservation_holders_runs_go_first_on_her_rig(tmp_path):
    with client_for(make_settings(tmp_path, lease_ttl_s=3.0, max_parallel=1)) as api:
        db, op = api.service.db, api.tokens.operator
        api.service.runner.settings.max_parallel = 0          # hold the queue while it is filled
        assert api.post("/api/rigs/real-a/lease", json={"ttl_s": 300, "reason": "her own tests"},
                        headers=H(op)).status_code == 201
        others = _queue(db, "real-a", 1, owner="oscar")       # blocked by olga's reservation
        hers = _queue(db, "real-a", 1, owner="olga")
        sim = _queue(db, "sim-a", 2, owner="oscar")           # FIFO on sim-a, after hers (one host slot)
        api.service.runner.settings.max_parallel = 1
        api.service.runner.wake()

        from bench.service.db import Run

        def started():
            with db.session() as s:
                return {i: s.get(Run, i) for i in (*others, *hers, *sim)}

        runs = wait_until(lambda: (r := started()) and all(r[i].state == "pass" for i in (*hers, *sim)) and r, 90,
                          0.2, "her run and the two sim-a runs to pass")
        order = sorted((*hers, *sim), key=lambda i: runs[i].started_ts)
        assert order == [*hers, *sim]
        assert runs[others[0]].state == "queued"
