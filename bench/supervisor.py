"""Safety supervisor: judges live samples and link status against the scenario's limits in its own thread.

It never touches a link. The run loop feeds it (a queue) and polls `tripped`; on the first trip the
supervisor records what tripped, at which drive time and with which values, and stops judging. The
orchestrator then runs the safe-stop sequence (once: see SafeStop).
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Callable, Iterable, Protocol

from drivers.api import DriveStatus, LiveSample, LoadFeedback


class SupervisorLimits(Protocol):
    overspeed_mech_rad_s: float
    overcurrent_a: float
    max_duration_s: float          # wall-clock seconds the whole run may take
    pos_err_max_elec_rad: float | None
    vdc_max_v: float | None


@dataclass(frozen=True)
class Trip:
    reason: str  # overspeed overcurrent position_error dc_link_overvoltage unit_mismatch feedback_lost max_duration fault
                 # emcy heartbeat load_fault
    t_s: float | None            # drive time of the sample or status that tripped
    values: dict[str, float] = field(default_factory=dict)
    message: str = ""

    def as_dict(self) -> dict:
        return {"reason": self.reason, "t_s": self.t_s, "values": dict(self.values), "message": self.message}


def check_sample(limits: SupervisorLimits, t_s: float, values: dict[str, float]) -> Trip | None:
    """The first limit this sample violates, or None. Missing signals are not judged."""
    for name in ("speed_true_mech_rad_s", "speed_est_mech_rad_s"):
        value = values.get(name)
        if value is not None and abs(value) > limits.overspeed_mech_rad_s:
            return Trip("overspeed", t_s, {name: value, "limit": limits.overspeed_mech_rad_s},
                        f"overspeed at t={t_s:.4f} s: |{name}| = {abs(value):.2f} > {limits.overspeed_mech_rad_s:g} rad/s")
    for name in ("i_sx_a", "i_sy_a"):
        value = values.get(name)
        if value is not None and abs(value) > limits.overcurrent_a:
            return Trip("overcurrent", t_s, {name: value, "limit": limits.overcurrent_a},
                        f"overcurrent at t={t_s:.4f} s: |{name}| = {abs(value):.2f} > {limits.overcurrent_a:g} A")
    if limits.pos_err_max_elec_rad is not None:
        value = values.get("pos_err_elec_rad")
        if value is not None and abs(value) > limits.pos_err_max_elec_rad:
            return Trip("position_error", t_s, {"pos_err_elec_rad": value, "limit": limits.pos_err_max_elec_rad},
                        f"position error at t={t_s:.4f} s: |pos_err_elec_rad| = {abs(value):.3f} > "
                        f"{limits.pos_err_max_elec_rad:g} rad")
    if limits.vdc_max_v is not None:
        value = values.get("vdc_v")
        if value is not None and value > limits.vdc_max_v:
            return Trip("dc_link_overvoltage", t_s, {"vdc_v": value, "limit": limits.vdc_max_v},
                        f"DC-link overvoltage at t={t_s:.4f} s: vdc_v = {value:.1f} > {limits.vdc_max_v:g} V")
    return None


def check_status(t_s: float | None, status: DriveStatus) -> Trip | None:
    when = "" if t_s is None else f" at t={t_s:.4f} s"
    if status.fault:
        return Trip("fault", t_s, {}, f"drive fault{when} (state {status.state})"
                    + "".join(f"; EMCY 0x{code:04X} {text}" for code, text in status.emcy))
    errors = [(code, text) for code, text in status.emcy if code != 0]  # 0x0000 = error reset
    if errors:
        code, text = errors[0]
        return Trip("emcy", t_s, {"emcy_code": float(code)}, f"EMCY 0x{code:04X} {text}{when}")
    if not status.heartbeat_ok:
        return Trip("heartbeat", t_s, {}, f"drive heartbeat lost{when}")
    return None


def check_load(t_s: float | None, feedback: LoadFeedback) -> Trip | None:
    if feedback.fault:
        when = "" if t_s is None else f" at t={t_s:.4f} s"
        return Trip("load_fault", t_s, {"load_speed_mech_rad_s": feedback.speed_mech_rad_s,
                                        "load_torque_nm": feedback.torque_nm},
                    f"load machine reports a fault{when}")
    return None


@dataclass
class UnitCheck:
    """The first second of motion: the drive's own speed, converted through the units the bench read or was told,
    must agree with the reference sensor. A wrong velocity unit or gear ratio shows as a ratio far from 1 (rpm taken
    for rad/s is 9.55, mrad/s for rad/s 1000) before it can hurt; a sensorless estimate is never that far off."""

    moving_mech_rad_s: float = 2.0       # the check starts when the reference sees the shaft turn this fast
    window_s: float = 1.0                # for this long
    ratio: float = 2.0                   # |est / true| outside [1/ratio, ratio] ...
    hold_s: float = 0.02                 # ... for this long trips (a factor of 9.55 or 1000 is never noise)
    min_valid: int = 10                  # a window passes only on this many samples with both speeds (NaN: none)
    _start: float | None = None
    _bad_since: float | None = None
    _valid: int = 0
    done: bool = False

    def check(self, t_s: float, values: dict[str, float]) -> Trip | None:
        est, true = values.get("speed_est_mech_rad_s"), values.get("speed_true_mech_rad_s")
        if self.done or est is None or true is None or est != est or true != true:
            return None
        if self._start is None:
            if abs(true) < self.moving_mech_rad_s and abs(est) < self.moving_mech_rad_s:
                return None
            self._start = t_s
        if t_s - self._start > self.window_s and self._valid >= self.min_valid:
            self.done = True
            return None
        self._valid += 1
        ratio = abs(est) / max(abs(true), 1e-3)
        agree = 1.0 / self.ratio <= ratio <= self.ratio and est * true >= 0
        if agree:
            self._bad_since = None
            return None
        self._bad_since = t_s if self._bad_since is None else self._bad_since
        if t_s - self._bad_since < self.hold_s:
            return None
        return Trip("unit_mismatch", t_s, {"speed_est_mech_rad_s": est, "speed_true_mech_rad_s": true},
                    f"unit mismatch at t={t_s:.4f} s: the drive reports {est:.3f} rad/s, the reference sensor "
                    f"{true:.3f} rad/s (ratio {ratio:.3g}): check the drive's velocity unit, encoder resolution and "
                    "gear ratio in the record")


@dataclass
class FeedbackCheck:
    """Live feedback the drive's PDOs carry must keep arriving: a signal missing from `periods` samples in a row (its
    TPDO stopped, or never came) trips `feedback_lost` — a run must not go on blind with NaN rows."""

    signals: tuple[str, ...]
    sync_period_s: float
    periods: int = 5
    _missing: dict[str, int] = field(default_factory=dict)

    def check(self, t_s: float, values: dict[str, float]) -> Trip | None:
        for name in self.signals:
            if name in values:
                self._missing[name] = 0
                continue
            n = self._missing[name] = self._missing.get(name, 0) + 1
            if n >= self.periods:
                return Trip("feedback_lost", t_s, {"missing_samples": float(n)},
                            f"feedback lost at t={t_s:.4f} s: {name} missing from the last {n} live samples "
                            f"({n * self.sync_period_s * 1e3:.0f} ms of SYNC periods): the drive's TPDO carrying it "
                            "does not arrive")
        return None


def feedback_silence_trip(t_s: float | None, silent_s: float) -> Trip:
    when = "" if t_s is None else f" after t={t_s:.4f} s"
    return Trip("feedback_lost", t_s, {"silent_s": silent_s},
                f"feedback lost{when}: no live sample from the drive for {silent_s * 1e3:.0f} ms")


_STOP = object()
WATCHDOG_PERIOD_S = 0.05


class Supervisor:
    """Runs check_sample/check_status on everything fed to it, in a daemon thread.

    The thread also watches the wall clock from start(): past limits.max_duration_s it trips even if
    nothing is fed any more (a hung link, a run loop stuck somewhere).
    """

    def __init__(self, limits: SupervisorLimits, on_trip: Callable[[Trip], None] | None = None,
                 unit_check: UnitCheck | None = None, feedback_check: FeedbackCheck | None = None):
        self.limits = limits
        self.unit_check = unit_check
        self.feedback_check = feedback_check
        self.on_trip = on_trip
        self.tripped = threading.Event()
        self.trip: Trip | None = None
        self.trip_utc: str | None = None
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="drivebench-supervisor", daemon=True)
        self._idle = threading.Condition()
        self._pending = 0
        self._started = 0.0
        self._last_t_s: float | None = None

    def start(self) -> "Supervisor":
        self._started = time.monotonic()
        self._thread.start()
        return self

    def feed(self, samples: Iterable[LiveSample]) -> None:
        samples = list(samples)
        if samples and not self.tripped.is_set():
            self._put(("samples", samples))

    def feed_status(self, t_s: float | None, status: DriveStatus) -> None:
        if not self.tripped.is_set():
            self._put(("status", (t_s, status)))

    def feed_load(self, t_s: float | None, feedback: LoadFeedback) -> None:
        if not self.tripped.is_set():
            self._put(("load", (t_s, feedback)))

    def feed_feedback_lost(self, t_s: float | None, silent_s: float) -> None:
        """Real time: no live sample at all for silent_s (the run loop measures it)."""
        if not self.tripped.is_set():
            self._put(("silent", (t_s, silent_s)))

    def _put(self, item) -> None:
        with self._idle:
            self._pending += 1
        self._queue.put(item)

    def drain(self, timeout_s: float = 5.0) -> bool:
        """Wait until everything fed so far has been judged (tests; and before the final verdict)."""
        with self._idle:
            return self._idle.wait_for(lambda: self._pending == 0, timeout=timeout_s)

    def stop(self) -> None:
        if self._thread.is_alive():
            self._queue.put(_STOP)
            self._thread.join(timeout=5.0)

    def _run(self) -> None:
        while True:
            try:
                item = self._queue.get(timeout=WATCHDOG_PERIOD_S)
            except queue.Empty:
                item = None
            if item is _STOP:
                return
            try:
                if not self.tripped.is_set():
                    trip = self._judge(item) if item is not None else None
                    if trip is None:
                        trip = self._check_wall_clock()
                    if trip is not None:
                        self.trip = trip
                        self.trip_utc = datetime.now(timezone.utc).isoformat(timespec="milliseconds")
                        self.tripped.set()
                        if self.on_trip is not None:
                            self.on_trip(trip)
            finally:
                if item is not None:
                    with self._idle:
                        self._pending -= 1
                        self._idle.notify_all()

    def _check_wall_clock(self) -> Trip | None:
        elapsed = time.monotonic() - self._started
        limit = self.limits.max_duration_s
        if elapsed <= limit:
            return None
        when = "" if self._last_t_s is None else f" (drive time t={self._last_t_s:.4f} s)"
        return Trip("max_duration", self._last_t_s, {"wall_s": elapsed, "limit": limit},
                    f"run time limit: {elapsed:.1f} s wall > max_duration_s = {limit:g} s{when}")

    def _judge(self, item) -> Trip | None:
        kind, payload = item
        if kind == "load":
            return check_load(*payload)
        if kind == "status":
            if payload[0] is not None:
                self._last_t_s = payload[0]
            return check_status(*payload)
        if kind == "silent":
            return feedback_silence_trip(*payload)
        for sample in payload:
            self._last_t_s = sample.t_s
            if self.feedback_check is not None:
                trip = self.feedback_check.check(sample.t_s, sample.values)
                if trip is not None:
                    return trip
            trip = self.unit_check.check(sample.t_s, sample.values) if self.unit_check is not None else None
            if trip is None:       # a unit mismatch is the cause when both trip: the overspeed is its symptom
                trip = check_sample(self.limits, sample.t_s, sample.values)
            if trip is not None:
                return trip
        return None


STEP_TIMEOUT_S = 6.0   # one safe-stop step; above a serial link's 4 x 0.5 s retries or Modbus's 2 x 2 x 0.5 s


class SafeStop:
    """The end-of-run sequence: load to zero torque and disabled, drive quick stop, drive disabled.

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

    def run(self) -> list[str]:
        with self._lock:
            if self.done:
                return self.errors
            self.done = True
            steps: list[tuple[str, Callable[[], None]]] = []
            if self.load is not None:
                steps.append(("load zero torque and disabled", self.load.zero_and_disable))
            if self.drive is not None:
                steps.append(("drive quick stop", self.drive.quick_stop))
                steps.append(("drive disabled", self.drive.disable))
            for label, action in steps:
                error = _bounded(action, self.step_timeout_s)
                if error is None:
                    self.steps.append(label)
                else:              # keep going: the remaining steps matter more than this error
                    self.errors.append(f"{label}: {error}")
            return self.errors


def _bounded(action: Callable[[], None], timeout_s: float) -> str | None:
    """Run action in a daemon thread; None when it returned, else what went wrong (exception or timeout)."""
    outcome: list[str | None] = []

    def target() -> None:
        try:
            action()
            outcome.append(None)
        except BaseException as exc:
            outcome.append(f"{type(exc).__name__}: {exc}")

    worker = threading.Thread(target=target, name="drivebench-safe-stop", daemon=True)
    worker.start()
    worker.join(timeout_s)
    if worker.is_alive():
        return f"no answer within {timeout_s:g} s (step abandoned)"
    return outcome[0]

