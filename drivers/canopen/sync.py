"""SYNC production for a real-time link.

Where the interface sends cyclic frames in hardware or in its driver (python-can's `send_periodic` overridden by the
interface: socketcan's broadcast manager, IXXAT, ...), that is used. Otherwise a thread of ours that never bursts:
a SYNC that is late by more than half a period is skipped, never sent back to back with the next one (python-can's
software fallback catches up with bursts). Every SYNC sent is counted, so commands can be stamped with the SYNC
they went out with; the send times are kept for jitter figures.
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Callable

import can

SPIN_S = 0.0015              # the last part of a wait is spent spinning: time.sleep overshoots by ~0.1-1 ms


def has_native_cyclic(bus: can.BusABC) -> bool:
    return type(bus)._send_periodic_internal is not can.BusABC._send_periodic_internal


class SyncProducer:
    def __init__(self, send: Callable[[], None], period_s: float, on_error: Callable[[str], None],
                 keep_times: int = 1_000):
        self._send = send
        self.period_s = period_s
        self._on_error = on_error
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.count = 0                               # SYNCs sent
        self.skipped = 0                             # SYNC slots given up because the thread was late
        self.send_times_ns: collections.deque[int] = collections.deque(maxlen=keep_times)
        self.native = False

    def start(self) -> None:
        self.stop()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="drivebench-sync", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        period_ns = round(self.period_s * 1e9)
        due = time.perf_counter_ns()
        while not self._stop.is_set():
            now = time.perf_counter_ns()
            late = now - due
            if late > period_ns // 2:                # never two SYNCs closer than half a period: skip the slot
                missed = late // period_ns + (1 if late % period_ns > period_ns // 2 else 0)
                self.skipped += max(1, missed)
                due += max(1, missed) * period_ns
                continue
            try:
                self._send()
            except Exception as exc:
                self._on_error(f"SYNC producer stopped: {exc}")
                return
            self.send_times_ns.append(time.perf_counter_ns())
            self.count += 1
            due += period_ns
            remaining = (due - time.perf_counter_ns()) / 1e9
            if remaining > SPIN_S:
                if self._stop.wait(remaining - SPIN_S):
                    return
            while time.perf_counter_ns() < due:
                pass

    def stop(self) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join(timeout=2.0)
            self._thread = None


class NativeSync:
    """SYNC as the interface's own cyclic task (counted by elapsed time: the interface sends, not us)."""

    def __init__(self, bus: can.BusABC, period_s: float):
        self.period_s = period_s
        self._task = bus.send_periodic(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False), period_s)
        self._started = time.perf_counter()
        self.native = True
        self.skipped = 0
        self.send_times_ns: collections.deque[int] = collections.deque()

    @property
    def count(self) -> int:
        return int((time.perf_counter() - self._started) / self.period_s) + 1

    def start(self) -> None:
        pass

    def stop(self) -> None:
        if self._task is not None:
            self._task.stop()
            self._task = None
