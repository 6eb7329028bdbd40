"""The drive stops itself when the bench dies: the bench produces a heartbeat (CiA 301, COB 0x700 + its node id) and
configures the drive to consume it (0x1016) and to react to its loss (0x6007 abort connection option code, 0x1029
error behaviour) before anything moves. A SIGKILLed bench process or a bench PC losing power then looks to the drive
like a lost heartbeat, and the drive's own reaction stops the motor — nothing on the bench side has to run.

At a normal end the drive's own settings are put back (consumer heartbeat first, while the bench heartbeat still
runs, so the drive does not react to the bench leaving politely).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import canopen

from drivers.contract.errors import LinkError
from drivers.contract import objects as o
from drivers.canopen.sdo import SdoAccess
from drivers.contract.comm_loss import EXTERNAL_HINT, CommLossConfig

@dataclass
class CommLossGuard:
    """Configures the drive, keeps the bench heartbeat going, and puts the drive's settings back."""

    config: CommLossConfig
    sdo: SdoAccess
    network: canopen.Network
    report: dict[str, Any] = field(default_factory=dict)
    _restore: list[tuple[int, int, int, int, bool]] = field(default_factory=list)   # (index, sub, value, size, signed)
    _task: Any = None

    def arm(self) -> dict[str, Any]:
        cfg = self.config
        if cfg.mode == "external":
            self.report = {"mode": "external", "external_stop": cfg.external_stop,
                           "note": "the bench config says the rig stops the drive by other means; nothing configured "
                                   "in the drive, nothing proved: unverified comm-loss reaction"}
            return self.report
        cob = o.HEARTBEAT + cfg.bench_node_id
        sub = self._consumer_sub()
        if sub is None:
            raise LinkError(f"{self.sdo.where}: the drive has no consumer heartbeat (0x1016): it cannot stop itself when "
                            "the bench dies; only a rig that stops the drive by other means may run it, with "
                            f"[drive] {EXTERNAL_HINT}")
        value = cfg.bench_node_id << 16 | cfg.consumer_time_ms
        self._set(o.CONSUMER_HEARTBEAT, sub, value, 4)
        self.report = {"mode": "heartbeat", "bench_heartbeat": f"0x{cob:03X} every {cfg.producer_period_s * 1e3:g} ms",
                       "consumer_heartbeat_0x1016": f"sub {sub} = 0x{value:08X} ({cfg.consumer_time_ms} ms)"}
        if self._set(o.ABORT_CONNECTION_OPTION, 0, cfg.abort_option, 2, signed=True):
            self.report["abort_connection_0x6007"] = (f"{cfg.abort_option} "
                                                     f"({o.ABORT_CONNECTION_CODES.get(cfg.abort_option, 'vendor')})")
        else:
            self.report["abort_connection_0x6007"] = "not on this drive: it reacts with its own default"
        if cfg.error_behaviour is not None:
            if self._set(o.ERROR_BEHAVIOUR, 1, cfg.error_behaviour, 1):
                self.report["error_behaviour_0x1029"] = f"sub 1 = {cfg.error_behaviour}"
        # the heartbeat starts after the drive watches for it: its first frame, now, starts the drive's monitoring
        self.resume()
        return self.report

    @property
    def producing(self) -> bool:
        return self._task is not None

    def withhold(self) -> None:
        """The drill: the bench's heartbeat stops, as if the bench had died (everything else goes on)."""
        if self._task is not None:
            self._task.stop()
            self._task = None

    def resume(self) -> None:
        """The bench's heartbeat (again): its first frame goes out now."""
        if self._task is None and self.config.mode != "external":
            cob = o.HEARTBEAT + self.config.bench_node_id
            self._task = self.network.send_periodic(cob, [o.NMT_OPERATIONAL], self.config.producer_period_s)

    def _consumer_sub(self) -> int | None:
        """The 0x1016 entry to use: one that already watches the bench's node id, else the first empty one."""
        n = self.sdo.read_standard(o.CONSUMER_HEARTBEAT, 0)
        if not n:
            return None
        entries = {k: self.sdo.read_standard(o.CONSUMER_HEARTBEAT, k) or 0 for k in range(1, n + 1)}
        mine = [k for k, v in entries.items() if (v >> 16) & 0xFF == self.config.bench_node_id]
        free = [k for k, v in entries.items() if v & 0xFFFF == 0 or (v >> 16) & 0xFF == 0]
        return (mine or free or [None])[0]

    def _set(self, index: int, sub: int, value: int, size: int, signed: bool = False) -> bool:
        before = self.sdo.read_standard(index, sub, signed=signed)
        if before is None:
            return False
        if not self.sdo.write_standard(index, sub, value, size, signed):
            return False
        self._restore.append((index, sub, before, size, signed))
        return True

    def disarm(self) -> list[str]:
        """The drive's own settings back (consumer heartbeat first), then the bench heartbeat stops."""
        errors = []
        for index, sub, value, size, signed in reversed(self._restore):
            try:
                self.sdo.write_standard(index, sub, value, size, signed)
            except LinkError as exc:
                errors.append(str(exc))
        self._restore.clear()
        self.withhold()
        return errors
