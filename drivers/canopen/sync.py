"""SYNC production for a real-time link, its interval statistics, and the placement of answers on the SYNCs.

Where the interface sends cyclic frames in hardware or in its driver (python-can's `send_periodic` overridden by the
interface: socketcan's broadcast manager, IXXAT, ...), that is used. Otherwise a thread of ours on an absolute
deadline schedule (slot n is due at start + n periods, never `sleep(period)` drift) that never bursts: a SYNC that is
late by more than half a period is skipped, never sent back to back with the next one (python-can's software fallback
catches up with bursts). The thread holds no lock but the bus's own send lock for the one frame, and the process's
GIL switch interval is shortened while it runs (a pure-Python thread elsewhere in the bench then yields the GIL within
0.5 ms instead of 5 ms).

Time of a sample without a drive clock (`SyncTimeline`): the SYNC it answers x the period. Answers to synchronous
TPDOs come in the order of the SYNCs (CAN and TCP keep order), so the n-th answer belongs to the n-th SYNC; a late
frame (TCP, a busy host) is jitter and moves nothing. A missing answer shows as a backlog: every later answer is
stamped (by the interface, on the bus, or on receipt) after one more SYNC went out than its place in the sequence says.
When the backlog has stayed at n >= 1 (n or n + 1: the drive's own jitter) for the last `window` answers (0.5 s of
them), n SYNCs are counted unanswered and skipped: the time axis gets its gap there (`window` answers after the loss;
the answers in between sit n periods late), and the run is incomplete. A backlog that falls by more is a queue
draining (a slow host, a TCP burst), not a loss: the n-th answer stays on the n-th SYNC. (A drive that answers more
than a period late for 0.5 s on end looks the same as a lost answer: no CiA 301 TPDO says which SYNC it answers.)
"""

from __future__ import annotations

import bisect
import collections
import math
import os
import sys
import threading
import time
from typing import Callable

import can

SPIN_S = 0.0015              # the last part of a wait is spent spinning: time.sleep overshoots by ~0.1-1 ms
LATE_PERIODS = 1.5           # an interval between two SYNCs longer than this many periods is "late"
SWITCH_INTERVAL_S = 0.0005   # sys.setswitchinterval while a SYNC thread runs (Python's default: 0.005)
HIST_BIN_S = 10e-6           # interval histogram resolution
HIST_PERIODS = 8             # histogram range; longer intervals count in the last bin (max is kept exactly)
EPOCH_WINDOW_S = 3600.0      # an interface timestamp within this of time.time() is on the bench's clock
SYNC_RT_PRIORITY = 10        # SCHED_FIFO priority of the SYNC thread (1-99; kernel threads of IRQs run at 50)


def has_native_cyclic(bus: can.BusABC) -> bool:
    return type(bus)._send_periodic_internal is not can.BusABC._send_periodic_internal


class IntervalStats:
    """Intervals between SYNCs as the bench sent them: a streaming histogram (10 µs bins), so memory does not grow
    with the run. p50/p99 to the bin's upper edge; max exact; late = intervals > LATE_PERIODS periods."""

    def __init__(self, period_s: float):
        self.period_s = period_s
        self._bins = [0] * (int(HIST_PERIODS * period_s / HIST_BIN_S) + 1)
        self.n = 0
        self.max_s = 0.0
        self.min_s = math.inf
        self.late = 0

    def add(self, interval_s: float) -> None:
        self.n += 1
        self._bins[min(len(self._bins) - 1, int(interval_s / HIST_BIN_S))] += 1
        self.max_s = max(self.max_s, interval_s)
        self.min_s = min(self.min_s, interval_s)
        if interval_s > LATE_PERIODS * self.period_s:
            self.late += 1

    def percentile(self, q: float) -> float:
        if not self.n:
            return math.nan
        rank, seen = q / 100.0 * self.n, 0
        for k, count in enumerate(self._bins):
            seen += count
            if seen >= rank and count:
                return min((k + 1) * HIST_BIN_S, self.max_s)
        return self.max_s

    def summary(self) -> dict:
        ms = lambda s: None if not math.isfinite(s) else round(s * 1e3, 3)  # noqa: E731
        return {"intervals": self.n, "p50_ms": ms(self.percentile(50)), "p99_ms": ms(self.percentile(99)),
                "max_ms": ms(self.max_s) if self.n else None, "min_ms": ms(self.min_s), "late": self.late,
                "late_means": f"interval > {LATE_PERIODS:g} periods"}


