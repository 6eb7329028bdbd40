"""The service's state and operations, shared by the JSON API (app.py) and the web pages (ui.py)."""

from __future__ import annotations

import json
import math
from typing import Callable
from dataclasses import dataclass, field
from pathlib import Path

from sqlalchemy import select, update

from drivers.contract.errors import InputError
from drivers.contract.checks import find_repo_root
from bench.service.auth import Principal, TokenCache
from bench.service.db import FINAL_STATES, STATES, CriterionValue, Database, Rig, Run, Token, iso, now, open_database
from bench.service.errors import ApiError, bad_input, not_found
from bench.service.events import EventHub
from bench.service.leases import active_leases, held_rigs, rig_view, rig_views
from bench.service.rigs import RigConfig, load_rigs
from bench.service.runner import Runner, RunnerSettings, run_event

RUN_FILES = ("record.json", "summary.png", "run.rrd", "telemetry.parquet", "junit.xml", "service.log")
MEDIA = {".json": "application/json", ".png": "image/png", ".rrd": "application/octet-stream",
         ".parquet": "application/vnd.apache.parquet", ".xml": "application/xml", ".log": "text/plain"}


MAX_LEASE_TTL_S = 3600.0
MIN_LEASE_TTL_S = 1.0        # renewed every TTL/3 by a loop that ticks every 0.2 s
MAX_PARALLEL = 256


def serve_option_problems(port: int | None = None, lease_ttl_s: float | None = None, max_parallel: int | None = None,
                          host_id: str | None = None, **ports: int | None) -> list[str]:
    """`drivebench serve`'s numbers and names, checked before anything starts: one line each."""
    problems = []
    for name, value in {"port": port, **ports}.items():
        if value is not None and not 1 <= value <= 65535:
            problems.append(f"serve: --{name.replace('_', '-')}: must be a TCP port in 1..65535, got {value}")
    if lease_ttl_s is not None and not (math.isfinite(lease_ttl_s)
                                        and MIN_LEASE_TTL_S <= lease_ttl_s <= MAX_LEASE_TTL_S):
        problems.append(f"serve: --lease-ttl: must be seconds in [{MIN_LEASE_TTL_S:g}, {MAX_LEASE_TTL_S:g}], "
                        f"got {lease_ttl_s}")
    if max_parallel is not None and not 1 <= max_parallel <= MAX_PARALLEL:
        problems.append(f"serve: --max-parallel: must be an integer in 1..{MAX_PARALLEL}, got {max_parallel}")
    if host_id is not None and not (0 < len(host_id) <= 200 and host_id.isprintable() and host_id.strip() == host_id):
        problems.append(f"serve: --host-id: must be 1-200 printable characters without surrounding spaces, "
                        f"got {host_id!r}")
    return problems


@dataclass
class ServiceSettings:
    data_dir: Path
    db_url: str | None = None
    rigs_path: Path | None = None
    scenario_root: Path | None = None
    lease_ttl_s: float = 10.0
    max_parallel: int | None = None
    run_start: str = "forkserver"       # run processes forked warm from a preloaded server, or "cold"
    host_id: str | None = None
    run_queue: bool = True              # False: API only (tests of the API without run processes)
    live: bool = False                  # `serve --live`: runs write their run.rrd at the live view's cadence
    rigs: list[RigConfig] = field(default_factory=list)

    def resolved(self) -> "ServiceSettings":
        problems = serve_option_problems(lease_ttl_s=self.lease_ttl_s, max_parallel=self.max_parallel,
                                         host_id=self.host_id)
        if self.run_start not in ("forkserver", "cold"):
            problems.append(f"serve: --run-start: must be forkserver or cold, got {self.run_start!r}")
        if problems:
            raise InputError(problems)
        root = find_repo_root()
        self.data_dir = Path(self.data_dir).resolve()
        self.rigs_path = Path(self.rigs_path or root / "config" / "rigs.toml")
        self.scenario_root = Path(self.scenario_root or root / "scenarios").resolve()
        return self


