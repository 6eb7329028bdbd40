"""A run's start-up on opened links: configure the drive's live and trace data, decide what is measured, arm the unit
check, prove the comm-loss reaction (drill), enable the drive and the load. A part of orchestrator._Run."""

from __future__ import annotations

import json
from dataclasses import asdict

from bench.run.drill import (DRILL_SETTINGS, DrillRefused, proved_recently, refusal as drill_refusal, remember, run_drills,
                         unverified as drill_unverified)
from drivers.contract.errors import InputError
from bench.run.run_periods import FEEDBACK_LOST_PERIODS, LIVE_SIGNALS
from bench.run.supervisor import FeedbackCheck, UnitCheck

STALE_REFERENCE_PERIODS = 2.5   # a reference reading older than this many SYNC periods is stale for the unit check
STALE_REFERENCE_MIN_S = 0.03    # real time: samples come in batches of up to 10 ms, the reading after each batch
from drivers.api import UnitsProfile
from drivers.contract.signals import SIGNAL_NAMES


class RunArming:
    """Start-up and arming, before the first motion (run on the run loop's thread)."""

    def _configure_and_enable(self) -> None:
        decimation = int(self.cfg.drive["trace_decimation"])
        self.drive.configure(tuple(n for n in LIVE_SIGNALS if n not in self.not_from_drive), self.trace_signals,
                             decimation)
        carried = self.drive.measured_signals()
        measured = (set(SIGNAL_NAMES if carried is None else carried) - self.not_from_drive) | set(self.reference_signals)
        self._arm_unit_check(self.drive.profile, measured)
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
        if carried is not None:   # what the drive's live PDOs carry must keep coming (feedback_lost)
            self.supervisor.feedback_check = FeedbackCheck(tuple(sorted(carried)), self.sync_period_s,
                                                           FEEDBACK_LOST_PERIODS)
        self._note_link_reports()
        if self.load is not None and "speed_true_mech_rad_s" in self.reference_signals:
            self.drive.set_reference_speed(lambda: self._load_call(self.load.feedback).speed_mech_rad_s)
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

    def _arm_unit_check(self, profile: UnitsProfile | None, measured: set[str]) -> None:
        """A drive in its own units: with a reference sensor, its speed and the shaft's must agree at first motion
        (UnitCheck); on a free shaft nothing can check them, so every velocity factor must have been read from the
        drive, or the bench config must say how the stated ones were checked (units_confirmed)."""
        if profile is None or profile.kind != "cia402":
            return
        if "speed_true_mech_rad_s" in measured:
            # lockstep: the reference is read while the drive waits for the next SYNC, at the same instant; real time:
            # up to a batch and a Modbus round trip later
            self.supervisor.unit_check = UnitCheck(
                skew_s=0.0 if not self.realtime else 2 * self.sync_period_s,
                lag_s=float(self.cfg.drive.get("velocity_filter_s") or 0.0),
                stale_s=max(STALE_REFERENCE_PERIODS * self.sync_period_s, STALE_REFERENCE_MIN_S if self.realtime else 0.0))
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
        (bench.run.drill); refused when one does not, shown as unverified where the config states an external stop."""
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
        self.recorder.note("drive_settings", self.drive.report)
        sync_report = self.drive.sync_report()
        if sync_report is not None:        # SYNC interval statistics at the bench, how samples were placed in time
            self.recorder.note("sync", sync_report)
        if self.load is not None:
            self.recorder.note("load_settings", self.load.report)
