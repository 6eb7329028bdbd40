"""The bench-death drill on a CANopen CiA 402 drive: prove, before the first motion of a run, that the drive stops
itself when the bench goes silent.

The drive is enabled at zero velocity; the bench withholds its heartbeat (0x700 + bench node id) and nothing else
changes; the drive must leave OPERATION ENABLED within its consumer heartbeat time (0x1016) plus a stated margin.
The bench watches the statusword by SDO (another service than the heartbeat the drive watches), and collects what
else the drive says: its EMCY (0x8130 heartbeat error) and the NMT state in its own heartbeat (0x1029). Then it
re-arms: heartbeat back, a fault the drill caused reset, power stage off, NMT operational. The run enables the drive
again only when it proceeds.
"""

from __future__ import annotations

import threading
import time
from datetime import datetime, timezone
from typing import Any, Callable, Protocol

from drivers.contract import cia402
from drivers.contract.errors import LinkError
from drivers.contract.comm_loss import EXTERNAL_HINT, CommLossConfig



class DrillLink(Protocol):
    """What the drill uses of an armed CANopen drive link (drivers.canopen.link.CanopenDriveLink)."""

    where: str
    comm_loss_config: CommLossConfig
    node: Any                                   # canopen.RemoteNode
    _guard: Any                                 # drivers.canopen.comm_loss.CommLossGuard
    _cancel: threading.Event
    _step_timeout_s: float

    def read_statusword(self) -> int: ...
    def write_controlword(self, word: int) -> None: ...
    def enable_velocity_mode(self) -> None: ...
    def disable(self) -> None: ...
    def take_emcy(self) -> list[tuple[int, str]]: ...
    def heartbeat_state(self) -> tuple[int | None, float]: ...
    def drop_pending(self) -> list[str]: ...

POLL_S = 0.005            # statusword polls (SDO) while the heartbeat is withheld
LATE_WATCH_S = 3.0        # after the deadline the bench keeps looking this long: a late reaction is told from none
NOTICED_NMT = (0x04, 0x7F)   # STOPPED, PRE-OPERATIONAL: the drive's 0x1029 reaction; OPERATIONAL is no sign
NMT_NAMES = {0x00: "BOOT-UP", 0x04: "STOPPED", 0x05: "OPERATIONAL", 0x7F: "PRE-OPERATIONAL"}


def _utc() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


def drill(link: DrillLink, before_withhold: Callable[[], None] | None = None) -> dict[str, Any]:
    """The drill (`attempt`); once more when the first was timed too coarsely to prove the drive late (a starved
    host's slow SDO reads: `inconclusive`), without the load machine's drill again. Passes only when proved."""
    result = attempt(link, before_withhold)
    if result.get("inconclusive"):
        result = {**attempt(link), "first_attempt": result}
    return result