class Service:
    def __init__(self, settings: ServiceSettings):
        self.settings = settings.resolved()
        self.settings.data_dir.mkdir(parents=True, exist_ok=True)
        if not self.settings.rigs:
            self.settings.rigs = load_rigs(self.settings.rigs_path)
        from bench.service.db import default_url

        self.db: Database = open_database(self.settings.db_url or default_url(self.settings.data_dir))
        self.tokens = TokenCache(self.db)
        self.events = EventHub()
        self.sync_rigs()
        runner_settings = RunnerSettings(data_dir=self.settings.data_dir, lease_ttl_s=self.settings.lease_ttl_s,
                                         run_start=self.settings.run_start)
        if self.settings.max_parallel:
            runner_settings.max_parallel = self.settings.max_parallel
        if self.settings.host_id:
            runner_settings.host_id = self.settings.host_id
        self.runner = Runner(self.db, runner_settings, self.events)

    def register(self) -> None:
        """Take this instance's liveness lease (before serving): InputError if a live one has the same id."""
        if self.settings.run_queue:
            self.runner.register()

    def start(self) -> None:
        if self.settings.run_queue:
            self.runner.start()

    def stop(self) -> None:
        if self.settings.run_queue:
            self.runner.stop()
        self.db.dispose()

    def sync_rigs(self) -> None:
        """rigs.toml is the truth for names, bench configs and tags; `enabled` (an admin's switch) is kept."""
        with self.db.session() as s:
            for rig in self.settings.rigs:
                row = s.get(Rig, rig.name)
                if row is None:
                    s.add(Rig(name=rig.name, bench=rig.bench, tags=list(rig.tags), simulated=rig.simulated,
                              max_concurrent=rig.max_concurrent, enabled=True, lock_seq=0))
                else:
                    row.bench, row.tags, row.simulated = rig.bench, list(rig.tags), rig.simulated
                    row.max_concurrent = rig.max_concurrent

    # -- rigs ---------------------------------------------------------------------------------------------

    def rigs(self) -> list[dict]:
        with self.db.session() as s:
            return [v.contract() for v in rig_views(s)]

    def rig(self, name: str) -> dict:
        with self.db.session() as s:
            row = s.get(Rig, name)
            if row is None:
                raise not_found(f"rig {name}")
            view = rig_view(row, active_leases(s, name), name in held_rigs(s)).contract()
            view["bench"] = row.bench
            view["enabled"] = row.enabled
            view["comm_loss_unverified"] = _stated_external(row.bench)
            return view

    def set_rig_enabled(self, name: str, enabled: bool) -> dict:
        with self.db.session() as s:
            row = s.get(Rig, name)
            if row is None:
                raise not_found(f"rig {name}")
            row.enabled = bool(enabled)
        self.runner.wake()
        return self.rig(name)

    # -- runs ---------------------------------------------------------------------------------------------

    def run_dicts(self, runs: list[Run]) -> list[dict]:
        """run_dict of each, the waiting reasons of the queued ones from one read of the rigs and the queue."""
        waiting = self.waiting_lookup()
        return [self.run_dict(run, waiting) for run in runs]

    def run_dict(self, run: Run, waiting: Callable[[Run], str] | None = None) -> dict:
        """`waiting`: a waiting_lookup() shared by the runs of one list."""
        has_dir = bool(run.run_dir)
        return {
            "id": run.id, "state": run.state, "verdict": run.verdict, "rig": run.rig, "scenario": run.scenario,
            "criteria": run.criteria or [],
            "record_url": f"/api/runs/{run.id}/files/record.json" if has_dir else None,
            "live_url": f"/runs/{run.id}/live",
            "url": f"/runs/{run.id}",
            "tag": run.tag, "scenario_name": run.scenario_name, "scenario_sha256": run.scenario_sha256,
            "seed": run.seed, "owner": run.owner, "submitted_utc": iso(run.submitted_ts),
            "started_utc": iso(run.started_ts), "ended_utc": iso(run.ended_ts), "duration_s": run.duration_s,
            "progress_s": run.progress_s, "scenario_duration_s": run.scenario_duration_s, "reason": run.reason,
            "abort_requested_by": run.abort_requested_by, "aborted_by": run.aborted_by, "drive": run.drive,
            "firmware_version": run.firmware_version, "revision": run.revision,
            "software": run.software, "host": run.host, "pid": run.pid,
            "waiting": (waiting or self.waiting_lookup())(run) if run.state == "queued" else None,
        }

    def waiting_lookup(self) -> Callable[[Run], str]:
        """Why a queued run has not started (bench.service.waiting), from this instance's point of view: for a run, a
        list or a page, the rigs and the queue read once, when first asked."""
        from bench.service.waiting import read_context, why_waiting

        runner, context = self.runner, []

        def waiting(run: Run) -> str:
            if not context:
                with self.db.session() as s:
                    context.append(read_context(s))
            return why_waiting(run, len(runner.children), runner.settings.max_parallel, context[0],
                               runner.warming_s())

        return waiting

    def get_run(self, run_id: int) -> Run:
        with self.db.session() as s:
            run = s.get(Run, run_id)
            if run is None:
                raise not_found(f"run {run_id}")
            return run

    def list_runs(self, rig: str | None = None, state: str | None = None, scenario: str | None = None,
                  verdict: str | None = None, revision: str | None = None, owner: str | None = None,
                  limit: int = 100, active: bool = False) -> list[Run]:
        if state is not None and state not in STATES:
            raise bad_input([f"request: state: must be one of {', '.join(STATES)}, got {state!r}"])
        if not 1 <= limit <= 1000:
            raise bad_input([f"request: limit: must be in [1, 1000], got {limit}"])
        q = select(Run)
        if rig:
            q = q.where(Run.rig == rig)
        if state:
            q = q.where(Run.state == state)
        if active:
            q = q.where(Run.state.in_(("queued", "running")))
        if scenario:
            q = q.where((Run.scenario_name == scenario) | (Run.scenario == scenario))
        if verdict:
            q = q.where(Run.verdict == verdict)
        if revision:
            q = q.where(Run.revision.startswith(revision))
        if owner:
            q = q.where(Run.owner == owner)
        with self.db.session() as s:
            return list(s.execute(q.order_by(Run.id.desc()).limit(limit)).scalars())

    def abort(self, run_id: int, who: Principal) -> Run:
        with self.db.session() as s:
            run = s.get(Run, run_id)
            if run is None:
                raise not_found(f"run {run_id}")
            if run.owner != who.name and not who.at_least("admin"):
                raise ApiError(403, f"run {run_id}: submitted by {run.owner}; an operator may abort only their own "
                                    f"runs (an admin any)")
            if run.state in FINAL_STATES:
                raise ApiError(409, f"run {run_id}: already {run.state}")
            verdict = self.runner.finished_verdict(run_id)
            if verdict is not None:         # its process has ended the run; the index follows within a tick
                raise ApiError(409, f"run {run_id}: already finished ({verdict}); its record is being indexed")
            cancelled = s.execute(update(Run).where(Run.id == run_id, Run.state == "queued").values(
                state="cancelled", aborted_by=who.name, reason=f"cancelled by {who.name} before it started",
                ended_ts=now())).rowcount
            if not cancelled:
                run.abort_requested_by = run.abort_requested_by or who.name
            s.flush()
            s.refresh(run)
            event = run_event(run)
        self.events.publish(event)
        self.runner.wake()
        return run

    def run_file(self, run_id: int, name: str) -> Path:
        run = self.get_run(run_id)
        if name not in RUN_FILES:
            raise not_found(f"run {run_id}: file {name}")
        if not run.run_dir:
            raise not_found(f"run {run_id}: file {name} (the run has not started)")
        base = Path(run.run_dir)
        for candidate in (base / name, base.parent / name) if name == "service.log" else (base / name,):
            if candidate.is_file():
                return candidate
        if name != "service.log" and (base / "service.log").is_file():   # run_dir is still the --out folder
            found = sorted(base.glob(f"*/{name}"))
            if found:
                return found[0]
        raise not_found(f"run {run_id}: file {name}")

    def record(self, run_id: int) -> dict:
        return json.loads(self.run_file(run_id, "record.json").read_text(encoding="utf-8"))

    # -- history ------------------------------------------------------------------------------------------

    def scenario_names(self) -> list[str]:
        with self.db.session() as s:
            return sorted(n for n in s.execute(select(Run.scenario_name).distinct()).scalars() if n)

    def criterion_names(self, scenario: str | None) -> list[str]:
        q = select(CriterionValue.name).distinct()
        if scenario:
            q = q.join(Run, Run.id == CriterionValue.run_id).where(Run.scenario_name == scenario)
        with self.db.session() as s:
            return sorted(s.execute(q).scalars())

    def failing_since(self, scenario: str | None = None) -> list[dict]:
        from bench.service.failing import failing_since

        with self.db.session() as s:
            return failing_since(s, scenario)

    def trend(self, criterion: str, scenario: str | None = None, limit: int = 500) -> list[dict]:
        q = (select(CriterionValue, Run).join(Run, Run.id == CriterionValue.run_id)
             .where(CriterionValue.name == criterion))
        if scenario:
            q = q.where(Run.scenario_name == scenario)
        with self.db.session() as s:
            rows = s.execute(q.order_by(Run.id.desc()).limit(limit)).all()
        return [{"run_id": r.id, "value": c.value, "limit": c.limit, "passed": c.passed, "status": c.status,
                 "revision": r.revision, "scenario": r.scenario_name, "rig": r.rig, "ended_utc": iso(r.ended_ts)}
                for c, r in reversed(rows)]

    # -- tokens -------------------------------------------------------------------------------------------

    def tokens_list(self) -> list[dict]:
        with self.db.session() as s:
            return [{"id": t.id, "name": t.name, "role": t.role, "created_utc": iso(t.created_ts),
                     "revoked": t.revoked} for t in s.execute(select(Token).order_by(Token.id)).scalars()]

    def revoke_token(self, token_id: int) -> None:
        with self.db.session() as s:
            row = s.get(Token, token_id)
            if row is None:
                raise not_found(f"token {token_id}")
            row.revoked = True
        self.tokens.forget()


def _stated_external(bench: str) -> str | None:
    """The rig page says plainly when the rig's comm-loss reaction is stated in its bench config, not drilled."""
    from bench.inputs.benchconfig import load_bench_config
    from bench.run.drill import stated_external
    from drivers.contract.errors import InputError

    try:
        return stated_external(load_bench_config(bench))
    except (InputError, OSError):
        return None
