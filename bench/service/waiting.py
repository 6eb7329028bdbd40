"""Why a queued run waits, in words a lab reads: its rig (or every rig of its tag) disabled, reserved by someone
else, busy with another run, this service instance's run slots (--max-parallel) full, or its run processes still
warming up (for at most a minute after the service starts) — or, when nothing holds it, which earlier run goes
first. Shown by GET /api/runs/{id} (`waiting`) and on the run and queue pages."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from bench.service.db import Run
from bench.service.leases import RigView, rig_views


def _rig_reason(view: RigView, owner: str) -> str | None:
    """None when this rig could take the owner's run now."""
    lease = view.lease or {}
    if view.state == "disabled":
        return f"rig {view.name} is disabled by an admin"
    if view.state == "reserved" and lease.get("holder") != owner:
        return f"rig {view.name} is reserved by {lease.get('holder')} until {lease.get('expires_utc')}"
    if view.state in ("busy", "full"):
        run_id = lease.get("run_id")
        return f"rig {view.name} is busy" + (f" with run {run_id}" if run_id else "") + (
            f" ({view.running} of {view.max_concurrent} runs)" if view.simulated else "")
    return None


WaitContext = tuple[dict[str, RigView], list]      # read_context: the rigs' views by name, the queued runs


def why_waiting(run: Run, running_here: int, max_parallel: int, context: WaitContext,
                warming_s: float | None = None) -> str:
    views, queued = context
    names = [run.rig] if run.rig else list(run.candidates or [n for n, v in views.items() if run.tag in v.tags])
    if not names:
        return f"no rig carries the tag {run.tag!r}" if run.tag else "no rig named"
    reasons, free = [], []
    for name in names:
        view = views.get(name)
        reason = f"rig {name} is not in the service's rigs" if view is None else _rig_reason(view, run.owner)
        (reasons.append(reason) if reason else free.append(name))
    if not free:
        return "; ".join(reasons)
    if warming_s is not None:
        return (f"run processes warming up: the service started {warming_s:.0f} s ago and its fork server is still "
                f"importing what a run needs; rig {free[0]} is free")
    if running_here >= max_parallel:
        return (f"host slots: this service instance runs {running_here} of its {max_parallel} runs at once "
                f"(--max-parallel); rig {free[0]} is free")
    earlier = next((q.id for q in queued if q.submitted_ts < run.submitted_ts and (q.rig in free or q.tag is not None)),
                   None)
    if earlier is not None:
        return f"behind run {earlier}, queued earlier for a rig it may take (FIFO per rig); rig {free[0]} is free"
    return f"starting: rig {free[0]} is free"


def read_context(s: Session) -> WaitContext:
    """What why_waiting reads for any run, read once for a run, a list or a page (a page of 20 queued runs made 80
    queries: 40 % of the service's CPU under benchmarks/service.py, measured): the rigs' views, and the queued runs
    (id, submitted_ts, rig, tag), oldest first."""
    queued = list(s.execute(select(Run.id, Run.submitted_ts, Run.rig, Run.tag).where(Run.state == "queued")
                            .order_by(Run.submitted_ts)))
    return {v.name: v for v in rig_views(s)}, queued
