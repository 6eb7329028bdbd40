"""The run queue's worker: claims queued runs for free rigs, runs each in its own `drivebench run` process, keeps
the run's lease alive while the process lives, indexes the record when it ends, and reconciles after a crash.

One thread does all of it (one loop, no locks between schedulers); a service instance only touches the runs it
started (`host`), so several instances can share one PostgreSQL database.
"""

from __future__ import annotations

import collections
import datetime as dt
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from sqlalchemy import select, update

from bench.errors import find_repo_root
from bench.service.db import CriterionValue, Database, Lease, Rig, Run, now
from bench.service.leases import active_leases
from bench.service.events import EventHub

TICK_S = 0.2
ABORT_KILL_AFTER_S = 60.0     # SIGTERM runs the safe stop; a run process still alive after this gets SIGKILL
STOP_WAIT_S = 30.0            # service shutdown: how long to wait for runs to finish their safe stop
PROGRESS_DB_PERIOD_S = 1.0
NICE = shutil.which("nice")
VERDICT_STATE = {"pass": "pass", "fail": "fail", "incomplete": "fail", "aborted": "aborted", "error": "error"}


@dataclass
class RunnerSettings:
    data_dir: Path
    lease_ttl_s: float = 10.0
    max_parallel: int = max(1, os.cpu_count() or 1)
    host_id: str = field(default_factory=socket.gethostname)
    rerun_url: str | None = None      # the service's Rerun gRPC server, if it runs one
    nice: int = 10                    # simulated runs only: the API answers first


@dataclass
class Child:
    run_id: int
    rig: str
    proc: subprocess.Popen
    out_dir: Path
    lease_id: int
    started: float
    tail: collections.deque = field(default_factory=lambda: collections.deque(maxlen=20))
    progress_s: float | None = None
    progress_written: float | None = None
    last_progress_db: float = 0.0
    term_sent: float | None = None
    reader: threading.Thread | None = None


