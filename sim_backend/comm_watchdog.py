"""What a drive and a dynamometer do on their own when their master goes silent.

A drive watches the bench's heartbeat (CANopen 0x1016, or any request on the serial line once the bench armed the
serial watchdog) and reacts as its abort connection option code says (0x6007: 1 fault, 2 disable voltage, 3 quick
stop); a dynamometer with a Modbus communication watchdog sets its torque to zero and disables itself. Monitoring
starts with the first sign of the master after arming, as CiA 301 prescribes for heartbeat consumers.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Callable

CHECK_PERIOD_S = 0.01


@dataclass
class Watchdog:
    """timeout_s 0: off. `touch()` on every sign of the master; `expired(now)` once per silence."""

    name: str
    timeout_s: float = 0.0
    last_s: float | None = None
    tripped: bool = False
    trips: int = 0
    # a front end's "bytes of the master are waiting": what a real drive's UART would already have received while
    # the simulator's process was not scheduled (a loaded host), so they count as a sign of the master
    arrived: Callable[[], bool] | None = None

    def arm(self, timeout_s: float) -> None:
        self.timeout_s, self.last_s, self.tripped = timeout_s, None, False

    def touch(self) -> None:
        if self.timeout_s > 0:
            self.last_s = time.monotonic()
            self.tripped = False

    def expired(self, now: float) -> bool:
        if self.timeout_s <= 0 or self.last_s is None or self.tripped or now - self.last_s <= self.timeout_s:
            return False
        if self.arrived is not None and self.arrived():
            self.last_s = now
            return False
        self.tripped = True
        self.trips += 1
        return True


@dataclass
class WatchdogThread:
    """Checks a device's watchdogs every CHECK_PERIOD_S and calls their reactions (under the device lock); `tick`
    gets the wall time since the last check (a drive whose master is gone runs on its own clock)."""

    lock: threading.RLock
    tick: Callable[[float], None] | None = None
    checks: list[tuple[Watchdog, Callable[[float], None]]] = field(default_factory=list)
    _stop: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None

    def add(self, watchdog: Watchdog, react: Callable[[float], None]) -> None:
        self.checks.append((watchdog, react))
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="comm-watchdog", daemon=True)
            self._thread.start()

    def _run(self) -> None:
        last = time.monotonic()
        while not self._stop.wait(CHECK_PERIOD_S):
            now = time.monotonic()
            with self.lock:
                for watchdog, react in self.checks:
                    if watchdog.expired(now):
                        react(now - watchdog.last_s)
                if self.tick is not None:
                    self.tick(now - last)
            last = now

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
