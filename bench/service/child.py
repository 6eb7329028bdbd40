"""What a run process started by the service does for it (stdlib only: imported by `drivebench run`).

DRIVEBENCH_PARENT_PID: die with the service. Linux delivers SIGTERM when the service goes (also by SIGKILL), and
SIGTERM is the run's one safe-stop path, so an orphaned run stops the drive and closes its record.
DRIVEBENCH_PROGRESS=jsonl: progress as `{"progress_s": t, "duration_s": T}` lines on stderr, and each trip as it
happens as `{"trip": {"reason", "t_s", "message", ...}}`.
"""

from __future__ import annotations

import ctypes
import json
import os
import signal
import sys
import time
from typing import Callable

PR_SET_PDEATHSIG = 1
PROGRESS_MIN_INTERVAL_S = 0.25


def apply_service_settings() -> None:
    parent = os.environ.get("DRIVEBENCH_PARENT_PID")
    if parent and sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
        except (OSError, AttributeError):
            pass
        if os.getppid() != int(parent):     # the service died before prctl took effect
            os.kill(os.getpid(), signal.SIGTERM)


def progress_reporter() -> Callable[[float, float], None] | None:
    if os.environ.get("DRIVEBENCH_PROGRESS") != "jsonl":
        return None
    last = [0.0]

    def report(t_s: float, total: float) -> None:
        wall = time.monotonic()
        if wall - last[0] >= PROGRESS_MIN_INTERVAL_S or t_s >= total:
            last[0] = wall
            print(json.dumps({"progress_s": round(t_s, 3), "duration_s": total}), file=sys.stderr, flush=True)

    return report


def trip_reporter() -> Callable[[dict], None] | None:
    if os.environ.get("DRIVEBENCH_PROGRESS") != "jsonl":
        return None

    def report(trip: dict) -> None:
        print(json.dumps({"trip": trip}), file=sys.stderr, flush=True)

    return report