def _record_of(out_dir: Path | None) -> tuple[Path | None, dict | None]:
    """The run directory `drivebench run --out out_dir` made, and its record.json (None if it made none)."""
    if out_dir is None or not out_dir.is_dir():
        return None, None
    for record in sorted(out_dir.glob("*/record.json")):
        try:
            return record.parent, json.loads(record.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return record.parent, None
    return None, None


def _parse_utc(value) -> float | None:
    try:
        return dt.datetime.fromisoformat(str(value).replace("Z", "+00:00")).timestamp() if value else None
    except ValueError:
        return None


def index_record(s, run: Run, record: dict | None, run_dir: Path | None) -> None:
    """Copy what the history needs from record.json into the run's row and its criterion rows."""
    if run_dir is not None:
        run.run_dir = str(run_dir)
    if not record:
        return
    verdict = record.get("verdict")
    run.verdict = verdict if verdict in VERDICT_STATE else None
    scenario = record.get("scenario") or {}
    run.scenario_name = scenario.get("name") or run.scenario_name
    run.scenario_sha256 = scenario.get("sha256") or run.scenario_sha256
    run.seed = record.get("seed", run.seed)
    drive = record.get("drive") or {}
    run.drive = drive.get("identity")
    run.firmware_version = drive.get("firmware_version")
    software = record.get("software") or {}
    run.software = software
    run.revision = software.get("git_revision")
    criteria = record.get("criteria") or []
    run.criteria = criteria
    s.query(CriterionValue).filter(CriterionValue.run_id == run.id).delete()
    for c in criteria:
        value, limit = c.get("value"), c.get("limit")
        s.add(CriterionValue(run_id=run.id, name=str(c.get("name")), signal=c.get("signal"),
                             value=value if isinstance(value, (int, float)) else None,
                             limit=limit if isinstance(limit, (int, float)) and not isinstance(limit, bool) else None,
                             passed=bool(c.get("passed")), status=c.get("status")))
    started, ended = _parse_utc(record.get("started_utc")), _parse_utc(record.get("ended_utc"))
    if started is not None and ended is not None:
        run.duration_s = max(0.0, ended - started)
    if record.get("abort_reason") and not run.reason:
        run.reason = record["abort_reason"]


def run_event(run: Run) -> dict:
    return {"type": "run", "id": run.id, "state": run.state, "verdict": run.verdict, "rig": run.rig,
            "progress_s": run.progress_s, "duration_s": run.scenario_duration_s, "reason": run.reason}


class Runner:
    def __init__(self, db: Database, settings: RunnerSettings, events: EventHub | None = None,
                 python: str = sys.executable):
        self.db = db
        self.settings = settings
        self.events = events or EventHub()
        self.python = python
        self.children: dict[int, Child] = {}
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_extend = 0.0
        self.root = find_repo_root()
        self.on_tick: Callable[[], None] | None = None

    # -- lifecycle ----------------------------------------------------------------------------------------

    def start(self) -> None:
        self.reconcile()
        self._thread = threading.Thread(target=self._loop, name="drivebench-runner", daemon=True)
        self._thread.start()

    def wake(self) -> None:
        self._wake.set()

    def stop(self, reason: str = "the service stopped") -> None:
        """Stop every run this instance started (SIGTERM: the safe stop), wait for them, record them aborted."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=10)
        for child in self.children.values():
            if child.proc.poll() is None:
                child.proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + STOP_WAIT_S
        for run_id, child in list(self.children.items()):
            try:
                child.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                child.proc.kill()
                child.proc.wait(timeout=10)
            self._finish(child, forced_reason=reason)
        self.children.clear()

    def reconcile(self) -> list[int]:
        """After a crash: this instance's runs still marked running become aborted, with the reason and whatever
        record their run process left; their leases are released. Queued runs stay queued."""
        done = []
        with self.db.session() as s:
            stale = s.execute(select(Run).where(Run.state == "running",
                                                (Run.host == self.settings.host_id) | Run.host.is_(None))).scalars()
            for run in stale:
                run_dir, record = _record_of(Path(run.run_dir) if run.run_dir else None)
                index_record(s, run, record, run_dir)
                run.state = "aborted"
                run.reason = ("the service stopped while the run was running (its run process was stopped with "
                              "it, SIGTERM: safe stop); reconciled at restart"
                              + (f"; the record says: {record.get('verdict')}"
                                 + (f" ({record.get('abort_reason')})" if record.get("abort_reason") else "")
                                 if record else "; no record"))
                run.ended_ts = run.ended_ts or now()
                s.execute(update(Lease).where(Lease.run_id == run.id, Lease.released_ts.is_(None))
                          .values(released_ts=now(), released_by="reconcile"))
                done.append(run.id)
        return done

    # -- the loop -----------------------------------------------------------------------------------------

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                self.tick()
            except Exception as exc:  # the loop must survive a database hiccup; the next tick retries
                print(f"drivebench serve: runner: {type(exc).__name__}: {exc}", file=sys.stderr)
            self._wake.wait(TICK_S)
            self._wake.clear()

    def tick(self) -> None:
        self._reap()
        self._extend_leases()
        self._handle_aborts()
        self._write_progress()
        if not self._stop.is_set():
            self._schedule()
        if self.on_tick:
            self.on_tick()

    def _reap(self) -> None:
        for run_id, child in list(self.children.items()):
            if child.proc.poll() is not None:
                if child.reader is not None:
                    child.reader.join(timeout=5)
                self._finish(child)
                del self.children[run_id]

    def _extend_leases(self) -> None:
        t = now()
        if not self.children or t - self._last_extend < self.settings.lease_ttl_s / 3:
            return
        alive = [c.lease_id for c in self.children.values() if c.proc.poll() is None]
        if alive:
            with self.db.session() as s:
                s.execute(update(Lease).where(Lease.id.in_(alive), Lease.released_ts.is_(None))
                          .values(expires_ts=t + self.settings.lease_ttl_s))
        self._last_extend = t

    def _handle_aborts(self) -> None:
        if not self.children:
            return
        with self.db.session() as s:
            wanted = s.execute(select(Run.id).where(Run.id.in_(list(self.children)),
                                                    Run.abort_requested_by.is_not(None))).scalars().all()
        for run_id in wanted:
            child = self.children[run_id]
            if child.proc.poll() is not None:
                continue
            if child.term_sent is None:
                child.proc.send_signal(signal.SIGTERM)      # the run's single safe-stop sequence
                child.term_sent = time.monotonic()
            elif time.monotonic() - child.term_sent > ABORT_KILL_AFTER_S:
                child.proc.kill()

    def _write_progress(self) -> None:
        t = time.monotonic()
        due = [c for c in self.children.values()
               if c.progress_s is not None and c.progress_s != c.progress_written
               and t - c.last_progress_db >= PROGRESS_DB_PERIOD_S]
        if not due:
            return
        with self.db.session() as s:
            for c in due:
                s.execute(update(Run).where(Run.id == c.run_id).values(progress_s=c.progress_s))
                c.progress_written = c.progress_s
                c.last_progress_db = t

    # -- scheduling ---------------------------------------------------------------------------------------

    def _schedule(self) -> None:
        if len(self.children) >= self.settings.max_parallel:
            return
        with self.db.session() as s:
            queued = s.execute(select(Run).where(Run.state == "queued").order_by(Run.id).limit(100)).scalars().all()
            rigs = {r.name: r for r in s.execute(select(Rig).where(Rig.enabled.is_(True))).scalars()}
        busy: set[str] = set()
        for run in queued:
            if len(self.children) >= self.settings.max_parallel:
                return
            names = [run.rig] if run.rig else sorted(n for n, r in rigs.items() if run.tag in r.tags
                                                     and (run.candidates is None or n in run.candidates))
            names = [n for n in names if n in rigs and n not in busy]
            names.sort(key=lambda n: sum(c.rig == n for c in self.children.values()))
            for name in names:
                lease_id = self._claim(run, rigs[name])
                if lease_id is not None:
                    self._spawn(run, rigs[name], lease_id)
                    break
                busy.add(name)

    def _claim(self, run: Run, rig: Rig) -> int | None:
        """In one transaction holding the rig's lock: is there room, is the run still queued; then mark it
        running and give it a lease."""
        t = now()
        with self.db.session() as s:
            if not self.db.lock_rig(s, rig.name):
                return None
            leases = active_leases(s, rig.name, at=t)
            runs = [l for l in leases if l.kind == "run"]
            if rig.simulated:
                if len(runs) >= rig.max_concurrent:
                    return None
            elif any(l.kind == "run" or l.holder != run.owner for l in leases):
                return None
            claimed = s.execute(update(Run).where(Run.id == run.id, Run.state == "queued").values(
                state="running", rig=rig.name, started_ts=t, host=self.settings.host_id)).rowcount
            if claimed != 1:
                return None
            lease = Lease(rig=rig.name, holder=f"run {run.id} ({run.owner})", kind="run", run_id=run.id,
                          reason=run.scenario_name or run.scenario, created_ts=t,
                          expires_ts=t + self.settings.lease_ttl_s)
            s.add(lease)
            s.flush()
            return lease.id

    def _spawn(self, run: Run, rig: Rig, lease_id: int) -> None:
        out_dir = self.settings.data_dir / "runs" / f"{run.id:06d}"
        command = [self.python, "-m", "bench", "run", run.scenario_file, "--bench", rig.bench, "--out", str(out_dir),
                   "--json"]
        if self.settings.rerun_url:
            command += ["--rerun", "connect", "--rerun-url", self.settings.rerun_url]
        env = {**os.environ, "DRIVEBENCH_PROGRESS": "jsonl", "DRIVEBENCH_RECORDING_ID": f"run-{run.id}",
               "DRIVEBENCH_PARENT_PID": str(os.getpid()), "PYTHONUNBUFFERED": "1"}
        env.pop("DRIVEBENCH_TOKEN", None)
        if rig.simulated and self.settings.nice and NICE is not None:
            command = [NICE, "-n", str(self.settings.nice), *command]    # from exec on: imports are CPU-heavy too
        if run.seed is not None:
            command += ["--seed", str(run.seed)]
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
            stdout = open(out_dir / "stdout.jsonl", "wb")
            proc = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=stdout, stderr=subprocess.PIPE,
                                    cwd=self.root, env=env, start_new_session=True)
            stdout.close()
        except OSError as exc:
            with self.db.session() as s:
                row = s.get(Run, run.id)
                row.state, row.reason, row.ended_ts = "error", f"cannot start the run process: {exc}", now()
                s.execute(update(Lease).where(Lease.id == lease_id).values(released_ts=now(), released_by="runner"))
                self.events.publish(run_event(row))
            return
        child = Child(run.id, rig.name, proc, out_dir, lease_id, time.monotonic())
        child.reader = threading.Thread(target=self._read_stderr, args=(child,), daemon=True,
                                        name=f"run-{run.id}-stderr")
        child.reader.start()
        self.children[run.id] = child
        with self.db.session() as s:
            row = s.get(Run, run.id)
            row.pid, row.run_dir = proc.pid, str(out_dir)
            self.events.publish(run_event(row))

    def _read_stderr(self, child: Child) -> None:
        """Progress lines become events; trips become events and stay in service.log; the rest goes there too."""
        with open(child.out_dir / "service.log", "ab") as log:
            for raw in child.proc.stderr:
                line = raw.decode("utf-8", "replace").rstrip("\n")
                if line.startswith('{"progress_s"'):
                    try:
                        data = json.loads(line)
                        child.progress_s = float(data["progress_s"])
                        self.events.publish({"type": "progress", "id": child.run_id, "progress_s": child.progress_s,
                                             "duration_s": data.get("duration_s")})
                        continue
                    except (ValueError, KeyError, TypeError):
                        pass
                if line.startswith('{"trip"'):
                    try:
                        trip = json.loads(line)["trip"]
                        self.events.publish({"type": "trip", "id": child.run_id, "reason": str(trip["reason"]),
                                             "t_s": trip.get("t_s"), "message": str(trip.get("message", ""))})
                    except (ValueError, KeyError, TypeError):
                        pass
                log.write(raw)
                log.flush()
                if line.strip():
                    child.tail.append(line)
        child.proc.stderr.close()

    # -- finishing ----------------------------------------------------------------------------------------

    def _finish(self, child: Child, forced_reason: str | None = None) -> None:
        code = child.proc.poll()
        run_dir, record = _record_of(child.out_dir)
        t = now()
        with self.db.session() as s:
            run = s.get(Run, child.run_id)
            index_record(s, run, record, run_dir)
            verdict = (record or {}).get("verdict")
            if run.abort_requested_by and (child.term_sent is not None or verdict not in VERDICT_STATE):
                run.state = "aborted"
                run.aborted_by = run.abort_requested_by
                run.reason = f"aborted by {run.abort_requested_by}" + (
                    f" ({record.get('abort_reason')})" if record and record.get("abort_reason") else "")
            elif forced_reason and verdict not in VERDICT_STATE:
                run.state, run.reason = "aborted", forced_reason
            elif forced_reason:
                run.state = VERDICT_STATE[verdict]
                if run.state != "pass":
                    run.reason = f"{forced_reason}: {run.reason or verdict}"
            elif verdict in VERDICT_STATE:
                run.state = VERDICT_STATE[verdict]
            elif code is not None and code < 0:
                run.state, run.reason = "aborted", (f"the run process was killed by signal {-code}"
                                                    + (" (its record is incomplete)" if record else ""))
            else:
                run.state = "error"
                run.reason = " | ".join(list(child.tail)[-3:]) or f"the run process exited with {code}"
            run.ended_ts = t
            if run.duration_s is None:
                run.duration_s = t - (run.started_ts or t)
            if run.progress_s is None or child.progress_s is not None:
                run.progress_s = child.progress_s
            run.pid = None
            s.execute(update(Lease).where(Lease.id == child.lease_id, Lease.released_ts.is_(None))
                      .values(released_ts=t, released_by="runner"))
            event = run_event(run)
        self.events.publish(event)
        self._wake.set()      # a slot is free
