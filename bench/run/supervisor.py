"""Safety supervisor: judges live samples and link status against the scenario's limits in its own thread.

It never touches a link. The run loop feeds it (a queue) and polls `tripped`; on the first trip the
supervisor records what tripped, at which drive time and with which values, and stops judging. The
orchestrator then runs the safe-stop sequence (once: see SafeStop).
"""

from __future__ import annotations

import math
import queue
import threading
import time
from collections import deque
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


def is_warning(status: DriveStatus) -> bool:
    """An EMCY with the statusword's warning bit (7) set and the drive still OPERATION ENABLED: the drive warns and
    runs on (docs/rig.md); recorded and shown, not a trip. A fault shows in the state machine."""
    return status.warning and not status.fault and status.state == "OPERATION ENABLED"


def check_status(t_s: float | None, status: DriveStatus) -> Trip | None:
    when = "" if t_s is None else f" at t={t_s:.4f} s"
    if status.fault:
        return Trip("fault", t_s, {}, f"drive fault{when} (state {status.state})"
                    + "".join(f"; EMCY 0x{code:04X} {text}" for code, text in status.emcy))
    errors = [(code, text) for code, text in status.emcy if code != 0]  # 0x0000 = error reset
    if errors and not is_warning(status):
        code, text = errors[0]
        return Trip("emcy", t_s, {"emcy_code": float(code)}, f"EMCY 0x{code:04X} {text}{when}")
    if status.control_lost:
        return Trip("remote_lost", t_s, {}, status.control_lost)
    if status.bus_drop:
        return Trip("bus_drop", t_s, {}, f"{status.bus_drop} (seen{when})")
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
    """First motion: the drive's own speed, converted through the units the bench read or was told, against the
    reference sensor, one sample per SYNC. A wrong velocity unit, encoder resolution, gear ratio or gear side makes the
    two differ by a constant factor k (rpm taken for rad/s 9.55, a 3:2 gear on the wrong side 1.5, an 11:10 one 1.1);
    a sensorless estimate differs by noise, and by a lag in hard acceleration that comes and goes. Two tests, from the
    first sample where either shows the shaft turning (`moving_mech_rad_s`), for `window_s` and until the reference has
    travelled `min_travel_rad` (enough for a 1.1 factor to show through the allowances), at most `max_window_s`:

    - angle: the angles both have travelled since then (sums of speed x SYNC period) must agree,
      |A_est - A_true| <= rel_tol x max(|A_est|, |A_true|) + angle_noise_rad + skew_s x |speed_true|
      (`skew_s`: how far apart in time the two are sampled; 0 in lockstep). A constant factor grows without bound
      there, a transient lag does not: with 5 % and 0.1 rad, k = 1.5 is seen after 0.3 rad of travel, k = 1.1 after
      2.4 rad; `hold_samples` consecutive disagreeing samples trip.
    - gross: one sample's speeds more than a factor `gross_ratio` apart (and more than `noise_mech_rad_s`) for
      `gross_hold_samples` samples trips at once: a 10x error is stopped within two SYNCs of first motion, before the
      shaft has much speed (a run-away under the drive's own torque gains ~15 rad/s per 10 ms on the PMSM rig).

    A missing value (NaN, a signal that did not arrive) while the check runs is a disagreeing sample, never an agreeing
    one: a drive whose speed never arrives cannot pass the check.

    Lag is not a unit error: a drive whose 0x606C is filtered (`lag_s`, [drive] velocity_filter_s: a first-order time
    constant) reports the shaft's speed lag_s late, so the angles differ by up to lag_s x |speed| and the speeds by
    lag_s x |acceleration| — both allowed for, and the travel judged grows so that a 1.1 factor still shows. A sample
    whose reference reading is stale (`reference_age_s` more than `stale_s`: the bench stalled and read the dynamometer
    once for several SYNCs) is not judged at all: its interval is left out of both angles. A reading younger than that
    still shows the shaft up to `skew_s` + its age before the sample's time; at first motion the drive's speed leads it
    by that much (e35 under load: 2.09 rad/s reported, 0.002 rad/s read 20-30 ms earlier), so the gross test compares
    the reading with the drive's speeds over that span (the nearest of them), and the angle test allows the age too."""

    moving_mech_rad_s: float = 0.5
    window_s: float = 1.0
    min_travel_rad: float = 20.0
    max_window_s: float = 10.0
    rel_tol: float = 0.05
    angle_noise_rad: float = 0.1
    skew_s: float = 0.0
    hold_samples: int = 3
    gross_ratio: float = 3.0
    noise_mech_rad_s: float = 0.5
    gross_hold_samples: int = 2
    lag_s: float = 0.0
    stale_s: float = math.inf
    _start: float | None = None
    _last_true: float | None = None
    skipped_stale: int = 0               # samples not judged: their reference reading was stale
    _last_t: float | None = None
    _angle_est: float = 0.0
    _angle_true: float = 0.0
    _bad: int = 0
    _gross: int = 0
    judged: int = 0                      # samples judged (agreeing or not)
    missing: int = 0                     # of which a value was missing
    worst_excess: float = 0.0            # max of the angle test's |A_est - A_true| / allowance: > 1 disagrees
    max_speed: float = 0.0               # the fastest |true| judged
    max_age: float = 0.0                 # the oldest reference reading judged (its age is allowed for, as lag is)
    done: bool = False
    _recent: deque = field(default_factory=lambda: deque(maxlen=64))   # (t_s, drive speed): the lead span's samples

    def settings(self) -> dict[str, float]:
        return {"moving_mech_rad_s": self.moving_mech_rad_s, "window_s": self.window_s,
                "min_travel_rad": self.min_travel_rad, "max_window_s": self.max_window_s, "rel_tol": self.rel_tol,
                "angle_noise_rad": self.angle_noise_rad, "skew_s": self.skew_s, "hold_samples": self.hold_samples,
                "gross_ratio": self.gross_ratio, "noise_mech_rad_s": self.noise_mech_rad_s,
                "gross_hold_samples": self.gross_hold_samples, "lag_s": self.lag_s,
                "stale_s": None if math.isinf(self.stale_s) else self.stale_s}

    def summary(self) -> dict:
        state = ("not started (the shaft never turned)" if self._start is None
                 else "judging" if not self.done else "agreed")
        return {**self.settings(), "state": state, "started_t_s": self._start, "judged_samples": self.judged,
                "missing_samples": self.missing, "stale_reference_samples": self.skipped_stale,
                "worst_angle_excess": round(self.worst_excess, 4),
                "angle_est_rad": round(self._angle_est, 4), "angle_true_rad": round(self._angle_true, 4),
                "max_speed_true_mech_rad_s": round(self.max_speed, 4),
                "max_reference_age_s": round(self.max_age, 4)}

    def check(self, t_s: float, values: dict[str, float]) -> Trip | None:
        if self.done:
            return None
        est, true = values.get("speed_est_mech_rad_s"), values.get("speed_true_mech_rad_s")
        known = [abs(v) for v in (est, true) if v is not None and v == v]
        if est is not None and est == est:
            self._recent.append((t_s, est))
        if self._start is None:
            if not any(v >= self.moving_mech_rad_s for v in known):
                self._last_t = t_s
                return None
            self._start = t_s
        elapsed = t_s - self._start
        travel = self.min_travel_rad + 2.0 * (self.lag_s + self.max_age) * self.max_speed / self.rel_tol
        if elapsed > self.max_window_s or (elapsed > self.window_s and abs(self._angle_true) >= travel):
            self.done = True
            return None
        if values.get("reference_age_s", 0.0) > self.stale_s:
            self.skipped_stale += 1
            self._last_t, self._last_true = t_s, None
            return None
        dt = t_s - self._last_t if self._last_t is not None else 0.0
        self._last_t = t_s
        self.judged += 1
        if len(known) < 2:
            self.missing += 1
            self._bad += 1
            self._gross = 0
            if self._bad < self.hold_samples:
                return None
            which = " and ".join(n for n, v in (("the drive's speed", est), ("the reference sensor's", true))
                                 if v is None or v != v)
            return Trip("feedback_lost", t_s, {"speed_est_mech_rad_s": math.nan if est is None else est,
                                               "speed_true_mech_rad_s": math.nan if true is None else true},
                        f"feedback lost at t={t_s:.4f} s: {which} missing for {self._bad} SYNC periods while the "
                        "shaft turns, during the unit check: the drive's units cannot be checked, stopping")
        self.max_speed = max(self.max_speed, abs(true))
        accel = abs(true - self._last_true) / dt if self._last_true is not None and dt > 0 else 0.0
        self._last_true = true
        self._angle_est += est * dt
        self._angle_true += true * dt
        age = max(0.0, values.get("reference_age_s", 0.0))
        self.max_age = max(self.max_age, age)
        gap = abs(self._angle_est - self._angle_true)
        allowance = (self.rel_tol * max(abs(self._angle_est), abs(self._angle_true)) + self.angle_noise_rad
                     + (self.skew_s + age + self.lag_s) * abs(true))
        excess = gap / allowance
        self.worst_excess = max(self.worst_excess, excess)
        # the reading shows the shaft somewhere in the last skew_s + age: judge it against the drive's nearest speed
        # of that span (lockstep, a fresh reading: this sample's alone)
        since = t_s - self.skew_s - age - 1e-9
        near = min((e for t_e, e in self._recent if t_e >= since), key=lambda e: abs(e - true), default=est)
        ratio = abs(near) / max(abs(true), 1e-3)
        gross = (abs(near - true) > self.noise_mech_rad_s + self.lag_s * accel
                 and (near * true < 0 or not 1.0 / self.gross_ratio <= ratio <= self.gross_ratio))
        self._gross = self._gross + 1 if gross else 0
        self._bad = self._bad + 1 if excess > 1.0 else 0
        if self._bad < self.hold_samples and self._gross < self.gross_hold_samples:
            return None
        gross = self._gross >= self.gross_hold_samples
        what = (f"speeds a factor {ratio:.3g} apart for {self._gross} SYNC periods" if gross
                else f"angles since first motion {self._angle_est:.3f} rad (drive) and {self._angle_true:.3f} rad "
                     f"(reference), ratio {abs(self._angle_est) / max(abs(self._angle_true), 1e-6):.3g}, outside "
                     f"{self.rel_tol:.0%} + {self.angle_noise_rad:g} rad for {self._bad} SYNC periods")
        what += f"; the reference reading {age * 1e3:.0f} ms old"
        return Trip("unit_mismatch", t_s, {"speed_est_mech_rad_s": est, "speed_true_mech_rad_s": true,
                                           "angle_est_rad": self._angle_est, "angle_true_rad": self._angle_true,
                                           "reference_age_s": age},
                    f"unit mismatch at t={t_s:.4f} s: the drive reports {est:.3f} rad/s, the reference sensor "
                    f"{true:.3f} rad/s ({what}): check the drive's velocity unit, encoder resolution, gear ratio "
                    "and velocity_side in the record; or a lag: a drive filtering its velocity actual value (0x606C) "
                    f"reports the shaft late (velocity_filter_s = {self.lag_s:g} s stated; write its time constant, "
                    "e.g. velocity_filter_s = 0.1, in [drive])")


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
    """Runs check_sample/check_status on everything fed to it, in a daemon thread — or, with `judge_inline`
    (lockstep: the drive's time stands still while the bench judges), in the feeding thread at once, so a trip is
    seen at the SYNC whose sample shows it.

    The thread also watches the wall clock from start(): past limits.max_duration_s it trips even if
    nothing is fed any more (a hung link, a run loop stuck somewhere).
    """

    def __init__(self, limits: SupervisorLimits, on_trip: Callable[[Trip], None] | None = None,
                 unit_check: UnitCheck | None = None, feedback_check: FeedbackCheck | None = None,
                 judge_inline: bool = False):
        self.judge_inline = judge_inline
        self._trip_lock = threading.Lock()      # one judge at a time: the feeding thread (inline) or the thread
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
        if self.judge_inline:
            self._settle(item)
            return
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
                self._settle(item)
            finally:
                if item is not None:
                    with self._idle:
                        self._pending -= 1
                        self._idle.notify_all()

    def _settle(self, item) -> None:
        """Judge one fed item (None: the wall clock only); the first trip is the run's."""
        with self._trip_lock:
            if self.tripped.is_set():
                return
            trip = self._judge(item) if item is not None else None
            if trip is None:
                trip = self._check_wall_clock()
            if trip is not None:
                self.trip = trip
                self.trip_utc = datetime.now(timezone.utc).isoformat(timespec="milliseconds")
                self.tripped.set()
                if self.on_trip is not None:
                    self.on_trip(trip)

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


from bench.run.safe_stop import STEP_TIMEOUT_S, SafeStop, _bounded  # noqa: E402,F401  (one home: safe_stop)
