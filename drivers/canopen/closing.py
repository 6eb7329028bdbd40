"""The end of a CANopen session (CanopenDriveLink.close): the drive's own settings back only once it is disabled,
else the last resort of drivers.contract.last_resort with 0x1016 left armed; and the drive's heartbeat producer
(0x1017), which the bench sets at open so it can watch the drive, written back like every other object it changed.
"""

from __future__ import annotations

import logging
from typing import Any

from drivers.contract import last_resort as lr
from drivers.contract import objects as o
from drivers.contract.errors import LinkError

log = logging.getLogger(__name__)

GUARD_TIME = 0x100C
SYNC_COUNTER_OVERFLOW = 0x1019
NMT_COMMANDS = {"stop": "STOPPED", "reset": "RESET"}   # [drive] last_resort_nmt


def set_producer_heartbeat(link: Any, period_ms: int) -> None:
    """0x1017 at `period_ms`, the drive's own value kept for close (item: 0x1017 is restored like the rest)."""
    sdo = link.sdo
    before = sdo.read_standard(o.PRODUCER_HEARTBEAT, 0)      # the device's word, not the EDS's
    if before is None:
        if sdo.read_standard(GUARD_TIME, 0) is not None:
            raise LinkError(f"{link.where}: the drive has node guarding (0x100C guard time, 0x100D life time factor) "
                            f"and no heartbeat (0x1016 consumer, 0x1017 producer): drivebench's comm-loss mechanism is "
                            f"the CiA 301 heartbeat, proved by its drill, and node guarding is not supported; enable "
                            f"the drive's heartbeat (its manual or firmware: 0x1016/0x1017) to run it")
        return
    sdo.write(o.PRODUCER_HEARTBEAT, 0, period_ms)
    if before is not None and before != period_ms:
        link.report["producer_heartbeat_0x1017"] = {"drive_had_ms": before, "bench_set_ms": period_ms}
        link._producer_restore = before


def restore_producer_heartbeat(link: Any) -> list[str]:
    before = getattr(link, "_producer_restore", None)
    if before is None:
        return []
    try:
        link.sdo.write_standard(o.PRODUCER_HEARTBEAT, 0, before, 2)
        link._producer_restore = None
        return []
    except LinkError as exc:
        return [str(exc)]


def _drive_speed(link: Any) -> float | None:
    """|speed| the drive reports, read now by SDO (a live sample may be stale: SYNC has stopped)."""
    source = link.profile.source("speed_est_mech_rad_s") if link.profile is not None else None
    if source is None:
        return None
    raw = link.sdo.read_standard(source.index, source.subindex, signed=True)
    return None if raw is None else abs(raw * source.factor)


def _speed(link: Any) -> float | None:
    """The reference sensor (the dynamometer's encoder) where the rig has one, else the drive's own report."""
    reference = link._reference_speed
    if reference is not None:
        try:
            value = reference()
            if value is not None:
                return abs(value)
        except Exception as exc:       # the load link may be closed already: the drive's word then
            log.info("%s: reference speed at close: %s", link.where, exc)
    return _drive_speed(link)


def _statusword(link: Any) -> int:
    word = link.sdo.read(o.STATUSWORD)
    link.control.feed(word)
    return word


def last_resort_bound_s(link: Any) -> float:
    consumer_s = link.comm_loss_config.consumer_time_ms / 1000.0 if link._guard is not None else 0.0
    return consumer_s + link.stop_timeout_s + lr.MARGIN_S


def secured(link: Any) -> bool:
    """True when the drive is confirmed disabled (possibly after the last resort made it stop itself): its settings
    may go back. False: 0x1016 stays armed, the bench heartbeat stays withheld, the one line has been shown."""
    done = link.report.get("last_resort")
    if done is not None and done.get("outcome") != "stopped itself":
        return False                   # the last resort has run (the safe stop's last step): not twice
    check = lr.RestCheck(lambda: _statusword(link), lambda: _speed(link), link.standstill_mech_rad_s)
    seen = check.look()
    if seen["powered"] is False:
        return True
    guard = link._guard
    bound = last_resort_bound_s(link)
    choice = link.section.get("last_resort_nmt") or "none"

    def nmt() -> str | None:
        if choice not in NMT_COMMANDS:
            return None
        link.node.nmt.state = NMT_COMMANDS[choice]
        return f"NMT {NMT_COMMANDS[choice]} sent ([drive] last_resort_nmt = {choice!r})"

    link._stop_sync_producer()
    result = lr.last_resort(check, guard.withhold if guard is not None else (lambda: None), bound, nmt)
    result["found_at_close"] = seen
    if guard is None:
        result["what"] = "last resort: nothing armed in the drive; the shaft watched"
    link.report["last_resort"] = result
    lr.announce(f"{link.where}: {result['line']}")
    return result["outcome"] == "stopped itself"


def restore(link: Any) -> list[str]:
    """The drive is disabled: what the bench changed goes back — the comm-loss objects first (while the bench's
    heartbeat still runs), then 0x1017, the SYNC counter and the PDOs."""
    errors: list[str] = []
    if link._guard is not None:
        errors += link._guard.disarm()
    errors += restore_producer_heartbeat(link) + restore_sync_counter(link)
    if link._snapshot is not None and link._snapshot.touched:
        link.node.nmt.state = "PRE-OPERATIONAL"
        errors += link._snapshot.restore(link.sdo)
    return errors


def restore_sync_counter(link: Any) -> list[str]:
    """0x1019 (SYNC counter overflow) as the drive had it; 0x1006 is zeroed around the write, as CiA 301 asks."""
    if link._sync_counter_restore is None:
        return []
    try:
        link.sdo.write_standard(o.COMM_CYCLE_PERIOD, 0, 0, 4)
        link.sdo.write_standard(SYNC_COUNTER_OVERFLOW, 0, link._sync_counter_restore, 1)
        link.sdo.write_standard(o.COMM_CYCLE_PERIOD, 0, round(link.sync_period_s * 1e6), 4)
        link._sync_counter_restore = None
        return []
    except LinkError as exc:
        return [str(exc)]
