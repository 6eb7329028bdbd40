"""The end of every session with a drive, whatever the transport: the drive's own protection is put back only once
the drive is at rest and disabled; otherwise the last resort.

At close the bench asks the drive (statusword by a confirmed read) and the reference sensor (or the drive's own speed
where the rig has none): powered, or the shaft turning, or no answer at all means the drive "may still be enabled or
turning". Then the bench never weakens the drive's comm-loss reaction (CANopen 0x1016 stays armed, the serial
WATCHDOG stays on): it withholds its heartbeat so that the reaction the drill proved acts, sends the NMT command the
bench config says the drive honours (`last_resort_nmt`), and watches the shaft to standstill, bounded by the drive's
consumer time plus its stop time. The outcome is one line: the drive stopped itself, or "MOTOR STILL TURNING at X
rad/s: use the E-stop". The objects the bench changed are restored only when the drive ended at rest and disabled.
"""

from __future__ import annotations

import logging
import math
import sys
import time
from dataclasses import dataclass
from typing import Any, Callable

from drivers.contract.cia402 import POWERED_STATES, decode, state_name
from drivers.contract.errors import LinkError

log = logging.getLogger(__name__)

POLL_S = 0.02
COAST_WATCH_S = 1.0     # once the power stage is off, the shaft is watched this much longer for standstill
MARGIN_S = 1.0          # on top of consumer time + stop time: the drive's own check period, a loaded host


def still_turning_line(speed: float | None) -> str:
    shown = "an unknown speed" if speed is None or not math.isfinite(speed) else f"{speed:.1f} rad/s"
    return f"MOTOR STILL TURNING at {shown}: use the E-stop"


def announce(line: str) -> None:
    """The outcome where a person sees it at once (stderr), and in the log."""
    log.error(line)
    print(line, file=sys.stderr, flush=True)


@dataclass
class RestCheck:
    """What tells whether the drive is at rest and disabled (each call may raise LinkError: an unknown answer)."""

    statusword: Callable[[], int]
    speed: Callable[[], float | None]          # |shaft speed| mech rad/s: the reference sensor first, else the drive's
    standstill_mech_rad_s: float

    def look(self) -> dict[str, Any]:
        out: dict[str, Any] = {"state": None, "speed_mech_rad_s": None}
        try:
            word = self.statusword()
            out["state"] = state_name(word)
            out["powered"] = decode(word) in POWERED_STATES
        except LinkError as exc:
            out["powered"] = None
            out["state_error"] = str(exc)
        try:
            speed = self.speed()
            out["speed_mech_rad_s"] = None if speed is None or not math.isfinite(speed) else round(abs(speed), 3)
        except Exception as exc:          # the reference's link may be gone: the speed is then unknown
            out["speed_error"] = str(exc)
        speed = out["speed_mech_rad_s"]
        out["at_rest_and_disabled"] = (out["powered"] is False
                                       and (speed is None or speed <= self.standstill_mech_rad_s)
                                       and "speed_error" not in out)
        return out


def last_resort(check: RestCheck, withhold: Callable[[], None], bound_s: float,
                nmt: Callable[[], str | None] | None = None) -> dict[str, Any]:
    """The drive may still be enabled or turning and the controlword did not stop it: let its comm-loss reaction act
    (withhold: the bench's heartbeat / watchdog feed stops, the drive's monitoring left armed), the NMT command where
    the config says the drive honours it, then watch to standstill for at most `bound_s`. Returns the record's
    section, with `line` the one line to show."""
    started = time.monotonic()
    out: dict[str, Any] = {"what": "last resort: the bench's heartbeat withheld with the drive's comm-loss reaction "
                                   "armed"}
    try:
        withhold()
    except Exception as exc:           # e.g. the bus is gone: then the heartbeat is gone too
        out["withhold_error"] = str(exc)
    if nmt is not None:
        try:
            out["nmt"] = nmt()
        except Exception as exc:
            out["nmt_error"] = str(exc)
    seen = check.look()
    off_at: float | None = None
    while not seen["at_rest_and_disabled"] and time.monotonic() - started < bound_s:
        if seen["powered"] is False:      # the reaction has switched it off: the shaft may coast a little longer
            off_at = off_at or time.monotonic()
            if time.monotonic() - off_at > COAST_WATCH_S:
                break
        time.sleep(POLL_S)
        seen = check.look()
    waited = time.monotonic() - started
    out.update(seen, waited_s=round(waited, 3), bound_s=round(bound_s, 3))
    speed = seen["speed_mech_rad_s"]
    if seen["powered"] is False:
        out["outcome"] = "stopped itself"
        shaft = ("shaft speed not measured" if speed is None else f"shaft at {speed:.1f} rad/s"
                 + ("" if seen["at_rest_and_disabled"] else ", coasting with the power stage off"))
        out["line"] = (f"the drive did not obey the bench's stop; with the bench's heartbeat withheld it stopped itself "
                       f"within {waited:.1f} s ({seen['state']}, {shaft})")
    elif speed is not None and speed <= check.standstill_mech_rad_s and seen["powered"] is not False:
        out["outcome"] = "at rest, maybe enabled"
        out["line"] = (f"the drive may still be enabled ({seen['state'] or 'no answer'}) though the shaft is at rest "
                       f"({speed:.1f} rad/s): its comm-loss reaction is left armed; switch it off at the drive")
    else:
        out["outcome"] = "still turning"
        out["line"] = still_turning_line(speed)
    return out


def request_fed_last_resort(statusword: Callable[[], int], reference: Callable[[], float | None] | None,
                            standstill_mech_rad_s: float, quiet_s: float, stop_s: float) -> dict[str, Any] | None:
    """For a drive whose watchdog any request feeds (the serial line): None when it is disabled; else nothing is
    asked of it for `quiet_s` (its watchdog time plus margin) while the reference sensor is watched, then its
    statusword again, at most `stop_s` + MARGIN_S more."""
    if RestCheck(statusword, lambda: None, standstill_mech_rad_s).look()["powered"] is False:
        return None
    quiet_until = time.monotonic() + quiet_s

    def quiet_statusword() -> int:
        if time.monotonic() < quiet_until:
            raise LinkError("not asked while the drive's watchdog runs down")
        return statusword()

    check = RestCheck(quiet_statusword, reference or (lambda: None), standstill_mech_rad_s)
    return last_resort(check, lambda: None, quiet_s + stop_s + MARGIN_S)
