"""The service's fork server (multiprocessing's forkserver, preloaded once with what `drivebench run` imports) and
the run processes it forks.

A fork server that dies (SIGKILL, the kernel's OOM killer: it is the service's largest process) takes no run with
it: a forked run follows the service, not its parent (bench.service.worker._follow); the runner learns whether a
run ended from the run's own pidfd, never from the fork server's pipe (which says 255 once the server is gone).
The loss is seen by the runner's next tick, said in the service's log and in `/api/health` (`fork_server`), and a new
fork server is started in the background: queued runs wait for its preload as at start-up, at most FORKSERVER_WAIT_S,
then start cold; the runner's own thread never waits for a preload.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import select
import signal
import subprocess
import sys
import threading
import time
from typing import Callable

FORKSERVER_WAIT_S = 60.0      # queued runs wait this long for the fork server's preload, then start cold
STATUS_WAIT_S = 2.0           # a run process that ended: how long its exit status may take to come from the server


def _readable(fd: int | None, timeout: float | None = 0.0) -> bool:
    return fd is None or bool(select.select([fd], [], [], timeout)[0])


class ForkedProcess:
    """A run process forked by the fork server, with the part of Popen's surface the runner uses. Whether it lives
    is asked of its own pidfd; its exit status comes from the fork server, or is lost with it (`status_lost`, 255)."""

    def __init__(self, process, stdout, stderr, server_pidfd: int | None):
        self.process = process
        self.pid: int = process.pid
        self.stdout, self.stderr = stdout, stderr
        self._server_pidfd = server_pidfd
        self._ended_at: float | None = None
        self._code: int | None = None
        self.status_lost = False
        try:
            self._pidfd: int | None = os.pidfd_open(self.pid)
        except OSError:           # it already ended and the fork server reaped it
            self._pidfd = None

    @property
    def returncode(self) -> int | None:
        return self._code

    def poll(self) -> int | None:
        """The exit code once the process ended (negative: the signal, as Popen says), else None."""
        if self._code is not None:
            return self._code
        if not _readable(self._pidfd):
            return None
        self._ended_at = self._ended_at or time.monotonic()
        server_gone = _readable(self._server_pidfd)
        if not server_gone and not _readable(self.process.sentinel) and time.monotonic() - self._ended_at < STATUS_WAIT_S:
            return None           # ended; the fork server has not written its status yet
        code = self.process.exitcode
        if code is None or (code == 255 and server_gone):
            code, self.status_lost = 255, True
        self._code = code
        return code

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:
            try:
                if self._pidfd is not None:
                    signal.pidfd_send_signal(self._pidfd, sig)
                else:
                    os.kill(self.pid, sig)
            except ProcessLookupError:
                pass

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        if not _readable(self._pidfd, timeout):
            raise subprocess.TimeoutExpired(f"run process {self.pid}", timeout)
        while (code := self.poll()) is None:
            if deadline is not None and time.monotonic() > deadline + STATUS_WAIT_S:
                raise subprocess.TimeoutExpired(f"run process {self.pid}", timeout)
            time.sleep(0.01)
        return code

    def close(self) -> None:
        if self._pidfd is not None:
            os.close(self._pidfd)
            self._pidfd = None
        try:
            self.process.close()
        except ValueError:
            pass


def _how_it_ended(pid: int) -> str:
    """'killed by signal 9' / 'exited with 1' for a child that ended, without reaping it (multiprocessing does)."""
    try:
        info = os.waitid(os.P_PID, pid, os.WEXITED | os.WNOHANG | os.WNOWAIT)
    except ChildProcessError:
        return "ended"
    if info is None:
        return "ended"
    if info.si_code in (os.CLD_KILLED, os.CLD_DUMPED):
        return f"killed by signal {info.si_status}"
    return f"exited with {info.si_status}"


class ForkServer:
    """One fork server at a time: started (and restarted after a loss) in the background, ready once preloaded."""

    def __init__(self, on_ready: Callable[[], None]):
        self.on_ready = on_ready
        self.context = None
        self.ready = threading.Event()      # its preload done: forking no longer waits for imports
        self.since: float | None = None     # monotonic time its preload began; None once it failed
        self.pid: int | None = None
        self.pidfd: int | None = None
        self.benches: list[str] = []
        self.losses = 0
        self.last_loss: dict | None = None  # {"pid", "how", "at_utc"} of the latest fork server lost

    def start(self, benches: list[str]) -> None:
        """Preloads in the background: until it is ready `waiting_s` says how long queued runs have waited."""
        import multiprocessing
        import multiprocessing.forkserver

        from bench.service import worker

        self.benches = benches
        self.ready.clear()
        context = multiprocessing.get_context("forkserver")
        context.set_forkserver_preload(worker.preload_modules())
        os.environ[worker.WARM_BENCHES_ENV] = json.dumps(benches)   # read by bench.service.fork_warm in the server
        self.since = time.monotonic()
        multiprocessing.forkserver.ensure_running()      # reaps a lost one and starts another (does not wait)
        self.context = context
        self.pid = multiprocessing.forkserver._forkserver._forkserver_pid
        if self.pidfd is not None:
            os.close(self.pidfd)
        try:
            self.pidfd = os.pidfd_open(self.pid)
        except OSError:
            self.pidfd = None

        def wait_for_preload() -> None:
            try:
                probe = context.Process(target=worker.ready, name="drivebench-forkserver-probe")
                probe.start()
                probe.join(300)
                if probe.exitcode == 0:
                    self.ready.set()
                else:
                    self.since = None
                    print(f"drivebench serve: the fork server did not start (exit {probe.exitcode}); runs start cold",
                          file=sys.stderr)
            except Exception as exc:
                self.since = None
                print(f"drivebench serve: the fork server did not start: {exc}; runs start cold", file=sys.stderr)
            self.on_ready()               # the runs it held start now

        threading.Thread(target=wait_for_preload, daemon=True, name="drivebench-forkserver").start()

    def alive(self) -> bool:
        return self.pidfd is not None and not _readable(self.pidfd)

    def lost(self) -> bool:
        """Whether the started fork server has died (asked by the runner's thread and the health check alike)."""
        return self.context is not None and self.pidfd is not None and _readable(self.pidfd)

    def check(self) -> None:
        """From the runner's thread, each tick: a fork server that died is said and replaced."""
        if not self.lost():
            return
        was_ready = self.ready.is_set()
        how = _how_it_ended(self.pid)
        at = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
        self.losses += 1
        self.last_loss = {"pid": self.pid, "how": how, "at_utc": at}
        if not was_ready:             # it died in its preload: not again and again, runs start cold
            print(f"drivebench serve: the fork server (pid {self.pid}) {how} before it was ready; runs start cold",
                  file=sys.stderr)
            self.context, self.since = None, None
            return
        print(f"drivebench serve: the fork server (pid {self.pid}) {how} at {at}; its runs go on (they follow the "
              f"service); starting a new one, queued runs wait for its preload or start cold", file=sys.stderr)
        self.start(self.benches)

    def waiting_s(self) -> float | None:
        """Seconds queued runs have waited for the preload; None when they may start (ready, failed, waited
        FORKSERVER_WAIT_S). A lost fork server counts as warming: the runner's next tick replaces it."""
        since = self.since
        if since is None or (self.ready.is_set() and not self.lost()):
            return None
        waited = time.monotonic() - since
        return waited if waited < FORKSERVER_WAIT_S else None

    def warm(self) -> bool:
        return self.ready.is_set() and not self.lost()

    def fork(self, data: bytes, nice: int, service_pid: int) -> ForkedProcess:
        """A run process forked from the fork server, the request and the two pipes (protocol, log) handed over."""
        from multiprocessing.connection import Connection

        from bench.service import worker

        events_r, events_w = os.pipe()
        log_r, log_w = os.pipe()
        events, log = Connection(events_w), Connection(log_w)
        try:
            process = self.context.Process(target=worker.forked, args=(data, events, log, nice, service_pid),
                                           name="drivebench-run")
            process.start()
        except BaseException:
            os.close(events_r)
            os.close(log_r)
            raise
        finally:
            events.close()
            log.close()
        return ForkedProcess(process, os.fdopen(events_r, "rb"), os.fdopen(log_r, "rb"), self.pidfd)

    def health(self) -> dict:
        return {"pid": self.pid if self.alive() else None, "lost": self.losses, "last_lost": self.last_loss}
