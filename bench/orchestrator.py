"""Runs one scenario against one bench: connect, configure, drive the profile, supervise, stop safely, judge.

The same code runs a real rig and the simulator; everything simulator-specific comes from the bench
config's [services] entry and the link classes its transports name.
"""

from __future__ import annotations

import json
import math
import os
import signal
import threading
import time
import traceback
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from bench.benchconfig import BenchConfig, load_bench_config
from bench.criteria import TimeAxis, signals_of, time_axis
from bench.drill import (DRILL_SETTINGS, DrillRefused, proved_recently, refusal as drill_refusal, remember, run_drills,
                         unverified as drill_unverified)
from drivers.contract.errors import InputError
from drivers.contract.checks import find_repo_root
from bench.links import make_links, started_services
from bench.load_emulation import SPEED_SIGNAL, LoadEmulation
from bench.records import RunRecord, RunRecorder, freeze_long_lived, json_safe, release_freed_memory
from bench.rerun_view import RerunStream
from bench.scenario import load_scenario
from bench.summary_plot import BUCKETS as PLOT_BUCKETS, PLOT_SIGNALS, events_of, write_summary_png
from bench.supervisor import FeedbackCheck, SafeStop, Supervisor, UnitCheck, check_status
from bench.run_thread import LoopThread
from bench.telemetry import TelemetryWorker
from bench.verdict import judge_run
from drivers.contract.errors import LinkError
from drivers.api import LiveSample
from drivers.contract.load_map import LoadMode
from drivers.reference import ReferenceConfig, onto_rows, values_from_load
from drivers.contract.signals import SIGNAL_NAMES, TIME_COLUMN

# Live (PDO) signals, judged by the supervisor every SYNC. Eight REAL32 fit a 1 Mbit/s CAN bus at one SYNC
# per ms within the links' 80 % budget; everything else comes from the trace recorder.
LIVE_SIGNALS: tuple[str, ...] = (
    "speed_ref_mech_rad_s", "speed_est_mech_rad_s", "speed_true_mech_rad_s", "pos_err_elec_rad",
    "i_sx_a", "i_sy_a", "vdc_v", "torque_load_nm",
)
# Trace recorder (the verdict's data): what the record promises — speeds, position error, fluxes, currents,
# voltages, load torque — plus the frame angle for the flux-vector view. A bench config may name its own set
# ([drive] trace_signals); the criteria's signals are always added. Each signal costs bus time: the trace is
# uploaded by SDO block transfer at 7 bytes per frame.
TRACE_SIGNALS: tuple[str, ...] = (
    "speed_ref_mech_rad_s", "speed_est_mech_rad_s", "speed_true_mech_rad_s", "pos_est_elec_rad",
    "pos_err_elec_rad", "flux_est_wb", "flux_true_wb", "i_sx_a", "i_sy_a", "u_sx_v", "u_sy_v", "torque_load_nm",
)
MAX_DEFERRED_APPENDS = 8   # lockstep: trace blocks waiting for the journal writer before the command thread waits
FETCH_PERIOD_S = 0.25      # upload the trace recorder every 0.25 s of drive time (a killed bench loses at most that)
RERUN_MAX_RATE_HZ = 2000.0 # run.rrd / viewer: a 10 kHz trace is thinned to 2 kHz (3.6 -> 0.8 MB/s); parquet has all
STATUS_PERIOD_S = 0.02     # poll the drive's status (fault, EMCY, heartbeat) every 20 ms of drive time
PROGRESS_PERIOD_S = 0.1
MAX_SEED = 2**63 - 1
STUCK_GRACE_S = 2.0        # after a trip, how long the run loop may take to notice before it is abandoned
SUPERVISE_POLL_S = 0.05    # the main thread's wait on the run loop (signals are handled between waits)
STALL_TIMEOUT_S = 5.0      # wall seconds without any live sample -> the link is dead
LOAD_POLL_PERIOD_S = 0.1   # read the load machine's status (fault bit; a dead Modbus link) every 0.1 s of drive time
FEEDBACK_LOST_PERIODS = 5  # real time: a measured live signal missing this many SYNC periods in a row trips
FEEDBACK_LOST_MIN_S = 0.5  # ... and no live sample at all for this long (or 5 periods, the longer): a loaded host
                           # stalls the bench's own threads for 40-80 ms, more under heavy load

DEFAULT_SEED = 0           # a scenario without a seed runs with this one (recorded), so reruns are identical
ProgressFn = Callable[[float, float], None]


class Interrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM during a run."""


@dataclass
class RunResult:
    run_dir: Path
    verdict: str                       # pass | fail | aborted | error
    record: RunRecord                  # what record.json holds
    criteria: list = field(default_factory=list)
    interrupted: bool = False          # Ctrl-C/SIGTERM: callers should not start further runs
    error: str | None = None           # one line when verdict == "error"

    @property
    def passed(self) -> bool:
        return self.verdict == "pass"


def live_columns(samples: Sequence[LiveSample], names: Sequence[str]) -> dict[str, np.ndarray]:
    t = np.fromiter((s.t_s for s in samples), dtype=np.float64, count=len(samples))
    cols = {TIME_COLUMN: t}
    for n in names:
        cols[n] = np.fromiter((s.values.get(n, math.nan) for s in samples), dtype=np.float64, count=len(samples))
    return cols


def trace_signals_for(cfg: BenchConfig, scenario) -> tuple[str, ...]:
    """The configured trace set (or the default) plus every signal a criterion reads, in catalogue order."""
    wanted = set(cfg.drive.get("trace_signals") or TRACE_SIGNALS)
    wanted |= {c.signal for c in scenario.criteria if c.signal in SIGNAL_NAMES}
    wanted |= {v for c in scenario.criteria for v in c.params.values() if isinstance(v, str) and v in SIGNAL_NAMES}
    wanted -= ReferenceConfig(cfg.reference_source).not_from_drive()    # rig truth only from the reference sensor
    return tuple(name for name in SIGNAL_NAMES if name in wanted)


def prepare(scenario_path: str | Path, bench_path: str | Path | None = None):
    """Load and validate the scenario against its bench config; InputError lists every problem."""
    scenario = load_scenario(scenario_path, bench=bench_path)
    return scenario, load_bench_config(scenario.bench)


class _StopSignals:
    """Ctrl-C (SIGINT) and SIGTERM raise Interrupted in the main thread for the duration of the run, once.

    Every further signal — a second Ctrl-C, SIGTERM after SIGINT — and any signal once the safe stop has begun
    is only counted: the safe-stop sequence and the record must finish, and they run exactly once.
    """

    NAMES = {signal.SIGINT: "interrupted (Ctrl-C)", signal.SIGTERM: "terminated (SIGTERM)"}

    def __init__(self):
        self._previous: dict = {}
        self.fired: str | None = None
        self.stopping = False
        self.ignored = 0

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            def handler(signum, frame):
                if self.fired is not None or self.stopping:
                    self.ignored += 1
                    return
                self.fired = self.NAMES[signum]
                raise Interrupted(self.fired)
            for sig in self.NAMES:
                self._previous[sig] = signal.signal(sig, handler)
        return self

    def __exit__(self, *exc):
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)
        return False


def run_scenario(
    scenario_path: str | Path,
    bench_path: str | Path | None = None,
    out_root: str | Path = "runs",
    seed: int | None = None,
    rerun_mode: str = "save",
    rerun_url: str | None = None,
    progress: ProgressFn | None = None,
    *,
    links: tuple[Any, Any] | None = None,
    warn: Callable[[str], None] | None = None,
    on_trip: Callable[[dict], None] | None = None,
) -> RunResult:
    """Run one scenario. Raises InputError (bad files, refused injections) and LinkError (cannot connect)
    before a run directory exists; after that every outcome is a record and a RunResult.

    `links` replaces the links and services the bench config names (unit tests with in-memory fakes).
    """
    scenario, cfg = prepare(scenario_path, bench_path)
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED):
        raise InputError([f"--seed: must be an integer from 0 to {MAX_SEED}, got {seed!r}"])
    if seed is None:
        seed = scenario.seed if scenario.seed is not None else DEFAULT_SEED
    check_out_root(Path(out_root))      # before anything is connected: a bad --out must not leave a rig touched
    freeze_long_lived()
    with _StopSignals() as signals:
        if links is not None:
            return _run_connected(scenario, cfg, seed, *links, Path(out_root), rerun_mode, rerun_url, progress, warn,
                                  signals, on_trip)
        with started_services(cfg, seed) as live_cfg:
            drive, load = make_links(live_cfg, find_repo_root(cfg.path))
            return _run_connected(scenario, live_cfg, seed, drive, load, Path(out_root), rerun_mode, rerun_url,
                                  progress, warn, signals, on_trip)


def check_out_root(out_root: Path) -> None:
    """The run-directory root exists (or is created) and takes files; else one line naming --out."""
    try:
        if out_root.is_symlink() and not out_root.exists():
            raise NotADirectoryError(0, "a symbolic link that leads nowhere or into a loop")
        out_root.mkdir(parents=True, exist_ok=True)
        if not out_root.is_dir():
            raise NotADirectoryError(f"{out_root} is not a directory")
        probe = out_root / f".drivebench-write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise InputError([f"{out_root}: --out: cannot hold run directories: {reason}"]) from None


def _open(drive, load):
    identity = drive.open()
    try:
        load_name = load.open() if load is not None else None
    except BaseException:
        _close_quietly(drive)
        raise
    return identity, load_name


def _close_quietly(*links) -> list[str]:
    errors = []
    for link in links:
        if link is None:
            continue
        try:
            link.close()
        except Exception as exc:
            errors.append(f"close {type(link).__name__}: {exc}")
    return errors


def _run_connected(scenario, cfg, seed, drive, load, out_root, rerun_mode, rerun_url, progress, warn,
                   signals: _StopSignals | None = None, on_trip: Callable[[dict], None] | None = None) -> RunResult:
    identity, load_name = _open(drive, load)  # LinkError here: nothing started, nothing to stop
    recorder = None
    safe_stop = SafeStop(drive, load)
    try:
        recorder = RunRecorder(out_root, scenario, seed, cfg)
    except OSError as exc:
        _close_quietly(drive, load)
        raise InputError([f"{out_root}: --out: cannot create the run directory: {exc.strerror or exc}"]) from None
    except BaseException:
        _close_quietly(drive, load)
        raise
    run = _Run(scenario, cfg, seed, drive, load, identity, load_name, recorder, safe_stop, rerun_mode, rerun_url,
               progress, warn, on_trip)
    run.signals = signals
    return run.execute()


@dataclass(eq=False)
class _Run:
    """One run on connected links: the run loop's state, the supervisor side, the safe stop and the record."""
    scenario: Any
    cfg: BenchConfig
    seed: int
    drive: Any
    load: Any
    identity: Any
    load_name: str | None
    recorder: RunRecorder
    safe_stop: SafeStop
    rerun_mode: str
    rerun_url: str | None
    progress: Callable[[str], None] | None
    warn: Callable[[str], None] | None
    on_trip: Callable[[dict], None] | None = None   # told of each trip as it happens (the service's live view)

    def __post_init__(self) -> None:
        self._t_recorded_last = -math.inf    # drive time of the last recorded row (the data is on disk only)
        self.live_buffer: list[LiveSample] = []
        self.telemetry = TelemetryWorker()
        self.realtime = self.cfg.bench.timing == "realtime"
        self._live_lock = threading.Lock()        # live_buffer: the command thread adds, the worker prunes
        self.supervisor = Supervisor(self.scenario.limits)
        self.sync_period_s = float(self.cfg.drive["sync_period_s"])
        # real time: no live sample for this long is lost feedback (a host hiccup is not)
        self._feedback_lost_s = max(FEEDBACK_LOST_MIN_S, FEEDBACK_LOST_PERIODS * self.sync_period_s)
        self.data_source = "trace" if self.identity.has_trace_recorder else "pdo"
        self.trace_signals = trace_signals_for(self.cfg, self.scenario)
        self.reference = ReferenceConfig(self.cfg.reference_source)
        self.reference_signals = self.reference.signals(self.load is not None)
        self.not_from_drive = self.reference.not_from_drive()
        self.emulation = LoadEmulation(tuple(getattr(self.load, "modes", None) or ()) or tuple(LoadMode),
                                       SPEED_SIGNAL in self.reference_signals, self.sync_period_s)
        self._reference_readings: list[tuple[float, dict[str, float]]] = []   # (t_s, values), for the trace rows
        self.measured: frozenset[str] | None = None
        self.live_recorded: tuple[str, ...] = LIVE_SIGNALS
        # t_s in the record is drive time since this run's first SYNC; the drive clock counts from power-up
        self._clock_start: float | None = None
        self.signals: _StopSignals | None = None
        self.trips: list[dict] = []          # every cause of the abort, in the order they were seen
        self.drive_warnings: list[dict] = []  # statusword bit 7 changes
        self._warning = False
        self._link_in_use = "drive"          # which link a LinkError came from
        self._t_drive = 0.0
        self._started_wall = time.monotonic()
        self._stop_loop = threading.Event()        # the main thread asks the run loop to end (operator abort)
        try:
            self.rerun = RerunStream(self.rerun_mode, self.recorder.run_dir / "run.rrd", url=self.rerun_url,
                                     recording_name=self.recorder.run_dir.name,
                                     recorded=((*self.trace_signals, *self.reference_signals)
                                               if self.data_source == "trace" else LIVE_SIGNALS),
                                     **({"warn": self.warn} if self.warn is not None else {}))
        except Exception as exc:  # no view is better than no run
            (self.warn or print)(f"rerun: cannot open the stream ({type(exc).__name__}: {exc}); no run.rrd")
            self.rerun = RerunStream("off", None)
        self.recorder.set_drive(asdict(self.identity))
        self.recorder.note("load_machine",
                           self.load_name if self.load is not None else "none: free shaft (no [load])")
        self.recorder.note("reference", self.reference.as_record(self.load is not None))
        self.recorder.note("instruments", self.reference.instruments(
            self.load is not None, getattr(self.load, "map", None),
            getattr(self.identity, "device_name", "") or "the drive"))
        if any(self.emulation.emulates(seg.mode) for seg in self.scenario.load_segments):
            self.recorder.note("load_emulation", self.emulation.as_record(s.mode for s in self.scenario.load_segments))
        self.recorder.note("bench", {"name": self.cfg.bench.name, "path": self.cfg.path,
                                     "timing": self.cfg.bench.timing})
        self._rerun_note = {"mode": self.rerun_mode, "url": self.rerun_url, "sinks": self.rerun.sinks}
        self._rerun_stride: int | None = None
        self.recorder.note("rerun", self._rerun_note)

    # -- the run ------------------------------------------------------------------------------------------

    def execute(self) -> RunResult:
        abort_reason: str | None = None
        error: str | None = None
        interrupted = False
        self.supervisor.start()
        loop = LoopThread(self)
        try:
            loop.start()
            abort_reason = loop.result(self._supervise(loop))
        except KeyboardInterrupt as exc:      # Interrupted (SIGINT/SIGTERM handler) or a bare KeyboardInterrupt
            interrupted = True
            loop.stop_and_wait(STUCK_GRACE_S)
            abort_reason = (str(exc) if isinstance(exc, Interrupted) else "") or "interrupted (Ctrl-C)"
            self._add_trip("operator", abort_reason)
        except DrillRefused as exc:
            error = f"refused: {exc}"
            self._add_trip("comm_loss_drill", str(exc))
        except LinkError as exc:
            error = f"link error: {exc}"
            self._add_trip(f"{self._link_in_use}_link", str(exc))
        except Exception as exc:
            error = f"{type(exc).__name__}: {exc}"
            self.recorder.note("traceback", loop.traceback or traceback.format_exc())
            self._add_trip("exception", error)
        finally:
            if self.signals is not None:
                self.signals.stopping = True     # from here on a signal is counted, never raised
            stop_errors = self.safe_stop.run()
        try:
            return self._finish(abort_reason, error, interrupted, stop_errors)
        finally:
            for cleanup in (self.supervisor.stop, self.telemetry.stop, self.rerun.close):
                try:
                    cleanup()
                except Exception:
                    pass  # the record is written; a failing viewer or thread must not lose the result
            _close_quietly(self.drive, self.load)

    def _supervise(self, loop: LoopThread) -> bool:
        """Wait for the run loop; True when it ended by itself. Once the supervisor has tripped (a limit, the
        wall-clock bound), the loop gets STUCK_GRACE_S to notice; a loop stuck in a call past that is abandoned:
        its links are interrupted, its further calls refused, and the safe stop runs from here."""
        tripped_at: float | None = None
        while not loop.wait(SUPERVISE_POLL_S):
            if self.supervisor.tripped.is_set() and tripped_at is None:
                tripped_at = time.monotonic()
                self._tell_supervisor_trip()
            if tripped_at is not None and time.monotonic() - tripped_at > STUCK_GRACE_S:
                loop.abandon()
                trip = self.supervisor.trip
                self._add_trip("stuck", f"the run loop did not return within {STUCK_GRACE_S:g} s after "
                                        f"{trip.reason if trip else 'the trip'}; abandoned, safe stop from the "
                                        f"supervisor side")
                return False
        if self.supervisor.tripped.is_set() and tripped_at is None:   # the loop saw the trip first and ended
            self._tell_supervisor_trip()
        return True

    def _tell_supervisor_trip(self) -> None:
        if self.supervisor.trip is not None:
            self._tell_trip(self.supervisor.trip.as_dict())

    def _add_trip(self, reason: str, message: str, values: dict | None = None, t_s: float | None = None) -> None:
        self.trips.append({"reason": reason, "t_s": self._t_drive if t_s is None else t_s, "values": values or {},
                           "message": message, "wall_s": round(time.monotonic() - self._started_wall, 4),
                           "utc": datetime.now(timezone.utc).isoformat(timespec="milliseconds")})
        self._tell_trip(self.trips[-1])

    def _tell_trip(self, trip: dict) -> None:
        if isinstance(trip.get("t_s"), (int, float)):
            self.rerun.log_event(float(trip["t_s"]), "trip", f"{trip.get('reason')}: {trip.get('message', '')}")
        if self.on_trip is not None:
            try:
                self.on_trip(json_safe(trip))
            except Exception:
                pass               # a viewer that cannot be told must not change the run

    def _load_call(self, fn, *args):
        self._link_in_use = "load"
        result = fn(*args)
        self._link_in_use = "drive"
        return result

    def _configure_and_enable(self) -> None:
        decimation = int(self.cfg.drive["trace_decimation"])
        self.drive.configure(tuple(n for n in LIVE_SIGNALS if n not in self.not_from_drive), self.trace_signals,
                             decimation)
        measured = (set(getattr(self.drive, "measured_signals", lambda: SIGNAL_NAMES)()) - self.not_from_drive) \
            | set(self.reference_signals)
        self._arm_unit_check(getattr(self.drive, "profile", None), measured)
        self.live_recorded = tuple(n for n in SIGNAL_NAMES if n in measured or (n in LIVE_SIGNALS and
                                                                                self.data_source == "trace"))
        self.recorder.note("trace_signals", list(self.trace_signals))
        self.recorder.note("data_source", self.data_source)
        self.recorder.note("live_signals", list(self.live_recorded))
        if self.data_source == "trace":
            measured |= set(self.trace_signals)          # the drive's recorder: every traced signal, full rate
            measured |= set(self.reference_signals)      # the reference's readings, interpolated onto its rows
        self.measured = frozenset(measured)
        self.recorder.note("measured_signals", sorted(measured))
        self.recorder.note("trace_decimation", decimation)
        carried = getattr(self.drive, "measured_signals", None)
        if carried is not None:   # what the drive's live PDOs carry must keep coming (feedback_lost)
            self.supervisor.feedback_check = FeedbackCheck(tuple(sorted(carried())), self.sync_period_s,
                                                           FEEDBACK_LOST_PERIODS)
        self._note_link_reports()
        set_reference = getattr(self.drive, "set_reference_speed", None)
        if set_reference is not None and self.load is not None and "speed_true_mech_rad_s" in self.reference_signals:
            set_reference(lambda: self._load_call(self.load.feedback).speed_mech_rad_s)
        self._comm_loss_drill()
        if self._stop_loop.is_set():          # stopped during the drill (operator): the drive is not enabled again
            return
        # the drive holds the shaft before the load machine may pull on it (an active load drops a crane's mass)
        self.drive.enable_velocity_mode()
        # after enabling: enable_velocity_mode starts the drive from a zero target (CiA 402 links reset it)
        self._speed_ref = self.scenario.speed_ref_at(0.0)
        self.drive.set_speed_ref(self._speed_ref)
        mode, value = self._load_to_send(0.0)
        if self.load is not None:
            self._load_call(self.load.set_load, mode, value)
            self._load_call(self.load.enable, True)
        self._load_setting = (mode, value)

    def _arm_unit_check(self, profile, measured: set[str]) -> None:
        """A drive in its own units: with a reference sensor, its speed and the shaft's must agree at first motion
        (UnitCheck); on a free shaft nothing can check them, so every velocity factor must have been read from the
        drive, or the bench config must say how the stated ones were checked (units_confirmed)."""
        if profile is None or profile.kind != "cia402":
            return
        if "speed_true_mech_rad_s" in measured:
            # lockstep: the reference is read while the drive waits for the next SYNC, at the same instant; real time:
            # up to a batch and a Modbus round trip later
            self.supervisor.unit_check = UnitCheck(skew_s=0.0 if not self.realtime else 2 * self.sync_period_s)
            self.recorder.note("unit_check", self.supervisor.unit_check.settings())
            return
        if profile.unread and not profile.units_confirmed:
            raise InputError([f"{self.cfg.path}: drive.units_confirmed: this rig has no reference sensor to check the "
                              f"drive's units against at first motion and {', '.join(profile.unread)} were not read "
                              "from the drive: check them on the rig (hand tachometer, a turn counted by eye at low "
                              "speed) and say how in units_confirmed = \"...\""])
        self.recorder.note("unit_check", {"state": "free shaft: no reference sensor",
                                          "velocity_factors_not_read": list(profile.unread),
                                          "units_confirmed": profile.units_confirmed})

    def _comm_loss_drill(self) -> None:
        """Before the first motion: prove the drive and the load machine stop themselves when the bench dies
        (bench.drill); refused when one does not, shown as unverified where the config states an external stop."""
        # the drive and machine proved (identity, settings), not the endpoints a simulator's start hands out
        settings = {k: v for k, v in {**self.cfg.drive, **{f"load.{k}": v for k, v in self.cfg.load.items()}}.items()
                    if k.split(".")[-1] in DRILL_SETTINGS}
        key = (self.cfg.path, tuple(sorted(asdict(self.identity).items())), self.load_name,
               json.dumps(settings, sort_keys=True, default=str))
        summary = proved_recently(key, self.cfg.bench.drill_valid_s)
        if summary is None:
            summary = run_drills(self.drive, self.load)
            remember(key, summary)
        self.recorder.note("comm_loss", summary)
        note = drill_unverified(summary)
        if note is not None:
            self.recorder.note("comm_loss_unverified", note)
            (self.warn or (lambda _m: None))(note)
        reason = drill_refusal(summary)
        if reason is not None:
            raise DrillRefused(reason)

    def _note_link_reports(self) -> None:
        """What each link read from its device and set in it (profile, units, PDOs, comm loss, watchdog)."""
        self.recorder.note("drive_settings", getattr(self.drive, "report", {}))
        sync_report = getattr(self.drive, "sync_report", None)
        if sync_report is not None:        # SYNC interval statistics at the bench, how samples were placed in time
            self.recorder.note("sync", sync_report())
        if self.load is not None:
            self.recorder.note("load_settings", getattr(self.load, "report", {}))

    def _loop(self) -> str | None:
        if self._stop_loop.is_set():          # the operator stopped the run before its first motion
            return None
        duration = float(self.scenario.duration_s)
        injections = list(self.scenario.injections)
        applied: list[dict] = []
        t_drive = 0.0
        next_fetch = FETCH_PERIOD_S
        next_status = 0.0
        next_load_poll = 0.0
        next_progress = 0.0
        last_sample_wall = time.monotonic()
        k = 0
        if self.reference_signals:     # the shaft as the reference sensor reads it at t = 0, before the first SYNC
            self._reference_readings.append((0.0, values_from_load(self._load_call(self.load.feedback))))
        self._command(0.0, injections, applied)
        while t_drive < duration - 1e-9:
            if self.supervisor.tripped.is_set() or self._stop_loop.is_set():
                break
            samples = self._run_time(self.drive.sync())
            if samples and self.reference_signals:
                # the rig's reference sensor, read now, stamped with the drive time of now: the last SYNC sent where
                # the link knows it (real time: a batch may hold samples that arrived late), else this batch's
                before = self._drive_now(samples[-1].t_s)
                feedback = self._load_call(self.load.feedback)
                values = values_from_load(feedback)
                now = 0.5 * (before + self._drive_now(samples[-1].t_s))    # the reading is of some time in between
                with self._live_lock:
                    self._reference_readings.append((now, values))
                    if self.data_source != "trace" and len(self._reference_readings) > 64:
                        del self._reference_readings[:-64]      # live rows only need the last few (sample and hold)
                samples = [LiveSample(s.t_s, {**{name: v for name, v in s.values.items()
                                                 if name not in self.not_from_drive}, **self._reference_at(s.t_s)})
                           for s in samples]
                self.supervisor.feed_load(now, feedback)
                next_load_poll = samples[-1].t_s + LOAD_POLL_PERIOD_S
            k += 1
            if samples:
                last_sample_wall = time.monotonic()
                t_drive = samples[-1].t_s
                self._t_drive = t_drive
                self.supervisor.feed(samples)
                # kept in trace mode too (until the next upload): if the drive's link dies, the live samples
                # are the only record of the time since the last upload
                with self._live_lock:
                    self.live_buffer.extend(samples)
                if t_drive < duration - 1e-9:
                    # commands for the coming SYNC period take the profile's values at its start, and go out now:
                    # in real time a step is on the wire within the SYNC period it falls in
                    self._command(t_drive, injections, applied)
            else:
                silent_s = time.monotonic() - last_sample_wall
                if self.realtime and silent_s > self._feedback_lost_s:
                    self.supervisor.feed_feedback_lost(t_drive, silent_s)
                if silent_s > STALL_TIMEOUT_S:
                    raise LinkError(f"no telemetry from the drive for {STALL_TIMEOUT_S:g} s (after t={t_drive:.3f} s)")
                time.sleep(self.sync_period_s)  # real-time links: nothing arrived yet; do not spin

            if t_drive >= next_status:
                status = self.drive.status()
                self._note_warning(t_drive, getattr(status, "warning", False))
                self.supervisor.feed_status(t_drive, status)
                next_status = t_drive + STATUS_PERIOD_S
            if t_drive >= next_load_poll and self.load is not None:
                self.supervisor.feed_load(t_drive, self._load_call(self.load.feedback))
                next_load_poll = t_drive + LOAD_POLL_PERIOD_S
            worker_error = self.telemetry.take_error()
            if worker_error is not None:
                raise worker_error
            if t_drive >= next_fetch:
                if self.realtime:
                    # real time: the drive's clock runs on while a block upload holds the bus for ~100 ms; commands
                    # must not wait for it. Lockstep: the drive's time stands still during an upload, so it runs
                    # here, keeping the journal level with drive time.
                    if not self.telemetry.busy:                  # never queue uploads behind a slow one
                        self.telemetry.submit(self._record_pending)
                else:
                    self._record_pending(defer_append=True)
                next_fetch = t_drive + FETCH_PERIOD_S
            if self.progress is not None and t_drive >= next_progress:
                self.progress(min(t_drive, duration), duration)
                next_progress = t_drive + PROGRESS_PERIOD_S
        # judge what has been fed before deciding the run went to its end
        self.supervisor.drain()
        if self.progress is not None:
            self.progress(min(t_drive, duration), duration)
        if self.supervisor.trip is not None:
            return self.supervisor.trip.message + self._drive_fault_behind(self.supervisor.trip)
        return None

    def _note_warning(self, t_s: float, on: bool) -> None:
        """The statusword's warning bit (CiA 402 bit 7): every change, as an event in the record."""
        if on == self._warning:
            return
        self._warning = on
        self.drive_warnings.append({"t_s": t_s, "warning": on,
                                    "utc": datetime.now(timezone.utc).isoformat(timespec="milliseconds")})
        self.recorder.note("drive_warnings", self.drive_warnings)

    def _command(self, t_cmd: float, injections: list, applied: list[dict]) -> None:
        """Due injections, the speed reference and the load of the profile at t_cmd (only what changed)."""
        while injections and injections[0].at_s <= t_cmd + 1e-9:
            inj = injections.pop(0)
            self.drive.write_parameter(inj.name, inj.value)
            applied.append({"at_s": inj.at_s, "name": inj.name, "value": inj.value, "applied_t_s": t_cmd})
            self.rerun.log_event(t_cmd, "injection", f"{inj.name} = {inj.value}")
            self.recorder.note("injections_applied", applied)
        ref = self.scenario.speed_ref_at(t_cmd)
        if ref != self._speed_ref:
            self.drive.set_speed_ref(ref)
            self._speed_ref = ref
        setting = self._load_to_send(t_cmd)
        if setting != self._load_setting and self.load is not None:
            self._load_call(self.load.set_load, *setting)
            self._load_setting = setting

    def _load_to_send(self, t_cmd: float) -> tuple:
        """The profile's load at t_cmd, or the torque that emulates it from the last shaft speed read (load_emulation)."""
        mode, value = self.scenario.load_at(t_cmd)
        if not self.emulation.emulates(mode):
            return mode, value
        with self._live_lock:
            speed = self._reference_readings[-1][1][SPEED_SIGNAL] if self._reference_readings else 0.0
        return self.emulation.setting(mode, value, speed)

    def _row_period_s(self) -> float | None:
        """The drive-clock period recorded rows come at: the recorder's decimation x control period, else one SYNC."""
        if self.data_source == "trace":
            control = getattr(self.drive, "control_period_s", None)
            return control * int(self.cfg.drive["trace_decimation"]) if control else None
        return self.sync_period_s

    def _drive_fault_behind(self, trip) -> str:
        """A limit trip is often the symptom (a drive that faulted loses its angle): ask the drive once, now."""
        if trip.reason in ("fault", "emcy", "heartbeat", "max_duration"):
            return ""
        try:
            status = self.drive.status()
        except LinkError as exc:
            self.recorder.note("status_after_trip_error", str(exc))
            return ""
        cause = check_status(self._t_drive, status)
        if cause is None or cause.reason == "heartbeat":
            return ""
        self._add_trip(cause.reason, cause.message, cause.values)
        return f"; the drive reports: {cause.message}"

    def _drive_now(self, last_sample_t: float) -> float:
        now = getattr(self.drive, "now_s", None)
        now = now() if callable(now) else None
        if now is None or self._clock_start is None:
            return last_sample_t
        return max(last_sample_t, now - self._clock_start)

    def _reference_at(self, t_s: float) -> dict[str, float]:
        """The reference reading taken last at or before drive time t_s (sample and hold); the oldest one kept for
        samples older than every reading."""
        readings = self._reference_readings
        for t_read, values in reversed(readings):
            if t_read <= t_s + 0.5 * self.sync_period_s:
                return values
        return readings[0][1]

    def _run_time(self, samples: list[LiveSample]) -> list[LiveSample]:
        """Shift drive-clock stamps to time since this run's first SYNC (the drive may have run before)."""
        if not samples:
            return samples
        if self._clock_start is None:
            self._clock_start = samples[0].t_s - self.sync_period_s
            self.recorder.note("drive_clock_start_s", self._clock_start)
        return [LiveSample(s.t_s - self._clock_start, s.values) for s in samples]

    def _record_pending(self, defer_append: bool = False) -> None:
        """One upload (trace mode) or the live samples since the last call (pdo mode), recorded; on the telemetry
        worker during a real-time run, on the main thread for the final upload. Lockstep uploads on the command
        thread (drive time stands still meanwhile) and, with defer_append, hands the writing to the worker: the
        journal's start (its file, the first Parquet and Rerun calls) took hundreds of ms on a loaded host, a pause
        in the request stream long enough for a drive's 300 ms comm-loss watchdog."""
        append = self._append
        if defer_append:
            if self.telemetry.pending > MAX_DEFERRED_APPENDS:     # the journal fell far behind: let it catch up
                self.telemetry.drain(STALL_TIMEOUT_S)

            def append(block: dict[str, np.ndarray]) -> None:
                self.telemetry.submit(lambda: self._append(block))
        if self.data_source == "trace":
            block = self.drive.fetch_trace()
            if block is not None and len(block.get(TIME_COLUMN, ())):
                block[TIME_COLUMN] = block[TIME_COLUMN] - (self._clock_start or 0.0)
            if block is None:  # the drive said it has a recorder but gives nothing: fall back to live data
                self.data_source = "pdo"
                self.recorder.note("data_source", "pdo")
                return
            if len(block.get(TIME_COLUMN, ())):
                uploaded_to = block[TIME_COLUMN][-1]
                with self._live_lock:       # live samples now in the trace are no longer the only record
                    self.live_buffer = [s for s in self.live_buffer if s.t_s > uploaded_to]
                    readings = list(self._reference_readings)
                    keep = max(0, sum(1 for r in readings if r[0] <= uploaded_to) - 1)
                    self._reference_readings = self._reference_readings[keep:]
                for name in self.not_from_drive:
                    block.pop(name, None)
                if self.reference_signals:
                    block.update(onto_rows(block[TIME_COLUMN], readings, self.reference_signals))
                append(block)
        else:
            with self._live_lock:
                pending, self.live_buffer = self.live_buffer, []
            if pending:
                append(live_columns(pending, self.live_recorded))

    def _record_live_tail(self) -> None:
        """The trace since the last upload is out of reach (dead link): keep the live samples of that time."""
        t_last = self._t_recorded_last
        with self._live_lock:
            tail = [s for s in self.live_buffer if s.t_s > t_last]
            self.live_buffer = []
        if tail:
            self._append(live_columns(tail, self.live_recorded))
            self.recorder.note("live_tail", {"rows": len(tail), "t_first_s": tail[0].t_s, "t_last_s": tail[-1].t_s,
                                             "signals": list(self.live_recorded)})

    def _append(self, block: dict[str, np.ndarray]) -> None:
        block = {k: np.asarray(v) for k, v in block.items()}
        self.recorder.append(block)
        if len(block[TIME_COLUMN]):
            self._t_recorded_last = float(block[TIME_COLUMN][-1])
        # the viewer shows what is recorded (every signal), in blocks of FETCH_PERIOD_S, at most RERUN_MAX_RATE_HZ
        t = block[TIME_COLUMN]
        step = self._rerun_step(t)
        self.rerun.log_columns(t[::step], {k: v[::step] for k, v in block.items() if k != TIME_COLUMN})

    def _rerun_step(self, t: np.ndarray) -> int:
        if self._rerun_stride is None and len(t) > 1:
            dt = float(np.median(np.diff(t)))
            self._rerun_stride = max(1, math.ceil(1.0 / (RERUN_MAX_RATE_HZ * dt) - 1e-6)) if dt > 0 else 1
            self.recorder.note("rerun", {**self._rerun_note, "rate_hz": round(1.0 / (dt * self._rerun_stride), 3)})
        return self._rerun_stride or 1

    # -- after the safe stop --------------------------------------------------------------------------------

    def _finish(self, abort_reason, error, interrupted, stop_errors) -> RunResult:
        trip = self.supervisor.trip
        if trip is not None:
            self.recorder.note("supervisor_trip", trip.as_dict())
            self.trips.insert(0, {**trip.as_dict(), "wall_s": None, "utc": self.supervisor.trip_utc})
        self.recorder.note("trips", self.trips)
        if self.signals is not None and self.signals.ignored:
            self.recorder.note("signals_ignored_while_stopping", self.signals.ignored)
        self.recorder.note("safe_stop", {"steps": self.safe_stop.steps, "errors": stop_errors})
        if self.supervisor.unit_check is not None:
            self.recorder.note("unit_check", self.supervisor.unit_check.summary())
        self._note_link_reports()          # now with how the stop went (standstill, speed at disable)
        try:
            if not self.telemetry.drain(STALL_TIMEOUT_S):
                raise LinkError(f"a trace upload did not finish within {STALL_TIMEOUT_S:g} s")
            worker_error = self.telemetry.take_error()
            if worker_error is not None:
                raise worker_error
            self._record_pending()  # final trace upload (includes the stop)
        except Exception as exc:
            self.recorder.note("final_fetch_error", f"{type(exc).__name__}: {exc}")
            if error is None and abort_reason is None:
                error = f"final trace upload failed: {exc}"
            self._record_live_tail()
        # read back from the run's journal only what the verdict and the plot need: memory does not grow with the
        # run's length (the time axis: checked batch by batch; the criteria: their windows; the plot: an envelope)
        duration = float(self.scenario.duration_s)
        row_period = self._row_period_s()
        # live samples of a drive without a clock are stamped on receipt in real time: they jitter, allow for it
        # (placed on the SYNC they answer, or on the drive's clock, they do not: a single missing row is a gap)
        receive_stamped = getattr(self.drive, "time_base", "receive time") == "receive time"
        tolerance = 1.9 if self.realtime and self.data_source == "pdo" and receive_stamped else 1.5
        if row_period:
            axis = TimeAxis(row_period, tolerance)
            for chunk in self.recorder.iter_back([], t_max=duration + 1e-9):
                axis.add(chunk[TIME_COLUMN])
            holes = axis.result()
        else:        # the period is the median interval: the whole axis at once
            holes = time_axis(self.recorder.read_back([], t_max=duration + 1e-9)[TIME_COLUMN], None, tolerance)
        specs = self.scenario.criteria
        first = min((s.window_s[0] - float(s.params.get("smooth_s") or 0.0) for s in specs), default=0.0) - 1.0
        needed = {name for spec in specs for name in signals_of(spec)}
        columns = self.recorder.read_back(needed, t_min=first, t_max=duration + 1e-9)
        t = columns.pop(TIME_COLUMN)
        judged = judge_run(self.scenario, t, columns, measured=self.measured, row_period_s=row_period,
                           tolerance=tolerance, abort_reason=abort_reason, error=error, stop_errors=stop_errors,
                           holes=holes)
        del columns, t
        self.recorder.note("time_axis", judged.time_axis)
        verdict, reason, results, error = judged.verdict, judged.reason, judged.results, judged.error
        self.rerun.log_judgement([r.to_dict() for r in results], {c.name: c.params for c in specs})
        try:
            t_env, envelope = self.recorder.read_back_envelope(PLOT_SIGNALS, PLOT_BUCKETS)
            if len(t_env):
                write_summary_png(self.recorder.run_dir / "summary.png", t_env, envelope,
                                  title=f"{self.scenario.name} - {verdict}", criteria=[r.to_dict() for r in results],
                                  params={c.name: c.params for c in specs},
                                  events=events_of({"trips": self.trips, **self.recorder.record}))
        except Exception as exc:
            self.recorder.note("summary_png_error", f"{type(exc).__name__}: {exc}")
        release_freed_memory()
        record = self.recorder.finish(verdict, results, reason)
        return RunResult(self.recorder.run_dir, verdict, record, results, interrupted, error)
