"""One real rig, one holder, provably: two `drivebench serve` processes on one database (SQLite file and
PostgreSQL) race for one exclusive rig through start-ups, a refused duplicate --host-id, SIGKILLs, restarts and a
graceful restart. The database's own record of every run's interval must show one run at a time; no live run is
taken over; a SIGKILLed holder's run is taken over only after its instance lease expired and its process ended.
Below that, the claim itself: many runners in threads claiming one real rig at the same moment, one wins."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

pytest.importorskip("fastapi", reason="the [service] extra is not installed")

from tests.service_fixtures import (LONG, REPO, SCENARIOS, SHORT, fresh_pg_database, free_port,  # noqa: E402
                                    make_settings, make_tokens, pg_url, stop_process, wait_until, write_rigs)

__all__ = ["pg_url"]
TTL_S = 2.0
RIG = "real-a"


def _database(kind: str, request, tmp_path: Path, name: str) -> str | None:
    """None: the default SQLite file in --data; else a fresh PostgreSQL database."""
    if kind == "sqlite":
        return None
    return fresh_pg_database(request.getfixturevalue("pg_url"), name)


def _serve(tmp_path: Path, db_url: str | None, *extra: str, capture: bool = False) -> tuple[subprocess.Popen, int]:
    """`drivebench serve` on a free port; its output in serve-PORT.log (or piped, for a process that exits)."""
    port = free_port()
    args = [sys.executable, "-m", "bench", "serve", "--data", str(tmp_path / "data"), "--port", str(port),
            "--rigs", str(tmp_path / "rigs.toml"), "--scenarios", str(SCENARIOS), "--lease-ttl", str(TTL_S), *extra]
    if db_url:
        args += ["--db", db_url]
    if capture:
        out = err = subprocess.PIPE
    else:
        out = open(tmp_path / f"serve-{port}.log", "ab")
        err = subprocess.STDOUT
    proc = subprocess.Popen(args, cwd=REPO, stdout=out, stderr=err, text=capture, start_new_session=True)
    proc.log = tmp_path / f"serve-{port}.log"
    if not capture:
        out.close()
    return proc, port


def _up(proc: subprocess.Popen, port: int) -> None:
    import urllib.request

    def answers():
        assert proc.poll() is None, f"serve exited {proc.returncode}: {proc.log.read_text()[-2000:]}"
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/health", timeout=1):
                return True
        except OSError:
            return False

    wait_until(answers, 40, 0.1, "drivebench serve to answer")


def _runs(db) -> list:
    from sqlalchemy import select

    from bench.service.db import Run

    with db.session() as s:
        return list(s.execute(select(Run).order_by(Run.id)).scalars())


def _running(db):
    return next((r for r in _runs(db) if r.state == "running" and r.pid), None)


@pytest.mark.parametrize("kind", ["sqlite", "postgresql"])
def test_two_services_race_for_one_real_rig_through_startups_kills_and_restarts(kind, request, tmp_path):
    from sqlalchemy import select

    from bench.service.client import Client
    from bench.service.core import Service
    from bench.service.db import Instance, open_database
    from bench.service.instances import process_alive, process_start

    write_rigs(tmp_path)
    db_url = _database(kind, request, tmp_path, "rig_race")
    service = Service(make_settings(tmp_path, db_url=db_url, lease_ttl_s=TTL_S))     # migrate, tokens
    tokens = make_tokens(service.db)
    url = service.db.url
    service.db.dispose()
    db = open_database(url)
    text = (SCENARIOS / SHORT).read_text().replace("duration_s = 1.0", "duration_s = 3.0")
    servers: dict[str, tuple[subprocess.Popen, int]] = {}

    def submit(n: int, scenario: str = text) -> list[int]:
        proc, port = next(v for v in servers.values() if v[0].poll() is None)
        client = Client(f"http://127.0.0.1:{port}", tokens.operator)
        return [client.request("POST", "/api/runs", {"scenario_toml": scenario, "filename": "race.toml",
                                                     "rig": RIG})["id"] for _ in range(n)]

    takeovers: list[dict] = []
    killed_instances: set[int] = set()
    try:
        # A starts (default --host-id: the host name) and runs on the real rig
        servers["a"] = _serve(tmp_path, db_url)
        _up(*servers["a"])
        first = submit(1, text.replace("duration_s = 3.0", "duration_s = 30.0"))[0]   # alive while B is refused
        run = wait_until(lambda: _running(db), 30, 0.05, "the first run to start")
        assert run.id == first

        # B with the same default --host-id while A lives: refused at start-up with one line, exit 2;
        # A's live run goes on untouched
        dup, _ = _serve(tmp_path, db_url, capture=True)
        out, err = dup.communicate(timeout=60)
        lines = [line for line in err.splitlines() if line.strip()]
        assert dup.returncode == 2 and len(lines) == 1 and "--host-id" in lines[0] and "live service instance" \
            in lines[0], err
        assert "Traceback" not in err
        again = {r.id: r for r in _runs(db)}[first]
        untouched = (again.state == "running" and process_alive(again.pid, again.pid_start)) or (
            again.state == "pass" and again.reason is None and again.instance_id == run.instance_id)  # ended by itself
        assert untouched, (again.state, again.reason)

        # B as another instance: both schedule from one queue on one rig
        servers["b"] = _serve(tmp_path, db_url, "--host-id", "race-b")
        _up(*servers["b"])
        submit(5)

        # SIGKILL the holder of the rig three times (alternating as it happens), restart it at once
        for round_ in range(3):
            holder = wait_until(lambda: (r := _running(db)) and r.id not in [t["run"] for t in takeovers] and r,
                                60, 0.05, "a run on the rig")
            who = "b" if holder.host == "race-b" else "a"
            pid, pid_start = holder.pid, holder.pid_start
            assert pid_start == process_start(pid)
            proc, _ = servers[who]
            proc.kill()
            proc.wait(timeout=10)
            killed = time.time()
            with db.session() as s:
                inst = s.get(Instance, holder.instance_id)
                expires = inst.expires_ts
            killed_instances.add(holder.instance_id)
            # restart the killed one at once with its --host-id: its process is gone, so it may
            servers[who] = _serve(tmp_path, db_url, *(["--host-id", "race-b"] if who == "b" else []))
            gone = wait_until(lambda: not process_alive(pid, pid_start) and time.time(), 60, 0.02,
                              "the orphaned run process to stop")
            taken = wait_until(lambda: (r := {r.id: r for r in _runs(db)}[holder.id]).state != "running" and r,
                               30, 0.05, "the takeover")
            assert taken.state == "aborted" and "taken over by" in taken.reason, taken.reason
            assert taken.ended_ts >= expires, (taken.ended_ts, expires)   # only after its instance lease expired
            assert taken.ended_ts >= gone - 0.1                             # ... and its process had ended
            takeovers.append({"run": holder.id, "instance": who, "kill_to_takeover_s": taken.ended_ts - killed,
                              "kill_to_expiry_s": expires - killed, "kill_to_process_end_s": gone - killed})
            _up(*servers[who])

        # a graceful restart of one instance mid-queue
        proc, _ = servers["a"]
        stop_process(proc)
        servers["a"] = _serve(tmp_path, db_url)
        _up(*servers["a"])
        submit(1)
        wait_until(lambda: all(r.state not in ("queued", "running") for r in _runs(db)), 180, 0.2,
                   "every run to end")
    finally:
        for proc, _ in servers.values():
            stop_process(proc)

    runs = [r for r in _runs(db) if r.started_ts is not None]
    with db.session() as s:
        instances = {i.id: i for i in s.execute(select(Instance)).scalars()}
    db.dispose()
    intervals = sorted((r.started_ts, r.ended_ts, r.id) for r in runs)
    overlaps = [(a, b) for a, b in zip(intervals, intervals[1:]) if b[0] < a[1]]
    aborted = [r for r in runs if r.state == "aborted"]
    print(f"\nRACE {kind}: runs={len(runs)} states={sorted(r.state for r in runs)} overlaps={len(overlaps)} "
          f"instances={len(instances)} takeovers=" + "; ".join(
              f"run {t['run']} ({t['instance']}): expiry +{t['kill_to_expiry_s']:.2f} s, process end "
              f"+{t['kill_to_process_end_s']:.2f} s, takeover +{t['kill_to_takeover_s']:.2f} s" for t in takeovers))
    assert len(runs) == 7 and not overlaps, overlaps
    # aborted: the three SIGKILLed holders' runs (taken over) and whatever ran at the graceful restart; never a
    # run of an instance that was alive
    assert {r.id for r in aborted if "taken over" in r.reason} == {t["run"] for t in takeovers}
    for r in aborted:
        assert r.instance_id in killed_instances or "taken over" not in r.reason
    assert sum(r.state == "pass" for r in runs) >= 3


@pytest.mark.parametrize("kind", ["sqlite", "postgresql"])
def test_many_runners_claiming_one_real_rig_at_once_one_wins(kind, request, tmp_path):
    """Eight runner instances (own database connections and instance leases) claim eight queued runs on one real
    rig at the same moment: exactly one claim succeeds; then, on the database itself, a second unreleased run lease
    on the rig is refused whatever the code above it decided."""
    from sqlalchemy.exc import IntegrityError

    from bench.service.core import Service
    from bench.service.db import Lease, Rig, Run, now, open_database
    from bench.service.runner import Runner, RunnerSettings

    db_url = _database(kind, request, tmp_path, "claim_race")
    service = Service(make_settings(tmp_path, db_url=db_url))
    url = service.db.url
    service.db.dispose()
    setup = open_database(url)
    with setup.session() as s:
        ids = []
        for i in range(8):
            run = Run(state="queued", rig=RIG, scenario=SHORT, scenario_file=str(SCENARIOS / SHORT), owner="olga")
            s.add(run)
            s.flush()
            ids.append(run.id)
    runners = []
    for i in range(8):
        runner = Runner(open_database(url), RunnerSettings(data_dir=tmp_path / "data", host_id=f"claimer-{i}"))
        runner.register()
        runners.append(runner)
    with setup.session() as s:
        rig = s.get(Rig, RIG)
        runs = [s.get(Run, i) for i in ids]
    barrier = threading.Barrier(len(runners))
    won: list[int] = []

    def claim(i):
        barrier.wait(timeout=30)
        if runners[i]._claim(runs[i], rig) is not None:
            won.append(i)

    threads = [threading.Thread(target=claim, args=(i,)) for i in range(len(runners))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert len(won) == 1, won
    with setup.session() as s:
        assert sum(s.get(Run, i).state == "running" for i in ids) == 1
    # below the code: the partial unique index refuses a second unreleased run lease on a real rig
    with pytest.raises(IntegrityError):
        with setup.session() as s:
            s.add(Lease(rig=RIG, holder="forged", kind="run", run_id=ids[-1], created_ts=now(),
                        expires_ts=now() + 60, exclusive_rig=True))
    for runner in runners:
        runner.db.dispose()
    setup.dispose()


BAD_SERVE_OPTIONS = [
    (["--lease-ttl", "-1"], "--lease-ttl"), (["--lease-ttl", "nan"], "--lease-ttl"),
    (["--lease-ttl", "inf"], "--lease-ttl"), (["--lease-ttl", "0"], "--lease-ttl"),
    (["--lease-ttl", "1e9"], "--lease-ttl"), (["--max-parallel", "-1"], "--max-parallel"),
    (["--max-parallel", "0"], "--max-parallel"), (["--max-parallel", "100000"], "--max-parallel"),
    (["--port", "0"], "--port"), (["--port", "99999"], "--port"), (["--port", "-5"], "--port"),
    (["--live-grpc-port", "70000"], "--live-grpc-port"), (["--live-web-port", "0"], "--live-web-port"),
    (["--host-id", ""], "--host-id"), (["--host-id", " padded "], "--host-id"),
]


@pytest.mark.parametrize("args,field", BAD_SERVE_OPTIONS, ids=[" ".join(a) for a, _ in BAD_SERVE_OPTIONS])
def test_serve_numbers_out_of_range_give_one_line_and_exit_2(args, field, tmp_path):
    from click.testing import CliRunner

    from bench.faces.cli import cli

    result = CliRunner().invoke(cli, ["serve", "--data", str(tmp_path / "data"), *args])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1 and lines[0].startswith(f"serve: {field}: "), result.output
    assert not (tmp_path / "data").exists()          # refused before anything was opened or started


def test_a_frozen_holder_keeps_its_run_and_fences_itself_when_it_wakes(tmp_path):
    """SIGSTOP the service holding the real rig for three TTLs: its lease expires, but its process and its run's
    process live (the run goes on driving the rig), so the other instance takes nothing over and starts nothing on
    the rig. SIGCONT: the woken instance finds its lease gone, stops its run (SIGTERM, safe stop), registers anew;
    then the queue goes on."""
    from bench.service.client import Client
    from bench.service.core import Service
    from bench.service.db import Instance, open_database
    from bench.service.instances import process_alive

    write_rigs(tmp_path)
    service = Service(make_settings(tmp_path, lease_ttl_s=TTL_S))
    tokens = make_tokens(service.db)
    url = service.db.url
    service.db.dispose()
    db = open_database(url)
    servers = {"frozen-a": _serve(tmp_path, None, "--host-id", "frozen-a"),
               "other-b": _serve(tmp_path, None, "--host-id", "other-b")}
    try:
        for proc, port in servers.values():
            _up(proc, port)
        client = Client(f"http://127.0.0.1:{servers['other-b'][1]}", tokens.operator)
        endless = (SCENARIOS / LONG).read_text().replace("duration_s = 60.0", "duration_s = 300.0")
        first = client.request("POST", "/api/runs", {"scenario_toml": endless, "filename": "endless.toml",
                                                      "rig": RIG})["id"]
        run = wait_until(lambda: (r := _running(db)) and (r.progress_s or 0) > 0 and r, 60, 0.05, "the run")
        second = client.request("POST", "/api/runs", {"scenario": SHORT, "rig": RIG})["id"]
        holder = servers[run.host][0]
        os.kill(holder.pid, signal.SIGSTOP)        # the service only: its run process goes on
        frozen = time.time()
        try:
            time.sleep(3 * TTL_S)
            runs = {r.id: r for r in _runs(db)}
            with db.session() as s:
                assert s.get(Instance, run.instance_id).expires_ts < time.time()      # its lease expired ...
            assert runs[first].state == "running" and runs[second].state == "queued"  # ... nothing taken over
            assert process_alive(run.pid, run.pid_start)
        finally:
            os.kill(holder.pid, signal.SIGCONT)
        ended = wait_until(lambda: (r := {r.id: r for r in _runs(db)}[first]).state != "running" and r, 60, 0.1,
                           "the woken instance to stop its run")
        assert ended.state == "aborted" and "SIGTERM" in (ended.reason or ""), ended.reason
        assert "taken over" not in ended.reason and not process_alive(run.pid, run.pid_start)
        nxt = wait_until(lambda: (r := {r.id: r for r in _runs(db)}[second]).state not in ("queued", "running")
                         and r, 60, 0.1, "the queued run")
        assert nxt.state == "pass" and nxt.started_ts >= ended.ended_ts
        with db.session() as s:
            names = [i.name for i in s.execute(select_instances()).scalars()]
        assert names.count(run.host) == 2            # it registered anew after fencing
        print(f"\nFROZEN holder: stopped {3 * TTL_S:.0f} s (TTL {TTL_S:g} s): no takeover; woken, its run ended "
              f"{ended.ended_ts - frozen:.2f} s after the freeze; the next run started "
              f"{nxt.started_ts - ended.ended_ts:.2f} s after that")
    finally:
        for proc, _ in servers.values():
            stop_process(proc)
        db.dispose()


def select_instances():
    from sqlalchemy import select

    from bench.service.db import Instance

    return select(Instance).order_by(Instance.id)


def test_a_real_rig_whose_run_lease_expired_unreleased_stays_busy_until_released(tmp_path):
    """A run's lease on a real rig that expired without release (its service died; the run not yet taken over):
    the rig shows busy and cannot be reserved; once the lease is released (takeover), it is free."""
    from fastapi.testclient import TestClient  # noqa: F401  (the [service] extra)

    from bench.service.db import Lease, Run, now
    from bench.service.limits import READ_CACHE_S
    from tests.service_fixtures import Tokens, client_for, wait_until

    H = Tokens.header
    with client_for(make_settings(tmp_path, run_queue=False)) as api:
        with api.service.db.session() as s:
            run = Run(state="running", rig=RIG, scenario=SHORT, scenario_file=str(SCENARIOS / SHORT), owner="olga")
            s.add(run)
            s.flush()
            lease = Lease(rig=RIG, holder=f"run {run.id} (olga)", kind="run", run_id=run.id, created_ts=now() - 60,
                          expires_ts=now() - 30, exclusive_rig=True)
            s.add(lease)
            s.flush()
            lease_id = lease.id
        viewer = H(api.tokens.viewer)
        assert api.get(f"/api/rigs/{RIG}", headers=viewer).json()["state"] == "busy"
        assert {r["name"]: r["state"] for r in api.get("/api/rigs", headers=viewer).json()}[RIG] == "busy"
        refused = api.post(f"/api/rigs/{RIG}/lease", json={"ttl_s": 60}, headers=H(api.tokens.operator2))
        assert refused.status_code == 409 and "not released" in refused.json()["detail"]
        with api.service.db.session() as s:      # released by another instance's takeover: this one's answers
            s.get(Lease, lease_id).released_ts = now()     # show it within their age
        wait_until(lambda: api.get(f"/api/rigs/{RIG}", headers=viewer).json()["state"] == "free",
                   READ_CACHE_S + 0.5, 0.05, "the rig to show free")
        assert api.post(f"/api/rigs/{RIG}/lease", json={"ttl_s": 60}, headers=H(api.tokens.operator2)
                        ).status_code == 201
