"""The run queue's worker: claims queued runs for free rigs, runs each in its own run process (bench/service/worker.py,
speaking bench/service/run_protocol.py), keeps the run's lease alive while the process lives, indexes the record its
Finished message names when it ends, and reconciles after a crash.

Warm run processes: each run process is forked from the service's fork server (multiprocessing's forkserver,
preloaded once with what `drivebench run` imports), so a run pays no imports; one run per process, so a crashing run
takes only its own process with it. `run_start = "cold"`: each run starts its own interpreter (the baseline).

One thread does all of it (one loop, no locks between schedulers). Each service instance holds a liveness lease of
its own (bench/service/instances.py), renewed by this loop; it touches the runs it started, and takes over another
instance's run only when that instance's lease has expired and the run's process is gone. A real rig's run lease
stays until released, and the database refuses a second unreleased one on the rig (a partial unique index), so
two instances cannot both claim a real rig, whatever they decide at the same moment.

Scheduling: each tick, for every rig with room, the oldest queued run that may start there (pinned to it, or
submitted by tag with the rig among its candidates; on a reserved real rig only the holder's own runs); of these
heads the oldest starts first. What is queued for other rigs costs nothing (docs/service.md, "Queue order").
"""

from __future__ import annotations

import collections
import datetime as dt
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from sqlalchemy import and_, or_, select, update
from sqlalchemy.exc import IntegrityError

from drivers.contract.checks import find_repo_root
from bench.service import instances
from bench.service.db import CriterionValue, Database, Instance, Lease, Rig, Run, RunCandidate, iso, now
from bench.service.leases import active_leases, held_rigs
from bench.service.live import recording_name
from bench.service.events import EventHub
from bench.service.forkserver import FORKSERVER_WAIT_S, ForkedProcess, ForkServer  # noqa: F401 (re-exported)
from bench.service.run_protocol import (MAX_LINE_BYTES, Failed, Finished, Log, Progress, ProtocolError, RunRequest, Trip,
                                        decode, encode)

TICK_S = 0.2
REAP_WAIT_S = 5.0             # a run process whose protocol pipe closed is waited for this long, then reaped at once
ABORT_KILL_AFTER_S = 60.0     # SIGTERM runs the safe stop; a run process still alive after this gets SIGKILL
STOP_WAIT_S = 30.0            # service shutdown: how long to wait for runs to finish their safe stop
PROGRESS_DB_PERIOD_S = 1.0
LOG_REPEAT_S = 30.0           # the same runner error is logged at most this often
SWEEP_PERIOD_S = 1.0          # how often a live instance looks for runs of gone instances to take over
WORKER = ("-m", "bench.service.worker")
VERDICT_STATE = {"pass": "pass", "fail": "fail", "incomplete": "fail", "aborted": "aborted", "error": "error"}


@dataclass
class RunnerSettings:
    data_dir: Path
    lease_ttl_s: float = 10.0
    max_parallel: int = max(1, os.cpu_count() or 1)
    host_id: str = field(default_factory=socket.gethostname)
    nice: int = 10                    # simulated runs only: the API answers first
    run_start: str = "forkserver"     # "forkserver": forked warm from a preloaded server; "cold": a new interpreter
    worker: tuple[str, ...] = WORKER  # how the service's python starts a cold run process (tests: a misbehaving one)


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
    readers: list[threading.Thread] = field(default_factory=list)
    warm: bool = False
    result: Finished | None = None          # the run process's Finished message
    failure: str | None = None              # its Failed message
    protocol_error: str | None = None       # a message it sent that the service refused (the run is stopped)
    log_lock: threading.Lock = field(default_factory=threading.Lock)
    log: object | None = None               # service.log, written by both readers


def _rerun_interval_s() -> float | None:
    """How often a run writes its run.rrd: `serve --live` sets it in this process's environment."""
    value = os.environ.get("DRIVEBENCH_RERUN_INTERVAL_S")
    try:
        return float(value) if value else None
    except ValueError:
        return None


