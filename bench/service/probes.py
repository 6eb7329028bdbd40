"""`drivebench probe` of a rig from the service, for its operator's page: the drive's identity and the probe's
checklist (bench/faces/checklist.py), kept per rig in the database (table rig_probes; the page shows the newest).

The probe runs as its own process (`python -m bench probe --bench BENCH --json`, reads only: no drill, no motion)
under a manual lease of the rig named "probe", so on a real rig no run starts meanwhile and a rig that a run or a
person holds is refused (409) instead of probed under them."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass

from sqlalchemy import select

from drivers.contract.checks import find_repo_root
from bench.service.auth import Principal
from bench.service.db import Database, Rig, RigProbe, iso, now
from bench.service.errors import ApiError, not_found
from bench.service.leases import release, reserve

PROBE_TIMEOUT_S = 120.0          # the probe process is killed after this (a drive that never answers its SDOs)
LEASE_MARGIN_S = 30.0            # the probe's lease outlives its timeout by this much, then expires by itself
ERROR_CHARS = 2000
IDENTITY_FIELDS = (("device_name", "device name"), ("vendor_id", "vendor id"), ("product_code", "product code"),
                   ("revision", "revision"), ("serial", "serial number"), ("software_version", "software version"))


@dataclass(frozen=True)
class ProbeView:
    id: int
    rig: str
    by: str
    ended_utc: str | None
    ok: bool
    identity: list[tuple[str, str]]       # (label, value) in IDENTITY_FIELDS order, those the drive gave
    node_id: int | None
    checklist: list[dict]                 # bench.faces.checklist.as_json items: item, status, detail, config_line
    error: str | None


def probe_rig(db: Database, rig_name: str, who: Principal, python: str = sys.executable,
              timeout_s: float = PROBE_TIMEOUT_S) -> ProbeView:
    """Probe the rig now (blocks up to timeout_s) and keep the result; ApiError 404/409 when it cannot."""
    with db.session() as s:
        rig = s.get(Rig, rig_name)
        if rig is None:
            raise not_found(f"rig {rig_name}")
        bench, enabled = rig.bench, rig.enabled
    if not enabled:
        raise ApiError(409, f"rig {rig_name}: disabled by an admin; not probed")
    lease = reserve(db, rig_name, who, timeout_s + LEASE_MARGIN_S, "probe")
    started = now()
    exit_code, report, error = None, None, None
    try:
        done = subprocess.run([python, "-m", "bench", "probe", "--bench", bench, "--json"], cwd=find_repo_root(),
                              stdin=subprocess.DEVNULL, capture_output=True, timeout=timeout_s)
        exit_code = done.returncode
        if exit_code == 0:
            try:
                report = json.loads(done.stdout)
            except ValueError as exc:
                error = f"probe: its --json output is not JSON ({exc})"
        else:
            error = done.stderr.decode("utf-8", errors="replace").strip()[-ERROR_CHARS:] or f"exit code {exit_code}"
    except subprocess.TimeoutExpired:
        error = f"probe: no result within {timeout_s:g} s (the drive does not answer?); the probe was stopped"
    except OSError as exc:
        error = f"probe: cannot start the probe process: {exc}"
    finally:
        release(db, lease.id, who)
    with db.session() as s:
        row = RigProbe(rig=rig_name, by=who.name, started_ts=started, ended_ts=now(), exit_code=exit_code,
                       report=report, error=error)
        s.add(row)
        s.flush()
        return probe_view(row)


def last_probe(db: Database, rig_name: str) -> ProbeView | None:
    with db.session() as s:
        row = s.execute(select(RigProbe).where(RigProbe.rig == rig_name)
                        .order_by(RigProbe.ended_ts.desc(), RigProbe.id.desc()).limit(1)).scalar_one_or_none()
        return probe_view(row) if row is not None else None


def probe_view(row: RigProbe) -> ProbeView:
    drive = (row.report or {}).get("drive") or {}
    identity = drive.get("identity") or {}
    shown = [(label, str(identity[key])) for key, label in IDENTITY_FIELDS if identity.get(key) not in (None, "")]
    return ProbeView(row.id, row.rig, row.by, iso(row.ended_ts), row.exit_code == 0 and row.report is not None,
                     shown, drive.get("node_id"), list((row.report or {}).get("checklist") or []), row.error)

