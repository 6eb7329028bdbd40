"""A run's journal: the trace uploads (or the live samples) appended to the record and the viewer as the run goes,
the live tail kept when the trace is out of reach. A part of orchestrator._Run."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from bench.run.run_periods import MAX_DEFERRED_APPENDS, RERUN_MAX_RATE_HZ, STALL_TIMEOUT_S
from drivers.api import LiveSample
from drivers.reference import onto_rows
from drivers.contract.signals import TIME_COLUMN


def live_columns(samples: Sequence[LiveSample], names: Sequence[str]) -> dict[str, np.ndarray]:
    t = np.fromiter((s.t_s for s in samples), dtype=np.float64, count=len(samples))
    cols = {TIME_COLUMN: t}
    for n in names:
        cols[n] = np.fromiter((s.values.get(n, math.nan) for s in samples), dtype=np.float64, count=len(samples))
    return cols


class RunJournal:
    """Recording as the run goes (the command thread in lockstep, the telemetry worker in real time)."""

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