def raise_priority() -> str:
    """The calling thread (the SYNC thread) in the real-time class where the OS allows it (Linux SCHED_FIFO: root or
    CAP_SYS_NICE), so a busy host does not keep it off the CPU; what it got, for the record."""
    if not hasattr(os, "sched_setscheduler"):
        return "normal (no SCHED_FIFO on this OS)"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(SYNC_RT_PRIORITY))
        return f"SCHED_FIFO {SYNC_RT_PRIORITY}"
    except (PermissionError, OSError) as exc:
        return f"normal (SCHED_FIFO refused: {exc.strerror or exc}; give the bench CAP_SYS_NICE)"


class SyncProducer:
    """`send(data)` puts one SYNC on the bus (data: b"" or the counter byte). `counter_overflow` > 1: CiA 301 SYNC
    counter 1..overflow in the SYNC's data byte (0x1019 of the drive)."""

    def __init__(self, send: Callable[[bytes], None], period_s: float, on_error: Callable[[str], None],
                 keep_times: int = 1_000, counter_overflow: int = 0):
        self._send = send
        self.period_s = period_s
        self._on_error = on_error
        self.counter_overflow = counter_overflow
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.count = 0                               # SYNCs sent (the last one's sequence number, from 1)
        self.skipped = 0                             # SYNC slots given up because the thread was late
        self.send_times_ns: collections.deque[int] = collections.deque(maxlen=keep_times)
        self.stats = IntervalStats(period_s)
        self.frozen = False                          # freeze(): the statistics stop here (the run's part is over)
        self.native = False
        self._epochs: list[float] = []               # time.time() just before SYNC n+1 went out (n from 0)
        self._first_seq = 1
        self._lock = threading.Lock()                # guards _epochs only (O(1) under it)
        self._switch_interval: float | None = None
        self.scheduling = "not started"

    def start(self) -> None:
        self.stop()
        self._stop.clear()
        self._switch_interval = sys.getswitchinterval()
        sys.setswitchinterval(min(self._switch_interval, SWITCH_INTERVAL_S))
        self._thread = threading.Thread(target=self._run, name="drivebench-sync", daemon=True)
        self._thread.start()

    def _data(self, seq: int) -> bytes:
        return bytes([(seq - 1) % self.counter_overflow + 1]) if self.counter_overflow > 1 else b""

    def _run(self) -> None:
        self.scheduling = raise_priority()
        period_ns = round(self.period_s * 1e9)
        due = time.perf_counter_ns()
        last_sent: int | None = None
        while not self._stop.is_set():
            now = time.perf_counter_ns()
            late = now - due
            if late > period_ns // 2:                # never two SYNCs closer than half a period: skip the slot
                missed = late // period_ns + (1 if late % period_ns > period_ns // 2 else 0)
                if not self.frozen:
                    self.skipped += max(1, missed)
                due += max(1, missed) * period_ns
                continue
            seq = self.count + 1
            with self._lock:                         # recorded before the send: an answer may beat the append
                self._epochs.append(time.time())
                if len(self._epochs) > 8192:
                    del self._epochs[:4096]
                    self._first_seq += 4096
            self.count = seq
            try:
                self._send(self._data(seq))
            except Exception as exc:
                self._on_error(f"SYNC producer stopped: {exc}")
                return
            sent = time.perf_counter_ns()
            self.send_times_ns.append(sent)
            if last_sent is not None and not self.frozen:
                self.stats.add((sent - last_sent) * 1e-9)
            last_sent = sent
            due += period_ns
            remaining = (due - time.perf_counter_ns()) / 1e9
            if remaining > SPIN_S:
                if self._stop.wait(remaining - SPIN_S):
                    return
            while time.perf_counter_ns() < due:
                pass

    def freeze(self) -> None:
        """Statistics end here; SYNC goes on (the drive is disabled; what the bench does next is not timed)."""
        self.frozen = True

    def sent_before(self, epoch_s: float) -> tuple[int, float | None]:
        """(the last SYNC sent at or before epoch_s, 0 if none; its send time)."""
        with self._lock:
            k = bisect.bisect_right(self._epochs, epoch_s)
            return (self._first_seq + k - 1, self._epochs[k - 1]) if k else (self._first_seq - 1, None)

    def epoch_of(self, seq: int) -> float | None:
        with self._lock:
            k = seq - self._first_seq
            return self._epochs[k] if 0 <= k < len(self._epochs) else None

    def stop(self) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join(timeout=2.0)
            self._thread = None
        if self._switch_interval is not None:
            sys.setswitchinterval(self._switch_interval)
            self._switch_interval = None

    def report(self) -> dict:
        return {**self.stats.summary(), "sent": self.count, "skipped": self.skipped, "scheduling": self.scheduling,
                "window": "from the start of SYNC to the drive disabled" if self.frozen else "whole connection",
                "skipped_means": "SYNC slots not sent because the bench's SYNC thread woke > 0.5 period late"}


