"""Before the power stage is switched on (CanopenDriveLink.enable_velocity_mode): the drive obeys the bench at all
(statusword bit 9), the velocity mode written to 0x6060 and seen in 0x6061 — which many drives show 10-50 ms late,
so it is polled with a timeout — and the target zero.
"""

from __future__ import annotations

import time
from typing import Any

from drivers.contract import cia402
from drivers.contract import objects as o
from drivers.contract.control_watch import local_control_line
from drivers.contract.errors import LinkError

MODE_DISPLAY_TIMEOUT_S = 0.5     # 0x6061 may follow 0x6060 this late (drives seen: 10-50 ms)
MODE_POLL_S = 0.005
MODE_NAMES = {cia402.Mode.PROFILE_VELOCITY: "profile velocity (3)",
              cia402.Mode.CYCLIC_SYNC_VELOCITY: "cyclic synchronous velocity (9): a target with every SYNC"}


def check_remote(link: Any) -> int:
    """A drive in local control (bit 9 = 0) ignores the controlword: said so, instead of a state that never came."""
    word = link.read_statusword()
    if not word & cia402.StatusBit.REMOTE:
        raise LinkError(f"{link.where}: {local_control_line(word)}")
    return word


def select_mode(link: Any) -> None:
    """0x6060 = the velocity mode, 0x6061 waited for (bounded), target 0 (power stage still off)."""
    link.mode = link._velocity_mode()
    link.report["velocity_mode"] = MODE_NAMES[link.mode]
    link._target = 0
    zero_target(link)
    try:
        link.sdo.write(o.MODES_OF_OPERATION, 0, link.mode)
    except LinkError as exc:
        other = 'velocity_mode = "csv"' if link.mode is cia402.Mode.PROFILE_VELOCITY else 'velocity_mode = "pv"'
        raise LinkError(f"{exc}: the drive refuses mode of operation {int(link.mode)} "
                        f"({link.mode.name.lower().replace('_', ' ')}) in 0x6060 (modes of operation); 0x6502 "
                        f"(supported drive modes) says which it has; write {other} in [drive] if it has that one") \
            from None
    if not link.sdo.has(o.MODES_DISPLAY):
        return
    started = time.monotonic()
    while True:
        mode = link.sdo.read(o.MODES_DISPLAY)
        waited = time.monotonic() - started
        if mode == link.mode:
            if waited > MODE_POLL_S:
                link.report["mode_display_after_ms"] = round(waited * 1e3, 1)
            return
        if waited > MODE_DISPLAY_TIMEOUT_S:
            raise LinkError(f"{link.where}: 0x6061 (mode of operation display) is still {mode} "
                            f"{MODE_DISPLAY_TIMEOUT_S * 1e3:.0f} ms after 0x6060 = {int(link.mode)}: the drive did "
                            f"not take the mode")
        time.sleep(MODE_POLL_S)


def zero_target(link: Any) -> None:
    """0x6060's target zero before the enable: by SDO; a drive that takes 0x60FF by SDO only in OPERATION ENABLED
    (abort 0x08000022) gets it by its RPDO where one carries it, else right after the enable (`after_enable`)."""
    link._zero_after_enable = False
    try:
        link.sdo.write_standard(o.TARGET_VELOCITY, 0, 0, 4, signed=True)
    except LinkError as exc:
        if "0x08000022" not in str(exc):
            raise
        rpdo = link.plan.rpdo if link.plan is not None else None
        if rpdo is not None and any(e.index == o.TARGET_VELOCITY for e in rpdo.entries):
            link._send(rpdo.cob, link._pack_rpdo())
            how = "by its RPDO"
        else:
            link._zero_after_enable = True
            how = "by SDO right after the enable"
        link.report["target_zero"] = (f"0x60FF by SDO refused outside OPERATION ENABLED (abort 0x08000022): "
                                      f"zero target {how}")


def after_enable(link: Any) -> None:
    """Right after OPERATION ENABLED: the zero target a drive refused by SDO before; and the drill's own heartbeat
    EMCY (0x8130), which a loaded bench can receive only after the drill re-armed, is the drill's, not the run's."""
    if getattr(link, "_zero_after_enable", False):
        link.sdo.write_standard(o.TARGET_VELOCITY, 0, 0, 4, signed=True)
        link._zero_after_enable = False
    if "drill" in link.report:
        with link._lock:
            late = [f"0x{code:04X} {text}" for code, text in link._emcy if code == o.EMCY_HEARTBEAT]
            link._emcy = [(code, text) for code, text in link._emcy if code != o.EMCY_HEARTBEAT]
        if late:
            link.report["drill"]["emcy_after_rearm"] = late
