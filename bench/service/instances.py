"""Service instances: each start of `drivebench serve` holds a liveness lease of its own in the database, and a
process is known by its pid *and* its start time, so that nobody takes over what still lives.

An instance is registered at start-up (refused while another live instance has the same name), renewed by the
runner loop every TTL/3 and stopped at shutdown. Its runs may be taken over by another instance only when the
instance is gone (its lease expired) and the run's process is gone too.
"""

from __future__ import annotations

import os
import socket
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy import select, update
from sqlalchemy.exc import IntegrityError

from drivers.contract.errors import InputError
from bench.service.db import Database, Instance, iso, now

# a run process of an instance on another host cannot be asked: its service's death reaches it by
# PDEATHSIG (SIGTERM, the safe stop, SIGKILL after the runner's 60 s), so its runs wait this long after expiry
REMOTE_TAKEOVER_GRACE_S = 75.0


def _read(path: str) -> str | None:
    try:
        return Path(path).read_text().strip()
    except OSError:
        return None


def boot_id() -> str | None:
    """Where pids can be compared: this boot of the kernel and this pid namespace (two containers on one host
    may share a host name, not their pids)."""
    boot = _read("/proc/sys/kernel/random/boot_id")
    try:
        namespace = os.readlink("/proc/self/ns/pid")
    except OSError:
        namespace = None
    return f"{boot}/{namespace}" if boot and namespace else boot


def process_start(pid: int) -> int | None:
    """The process's start time in clock ticks since boot (Linux /proc; None elsewhere or if gone)."""
    stat = _read(f"/proc/{pid}/stat")
    if stat is None:
        return None
    fields = stat.rsplit(")", 1)[-1].split()
    try:
        return int(fields[19])       # field 22 of proc(5); fields[0] is field 3 (state)
    except (IndexError, ValueError):
        return None


def process_alive(pid: int | None, start: int | None = None) -> bool:
    """Is this process (on this host) still there: it exists, is not a zombie, and — where its start time was
    recorded — started when it did (not a reused pid)."""
    if not pid or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass                          # another user's process: it exists
    stat = _read(f"/proc/{pid}/stat")
    if stat is not None:
        fields = stat.rsplit(")", 1)[-1].split()
        if fields and fields[0] in ("Z", "X"):
            return False
        if start is not None and process_start(pid) != start:
            return False
    return True


@dataclass(frozen=True)
class Me:
    hostname: str
    boot_id: str | None          # boot id and pid namespace
    pid: int
    pid_start: int | None


def me() -> Me:
    return Me(socket.gethostname(), boot_id(), os.getpid(), process_start(os.getpid()))


def same_machine(inst: Instance, here: Me | None = None) -> bool:
    here = here or me()
    return inst.hostname == here.hostname and (inst.boot_id or None) == here.boot_id


def instance_lives(inst: Instance, t: float | None = None, here: Me | None = None) -> bool:
    """On this machine: its process lives (whatever its lease says: a frozen service still holds its runs).
    Elsewhere: its lease has not expired. A stopped instance is gone."""
    here = here or me()
    if inst.stopped_ts is not None:
        return False
    if same_machine(inst, here):
        return process_alive(inst.pid, inst.pid_start)
    return inst.expires_ts > (now() if t is None else t)


def refused(inst: Instance) -> InputError:
    return InputError([f"drivebench serve: --host-id: {inst.name!r} is held by a live service instance (pid "
                       f"{inst.pid} on {inst.hostname}, its lease until {iso(inst.expires_ts)}); stop it or give "
                       f"another --host-id"])


def register(db: Database, name: str, ttl_s: float, replacing: int | None = None) -> int:
    """This process's instance under `name`; an earlier instance of that name that is gone is marked stopped
    (its runs stay its own until its lease has expired). Raises InputError if one lives. `replacing`: this
    process's own earlier incarnation, fenced and with its runs ended, which may be replaced though it lives."""
    here = me()
    for _ in range(3):
        t = now()
        with db.session() as s:
            old = s.execute(select(Instance).where(Instance.name == name, Instance.stopped_ts.is_(None))).scalar()
            if old is not None:
                if old.id != replacing and instance_lives(old, t, here):
                    raise refused(old)
                s.execute(update(Instance).where(Instance.id == old.id, Instance.stopped_ts.is_(None))
                          .values(stopped_ts=t, stopped_by=f"{name} (pid {here.pid}) at start-up: found gone"))
        try:
            with db.session() as s:
                row = Instance(name=name, hostname=here.hostname, boot_id=here.boot_id, pid=here.pid,
                               pid_start=here.pid_start, started_ts=t, heartbeat_ts=t, expires_ts=t + ttl_s)
                s.add(row)
                s.flush()
                return row.id
        except IntegrityError:      # another start-up of the same name won the race: look again
            continue
    with db.session() as s:
        old = s.execute(select(Instance).where(Instance.name == name, Instance.stopped_ts.is_(None))).scalar()
    raise refused(old) if old is not None else InputError([f"drivebench serve: --host-id: {name!r}: cannot "
                                                           f"register the instance"])


def renew(s, instance_id: int, t: float, ttl_s: float) -> bool:
    """Extend this instance's lease (in the caller's transaction); False if it expired or was stopped meanwhile:
    then it holds nothing any more and must not claim or keep running anything."""
    return s.execute(update(Instance).where(Instance.id == instance_id, Instance.stopped_ts.is_(None),
                                            Instance.expires_ts > t)
                     .values(heartbeat_ts=t, expires_ts=t + ttl_s)).rowcount == 1


def stop(db: Database, instance_id: int) -> None:
    t = now()
    with db.session() as s:
        s.execute(update(Instance).where(Instance.id == instance_id, Instance.stopped_ts.is_(None))
                  .values(stopped_ts=t, expires_ts=t, stopped_by="itself (shutdown)"))
