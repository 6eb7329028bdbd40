"""The run loop's thread, and the gate that shuts an abandoned loop out of the rig."""

from __future__ import annotations

import threading
import traceback
from typing import Any, Callable


class RunLoopAbandoned(Exception):
    """A call from a run loop that the supervisor has abandoned: the run is over, nothing more goes to the rig."""


class Gate:
    """The run loop's view of a link: once the loop is abandoned, its calls are refused (other threads — the safe
    stop, the final upload — still reach the link)."""

    def __init__(self, target: Any, loop_thread: Callable[[], int | None], closed: threading.Event):
        self._target, self._loop_thread, self._closed = target, loop_thread, closed

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self._target, name)
        if not callable(attr):
            return attr

        def call(*args, **kwargs):
            if self._closed.is_set() and threading.get_ident() == self._loop_thread():
                raise RunLoopAbandoned(f"{name}() refused: the run loop was abandoned")
            return attr(*args, **kwargs)
        return call


class LoopThread:
    """run._configure_and_enable() and run._loop() on a thread of their own, so that the main thread can end a run
    whose loop is stuck in a call (the supervisor's wall-clock bound) and take SIGINT/SIGTERM at any time. The run's
    drive and load become Gates: once the loop is abandoned, its calls are refused."""

    def __init__(self, run: Any):
        self.run = run
        self._thread = threading.Thread(target=self._body, name="run-loop", daemon=True)
        self._done = threading.Event()
        self._abandoned = threading.Event()
        self._abort_reason: str | None = None
        self._exc: BaseException | None = None
        self.traceback: str | None = None
        self._raw = (run.drive, run.load)
        ident = lambda: self._thread.ident    # noqa: E731
        run.drive = Gate(run.drive, ident, self._abandoned)
        if run.load is not None:
            run.load = Gate(run.load, ident, self._abandoned)

    def start(self) -> None:
        self._thread.start()

    def _body(self) -> None:
        try:
            self.run._configure_and_enable()
            self._abort_reason = self.run._loop()
        except BaseException as exc:
            self._exc = exc
            self.traceback = traceback.format_exc()
        finally:
            self._done.set()

    def wait(self, timeout_s: float) -> bool:
        return self._done.wait(timeout_s)

    def result(self, ended_by_itself: bool) -> str | None:
        """The loop's abort reason, or its exception raised here; an abandoned loop: the supervisor's trip."""
        if not ended_by_itself:
            trip = self.run.supervisor.trip
            return (trip.message if trip else "run loop abandoned") + "; the run loop was stuck and abandoned"
        if self._exc is not None:
            raise self._exc
        return self._abort_reason

    def stop_and_wait(self, grace_s: float) -> None:
        self.run._stop_loop.set()
        if not self._done.wait(grace_s):
            self.abandon()

    def abandon(self) -> None:
        self._abandoned.set()
        for link in self._raw:
            try:
                link.interrupt()
            except Exception:
                pass
