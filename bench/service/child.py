"""What `drivebench run` reports to the service that started it.

A run process of the service (bench/service/worker.py) attaches its event channel here, which installs this module
as the CLI's reporters (bench.faces.run_hooks); a plain `drivebench run` has none installed and reports nothing.
The messages are those of bench/service/run_protocol.py.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any, Callable

from bench.faces import run_hooks
from bench.service.run_protocol import Finished, Message, Progress, Trip

PR_SET_PDEATHSIG = 1
PROGRESS_MIN_INTERVAL_S = 0.25

_send: Callable[[Message], None] | None = None
finished = False          # a Finished message was sent


def attach(send: Callable[[Message], None] | None) -> None:
    global _send, finished
    _send, finished = send, False
    run_hooks.install(sys.modules[__name__] if send is not None else None)


def die_with(parent_pid: int) -> None:
    """Linux delivers SIGTERM when the service goes (also by SIGKILL), and SIGTERM is the run's one safe-stop path,
    so an orphaned run stops the drive and closes its record."""
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent_pid:      # the service died before prctl took effect
        os.kill(os.getpid(), signal.SIGTERM)


def progress_reporter() -> Callable[[float, float], None] | None:
    send = _send
    if send is None:
        return None
    last = [0.0]

    def report(t_s: float, total: float) -> None:
        wall = time.monotonic()
        if wall - last[0] >= PROGRESS_MIN_INTERVAL_S or t_s >= total:
            last[0] = wall
            send(Progress(t_s=round(float(t_s), 3), duration_s=float(total)))

    return report


def trip_reporter() -> Callable[[dict], None] | None:
    send = _send
    if send is None:
        return None

    def report(trip: dict) -> None:
        t_s = trip.get("t_s")
        send(Trip(reason=str(trip.get("reason")), t_s=float(t_s) if isinstance(t_s, (int, float)) else None,
                  message=str(trip.get("message", ""))))

    return report


def result_reporter() -> Callable[[Path, str, dict[str, Any]], None] | None:
    send = _send
    if send is None:
        return None

    def report(run_dir: Path, verdict: str, record: dict[str, Any]) -> None:
        global finished
        from bench.run.drill import export_proofs

        reason = record.get("abort_reason")
        send(Finished(run_dir=str(run_dir), record_path=str(Path(run_dir) / "record.json"), verdict=str(verdict),
                      abort_reason=str(reason) if reason else None, drill_proofs=tuple(export_proofs())))
        finished = True

    return report