def _read_record(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _record_of(out_dir: Path | None) -> tuple[Path | None, dict | None]:
    """What a run process that ended without a Finished message (killed, or its service gone) left in its own output
    directory: the run directory and its record.json as far as it was written (None if it made none)."""
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
                             passed=bool(c.get("passed")),      # a documented known gap fails no run
                             status="known_gap" if c.get("known_gap") and not c.get("passed") else c.get("status")))
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
        self._last_sweep = 0.0
        self._last_rejoin = 0.0
        self.root = find_repo_root()
        self.on_tick: Callable[[], None] | None = None
        self.instance_id: int | None = None
        self.lease_until = 0.0            # this instance's lease as last renewed (epoch s)
        self.fenced: str | None = None     # why this instance no longer holds anything
        self.drill_proofs: tuple[dict, ...] = ()   # comm-loss drills passed in this instance's runs (bench.run.drill)
        self.spawned = {"forked": 0, "cold": 0}
        self.forks = ForkServer(on_ready=self.wake)   # bench/service/forkserver.py, started with the runner

    @property
    def _forkserver_ready(self) -> threading.Event:
        return self.forks.ready

    @property
    def _forkserver_since(self) -> float | None:
        return self.forks.since

    @_forkserver_since.setter
    def _forkserver_since(self, value: float | None) -> None:
        self.forks.since = value

    # -- lifecycle ----------------------------------------------------------------------------------------

    def register(self, replacing: int | None = None) -> int:
        """This instance's liveness lease; InputError (one line) if a live instance has the same --host-id."""
        if self.instance_id is None:
            t = now()
            self.instance_id = instances.register(self.db, self.settings.host_id, self.settings.lease_ttl_s,
                                                  replacing)
            self.lease_until = t + self.settings.lease_ttl_s
            self._last_extend = t
        return self.instance_id

    def _rejoin(self) -> None:
        """A fenced instance whose runs have all ended registers anew (a new incarnation) once the database lets it."""
        old, self.instance_id = self.instance_id, None
        try:
            self.register(replacing=old)
        except Exception:
            self.instance_id = old
            raise
        self.fenced = None
        print(f"drivebench serve: instance {self.settings.host_id}: registered again (incarnation "
              f"{self.instance_id}); starting runs again", file=sys.stderr)

    def start(self) -> None:
        self.register()
        self.reconcile()
        if self.settings.run_start == "forkserver":
            self._start_forkserver()
        self._thread = threading.Thread(target=self._loop, name="drivebench-runner", daemon=True)
        self._thread.start()

    def wake(self) -> None:
        self._wake.set()

    def warming_s(self) -> float | None:
        """Seconds the fork server has been importing while queued runs wait for it; None when runs may start (it
        is ready, it failed, it took longer than FORKSERVER_WAIT_S, or runs start cold). A run started meanwhile would
        pay the same imports cold, on the same cores as the preload it waits for."""
        return self.forks.waiting_s() if self.settings.run_start == "forkserver" else None

    def run_processes(self) -> str:
        """How the next run process starts: "warm" (forked from the preloaded fork server), "warming" (queued runs
        wait for its preload), or "cold" (a new interpreter: --run-start cold, or the fork server is not there)."""
        if self.settings.run_start == "forkserver" and self.forks.warm():
            return "warm"
        return "warming" if self.warming_s() is not None else "cold"

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
        if self.instance_id is not None and not self.fenced:
            instances.stop(self.db, self.instance_id)

    def _orphaned(self, run: Run, inst: Instance | None, t: float, here: instances.Me) -> bool:
        """May this instance take `run` over: its instance is gone (lease expired, and on this machine its process
        too) and so is the run's process (on this machine: pid and start time; elsewhere: a grace period after
        expiry, in which a service's death reaches its run processes)."""
        if inst is None:      # a run from before instances were recorded: by --host-id, as before, and its pid
            return (run.host in (self.settings.host_id, None)) and not instances.process_alive(run.pid)
        if inst.id == self.instance_id or inst.expires_ts > t:
            return False
        if instances.same_machine(inst, here):
            if inst.stopped_ts is None and instances.process_alive(inst.pid, inst.pid_start):
                return False     # frozen or cut off from the database, but alive: it still holds its runs
            return not instances.process_alive(run.pid, run.pid_start)
        return t >= inst.expires_ts + instances.REMOTE_TAKEOVER_GRACE_S

    def reconcile(self) -> list[int]:
        """Runs still marked running whose instance and process are gone become aborted, with the reason and
        whatever record their run process left; their leases are released. Queued runs stay queued. Each takeover
        is a conditional update, so two instances never both take one run."""
        t, here = now(), instances.me()
        with self.db.session() as s:
            rows = s.execute(select(Run, Instance).outerjoin(Instance, Instance.id == Run.instance_id)
                             .where(Run.state == "running")).all()
        orphans = [(run.id, run.instance_id, inst) for run, inst in rows if self._orphaned(run, inst, t, here)]
        done = []
        me_ = self.settings.host_id
        for run_id, instance_id, inst in orphans:
            with self.db.session() as s:
                took = s.execute(update(Run).where(Run.id == run_id, Run.state == "running",
                                                   Run.instance_id.is_(None) if instance_id is None
                                                   else Run.instance_id == instance_id)
                                 .values(state="aborted", ended_ts=now())).rowcount
                if took != 1:
                    continue
                run = s.get(Run, run_id)
                run_dir, record = _record_of(Path(run.run_dir) if run.run_dir else None)
                index_record(s, run, record, run_dir)
                gone = (f"its service instance {inst.name} (pid {inst.pid} on {inst.hostname}) lease expired at "
                        f"{iso(inst.expires_ts)}" if inst is not None else "its service instance was gone")
                run.reason = ("the service stopped while the run was running (its run process was stopped with "
                              f"it, SIGTERM: safe stop); taken over by {me_}: {gone} and the run process had ended"
                              + (f"; the record says: {record.get('verdict')}"
                                 + (f" ({record.get('abort_reason')})" if record.get("abort_reason") else "")
                                 if record else "; no record"))
                s.execute(update(Lease).where(Lease.run_id == run_id, Lease.released_ts.is_(None))
                          .values(released_ts=now(), released_by=f"takeover by {me_}"))
                event = run_event(run)
            self.events.publish(event)
            done.append(run_id)
        return done

    # -- the loop -----------------------------------------------------------------------------------------

    def _loop(self) -> None:
        said: dict[str, float] = {}
        while not self._stop.is_set():
            try:
                self.tick()
            except Exception as exc:  # the loop must survive a database hiccup; the next tick retries
                first = (str(exc).splitlines() or [""])[0]
                line = f"drivebench serve: runner: {type(exc).__name__}: {first}"
                if time.monotonic() - said.get(line, -LOG_REPEAT_S) >= LOG_REPEAT_S:   # not 5 lines a second
                    if len(said) > 100:
                        said.clear()
                    said[line] = time.monotonic()
                    print(line, file=sys.stderr)
            self._wake.wait(TICK_S)
            self._wake.clear()

    def tick(self) -> None:
        if self.settings.run_start == "forkserver":
            self.forks.check()        # a lost fork server is said and replaced; its runs go on
        self._reap()
        if (self.fenced and not self.children and not self._stop.is_set()
                and time.monotonic() - self._last_rejoin >= self.settings.lease_ttl_s):
            self._last_rejoin = time.monotonic()
            self._rejoin()
        self._heartbeat()
        self._handle_aborts()
        self._write_progress()
        if time.monotonic() - self._last_sweep >= SWEEP_PERIOD_S:
            self._last_sweep = time.monotonic()
            self.reconcile()
        if not self._stop.is_set() and not self.fenced:
            self._schedule()
        if self.on_tick:
            self.on_tick()

    def _reap(self) -> None:
        for run_id, child in list(self.children.items()):
            if child.proc.poll() is not None:
                for reader in child.readers:
                    reader.join(timeout=5)
                self._finish(child)
                if isinstance(child.proc, ForkedProcess):
                    child.proc.close()
                del self.children[run_id]
                self._heartbeat()     # finishing a run reads its record: keep the lease renewed meanwhile

    def _heartbeat(self) -> None:
        """Every TTL/3: this instance's lease and its live runs' leases, in one transaction. An instance whose lease
        ran out (a stalled loop, a lost database) holds nothing any more: it fences itself."""
        t = now()
        if self.instance_id is not None and not self.fenced and t >= self.lease_until:
            self._fence(f"its lease ran out at {iso(self.lease_until)} without renewal")
        if self.fenced or t - self._last_extend < self.settings.lease_ttl_s / 3:
            return
        ttl = self.settings.lease_ttl_s
        alive = [c.lease_id for c in self.children.values() if c.proc.poll() is None]
        with self.db.session() as s:
            if self.instance_id is not None and not instances.renew(s, self.instance_id, t, ttl):
                renewed = False
            else:
                renewed = True
                if alive:
                    s.execute(update(Lease).where(Lease.id.in_(alive), Lease.released_ts.is_(None))
                              .values(expires_ts=t + ttl))
        if not renewed:
            self._fence("its lease was found expired or taken over")
            return
        self.lease_until = t + ttl
        self._last_extend = t

    def _fence(self, why: str) -> None:
        self.fenced = why
        print(f"drivebench serve: instance {self.settings.host_id}: {why}; its runs get SIGTERM (safe stop) and it "
              f"starts no more runs; restart it", file=sys.stderr)
        for child in self.children.values():
            if child.proc.poll() is None and child.term_sent is None:
                child.proc.send_signal(signal.SIGTERM)
                child.term_sent = time.monotonic()

    def finished_verdict(self, run_id: int) -> str | None:
        """The verdict a run of this instance sent before the runner indexed it (None: none yet, or not ours)."""
        child = self.children.get(run_id)
        result = child.result if child is not None else None
        return result.verdict if result is not None else None

    def _handle_aborts(self) -> None:
        if not self.children:
            return
        for child in self.children.values():      # an abort's or a fence's SIGTERM that did not end the run
            if (child.term_sent is not None and child.proc.poll() is None
                    and time.monotonic() - child.term_sent > ABORT_KILL_AFTER_S):
                child.proc.kill()
        with self.db.session() as s:
            wanted = s.execute(select(Run.id).where(Run.id.in_(list(self.children)),
                                                    Run.abort_requested_by.is_not(None))).scalars().all()
        for run_id in wanted:
            child = self.children[run_id]
            if child.proc.poll() is not None or child.result is not None:    # ended, or its verdict is in
                continue
            if child.term_sent is None:
                child.proc.send_signal(signal.SIGTERM)      # the run's single safe-stop sequence
                child.term_sent = time.monotonic()

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
        self.events.changed()       # the API's cached reads of runs are stale now, not at every progress event

    # -- scheduling ---------------------------------------------------------------------------------------

    def _open_rigs(self, s, t: float) -> dict[str, tuple[Rig, int, str | None]]:
        """Rigs a run could start on now: name -> (rig, free slots, the only owner whose runs may go there)."""
        leases = active_leases(s, at=t)
        held = held_rigs(s)
        found = {}
        for rig in s.execute(select(Rig).where(Rig.enabled.is_(True)).order_by(Rig.name)).scalars():
            mine = [l for l in leases if l.rig == rig.name]
            runs = sum(l.kind == "run" for l in mine)
            if rig.simulated:
                if runs < rig.max_concurrent:
                    found[rig.name] = (rig, rig.max_concurrent - runs, None)
                continue
            holders = {l.holder for l in mine if l.kind == "manual"}
            if rig.name in held or runs or len(holders) > 1:
                continue
            found[rig.name] = (rig, 1, holders.pop() if holders else None)
        return found

    @staticmethod
    def _head(s, rig: str, owner: str | None, skip: set[int]) -> Run | None:
        """The oldest queued run that may start on `rig`: pinned to it, or by tag with the rig a candidate."""
        q = select(Run).where(Run.state == "queued", or_(
            Run.rig == rig, and_(Run.rig.is_(None), Run.id.in_(select(RunCandidate.run_id)
                                                                 .where(RunCandidate.rig == rig)))))
        if owner is not None:
            q = q.where(Run.owner == owner)
        if skip:
            q = q.where(Run.id.not_in(skip))
        return s.execute(q.order_by(Run.id).limit(1)).scalar()

    def _schedule(self) -> None:
        """Fill this host's free slots: of the rigs with room, each one's oldest startable run is its head; the
        oldest head starts first (on the least busy of the rigs it may take). Nothing queued for a rig that cannot
        take a run is read."""
        room = self.settings.max_parallel - len(self.children)
        if room <= 0 or self.warming_s() is not None:
            return
        with self.db.session() as s:
            if s.execute(select(Run.id).where(Run.state == "queued").limit(1)).first() is None:
                return
            open_rigs = self._open_rigs(s, now())
        load = {name: info[0].max_concurrent - info[1] for name, info in open_rigs.items()}
        tried: set[int] = set()
        while room > 0 and open_rigs:
            with self.db.session() as s:
                heads = {name: head for name, (_, _, owner) in open_rigs.items()
                         if (head := self._head(s, name, owner, tried)) is not None}
            if not heads:
                return
            run = min(heads.values(), key=lambda r: r.id)
            tried.add(run.id)
            for name in sorted((n for n, h in heads.items() if h.id == run.id), key=lambda n: (load[n], n)):
                rig, free, owner = open_rigs[name]
                lease_id = self._claim(run, rig)
                if lease_id is None:
                    open_rigs.pop(name)        # taken meanwhile (another instance, a reservation): next tick
                    continue
                self._spawn(run, rig, lease_id)
                room -= 1
                load[name] += 1
                if free > 1:
                    open_rigs[name] = (rig, free - 1, owner)
                else:
                    open_rigs.pop(name)
                break

    def _claim(self, run: Run, rig: Rig) -> int | None:
        """In one transaction holding the rig's lock: does this instance still hold its lease, is there room, is the
        run still queued; then mark it running and give it a lease. On a real rig the database refuses a second
        unreleased run lease (IntegrityError) even if two services got here at once."""
        t = now()
        try:
            with self.db.session() as s:
                if not self.db.lock_rig(s, rig.name):
                    return None
                if self.instance_id is not None and s.execute(select(Instance.id).where(
                        Instance.id == self.instance_id, Instance.stopped_ts.is_(None),
                        Instance.expires_ts > t)).first() is None:
                    return None
                leases = active_leases(s, rig.name, at=t)
                runs = [l for l in leases if l.kind == "run"]
                if rig.simulated:
                    if len(runs) >= rig.max_concurrent:
                        return None
                elif any(l.kind == "run" or l.holder != run.owner for l in leases) or s.execute(
                        select(Lease.id).where(Lease.rig == rig.name, Lease.kind == "run",
                                               Lease.exclusive_rig.is_(True), Lease.released_ts.is_(None))).first():
                    return None
                claimed = s.execute(update(Run).where(Run.id == run.id, Run.state == "queued").values(
                    state="running", rig=rig.name, started_ts=t, host=self.settings.host_id,
                    instance_id=self.instance_id)).rowcount
                if claimed != 1:
                    return None
                lease = Lease(rig=rig.name, holder=f"run {run.id} ({run.owner})", kind="run", run_id=run.id,
                              reason=run.scenario_name or run.scenario, created_ts=t,
                              expires_ts=t + self.settings.lease_ttl_s, exclusive_rig=not rig.simulated)
                s.add(lease)
                s.flush()
                return lease.id
        except IntegrityError:
            return None

    # -- run processes ------------------------------------------------------------------------------------

    def _start_worker(self, nice: int) -> subprocess.Popen:
        """A run process; from the runner's thread only (its parent-death signal follows the thread that forked)."""
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        env.pop("DRIVEBENCH_TOKEN", None)
        command = [self.python, *self.settings.worker, "--parent", str(os.getpid()), "--nice", str(nice)]
        return subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                cwd=self.root, env=env,     # from exec on, as worker.detach for a forked one
                                **({"process_group": 0} if nice else {"start_new_session": True}))

    def _start_forkserver(self) -> None:
        """The fork server, preloaded in the background (bench/service/forkserver.py)."""
        with self.db.session() as s:        # read by bench.service.fork_warm in the fork server (its environment)
            benches = sorted({rig.bench for rig in s.execute(select(Rig)).scalars() if rig.bench})
        self.forks.start(benches)

    def _hand_over(self, request: RunRequest, simulated: bool) -> tuple[subprocess.Popen | ForkedProcess, bool]:
        """The run's process, forked warm or started cold; (process, warm)."""
        data = encode(request)
        nice = self.settings.nice if simulated else 0
        if self.run_processes() == "warm":
            self.spawned["forked"] += 1
            return self.forks.fork(data, nice, os.getpid()), True
        proc = self._start_worker(nice)
        try:
            proc.stdin.write(data)
            proc.stdin.close()
        except OSError:
            pass                      # it died at once: reaped as a failed run
        self.spawned["cold"] += 1
        return proc, False

    def _spawn(self, run: Run, rig: Rig, lease_id: int) -> None:
        out_dir = self.settings.data_dir / "runs" / f"{run.id:06d}"
        request = RunRequest(run_id=run.id, scenario_file=run.scenario_file, bench=rig.bench, out_dir=str(out_dir),
                             seed=run.seed, recording_id=f"run-{run.id}",
                             recording_name=recording_name(run.id, run.scenario_name or run.scenario),
                             rerun_interval_s=_rerun_interval_s(), drill_proofs=self.drill_proofs)
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
            proc, warm = self._hand_over(request, bool(rig.simulated))
        except OSError as exc:
            with self.db.session() as s:
                row = s.get(Run, run.id)
                row.state, row.reason, row.ended_ts = "error", f"cannot start the run process: {exc}", now()
                s.execute(update(Lease).where(Lease.id == lease_id).values(released_ts=now(), released_by="runner"))
                event = run_event(row)
            self.events.publish(event)      # after the commit: a read the event prompts sees what it says
            return
        child = Child(run.id, rig.name, proc, out_dir, lease_id, time.monotonic(), warm=warm)
        child.log = open(out_dir / "service.log", "ab")
        child.readers = [threading.Thread(target=self._read_events, args=(child,), daemon=True,
                                          name=f"run-{run.id}-events"),
                         threading.Thread(target=self._read_log, args=(child,), daemon=True, name=f"run-{run.id}-log")]
        for reader in child.readers:
            reader.start()
        self.children[run.id] = child
        with self.db.session() as s:
            row = s.get(Run, run.id)
            row.pid, row.pid_start, row.run_dir = proc.pid, instances.process_start(proc.pid), str(out_dir)
            event = run_event(row)
        self.events.publish(event)

    def _write_log(self, child: Child, raw: bytes) -> None:
        with child.log_lock:
            child.log.write(raw)
            child.log.flush()

    def _read_events(self, child: Child) -> None:
        """The run process's messages: progress and trips become events, its Finished or Failed is kept for _finish.
        A message the service refuses (another protocol version, ...) stops the run (SIGTERM: safe stop)."""
        for raw in iter(lambda: child.proc.stdout.readline(MAX_LINE_BYTES + 1), b""):
            if child.protocol_error is not None:
                continue                       # drained, not read: the run is being stopped
            try:
                message = decode(raw)
            except ProtocolError as exc:
                child.protocol_error = str(exc)
                self._write_log(child, f"drivebench serve: {exc}; the run process is stopped\n".encode())
                if child.proc.poll() is None and child.term_sent is None:
                    child.proc.send_signal(signal.SIGTERM)
                    child.term_sent = time.monotonic()
                continue
            if isinstance(message, Progress):
                child.progress_s = message.t_s
                self.events.publish({"type": "progress", "id": child.run_id, "progress_s": message.t_s,
                                     "duration_s": message.duration_s}, changed=False)   # the DB: _write_progress
            elif isinstance(message, Trip):
                self.events.publish({"type": "trip", "id": child.run_id, "reason": message.reason,
                                     "t_s": message.t_s, "message": message.message})
                self._write_log(child, raw)
            elif isinstance(message, Log):
                self._write_log(child, (message.line.rstrip("\n") + "\n").encode())
            elif isinstance(message, Finished):
                child.result = message
            elif isinstance(message, Failed):
                child.failure = message.reason
        child.proc.stdout.close()
        try:                      # the run process is ending: reap it now, not at the next tick (0.2 s of its slot)
            child.proc.wait(timeout=REAP_WAIT_S)
        except Exception:
            pass
        self._wake.set()

    def _read_log(self, child: Child) -> None:
        """The run process's stderr (and its own stdout): service.log, the last lines kept for an error's reason."""
        for raw in child.proc.stderr:
            self._write_log(child, raw)
            line = raw.decode("utf-8", "replace").rstrip("\n")
            if line.strip():
                child.tail.append(line)
        child.proc.stderr.close()

    # -- finishing ----------------------------------------------------------------------------------------

    def _finish(self, child: Child, forced_reason: str | None = None) -> None:
        code = child.proc.poll()
        if child.log is not None:
            child.log.close()
        if child.result is not None and child.protocol_error is None:
            run_dir, record = Path(child.result.run_dir), _read_record(Path(child.result.record_path))
            if child.result.drill_proofs:
                self.drill_proofs = child.result.drill_proofs
        else:
            run_dir, record = _record_of(child.out_dir)
        t = now()
        with self.db.session() as s:
            run = s.get(Run, child.run_id)
            if run.state != "running" or run.instance_id != self.instance_id:
                # taken over meanwhile (only possible once this instance had lost its lease): not ours to write
                s.execute(update(Lease).where(Lease.id == child.lease_id, Lease.released_ts.is_(None))
                          .values(released_ts=t, released_by="runner"))
                return
            index_record(s, run, record, run_dir)
            verdict = (record or {}).get("verdict")
            if run.abort_requested_by and verdict not in ("pass", "fail", "incomplete") and (
                    child.term_sent is not None or verdict not in VERDICT_STATE):   # a finished verdict stands
                run.state = "aborted"
                run.aborted_by = run.abort_requested_by
                run.reason = f"aborted by {run.abort_requested_by}" + (
                    f" ({record.get('abort_reason')})" if record and record.get("abort_reason") else "")
            elif child.protocol_error is not None:
                run.state, run.reason = "error", child.protocol_error + (
                    f" (the run process was stopped; its record says: {verdict})" if verdict else "")
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
                run.reason = (" | ".join(list(child.tail)[-3:]) or child.failure
                              or f"the run process exited with {code}")
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
