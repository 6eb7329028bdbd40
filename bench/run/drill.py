"""Before the first motion of every run (and `drivebench probe --drill`): the bench-death drill on the drive and the
load machine, and what the record, the verdict table and the service show about it.

The drive is drilled by its link (CANopen: heartbeat withheld, drivers.canopen.drill; serial: requests withheld);
once the drive holds the shaft at zero velocity the load machine is drilled alongside (its watchdog feed withheld),
so the drill costs the longer of the two times, not their sum. A drive or load machine that fails, or whose reaction
cannot be observed, refuses the run (`DrillRefused`, one line naming what and the config line to write); one whose
bench config states an external stop chain is run and shown as unverified comm-loss reaction everywhere.
"""

from __future__ import annotations

import json
import threading
import time
from datetime import datetime, timezone
from typing import Any, Iterable

from drivers.contract.errors import LinkError
from drivers.contract.comm_loss import EXTERNAL_HINT

UNVERIFIED = "unverified comm-loss reaction"
LOAD_JOIN_MARGIN_S = 10.0     # the load drill's own wait is its watchdog time plus margin; this bounds the rest


class DrillRefused(LinkError):
    """The drive or the load machine failed the drill, or its reaction cannot be observed."""


def run_drills(drive: Any, load: Any | None) -> dict[str, Any]:
    """Drill the drive (and the load machine alongside); the record's `comm_loss` section. Both are left disabled
    with their watchdogs fed again."""
    load_out: dict[str, Any] = {}
    thread: threading.Thread | None = None

    def drill_load() -> None:
        try:
            load_out["result"] = load.drill()
        except BaseException as exc:       # re-raised on the caller's thread
            load_out["error"] = exc

    def start_load() -> None:
        nonlocal thread
        if load is not None and thread is None:
            thread = threading.Thread(target=drill_load, name="load-drill", daemon=True)
            thread.start()

    try:
        drive_result = drive.drill(before_withhold=start_load)
    finally:
        # a drive whose watchdog only sees requests (serial) must hear from the bench while the load's drill goes on,
        # or it reacts a second time
        deadline = LOAD_JOIN_MARGIN_S + 60.0
        while thread is not None and thread.is_alive() and deadline > 0:
            thread.join(0.05)
            deadline -= 0.05
            drive.keepalive()
    if drive_result is None:
        drive_result = {"what": "drive", "result": "failed",
                        "refusal": f"drive: its link ({type(drive).__name__}) has no comm-loss drill, so its reaction "
                                   f"to the bench's death cannot be observed; where the rig stops it by other means "
                                   f"write [drive] {EXTERNAL_HINT}"}
    if load is None:
        load_result: Any = "none: free shaft"
    else:
        if thread is None:
            drill_load()                   # the drive was not enabled for its drill (external): the load alone
        if "error" in load_out:
            raise load_out["error"]
        load_result = load_out.get("result") or {
            "what": "load machine", "result": "failed",
            "refusal": "load machine: its link has no comm-loss drill (or it did not finish); where the rig stops it "
                       f"by other means write [load] {EXTERNAL_HINT}"}
    results = [r for r in (drive_result, load_result) if isinstance(r, dict)]
    return {"verified": all(r.get("result") == "passed" for r in results),
            "drive": drive_result, "load": load_result}


def refusal(summary: dict[str, Any]) -> str | None:
    lines = [r["refusal"] for r in (summary.get("drive"), summary.get("load"))
             if isinstance(r, dict) and r.get("result") == "failed"]
    return "; ".join(lines) or None


def unverified(summary: dict[str, Any] | None) -> str | None:
    """One line for the verdict table and the service: what was not proved and what the config states instead."""
    if not summary or summary.get("verified"):
        return None
    parts = []
    for r in (summary.get("drive"), summary.get("load")):
        if isinstance(r, dict) and r.get("result") == "unverified":
            parts.append(f"{r.get('what')}: stopped by the rig's own chain ({r.get('external_stop') or 'not said'}), "
                         "stated in the bench config, not proved")
    return f"{UNVERIFIED}: " + "; ".join(parts) if parts else None


DRILL_SETTINGS = ("comm_loss", "external_stop", "consumer_time_ms", "abort_option", "error_behaviour", "bench_node_id",
                  "drill_margin_ms", "map", "unit_id", "node_id", "transport")
_PROVED: dict[str, tuple[float, str, dict[str, Any]]] = {}   # key -> (monotonic, utc, summary) of a passed drill


def _key(key: tuple) -> str:
    return json.dumps(key, default=str)


