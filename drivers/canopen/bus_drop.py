"""A CAN bus that drops for a moment (a connector, the termination, the interface's bus-off) looks like a drive that
stopped answering: no TPDO for a string of SYNCs, no heartbeat, no EMCY, and afterwards the drive is still NMT
OPERATIONAL as if nothing happened. Named as what it is (trip `bus_drop`), not left to show up only as missing rows."""

from __future__ import annotations

from dataclasses import dataclass

MIN_PERIODS = 5          # a gap of at least this many SYNC periods ...
MIN_GAP_S = 0.05         # ... and at least this long (the bench's own hiccups are shorter)
NMT_OPERATIONAL = 0x05
CONFIRM_S = 1.0          # the SYNC timeline counts a gap's SYNCs unanswered within its window (0.5 s) after it


@dataclass
class BusDropWatch:
    sync_period_s: float
    lost: str | None = None
    heartbeat_at: float = 0.0
    _last_tpdo: float | None = None
    _emcy: int = 0
    _emcy_at_last_tpdo: int = 0
    _candidate: tuple[float, int] | None = None    # (gap, unanswered count when it ended)
    _candidate_at: float = 0.0

    def reset(self) -> None:
        """From now on (the drill's silence and the enable's SDO round trips are no bus drop)."""
        self.lost, self._last_tpdo, self._candidate = None, None, None

    def emcy(self) -> None:
        self._emcy += 1

    def tpdo(self, now: float, heartbeat_state: int | None, unanswered: int | None) -> None:
        """A TPDO stamped `now` by the interface (its receive time, not when this process got to it: a bench that
        stalled gets a backlog of frames, not a gap). `unanswered`: the SYNCs the bench's timeline has counted without
        an answer (drivers.canopen.sync.SyncTimeline; None: not known). A gap is a bus drop once the SYNCs in it turn
        out unanswered — a drive (or simulator) that stalled answers them late, all of them."""
        last, self._last_tpdo = self._last_tpdo, now
        emcy_in_gap, self._emcy_at_last_tpdo = self._emcy != self._emcy_at_last_tpdo, self._emcy
        if self.lost is not None or unanswered is None:
            return
        if self._candidate is not None:
            gap, before = self._candidate
            if unanswered - before >= MIN_PERIODS:
                self.lost = (f"the CAN bus dropped for {gap * 1e3:.0f} ms: no frame from the drive ({unanswered - before} "
                             f"SYNCs unanswered, no heartbeat, no EMCY), then back with the drive still NMT "
                             f"OPERATIONAL: a bus drop (connector, termination, the interface's bus-off), and the run "
                             f"went that long without speed feedback")
            elif now - self._candidate_at > CONFIRM_S:
                self._candidate = None           # answered late: a stall, not a drop
        if last is None:
            return
        gap = now - last
        if gap < max(MIN_GAP_S, MIN_PERIODS * self.sync_period_s):
            return
        heard_in_gap = last < self.heartbeat_at < now
        if heard_in_gap or emcy_in_gap or heartbeat_state not in (None, NMT_OPERATIONAL):
            return                   # the drive spoke (a TPDO stopped, a fault): not the bus
        self._candidate, self._candidate_at = (gap, unanswered), now
