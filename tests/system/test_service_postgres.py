"""The bench service on a real PostgreSQL server (a throwaway cluster from Debian's binaries, tests/
service_fixtures.py): migrations, the API, a run through the queue, and two services racing for one real rig."""

from __future__ import annotations

import threading

import pytest

pytest.importorskip("fastapi", reason="the [service] extra is not installed")

from tests.service_fixtures import (SHORT, Tokens, client_for, fresh_pg_database, make_settings,  # noqa: E402
                                    pg_url, wait_until)

H = Tokens.header
__all__ = ["pg_url"]


def test_migrations_api_and_a_run_on_postgresql(pg_url, tmp_path):
    url = fresh_pg_database(pg_url, "service_run")
    with client_for(make_settings(tmp_path, db_url=url, lease_ttl_s=3.0)) as api:
        assert not api.service.db.is_sqlite
        assert api.get("/api/health").json()["database"] == "postgresql"
        from bench.service.db import schema_tables
        assert {"tokens", "rigs", "runs", "leases", "criterion_values", "alembic_version"} <= \
            schema_tables(api.service.db.engine)
        op = api.tokens.operator
        assert api.get("/api/rigs", headers={}).status_code == 401
        assert api.post("/api/runs", json={"scenario": SHORT, "rig": "sim-a"}, headers=H(api.tokens.viewer)
                        ).status_code == 403
        run_id = api.post("/api/runs", json={"scenario": SHORT, "tag": "pmsm"}, headers=H(op)).json()["id"]
        run = wait_until(lambda: (r := api.get(f"/api/runs/{run_id}", headers=H(op)).json())["state"]
                         not in ("queued", "running") and r, 60, 0.1, "the run to finish")
        assert run["state"] == "pass" and run["criteria"]
        trend = api.get("/api/trend", params={"criterion": run["criteria"][0]["name"]}, headers=H(op)).json()
        assert trend[0]["run_id"] == run_id


def test_two_services_sharing_postgresql_never_both_lease_a_real_rig(pg_url, tmp_path):
    from bench.service.auth import Principal
    from bench.service.db import open_database
    from bench.service.errors import ApiError
    from bench.service.leases import reserve

    url = fresh_pg_database(pg_url, "service_race")
    with client_for(make_settings(tmp_path, db_url=url, run_queue=False)):
        pass                                  # migrated, rigs synced
    databases = [open_database(url) for _ in range(8)]
    barrier = threading.Barrier(len(databases))
    granted, refused = [], []

    def attempt(i):
        barrier.wait(timeout=30)
        try:
            granted.append(reserve(databases[i], "real-a", Principal(i, f"user{i}", "operator"), 60, "race").id)
        except ApiError as exc:
            refused.append(exc.status)

    threads = [threading.Thread(target=attempt, args=(i,)) for i in range(len(databases))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    for db in databases:
        db.dispose()
    assert len(granted) == 1 and refused == [409] * (len(databases) - 1)
