"""Telemetry off the command thread: trace uploads, recording and Rerun logging in a worker thread of their own.

The command thread (setpoints, SYNC, supervision) hands the worker jobs and never waits for it: a trace upload takes
~100 ms of bus time per 0.5 s of trace, which in real time would hold every command that falls due meanwhile. The
worker runs the jobs in order, so the record is written in drive-time order; a job's failure is kept for the command
thread to raise at its next iteration, and drain() waits (bounded) until every job handed over has run.
"""

from __future__ import annotations

import queue
import threading
from typing import Callable

_STOP = object()


class TelemetryWorker:
    def __init__(self, name: str = "drivebench-telemetry"):
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._idle = threading.Condition()
        self._pending = 0
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, job: Callable[[], None]) -> None:
        with self._idle:
            self._pending += 1
        self._jobs.put(job)

    @property
    def pending(self) -> int:
        with self._idle:
            return self._pending

    @property
    def busy(self) -> bool:
        with self._idle:
            return self._pending > 0

    def _run(self) -> None:
        while True:
            job = self._jobs.get()
            if job is _STOP:
                return
            try:
                if self.error is None:           # after a failure the rest is skipped: the run is ending anyway
                    job()
            except BaseException as exc:         # handed to the command thread
                self.error = exc
            finally:
                with self._idle:
                    self._pending -= 1
                    self._idle.notify_all()

    def drain(self, timeout_s: float) -> bool:
        """True once every job handed over has run; False if that takes longer than timeout_s (a stuck upload)."""
        with self._idle:
            return self._idle.wait_for(lambda: self._pending == 0, timeout=timeout_s)

    def take_error(self) -> BaseException | None:
        error, self.error = self.error, None
        return error

    def stop(self) -> None:
        self._jobs.put(_STOP)
        self._thread.join(timeout=1.0)
