"""The SYNC producer of a real-time link: one SYNC per period on the wall clock, never a burst."""

from __future__ import annotations

import threading
import time
from typing import Callable


class SyncProducer:
    def __init__(self, send: Callable[[], None], period_s: float, on_error: Callable[[str], None]):
        self._send = send
        self.period_s = period_s
        self._on_error = on_error
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self.stop()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="drivebench-sync", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        period_ns = round(self.period_s * 1e9)
        due = time.perf_counter_ns()
        while not self._stop.is_set():
            try:
                self._send()
            except Exception as exc:
                self._on_error(f"SYNC producer stopped: {exc}")
                return
            due += period_ns
            delay = due - time.perf_counter_ns()
            if delay > 0:
                time.sleep(delay / 1e9)
            elif delay < -100 * period_ns:   # hopelessly late (machine stalled): don't burst
                due = time.perf_counter_ns()

    def stop(self) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join(timeout=2.0)
            self._thread = None
