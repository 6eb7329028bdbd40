"""A run's trips: the main thread's watch over the run loop, every cause of an abort as it is seen (told to the viewer
and the service), and which link a LinkError came from. A part of orchestrator._Run."""

from __future__ import annotations

import time
from datetime import datetime, timezone

from bench.outputs.atomic_write import json_safe
from bench.run.run_periods import STUCK_GRACE_S, SUPERVISE_POLL_S
from bench.run.run_thread import LoopThread
from bench.run.supervisor import check_status
from drivers.contract.errors import LinkError


class RunTrips:
    """Trips and the watch over the run loop (state: trips, supervisor, recorder, rerun, on_trip, _t_drive)."""

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