def attempt(link: DrillLink, before_withhold: Callable[[], None] | None = None) -> dict[str, Any]:
    """Run the drill on an armed link (configure() done); the drive is left disabled, the bench heartbeat running.
    `before_withhold` is called once the drive holds the shaft (enabled at zero velocity), just before the heartbeat
    stops (the bench drills its load machine meanwhile). Returns the drill's record: `result` is "passed", "failed"
    (with `refusal`, one line) or "unverified"."""
    cfg = link.comm_loss_config
    guard = link._guard
    if cfg.mode == "external":
        return {"what": "drive", "result": "unverified", "mode": "external", "external_stop": cfg.external_stop,
                "note": "not drilled: the bench config states the rig's own stop chain; nothing proves it"}
    consumer, margin = cfg.consumer_time_ms, cfg.margin_ms
    report: dict[str, Any] = {"what": "drive", "mode": "heartbeat", "consumer_ms": consumer, "margin_ms": margin,
                              "producer_period_ms": round(cfg.producer_period_s * 1e3, 3),
                              "abort_connection_0x6007": guard.report.get("abort_connection_0x6007")}
    _check_cancelled(link)
    # always enabled by the bench itself, at zero velocity: a drive found enabled (running, maybe at speed) is
    # quick-stopped to standstill on the drive's word and the reference sensor's first, or refused (LinkError)
    link.enable_velocity_mode()
    if link.report.get("found_running"):
        report["found_running"] = link.report["found_running"]
    word = link.read_statusword()
    if cia402.decode(word) is not cia402.State.OPERATION_ENABLED:
        report.update(result="failed", refusal=f"{link.where}: comm-loss drill: the drive did not stay enabled at zero "
                                               f"velocity ({cia402.state_name(word)}) before the drill")
        return report
    if before_withhold is not None:
        before_withhold()
    link.take_emcy()
    nmt_before, _ = link.heartbeat_state
    report["withheld_utc"] = _utc()
    withheld = time.monotonic()
    guard.withhold()
    deadline = withheld + (consumer + margin) / 1000.0
    left_s: float | None = None
    enabled_seen_s = 0.0                       # start of the last read that found it enabled: surely enabled after it
    while True:
        started = time.monotonic()
        word = link.read_statusword()          # SDO: not the heartbeat the drive watches
        now = time.monotonic()
        if cia402.decode(word) is not cia402.State.OPERATION_ENABLED:
            left_s = now - withheld
            break
        enabled_seen_s = started - withheld
        if now > deadline + LATE_WATCH_S:
            break
        _check_cancelled(link)
        time.sleep(POLL_S)
    watched_s = time.monotonic() - withheld
    time.sleep(min(0.05, consumer / 4000.0))   # the EMCY and the NMT change may follow the state change
    emcy = link.take_emcy()
    nmt_after, heard_at = link.heartbeat_state
    if heard_at <= withheld:
        nmt_after = None                       # no heartbeat of the drive since: its NMT state is not known
    report.update(
        left_operation_enabled_ms=None if left_s is None else round(left_s * 1e3, 1),
        deadline_ms=consumer + margin,
        state_after=cia402.state_name(word),
        emcy=[f"0x{code:04X} {text}" for code, text in emcy],
        nmt_heartbeat_before=NMT_NAMES.get(nmt_before, nmt_before),
        nmt_heartbeat_after="no heartbeat of the drive since" if nmt_after is None else NMT_NAMES.get(nmt_after, nmt_after),
    )
    if left_s is not None:
        report["reaction_vs_consumer_ms"] = round(left_s * 1e3 - consumer, 1)
    complaints = _rearm(link, word)
    report["rearmed_utc"] = _utc()
    if complaints:
        report["link_during_drill"] = complaints
    if left_s is not None and left_s * 1e3 <= consumer + margin:
        report["result"] = "passed"
        return report
    report["result"] = "failed"
    if left_s is not None and enabled_seen_s * 1e3 <= consumer + margin:
        # the change is stamped when the read that showed it returned; no read begun after the deadline found the
        # drive enabled: a host too slow to time the reaction, not a proven late one
        report["inconclusive"] = (f"no statusword read begun after {consumer + margin} ms found the drive enabled "
                                  f"(last seen enabled by a read begun at {enabled_seen_s * 1e3:.0f} ms, seen left "
                                  f"when a read returned at {left_s * 1e3:.0f} ms): the host's slow SDO reads, not "
                                  "a proven late reaction")
    noticed = [f"EMCY {e.split()[0]}" for e in report["emcy"]]
    if nmt_after is not None and nmt_after != nmt_before and nmt_after in NOTICED_NMT:
        noticed.append(f"NMT {report['nmt_heartbeat_after']}")
    if left_s is not None:
        why = (f"the drive reacted after {left_s:.2f} s (left OPERATION ENABLED {left_s * 1e3:.0f} ms after the bench "
               f"withheld its heartbeat), later than the margin: consumer time {consumer} ms + margin {margin} ms")
    elif noticed:
        why = (f"the drive noticed the lost heartbeat ({', '.join(noticed)}) but stayed OPERATION ENABLED "
               f"{watched_s * 1e3:.0f} ms after the bench withheld it (consumer time {consumer} ms): no CiA 402 "
               f"reaction within {watched_s:.1f} s (0x6007: {report['abort_connection_0x6007']})")
    else:
        why = (f"the drive stayed OPERATION ENABLED {watched_s * 1e3:.0f} ms after the bench withheld its heartbeat "
               f"(consumer time {consumer} ms) and showed no sign of noticing (no EMCY, no NMT change)")
    report["refusal"] = (f"{link.where}: comm-loss drill failed: {why}; it would keep the motor running if the bench "
                         f"died. Fix the drive's reaction (0x1016/0x6007), or where the rig stops it by other means "
                         f"write [drive] {EXTERNAL_HINT}")
    return report


def _check_cancelled(link: DrillLink) -> None:
    """The run was abandoned (operator abort, the supervisor): the safe stop has the drive now, not the drill."""
    if link._cancel.is_set():
        raise LinkError(f"{link.where}: comm-loss drill abandoned: the run is stopping")


def _rearm(link: DrillLink, word: int) -> list[str]:
    """Heartbeat back, the drive off (a fault the drill caused reset), NMT operational, the drill's traces gone;
    returns the link's complaints during the drill (TPDOs stop while the drive is pre-operational)."""
    link._guard.resume()
    time.sleep(0.01)                       # its first frame restarts the drive's monitoring
    state = cia402.decode(word)
    timeout = link._step_timeout_s
    if state in cia402.FAULT_STATES:       # 0x6007 = 1 (fault): the drill's own fault, not the run's
        cia402.wait_state(link, {cia402.State.FAULT}, "fault reaction", timeout, where=link.where)
        cia402.fault_reset(link, timeout, link.where)
    elif state in cia402.POWERED_STATES:
        link.disable()                     # from QUICK STOP ACTIVE, or a drive that stayed enabled (at zero speed)
    link.node.nmt.state = "OPERATIONAL"    # 0x1029 may have sent it to pre-operational
    link.take_emcy()
    return link.drop_pending()
