"""The comm-loss drill the EtherCAT way: the drive enabled at zero velocity, the bench stops sending process data,
and the SM watchdog must take the slave out of OP and the drive out of OPERATION ENABLED (0x6007) within the
watchdog time plus a margin. The statusword is polled over the mailbox meanwhile (CoE does not feed the SM
watchdog), so the report says when the drive left OPERATION ENABLED. Then the AL error is acknowledged, OP entered
again, and the power stage left off."""

from __future__ import annotations

import struct
import time
from typing import Any, Callable

import pysoem

from drivers.contract import cia402
from drivers.contract import objects as o
from drivers.contract.comm_loss import EXTERNAL_HINT
from drivers.contract.errors import LinkError
from drivers.ethercat.master import al_text, state_name

POLL_S = 0.005


def drill(link, before_withhold: Callable[[], None] | None = None) -> dict[str, Any]:
    cfg = link.comm_loss
    if cfg.mode == "external":
        return {"what": "drive", "result": "unverified", "mode": "external", "external_stop": cfg.external_stop,
                "note": "not drilled: the bench config states the rig's own stop chain; nothing proves it"}
    master = link.master
    link.enable_velocity_mode()
    if before_withhold is not None:
        before_withhold()
    report: dict[str, Any] = {"what": "drive", "mode": "sm_watchdog", "consumer_ms": cfg.consumer_time_ms,
                              "margin_ms": cfg.margin_ms}
    cyclic = master.cyclic
    master.stop_cyclic()
    withheld = master.last_exchange or time.monotonic()
    deadline = withheld + (cfg.consumer_time_ms + cfg.margin_ms) / 1000.0
    left_ms = None
    word = None
    while time.monotonic() < deadline:
        (word,) = struct.unpack("<H", master.sdo_read(o.STATUSWORD, 0)[:2])
        if cia402.decode(word) is not cia402.State.OPERATION_ENABLED:
            left_ms = (time.monotonic() - withheld) * 1e3
            break
        time.sleep(POLL_S)
    master.master.read_state()
    slave = master.slave
    report.update(state_after=cia402.state_name(word) if word is not None else "unread",
                  al_after=state_name(slave.state), al_code=f"0x{slave.al_status:04X}" if slave.al_status else None)
    _recover(link, cyclic)
    if left_ms is not None:
        report.update(result="passed", left_operation_enabled_ms=round(left_ms, 1),
                      note=f"statusword polled over CoE every {POLL_S * 1e3:g} ms during the silence")
        return report
    report["result"] = "failed"
    report["refusal"] = (f"{link.where}: comm-loss drill failed: the drive stayed OPERATION ENABLED "
                         f"{cfg.consumer_time_ms + cfg.margin_ms} ms after the last process data (SM watchdog "
                         f"{cfg.consumer_time_ms} ms + margin {cfg.margin_ms} ms; slave {report['al_after']}); where "
                         f"the rig stops it by other means write [drive] {EXTERNAL_HINT}")
    return report


def _recover(link, cyclic: bool) -> None:
    """The AL error acknowledged, OP again, the drive's power stage off (a fault the drill caused reset)."""
    master = link.master
    slave = master.slave
    if slave.state & 0x0F != pysoem.OP_STATE:
        master.request(pysoem.SAFEOP_STATE | pysoem.STATE_ACK)
        master.require(pysoem.SAFEOP_STATE, "acknowledging the drill's SM watchdog error")
        master.go_op(link.state_cycle)
    if cyclic:
        master.start_cyclic(link.cycle_s)
    word = link.read_statusword()
    state = cia402.decode(word)
    if state in cia402.FAULT_STATES:
        cia402.fault_reset(link, link._step_timeout_s, link.where)
    elif state in cia402.POWERED_STATES:
        link.disable()
    if cia402.decode(link.read_statusword()) in cia402.POWERED_STATES:
        raise LinkError(f"{link.where}: after the drill the drive is still powered: {al_text(slave.al_status)}")