def proved_recently(key: tuple, valid_s: float) -> dict[str, Any] | None:
    """A drill of this drive and load machine (same bench config, identity and comm-loss settings) that passed in
    this process (or was handed to it by the service that started it, `adopt_proofs`) less than `valid_s` ago
    ([bench] drill_valid_s; 0: never), as a record section saying so."""
    if valid_s <= 0 or _key(key) not in _PROVED:
        return None
    at, utc, summary = _PROVED[_key(key)]
    age = time.monotonic() - at
    if age >= valid_s:
        return None
    return {**summary, "reused": {"drilled_utc": utc, "age_s": round(age, 3), "drill_valid_s": valid_s}}


def remember(key: tuple, summary: dict[str, Any]) -> None:
    if summary.get("verified") and refusal(summary) is None:
        _PROVED[_key(key)] = (time.monotonic(), datetime.now(timezone.utc).isoformat(timespec="milliseconds"), summary)


def export_proofs() -> list[dict[str, Any]]:
    """The passed drills of this process, for the service to hand to its next run processes (one bench process in
    the sense of drill_valid_s: the service's run processes on this machine; CLOCK_MONOTONIC is machine-wide)."""
    return [{"key": key, "monotonic_s": at, "drilled_utc": utc, "summary": summary}
            for key, (at, utc, summary) in _PROVED.items()]


def adopt_proofs(proofs: Iterable[dict[str, Any]]) -> None:
    """Proofs from `export_proofs` of an earlier run process; a failed or refused drill is never adopted, and each
    still holds only while drill_valid_s of its own drill time has not passed."""
    for proof in proofs:
        try:
            key, at, utc, summary = proof["key"], float(proof["monotonic_s"]), str(proof["drilled_utc"]), proof["summary"]
        except (KeyError, TypeError, ValueError):
            continue
        if (isinstance(key, str) and isinstance(summary, dict) and summary.get("verified")
                and refusal(summary) is None and at <= time.monotonic()):
            if key not in _PROVED or _PROVED[key][0] < at:
                _PROVED[key] = (at, utc, summary)


def timings(summary: dict[str, Any] | None) -> str | None:
    """The drill in one line (verdict table): reaction vs consumer time."""
    if not summary:
        return None
    parts = []
    drive, load = summary.get("drive"), summary.get("load")
    if isinstance(drive, dict) and drive.get("result") == "passed":
        parts.append(f"drive left OPERATION ENABLED {drive['left_operation_enabled_ms']:.0f} ms after the bench's "
                     f"heartbeat stopped (consumer {drive['consumer_ms']} ms + margin {drive['margin_ms']} ms)")
    if isinstance(load, dict) and load.get("result") == "passed":
        parts.append(f"load machine disabled within {load['disabled_within_ms']:.0f} ms of silence "
                     f"(watchdog {load['timeout_ms']} ms)")
    if not parts:
        return None
    reused = summary.get("reused")
    when = (f" (drilled {reused['age_s']:.0f} s ago in this bench process, at {reused['drilled_utc']}; valid "
            f"{reused['drill_valid_s']:g} s)" if isinstance(reused, dict) else "")
    return "comm-loss drill passed" + when + ": " + "; ".join(parts)


def stated_external(cfg: Any) -> str | None:
    """From a bench config alone (the service's rig list): the stop chains it states instead of a drill."""
    parts = []
    if cfg.drive.get("comm_loss") == "external":
        parts.append(f"drive: {cfg.drive.get('external_stop') or 'not said'}")
    if cfg.load and cfg.load.get("comm_loss") == "external":
        parts.append(f"load machine: {cfg.load.get('external_stop') or 'not said'}")
    return f"{UNVERIFIED}: the rig's own stop chain, stated, not proved ({'; '.join(parts)})" if parts else None


def drill_rig(live_cfg: Any, base_dir: Any, live_signals: tuple[str, ...]) -> dict[str, Any]:
    """`drivebench probe --drill`: connect as a run does (comm-loss armed, PDOs set for `live_signals`), drill, leave
    both off, close. The only probe step that writes to the drive and enables it (at zero velocity)."""
    from bench.run.links import make_links
    from bench.run.supervisor import SafeStop
    from drivers.reference import ReferenceConfig

    drive, load = make_links(live_cfg, base_dir)
    opened = []
    try:
        drive.open()
        opened.append(drive)
        if load is not None:
            load.open()
            opened.append(load)
        drive.configure(live_signals, (), 1)
        reference = ReferenceConfig(live_cfg.reference_source).signals(load is not None)
        if load is not None and "speed_true_mech_rad_s" in reference:
            drive.set_reference_speed(lambda: load.feedback().speed_mech_rad_s)
        return run_drills(drive, load)
    except BaseException:
        if opened:
            SafeStop(drive if drive in opened else None, load if load in opened else None).run()
        raise
    finally:
        for link in reversed(opened):
            try:
                link.close()
            except Exception:
                pass
