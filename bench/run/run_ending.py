"""A run's ending, after the safe stop: the last upload, the time axis and the criteria judged from the journal, the
summary plot, the record finished. A part of orchestrator._Run."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from bench.inputs.capture_criteria import is_capture_signal
from bench.inputs.criteria import TimeAxis, signals_of, time_axis
from bench.outputs.memory import release_freed_memory
from bench.outputs.record_schema import RunRecord
from bench.run.run_periods import STALL_TIMEOUT_S
from bench.outputs.summary_plot import BUCKETS as PLOT_BUCKETS, PLOT_SIGNALS, events_of, write_summary_png
from bench.run.verdict import judge_run
from drivers.contract.errors import LinkError
from drivers.contract.signals import TIME_COLUMN


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


class RunEnding:
    """The ending after the safe stop, once, on the main thread."""

    def _row_period_s(self) -> float | None:
        """The drive-clock period recorded rows come at: the recorder's decimation x control period, else one SYNC."""
        if self.data_source == "trace":
            control = self.drive.control_period_s
            return control * int(self.cfg.drive["trace_decimation"]) if control else None
        return self.sync_period_s

    def _lab_truths(self, t, columns, measured):
        """The rig's measured field angle and flux (bench.run.instrument_session) put on the rows to judge, and
        saved as instruments/truths.parquet; the measured set grows by what was derived."""
        try:
            rows = self.lab.truth_rows(t, columns.get("pos_est_elec_rad"))
        except Exception as exc:             # the instruments never cost the record: those criteria stay not judged
            self.recorder.note("lab_instruments", {**self.recorder.record.get("lab_instruments", {}),
                                                   "truths_error": f"{type(exc).__name__}: {exc}"})
            return measured
        if not rows:
            return measured
        import pyarrow as pa
        import pyarrow.parquet as pq
        pq.write_table(pa.table({TIME_COLUMN: t, **rows}), self.recorder.run_dir / "instruments" / "truths.parquet")
        columns.update(rows)
        return measured if measured is None else measured | frozenset(rows)

    def _plot_captures(self, criteria: list) -> None:
        """instruments/<name>.png of each capture, with the windows of the criteria judged on it."""
        from bench.outputs.capture_plot import write_capture_png
        summaries = (self.recorder.record.get("lab_instruments") or {}).get("captures") or {}
        for name, record in self.lab.captures.items():
            try:
                write_capture_png(self.recorder.run_dir / "instruments" / f"{name}.png", name, record,
                                  summaries.get(name) or {}, criteria)
            except Exception as exc:
                self.recorder.note("capture_plot_error", f"{name}: {type(exc).__name__}: {exc}")

    def _finish(self, abort_reason, error, interrupted, stop_errors) -> RunResult:
        if self.lab is not None:             # after the safe stop: pull the captures, write instruments/
            try:
                self.recorder.note("lab_instruments", self.lab.finish())
            except Exception as exc:         # the instruments never cost the record
                self.recorder.note("lab_instruments", {"errors": [f"{type(exc).__name__}: {exc}"]})
            for name, record in self.lab.records().items():     # to Rerun, each on the drive clock's timeline
                self.rerun.log_columns(record["t_s"], {f"instruments/{name}/{k}": v for k, v in record.items()
                                                       if k != "t_s"})
                self.rerun.flush()
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
        receive_stamped = self.drive.time_base == "receive time"
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
        needed = {name for spec in specs for name in signals_of(spec) if not is_capture_signal(name)}
        measured = self.measured
        if self.lab is not None and self.lab.truths is not None:
            needed.add("pos_est_elec_rad")
        columns = self.recorder.read_back(needed, t_min=first, t_max=duration + 1e-9)
        t = columns.pop(TIME_COLUMN)
        if self.lab is not None and self.lab.truths is not None:
            measured = self._lab_truths(t, columns, measured)
        judged = judge_run(self.scenario, t, columns, measured=measured, row_period_s=row_period,
                           tolerance=tolerance, abort_reason=abort_reason, error=error, stop_errors=stop_errors,
                           holes=holes, records=self.lab.records() if self.lab is not None else None,
                           instruments=self.cfg.instruments)
        del columns, t
        self.recorder.note("time_axis", judged.time_axis)
        verdict, reason, results, error = judged.verdict, judged.reason, judged.results, judged.error
        self.rerun.log_judgement([r.to_dict() for r in results], {c.name: c.params for c in specs})
        if self.lab is not None:
            self._plot_captures([r.to_dict() for r in results])
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