class NativeSync:
    """SYNC as the interface's own cyclic task (counted by elapsed time: the interface sends, not us)."""

    def __init__(self, bus: can.BusABC, period_s: float):
        self.period_s = period_s
        self._task = bus.send_periodic(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False), period_s)
        self._started = time.perf_counter()
        self._started_epoch = time.time()
        self.native = True
        self.skipped = 0
        self.counter_overflow = 0
        self.send_times_ns: collections.deque[int] = collections.deque()

    @property
    def count(self) -> int:
        return int((time.perf_counter() - self._started) / self.period_s) + 1

    def sent_before(self, epoch_s: float) -> tuple[int, float | None]:
        n = math.floor((epoch_s - self._started_epoch) / self.period_s) + 1
        return (n, self._started_epoch + (n - 1) * self.period_s) if n > 0 else (0, None)

    def epoch_of(self, seq: int) -> float | None:
        return self._started_epoch + (seq - 1) * self.period_s

    def start(self) -> None:
        pass

    def freeze(self) -> None:
        pass

    def stop(self) -> None:
        if self._task is not None:
            self._task.stop()
            self._task = None

    def report(self) -> dict:
        return {"sent": self.count, "skipped": 0, "note": "sent by the interface: intervals not seen by the bench"}


class SyncTimeline:
    """Places each answer (one SYNC's TPDOs, complete) on the SYNC it answers; see the module docstring.

    `sent_before(epoch) -> (seq, send time)` and `epoch_of(seq)` come from the SYNC producer. An answer's time is its
    interface timestamp when that is on the bench's clock (time.time(): socketcan, socketcand, virtual), else its
    receive time. A constant offset between the two clocks (or a constant transport delay) is taken out with the
    smallest lag seen."""

    def __init__(self, period_s: float, sent_before: Callable[[float], tuple[int, float | None]],
                 epoch_of: Callable[[int], float | None], window: int | None = None):
        self.period_s = period_s
        self._sent_before = sent_before
        self._epoch_of = epoch_of
        self.window = window or max(20, round(0.5 / period_s))
        self.last = 0                       # the SYNC the last answer was placed on
        self.unanswered = 0                 # SYNCs counted without an answer
        self.answers = 0
        self.bus_stamps = 0                 # answers placed by the interface's timestamp
        self._backlog: collections.deque[int] = collections.deque(maxlen=self.window)
        self._lag0: float | None = None     # smallest (answer time - its SYNC's send time) seen
        self.last_lag: float | None = None  # the latest answer's time - its SYNC's send time: how far behind the drive is
        self.lag = IntervalStats(period_s)  # answer time - its SYNC's send time - lag0: the transport's jitter
        self._rebase = False
        self.unanswered_before_run = 0      # counted before rebase(): the drive silent on purpose (the drill)

    def rebase(self) -> None:
        """The run starts: the next answer is placed on the SYNC it answers by its arrival time (the transport's
        smallest lag taken out), not after the last one placed. Before the run the drive may have been silent on
        purpose — pre-operational after the comm-loss drill's withheld heartbeat — and those SYNCs are not the run's
        missing data."""
        self._rebase = True
        self._backlog.clear()
        self.unanswered_before_run += self.unanswered
        self.unanswered = 0

    def place(self, stamp: float | None, received: float) -> int:
        """The sequence number (from 1) of the SYNC this answer belongs to."""
        on_clock = stamp is not None and stamp > 0 and abs(received - stamp) < EPOCH_WINDOW_S
        r = stamp if on_clock else received
        self.bus_stamps += bool(on_clock)
        self.answers += 1
        seq = self.last + 1
        if self._rebase and self._lag0 is not None:
            latest, _ = self._sent_before(r - self._lag0 + 1e-6)
            seq = max(seq, latest)
        self._rebase = False
        sent = self._epoch_of(seq)
        if sent is not None:
            lag = r - sent
            self._lag0 = lag if self._lag0 is None else min(self._lag0, lag)
            latest, _ = self._sent_before(r - self._lag0 + 1e-6)
            self._backlog.append(latest - seq)
            if latest - seq >= 1 and len(self._backlog) == self.window and \
                    1 <= min(self._backlog) >= max(self._backlog) - 1:    # (the first test keeps the healthy case O(1))
                missed = min(self._backlog)
                self.unanswered += missed
                seq += missed
                self._backlog.clear()
            sent = self._epoch_of(seq)
            if sent is not None:
                self.lag.add(max(0.0, r - sent - self._lag0))
                self.last_lag = r - sent
        self.last = seq
        return seq

    def report(self) -> dict:
        lag = self.lag.summary()
        return {"placement": "SYNC answered (n-th answer -> n-th SYNC; backlog over "
                             f"{self.window} answers -> unanswered)",
                "answers": self.answers, "unanswered": self.unanswered,
                "unanswered_before_run": self.unanswered_before_run,
                "stamps": "interface (bus) time" if self.bus_stamps * 2 > max(1, self.answers) else "receive time",
                "answer_jitter_p50_ms": lag["p50_ms"], "answer_jitter_p99_ms": lag["p99_ms"],
                "answer_jitter_max_ms": lag["max_ms"]}


