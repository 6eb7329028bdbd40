"""Leases: every hold of a rig — a run's or a person's — ends at its expiry unless extended.

A lease is active while `released_ts` is unset and `expires_ts` lies ahead, so a holder that dies (a run process,
a CI job, the service itself) stops extending it and the rig is free at expiry with no sweeper involved.
A real rig has at most one holder; a simulated rig gives each run its own simulator, so people's leases on it are
shared notes and runs are limited by the rig's max_concurrent.
"""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session

from bench.service.auth import Principal
from bench.service.db import Database, Lease, Rig, iso, now
from bench.service.errors import ApiError, bad_input, not_found

MAX_TTL_S = 7 * 24 * 3600.0


@dataclass(frozen=True)
class RigView:
    name: str
    tags: list[str]
    state: str                 # free | busy | reserved | full | disabled
    lease: dict | None         # the holder shown to people: a manual reservation first, else a run's lease
    simulated: bool
    max_concurrent: int
    running: int
    leases: list[dict]

    def contract(self) -> dict:
        return {"name": self.name, "tags": self.tags, "state": self.state, "lease": self.lease,
                "simulated": self.simulated, "max_concurrent": self.max_concurrent, "running": self.running,
                "leases": self.leases}


def lease_dict(lease: Lease) -> dict:
    return {"id": lease.id, "rig": lease.rig, "holder": lease.holder, "kind": lease.kind, "run_id": lease.run_id,
            "reason": lease.reason, "created_utc": iso(lease.created_ts), "expires_utc": iso(lease.expires_ts),
            "active": lease.active()}


def active_leases(s: Session, rig: str | None = None, at: float | None = None) -> list[Lease]:
    at = now() if at is None else at
    q = select(Lease).where(Lease.released_ts.is_(None), Lease.expires_ts > at)
    if rig is not None:
        q = q.where(Lease.rig == rig)
    return list(s.execute(q.order_by(Lease.id)).scalars())


def held_rigs(s: Session) -> set[str]:
    """Real rigs whose run lease is unreleased, expired or not: its run may still drive the rig until a live
    instance has taken it over (docs/service.md, "One holder per rig")."""
    return set(s.execute(select(Lease.rig).where(Lease.kind == "run", Lease.exclusive_rig.is_(True),
                                                 Lease.released_ts.is_(None))).scalars())


def rig_view(rig: Rig, leases: list[Lease], held: bool = False) -> RigView:
    runs = [l for l in leases if l.kind == "run"]
    manual = [l for l in leases if l.kind == "manual"]
    if not rig.enabled:
        state = "disabled"
    elif manual and not rig.simulated:
        state = "reserved"
    elif runs and len(runs) >= rig.max_concurrent:
        state = "full" if rig.simulated else "busy"
    elif runs or (held and not rig.simulated):
        state = "busy"
    else:
        state = "free"
    shown = (manual or runs or [None])[0]
    return RigView(rig.name, list(rig.tags), state, lease_dict(shown) if shown else None, rig.simulated,
                   rig.max_concurrent, len(runs), [lease_dict(l) for l in leases])


def rig_views(s: Session) -> list[RigView]:
    leases = active_leases(s)
    by_rig: dict[str, list[Lease]] = {}
    for lease in leases:
        by_rig.setdefault(lease.rig, []).append(lease)
    held = held_rigs(s)
    return [rig_view(r, by_rig.get(r.name, []), r.name in held)
            for r in s.execute(select(Rig).order_by(Rig.name)).scalars()]


def check_ttl(ttl_s, field: str = "ttl_s") -> float:
    if isinstance(ttl_s, bool) or not isinstance(ttl_s, (int, float)) or not 0 < ttl_s <= MAX_TTL_S:
        raise bad_input([f"request: {field}: must be a number of seconds in (0, {MAX_TTL_S:g}], got {ttl_s!r}"])
    return float(ttl_s)


def blocking_holder(rig: Rig, leases: list[Lease], holder: str) -> Lease | None:
    """On a real rig, the lease of someone else that keeps `holder` off it."""
    if rig.simulated:
        return None
    return next((l for l in leases if l.holder != holder), None)


def reserve(db: Database, rig_name: str, who: Principal, ttl_s: float, reason: str | None) -> Lease:
    ttl_s = check_ttl(ttl_s)
    with db.session() as s:
        if not db.lock_rig(s, rig_name):
            raise not_found(f"rig {rig_name}")
        rig = s.get(Rig, rig_name)
        other = blocking_holder(rig, active_leases(s, rig_name), who.name)
        if other is not None:
            raise ApiError(409, f"rig {rig_name}: leased by {other.holder} until {iso(other.expires_ts)}"
                                + (f" ({other.reason})" if other.reason else ""))
        if not rig.simulated and rig_name in held_rigs(s):
            raise ApiError(409, f"rig {rig_name}: its last run's lease expired but is not released: the run may "
                                f"still drive the rig until its service is found gone and the run taken over")
        t = now()
        lease = Lease(rig=rig_name, holder=who.name, kind="manual", reason=reason or "", created_ts=t,
                      expires_ts=t + ttl_s)
        s.add(lease)
        s.flush()
        return lease


def _own_or_admin(lease: Lease, who: Principal, verb: str) -> None:
    if lease.holder != who.name and not who.at_least("admin"):
        raise ApiError(403, f"lease {lease.id}: held by {lease.holder}; only the holder or an admin may {verb} it")


def extend(db: Database, lease_id: int, who: Principal, ttl_s: float | None) -> Lease:
    with db.session() as s:
        lease = s.get(Lease, lease_id)
        if lease is None or lease.kind != "manual":
            raise not_found(f"lease {lease_id}")
        _own_or_admin(lease, who, "extend")
        if not lease.active():
            raise ApiError(409, f"lease {lease_id}: already {'released' if lease.released_ts else 'expired'}")
        ttl = check_ttl(ttl_s) if ttl_s is not None else lease.expires_ts - lease.created_ts
        lease.expires_ts = max(lease.expires_ts, now() + ttl)
        return lease


def release(db: Database, lease_id: int, who: Principal) -> Lease:
    with db.session() as s:
        lease = s.get(Lease, lease_id)
        if lease is None:
            raise not_found(f"lease {lease_id}")
        if lease.kind == "run":
            raise ApiError(409, f"lease {lease_id}: held by run {lease.run_id}; abort the run instead")
        _own_or_admin(lease, who, "release")
        if lease.released_ts is None:
            lease.released_ts = now()
            lease.released_by = who.name
        return lease
