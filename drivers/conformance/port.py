"""What the conformance suite needs of a drive's transport: a port. Four services, as CiA 402 over any fieldbus has
them — object access (SDO-like), cyclic process data (SYNC-like cycle, PDO-like frames), a liveness channel (the
bench's heartbeat the drive watches) and emergency messages — plus network management where the transport has it.

The suite (drivers.conformance.suite) is written against this protocol only; a transport brings one implementation
(CANopen: drivers.canopen.conformance_port), registered under the entry-point group `drivebench.conformance_ports`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

from drivers.contract.errors import LinkError


class ObjectAbort(Exception):
    """The drive refused an object access with an abort code (CiA 301 SDO abort codes; CoE uses the same)."""

    def __init__(self, index: int, subindex: int, code: int, verb: str):
        super().__init__(f"{verb} of 0x{index:04X}:{subindex:02X} aborted with 0x{code:08X}")
        self.index, self.subindex, self.code = index, subindex, code


class PortError(LinkError):
    """The port itself failed (no answer within the timeout, interface gone): not the drive's word."""


@dataclass
class CycleAnswer:
    """What one process-data cycle brought: the drive's cyclic frames by PDO number, decoded where known."""

    frames: dict[int, bytes] = field(default_factory=dict)      # the last frame of each PDO in the cycle
    statusword: int | None = None
    velocity_raw: int | None = None
    syncs: int = 0                                               # SYNCs sent in the cycle (lockstep: 1)
    counts: dict[int, int] = field(default_factory=dict)        # frames received per PDO number in the cycle


@dataclass(frozen=True)
class ProcessDataPdo:
    number: int
    objects: tuple[tuple[int, int, int], ...]      # (index, subindex, bits)
    sync: bool                                     # sent on every cycle (SYNC), else event-driven
    event_timer_ms: int = 0


class ConformancePort(Protocol):
    where: str
    period_s: float                                 # process-data cycle
    timing: str                                     # "lockstep" (a simulator: drive time per cycle) | "realtime"

    # connection --------------------------------------------------------------------------------------------
    def open(self) -> dict[str, Any]:
        """Connect; wait (bounded) for a drive still booting. Returns identity and how the drive came up:
        {"identity": {...}, "boot": {"answered_after_s", "boot_up_seen", "boot_up_after_s"}}."""
    def close(self) -> None: ...

    # object access -----------------------------------------------------------------------------------------
    def has(self, index: int, subindex: int = 0) -> bool:
        """The drive answers a read of this object (asked once, remembered)."""
    def read(self, index: int, subindex: int = 0, signed: bool = False) -> int:
        """ObjectAbort when refused, PortError when unanswered."""
    def read_bytes(self, index: int, subindex: int = 0) -> bytes: ...
    def write(self, index: int, subindex: int, value: int, size: int, signed: bool = False) -> None: ...
    def write_bytes(self, index: int, subindex: int, data: bytes) -> None: ...

    # units -------------------------------------------------------------------------------------------------
    def to_drive_velocity(self, speed_mech_rad_s: float) -> int: ...
    def from_drive_velocity(self, value: int) -> float: ...

    # cyclic process data ------------------------------------------------------------------------------------
    def start_process_data(self) -> list[ProcessDataPdo]:
        """The drive's cyclic frames set up (its own mapping; sent on SYNC where it allows, else event-driven)."""
    def has_command_frame(self) -> bool:
        """A cyclic command frame (RPDO) carries the target."""
    def set_command(self, controlword: int | None = None, target: int | None = None) -> None:
        """What the command frame carries from now on (controlword, target velocity in drive units); where no
        command frame carries the target, it is written by object access."""
    def cycle(self, sync: bool = True, command: bool = True) -> CycleAnswer:
        """One cycle: the command frame (unless `command` is False), the SYNC (unless `sync` is False), and what
        the drive sent for it."""
    def remap(self, number: int, objects: list[tuple[int, int, int]]) -> None:
        """Transmit PDO `number` mapped to `objects` in the transport's prescribed order; ObjectAbort if refused."""
    def pdo_mapping(self, number: int) -> list[tuple[int, int, int]]: ...
    def restore_process_data(self) -> list[str]:
        """The drive's own process-data parameters back; what could not be restored, as text."""

    # liveness and emergencies -------------------------------------------------------------------------------
    def arm_liveness(self, timeout_ms: int) -> dict[str, Any]:
        """The drive watches the bench's liveness with this timeout; the bench's liveness runs."""
    def withhold_liveness(self) -> None: ...
    def resume_liveness(self) -> None: ...
    def disarm_liveness(self) -> list[str]: ...
    def take_emcy(self) -> list[tuple[int, int]]:
        """(error code, error register) received since the last call."""
    def drive_liveness(self) -> tuple[int | None, float]:
        """(the drive's last reported network state, monotonic time it came)."""

    # network management -------------------------------------------------------------------------------------
    def network_reset(self, what: str, timeout_s: float) -> float | None:
        """`what`: "node" | "communication". Seconds until the drive's boot-up message, None without one."""
    def network_operational(self) -> None: ...
    def network_stop(self) -> None: ...
    def bus_off_recovery(self) -> str | None:
        """Put the bench's controller through bus-off and recovery; None where the interface cannot (a reason is
        given by `bus_off_reason`)."""
    bus_off_reason: str
