"""The end-of-run safe stop (SafeStop), its bounded steps, and its last resort when the drive does not obey."""

from __future__ import annotations

import threading
import time
from typing import Callable


STEP_TIMEOUT_S = 6.0   # one safe-stop step; above a serial link's 4 x 0.5 s retries or Modbus's 2 x 2 x 0.5 s


class SafeStop:
    """The end-of-run sequence: drive quick stop commanded, load to zero torque and disabled, the drive braked to
    standstill, drive disabled.

    The drive is told first: on a unit or overspeed trip the shaft is running away under the drive's own torque, and
    the load machine is what brakes it until the drive does; a Modbus write takes milliseconds the drive should
    already be braking in. Its `begin_quick_stop` (the quick-stop command alone, state confirmed) comes before the
    load machine is touched, and its `quick_stop` then only waits for standstill.

    Runs at most once however often it is requested (trip, Ctrl-C, SIGTERM, normal end). Every step is
    tried even if an earlier one fails or hangs: each runs in a worker thread and is given up after
    `step_timeout_s` (a dead link must not keep the other link's steps from running). The failures are
    returned so the record can say so.
    """

    def __init__(self, drive, load, step_timeout_s: float = STEP_TIMEOUT_S):
        self.drive = drive
        self.load = load
        self.step_timeout_s = step_timeout_s
        self._lock = threading.Lock()
        self.done = False
        self.errors: list[str] = []
        self.steps: list[str] = []
        self.last_resort: str | None = None

    def run(self) -> list[str]:
        with self._lock:
            if self.done:
                return self.errors
            self.done = True
            if self.drive is not None:
                self._step("drive quick stop commanded", self.drive.begin_quick_stop)
            if self.load is not None:
                self._step("load zero torque and disabled", self.load.zero_and_disable)
            if self.drive is not None:
                self._step("drive quick stop", self.drive.quick_stop)
            if self.drive is not None:
                self._step("drive disabled", self.drive.disable)
            if self.drive is not None and any(not e.startswith("load") for e in self.errors):
                self._last_resort()
            return self.errors

    def _last_resort(self) -> None:
        """The drive did not obey its stop: its own comm-loss reaction, left armed, is let act (DriveLink.secure);
        the outcome's one line is shown at once and kept with the stop's errors when the motor may still turn."""
        outcome: list[str | None] = []
        bound = self.step_timeout_s + float(getattr(self.drive, "last_resort_bound_s", 0.0) or 0.0)
        error = _bounded(lambda: outcome.append(self.drive.secure()), bound)
        line = outcome[0] if outcome else None
        self.last_resort = line
        if error is not None:
            self.errors.append(f"last resort: {error}")
        elif line is not None and "stopped itself" not in line:
            self.errors.append(f"last resort: {line}")
        elif line is not None:
            self.steps.append(f"last resort: {line}")

    def _step(self, label: str, action: Callable[[], None]) -> None:
        self._outcome(label, _bounded(action, self.step_timeout_s))

    def _outcome(self, label: str, error: str | None) -> None:
        if error is None:
            self.steps.append(label)
        else:              # keep going: the remaining steps matter more than this error
            self.errors.append(f"{label}: {error}")


class _Worker:
    """One safe-stop step in a daemon thread, started at once; result() waits for it (bounded)."""

    def __init__(self, action: Callable[[], None]):
        self.outcome: list[str | None] = []
        self.started = time.monotonic()

        def target() -> None:
            try:
                action()
                self.outcome.append(None)
            except BaseException as exc:
                self.outcome.append(f"{type(exc).__name__}: {exc}")

        self.thread = threading.Thread(target=target, name="drivebench-safe-stop", daemon=True)
        self.thread.start()

    def result(self, timeout_s: float) -> str | None:
        self.thread.join(max(0.0, timeout_s - (time.monotonic() - self.started)))
        if self.thread.is_alive():
            return f"no answer within {timeout_s:g} s (step abandoned)"
        return self.outcome[0]


def _bounded(action: Callable[[], None], timeout_s: float) -> str | None:
    """Run action in a daemon thread; None when it returned, else what went wrong (exception or timeout)."""
    return _Worker(action).result(timeout_s)
