"""A run's step loop: SYNC by SYNC, the samples placed on the run's time axis with the reference sensor's readings,
fed to the supervisor, the profile's commands and injections sent, status and load polled, uploads scheduled.
A part of orchestrator._Run."""

from __future__ import annotations

import contextlib
import time
from datetime import datetime, timezone

from bench.run.load_emulation import SPEED_SIGNAL
from bench.run.supervisor import is_warning
from bench.run.run_periods import FETCH_PERIOD_S, LOAD_POLL_PERIOD_S, PROGRESS_PERIOD_S, STALL_TIMEOUT_S, STATUS_PERIOD_S
from drivers.contract.errors import LinkError
from drivers.api import LiveSample
from drivers.reference import values_from_load


class RunSteps:
    """The step loop and the commands of each SYNC period (run on the run loop's thread)."""

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
        if self.lab is not None:           # opened and armed before motion; a fault is a line, never a stop
            self.lab.start()
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
                if self.lab is not None:
                    self.lab.tick(t_drive)
            else:
                silent_s = time.monotonic() - last_sample_wall
                if self.realtime and silent_s > self._feedback_lost_s:
                    self.supervisor.feed_feedback_lost(t_drive, silent_s)
                if silent_s > STALL_TIMEOUT_S:
                    raise LinkError(f"no telemetry from the drive for {STALL_TIMEOUT_S:g} s (after t={t_drive:.3f} s)")
                time.sleep(self.sync_period_s)  # real-time links: nothing arrived yet; do not spin

            if t_drive >= next_status:
                status = self.drive.status()
                self._note_warning(t_drive, status.warning, status)
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

    def _note_warning(self, t_s: float, on: bool, status=None) -> None:
        """The statusword's warning bit (CiA 402 bit 7): every change, as an event in the record; with the warning
        EMCYs that came while the drive ran on (bench.run.supervisor.is_warning)."""
        if status is not None and status.emcy and is_warning(status):
            self.drive_warnings.extend({"t_s": t_s, "warning": on, "emcy": f"0x{code:04X} {text}",
                                        "utc": datetime.now(timezone.utc).isoformat(timespec="milliseconds")}
                                       for code, text in status.emcy if code)
            self.recorder.note("drive_warnings", self.drive_warnings)
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

    def _drive_now(self, last_sample_t: float) -> float:
        now = self.drive.now_s()
        if now is None or self._clock_start is None:
            return last_sample_t
        return max(last_sample_t, now - self._clock_start)

    def _reference_at(self, t_s: float) -> dict[str, float]:
        """The reference reading taken last at or before drive time t_s (sample and hold); the oldest one kept for
        samples older than every reading. `reference_age_s`: how old that reading is at t_s (a stalled bench reads the
        dynamometer once for several SYNCs: the unit check does not judge on a stale reading)."""
        readings = self._reference_readings
        for t_read, values in reversed(readings):
            if t_read <= t_s + 0.5 * self.sync_period_s:
                return {**values, "reference_age_s": max(0.0, t_s - t_read)}
        return {**readings[0][1], "reference_age_s": 0.0}

    def _run_time(self, samples: list[LiveSample]) -> list[LiveSample]:
        """Shift drive-clock stamps to time since this run's first SYNC (the drive may have run before)."""
        if not samples:
            return samples
        if self._clock_start is None:
            self._clock_start = samples[0].t_s - self.sync_period_s
            self.recorder.note("drive_clock_start_s", self._clock_start)
        return [LiveSample(s.t_s - self._clock_start, s.values) for s in samples]

    @contextlib.contextmanager
    def _shaft_followed_while_stopping(self):
        """The reference sensor keeps being read while the safe stop brakes the drive: a lockstep link advances its
        SYNCs through its own `sync` (here each one is followed by a reading stamped on the drive time it answered),
        so the rows of the stop get the shaft's speed to standstill instead of the last reading held. A reading that
        fails is left out (the stop is never disturbed); a real-time link paces its stop by the wall clock and is not
        followed (its stop's rows hold the last reading, as a gap would)."""
        link = self.safe_stop.drive          # the link itself, which the safe stop drives (not the loop's Gate)
        if self.load is None or not self.reference_signals or getattr(link, "timing", None) != "lockstep":
            yield
            return
        plain = link.sync

        def sync_and_read():
            samples = plain()
            shifted = self._run_time(samples)
            if shifted:
                try:
                    values = values_from_load(self._load_call(self.load.feedback))
                except Exception:     # a dead load link: the stop goes on, the reading is missing
                    return samples
                with self._live_lock:
                    self._reference_readings.append((shifted[-1].t_s, values))
            return samples

        link.sync = sync_and_read             # the link's own stop looks its `sync` up on the instance
        try:
            yield
        finally:
            del link.sync