class ReceiveClock:
    """Event-driven TPDOs answer no SYNC: their time is their interface timestamp (or receive time) on the bench's
    clock, from the first SYNC's send time; the jitter is stated as the spread of intervals between samples."""

    def __init__(self, period_s: float, origin_epoch: Callable[[], float | None]):
        self.period_s = period_s
        self._origin = origin_epoch
        self._fallback: float | None = None
        self.intervals = IntervalStats(period_s)
        self._last: float | None = None
        self.bus_stamps = 0
        self.answers = 0

    def place(self, stamp: float | None, received: float) -> float:
        on_clock = stamp is not None and stamp > 0 and abs(received - stamp) < EPOCH_WINDOW_S
        r = stamp if on_clock else received
        self.bus_stamps += bool(on_clock)
        self.answers += 1
        origin = self._origin()
        if origin is None:
            if self._fallback is None:
                self._fallback = r
            origin = self._fallback
        t = r - origin + self.period_s          # the first SYNC's answer would sit at one period, as with SYNCs
        if self._last is not None:
            self.intervals.add(max(0.0, t - self._last))
        self._last = t
        return t

    def report(self) -> dict:
        s = self.intervals.summary()
        return {"placement": "receive time (event-driven TPDOs answer no SYNC)",
                "stamps": "interface (bus) time" if self.bus_stamps * 2 > max(1, self.answers) else "receive time",
                "answers": self.answers, "interval_p50_ms": s["p50_ms"], "interval_p99_ms": s["p99_ms"],
                "interval_max_ms": s["max_ms"], "intervals_late": s["late"]}
