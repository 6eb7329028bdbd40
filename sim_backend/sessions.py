"""One bench at a time on a served rig, and every bench session starting from the same defined state.

A served simulator (`drivebench sim serve`) is a rig anyone on the machine can reach. Two benches on it would
corrupt each other's runs unnoticed (one such pair ended with a pass on 16,370 of 20,000 rows), and a bench arriving
after another would find the rotor turning and the last run's injections still acting. The drive front ends
(socketcand, serial) open a session when a bench connects: the first one is admitted and finds the drive as after
power-up (`SimulatedDevice.restart`); any other is refused with a clear error until it leaves. The load machine's
Modbus endpoint is the same bench's second connection and is not gated."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Callable


@dataclass
class BenchSessions:
    restart: Callable[[], None]
    holder: str | None = None
    admitted: int = 0
    refused: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def open(self, who: str) -> str | None:
        """None: admitted (the drive restarted for this bench); else who holds the rig."""
        with self._lock:
            if self.holder is not None:
                self.refused += 1
                return self.holder
            self.holder = who
            self.admitted += 1
        self.restart()
        return None

    def close(self, who: str) -> None:
        with self._lock:
            if self.holder == who:
                self.holder = None
