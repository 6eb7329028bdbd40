"""Runs one scenario against one bench: connect, configure, drive the profile, supervise, stop safely, judge.

The same code runs a real rig and the simulator; everything simulator-specific comes from the bench
config's [services] entry and the link classes its transports name.
"""

from __future__ import annotations

import math
import os
import signal
import threading
import time
import traceback
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

from bench.inputs.benchconfig import BenchConfig
from bench.run.drill import DrillRefused
from drivers.contract.errors import InputError
from drivers.contract.checks import find_repo_root
from bench.run.links import make_links, started_services
from bench.run.load_emulation import SPEED_SIGNAL, LoadEmulation
from bench.inputs.prepared import (DEFAULT_SEED, MAX_SEED, TRACE_SIGNALS, PreparedRun, prepare_run,  # noqa: F401
                            trace_signals_for)
from bench.outputs.memory import freeze_long_lived
from bench.outputs.recorder import RunRecorder
from bench.outputs.rerun_view import RerunStream
from bench.run.run_arming import RunArming
from bench.run.run_ending import RunEnding, RunResult
from bench.run.run_journal import RunJournal, live_columns  # noqa: F401
from bench.run.run_periods import FEEDBACK_LOST_MIN_S, FEEDBACK_LOST_PERIODS, LIVE_SIGNALS, STUCK_GRACE_S
from bench.run.run_steps import RunSteps
from bench.run.run_thread import LoopThread
from bench.run.run_trips import RunTrips
from bench.inputs.scenario import Scenario
from bench.run.supervisor import SafeStop, Supervisor
from bench.run.telemetry_worker import TelemetryWorker
from drivers.api import DriveIdentity, DriveLink, LiveSample, LoadLink
from drivers.contract.errors import LinkError
from drivers.contract.load_map import LoadMode
from drivers.reference import ReferenceConfig

ProgressFn = Callable[[float, float], None]


class Interrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM during a run."""


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
    scenario: PreparedRun | str | Path,
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
    """Run one prepared scenario (prepare_run), or a scenario file prepared here against `bench_path`. Raises
    InputError (bad files, refused injections) and LinkError (cannot connect) before a run directory exists; after
    that every outcome is a record and a RunResult. `seed` overrides the prepared one.

    `links` replaces the links and services the bench config names (unit tests with in-memory fakes).
    """
    if isinstance(scenario, PreparedRun):
        if bench_path is not None:
            raise ValueError("a prepared run has its bench config: give bench_path to prepare_run")
        prepared = scenario.with_seed(seed)
    else:
        prepared = prepare_run(scenario, bench_path, seed=seed)
    check_out_root(Path(out_root))      # before anything is connected: a bad --out must not leave a rig touched
    freeze_long_lived()
    cfg = prepared.bench
    with _StopSignals() as signals:
        if links is not None:
            return _run_connected(prepared, cfg, *links, Path(out_root), rerun_mode, rerun_url, progress, warn,
                                  signals, on_trip)
        with started_services(cfg, prepared.seed) as live_cfg:
            drive, load = make_links(live_cfg, find_repo_root(cfg.path))
            return _run_connected(prepared, live_cfg, drive, load, Path(out_root), rerun_mode, rerun_url,
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


def _run_connected(prepared: PreparedRun, cfg: BenchConfig, drive, load, out_root, rerun_mode, rerun_url, progress,
                   warn, signals: _StopSignals | None = None,
                   on_trip: Callable[[dict], None] | None = None) -> RunResult:
    """`cfg`: the prepared bench config with the endpoints a [services] starter handed out."""
    identity, load_name = _open(drive, load)  # LinkError here: nothing started, nothing to stop
    recorder = None
    safe_stop = SafeStop(drive, load)
    try:
        recorder = RunRecorder(out_root, prepared.scenario, prepared.seed, cfg)
    except OSError as exc:
        _close_quietly(drive, load)
        raise InputError([f"{out_root}: --out: cannot create the run directory: {exc.strerror or exc}"]) from None
    except BaseException:
        _close_quietly(drive, load)
        raise
    if prepared.overrides:
        recorder.note("overrides", {"injections_at_0_s": [list(o) for o in prepared.overrides]})
    run = _Run(prepared.scenario, cfg, prepared.seed, drive, load, identity, load_name, recorder, safe_stop,
               rerun_mode, rerun_url, progress, warn, on_trip, prepared.trace_signals)
    run.signals = signals
    return run.execute()


@dataclass(eq=False)
class _Run(RunArming, RunSteps, RunJournal, RunTrips, RunEnding):
    """One run on connected links: its state, set up here; start-up and arming (run_arming), the step loop
    (run_steps), the journal (run_journal), trips and the watch over the loop (run_trips), the safe stop and the
    ending (run_ending)."""
    scenario: Scenario
    cfg: BenchConfig
    seed: int
    drive: DriveLink
    load: LoadLink | None
    identity: DriveIdentity
    load_name: str | None
    recorder: RunRecorder
    safe_stop: SafeStop
    rerun_mode: str
    rerun_url: str | None
    progress: Callable[[str], None] | None
    warn: Callable[[str], None] | None
    on_trip: Callable[[dict], None] | None = None   # told of each trip as it happens (the service's live view)
    trace_signals: tuple[str, ...] = ()             # the prepared run's trace recorder set

    def __post_init__(self) -> None:
        self._t_recorded_last = -math.inf    # drive time of the last recorded row (the data is on disk only)
        self.live_buffer: list[LiveSample] = []
        self.telemetry = TelemetryWorker()
        self.realtime = self.cfg.bench.timing == "realtime"
        self._live_lock = threading.Lock()        # live_buffer: the command thread adds, the worker prunes
        self.supervisor = Supervisor(self.scenario.limits, judge_inline=not self.realtime)
        self.sync_period_s = float(self.cfg.drive["sync_period_s"])
        # real time: no live sample for this long is lost feedback (a host hiccup is not)
        self._feedback_lost_s = max(FEEDBACK_LOST_MIN_S, FEEDBACK_LOST_PERIODS * self.sync_period_s)
        self.data_source = "trace" if self.identity.has_trace_recorder else "pdo"
        self.reference = ReferenceConfig(self.cfg.reference_source)
        self.reference_signals = self.reference.signals(self.load is not None)
        self.not_from_drive = self.reference.not_from_drive()
        self.emulation = LoadEmulation((tuple(self.load.modes) if self.load is not None else ()) or tuple(LoadMode),
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
            self.load is not None, self.load.map if self.load is not None else None,
            self.identity.device_name or "the drive"))
        if any(self.emulation.emulates(seg.mode) for seg in self.scenario.load_segments):
            self.recorder.note("load_emulation", self.emulation.as_record(s.mode for s in self.scenario.load_segments))
        self.recorder.note("bench", {"name": self.cfg.bench.name, "path": self.cfg.path,
                                     "timing": self.cfg.bench.timing})
        self._rerun_note = {"mode": self.rerun_mode, "url": self.rerun_url, "sinks": self.rerun.sinks}
        self._rerun_stride: int | None = None
        self.recorder.note("rerun", self._rerun_note)
        self.lab = None                      # the rig's [[instruments]] (bench.run.instrument_session)
        if self.cfg.rig_truths is not None:
            truths = self.cfg.rig_truths
            how = ("the dynamometer encoder's angle since its index, aligned by the recorded step" if
                   truths.method == "encoder" else "the stator flux integral(v - R_s i) dt of the measured windings")
            self.recorder.note("instruments", {**self.recorder.record["instruments"], **{
                name: f"{truths.daq!r} (DAQ record of the run): {how}; judged on instruments/truths.parquet"
                for name in truths.signals()}})
        if self.cfg.instruments:
            from bench.run.instrument_session import InstrumentSession, marked_moment
            self.lab = InstrumentSession(self.cfg.instruments, self.recorder.run_dir, self.realtime,
                                         self.sync_period_s, self.drive.control_period_s,
                                         marked_moment(self.scenario), lambda: self._t_drive, self.warn,
                                         record_s=float(self.scenario.duration_s), truths=self.cfg.rig_truths)

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
            with self._shaft_followed_while_stopping():
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
