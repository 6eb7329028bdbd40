"""One warning line per interval for a failure that can repeat thousands of times a second (an accept loop out of
file descriptors, a port scan's resets): the first occurrence at once, later ones counted into the next line."""

from __future__ import annotations

import logging
import threading
import time

INTERVAL_S = 10.0


class RateLimitedLog:
    def __init__(self, logger: logging.Logger, what: str, interval_s: float = INTERVAL_S):
        self.logger, self.what, self.interval_s = logger, what, interval_s
        self.total = 0
        self._lock = threading.Lock()
        self._pending = 0
        self._next_s = 0.0

    def note(self, exc: BaseException) -> None:
        now = time.monotonic()
        with self._lock:
            self.total += 1
            self._pending += 1
            if now < self._next_s:
                return
            count, self._pending, self._next_s = self._pending, 0, now + self.interval_s
        self.logger.warning("%s: %s (%d time%s in the last %.0f s)", self.what, exc, count, "" if count == 1 else "s",
                            self.interval_s)
