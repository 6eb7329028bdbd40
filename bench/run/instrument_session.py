"""A run's lab instruments ([[instruments]]): opened before motion, the power analyser polled at its own rate, the
scope/DAQ armed for the scenario's marked moment and its record pulled after the run, everything stamped on the
drive clock and stored in the run directory (instruments/), a summary in record.json ("lab_instruments").

- Power analyser: one reading per 1/poll_hz of drive time. In lockstep the bench reads it from the run loop when
  the drive clock crosses the next poll instant (the simulator advances only on SYNC, so this is the update that
  just completed: deterministic); in real time a thread of its own polls at poll_hz and stamps each reading with
  the drive time of the last SYNC (the SYNC loop never waits on an instrument). Over-range values are NaN with
  their reason: not judged, never a number.
- Scope/DAQ: armed before motion; the marked moment is the scenario's first step (speed or load segment start or
  an injection) after t = 0; the bench forces the trigger on the first SYNC at or after it, so the capture's t = 0
  is that SYNC's drive time. Stated placement uncertainty: one SYNC period in real time (the force goes out within
  the SYNC period), one control period in lockstep (the drive has stepped up to the SYNC).
- Faults: an instrument that cannot be opened, stops answering, answers garbage or drops its connection gives one
  line in the record (and a warning), its data ends there, and the run goes on to its safe stop: the instruments
  never stop, hang or pass a run.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from drivers.contract.instruments import InstrumentConfig

CAPTURE_S = 0.25            # record length around the marked moment
PRETRIGGER = 0.2            # part of it before the moment
FETCH_TIMEOUT_S = 5.0


@dataclass
class _Analyser:
    cfg: InstrumentConfig
    driver: Any
    readings: list[tuple[float, dict[str, float]]] = field(default_factory=list)
    not_judged: dict[str, tuple[str, int]] = field(default_factory=dict)
    next_t: float = 0.0
    alive: bool = True


class InstrumentSession:
    def __init__(self, instruments: tuple[InstrumentConfig, ...], run_dir: Path, realtime: bool,
                 sync_period_s: float, control_period_s: float | None, moment_s: float | None,
                 drive_time: Callable[[], float], warn: Callable[[str], None] | None = None,
                 record_s: float = 0.0, truths: Any = None):
        self.instruments = instruments
        self.dir = run_dir / "instruments"
        self.realtime = realtime
        self.sync_period_s = sync_period_s
        self.control_period_s = control_period_s or sync_period_s
        self.moment_s = moment_s
        self.record_s = record_s             # a DAQ records the whole run: this long from the first SYNC
        self.truths = truths                 # [rig_truths]: the field angle and flux from the DAQ's record
        self.drive_time = drive_time
        self.warn = warn or (lambda line: None)
        self.errors: list[str] = []
        self.identities: dict[str, str] = {}
        self.analysers: list[_Analyser] = []
        self.scopes: list[tuple[InstrumentConfig, Any]] = []
        self.forced_at: float | None = None
        self.daq_forced_at: float | None = None
        self.captures: dict[str, dict[str, Any]] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _fault(self, line: str) -> None:
        self.errors.append(line)
        self.warn(f"instruments: {line}")

    def start(self) -> None:
        """Open and configure every instrument; arm the scopes. Failures are lines, never exceptions."""
        from drivers.instruments import InstrumentError, open_instrument

        for cfg in self.instruments:
            try:
                driver = open_instrument(cfg)
            except InstrumentError as exc:
                self._fault(str(exc))
                continue
            self.identities[cfg.name] = driver.identity
            if cfg.kind == "power_analyser":
                # its first update interval completes one poll period in
                self.analysers.append(_Analyser(cfg, driver, next_t=1.0 / cfg.poll_hz))
                continue
            try:
                if cfg.kind == "daq":            # the whole run and its last rows (the stop follows)
                    driver.arm(self.record_s + 2 * self.sync_period_s + 0.05, 0.0)
                elif self.moment_s is not None:
                    driver.arm(CAPTURE_S, PRETRIGGER)
                self.scopes.append((cfg, driver))
            except InstrumentError as exc:
                self._fault(str(exc))
                driver.close()
        for cfg, scope in self.scopes:      # a DAQ records from now, the drive clock's start (t = 0)
            if cfg.kind == "daq":
                try:
                    scope.force()
                    self.daq_forced_at = 0.0
                except InstrumentError as exc:
                    self._fault(str(exc))
        if self.realtime and self.analysers:
            self._thread = threading.Thread(target=self._poll_loop, name="analyser-poll", daemon=True)
            self._thread.start()

    def tick(self, t_drive: float) -> None:
        """After each SYNC, on the run loop: the scope's forced trigger; in lockstep the analyser's due readings."""
        if self.scopes and self.forced_at is None and self.moment_s is not None and t_drive >= self.moment_s - 1e-9:
            self.forced_at = t_drive
            for cfg, scope in self.scopes:
                if cfg.kind != "daq":
                    self._guard(cfg, scope.force)
        if not self.realtime:
            for a in self.analysers:
                if a.alive and t_drive >= a.next_t - 1e-9:
                    self._poll(a, t_drive)

    def _poll_loop(self) -> None:
        period = min(1.0 / a.cfg.poll_hz for a in self.analysers)
        due = time.monotonic() + period             # on a fixed grid: a slow answer does not lower the rate
        while not self._stop.wait(max(0.0, due - time.monotonic())):
            due += period
            for a in self.analysers:
                if a.alive:
                    self._poll(a, self.drive_time())

    def _poll(self, a: _Analyser, t_drive: float) -> None:
        reading = self._guard(a.cfg, a.driver.poll)
        if reading is None:
            a.alive = False
            return
        a.readings.append((t_drive, reading.values))
        for signal, why in reading.not_judged.items():      # the first reason, and how many readings had one
            first, count = a.not_judged.get(signal, (why, 0))
            a.not_judged[signal] = (first, count + 1)
        a.next_t = t_drive + 1.0 / a.cfg.poll_hz

    def _guard(self, cfg: InstrumentConfig, call: Callable[[], Any]) -> Any:
        from drivers.instruments import InstrumentError
        try:
            return call()
        except InstrumentError as exc:
            self._fault(f"{exc} (its data ends at t = {self.drive_time():.3f} s)")
            return None

    def finish(self) -> dict[str, Any]:
        """Stop polling, pull the captures, write the files; the record's "lab_instruments" summary."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=max(a.cfg.timeout_s for a in self.analysers) + 1.0 if self.analysers else 1.0)
        self.dir.mkdir(parents=True, exist_ok=True)
        summary: dict[str, Any] = {"identities": self.identities, "errors": self.errors, "analysers": {},
                                   "captures": {}}
        for a in self.analysers:
            summary["analysers"][a.cfg.name] = self._write_analyser(a)
        for cfg, scope in self.scopes:
            summary["captures"][cfg.name] = self._pull(cfg, scope)
        for driver in [a.driver for a in self.analysers] + [s for _, s in self.scopes]:
            try:
                driver.close()
            except Exception:
                pass
        return summary

    def _write_analyser(self, a: _Analyser) -> dict[str, Any]:
        import pyarrow as pa
        import pyarrow.parquet as pq

        names = [c.signal for c in a.cfg.channels]
        t = np.array([r[0] for r in a.readings], dtype=np.float64)
        table = {"t_s": t, **{n: np.array([r[1].get(n, math.nan) for r in a.readings]) for n in names}}
        path = self.dir / f"{a.cfg.name}.parquet"
        pq.write_table(pa.table(table), path)
        rate = (t.size - 1) / (t[-1] - t[0]) if t.size > 1 and t[-1] > t[0] else 0.0
        return {"file": str(path.relative_to(self.dir.parent)), "readings": int(t.size),
                "rate_hz_drive_clock": round(rate, 3),
                "not_judged": {k: f"{why} ({n} readings)" for k, (why, n) in a.not_judged.items()},
                "units": {c.signal: c.unit for c in a.cfg.channels}}

    def _pull(self, cfg: InstrumentConfig, scope: Any) -> dict[str, Any]:
        import pyarrow as pa
        import pyarrow.parquet as pq

        forced_at = self.daq_forced_at if cfg.kind == "daq" else self.forced_at
        if forced_at is None:
            return {"state": "not captured: the run ended before its marked moment" if self.moment_s is not None
                    else "not captured: the scenario has no marked moment (no step, load step or injection)"}
        try:
            if cfg.kind == "daq":            # recording since t = 0: what it has when the run has ended
                scope.stop()
            else:
                scope.wait(FETCH_TIMEOUT_S)
            cap = scope.fetch()
        except Exception as exc:          # InstrumentError, or a record that never completed
            self._fault(str(exc))
            return {"state": f"not captured: {exc}"}
        uncertainty = self.sync_period_s if self.realtime else self.control_period_s
        t_drive = cap.t_s + forced_at
        path = self.dir / f"{cfg.name}.parquet"
        pq.write_table(pa.table({"t_s": t_drive, **cap.signals}), path)
        self.captures[cfg.name] = {"t_s": t_drive, **cap.signals}
        return {"file": str(path.relative_to(self.dir.parent)), "samples": int(t_drive.size),
                "sample_rate_hz": round(cap.sample_rate_hz, 3), "t0_drive_s": float(t_drive[0]),
                "marked_moment_s": 0.0 if cfg.kind == "daq" else self.moment_s, "forced_at_drive_s": forced_at,
                "placement_uncertainty_s": uncertainty, "not_judged": cap.not_judged,
                "units": {c.signal: c.unit for c in cfg.channels}}


    def records(self) -> dict[str, dict[str, np.ndarray]]:
        """Each instrument's record on the drive clock (captures as pulled, the analysers' readings), for criteria
        naming `<instrument>:<signal>`; an instrument that gave nothing is absent (its criteria: not judged)."""
        out: dict[str, dict[str, np.ndarray]] = dict(self.captures)
        for a in self.analysers:
            if a.readings:
                out[a.cfg.name] = {"t_s": np.array([r[0] for r in a.readings], dtype=np.float64),
                                   **{c.signal: np.array([r[1].get(c.signal, math.nan) for r in a.readings])
                                      for c in a.cfg.channels}}
        return out

    def truth_rows(self, t_rows: np.ndarray, pos_est: np.ndarray | None) -> dict[str, np.ndarray]:
        """The measured pos_err_elec_rad (and SPIM flux_true_wb) on the telemetry's rows, from the DAQ's record;
        {} when the rig has no [rig_truths] or its DAQ gave no record (then those criteria stay not judged)."""
        from bench.run.rig_truths import field_angle_rows, measured_pos_err

        record = self.captures.get(self.truths.daq) if self.truths is not None else None
        if record is None or pos_est is None or not t_rows.size:
            return {}
        rows = field_angle_rows(self.truths, record["t_s"], record, t_rows)
        angle = rows.pop("field_angle_elec_rad")
        rows["pos_err_elec_rad"] = measured_pos_err(angle, pos_est)
        return rows


def marked_moment(scenario: Any) -> float | None:
    """The scenario's first step after t = 0: a speed or load segment's start, or an injection's time."""
    times = [s.start_s for s in scenario.speed_segments] + [s.start_s for s in scenario.load_segments]
    times += [float(getattr(i, "at_s", 0.0) or 0.0) for i in scenario.injections]
    after = [t for t in times if t > 1e-9]
    return min(after) if after else None
