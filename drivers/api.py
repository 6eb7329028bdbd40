"""What the bench needs from a drive and from a load machine, whatever the transport.

drivers.canopen_link and drivers.serial_link implement DriveLink; drivers.modbus_load implements
LoadLink. The bench talks only to these protocols, so a real rig and the simulator run the same code.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Protocol, Sequence

import numpy as np

from drivers.contract.cia402 import FAULT_RESET_POLICIES
from drivers.contract.errors import LinkError
from drivers.contract.load_map import LoadMode


TIMINGS = ("lockstep", "realtime")


@dataclass(frozen=True)
class LinkSettings:
    """The bench's own settings a drive link obeys ([bench] timing and fault_reset), for every bench config.

    timing: "lockstep" (one SYNC per sync() call, the drive advances only then: a simulator) or "realtime" (SYNC on
    the wall clock). fault_reset: "once" (a drive found in FAULT is reset once at enable) or "never"."""

    timing: str = "lockstep"
    fault_reset: str = "once"

    def __post_init__(self) -> None:
        if self.timing not in TIMINGS:
            raise ValueError(f"timing: {self.timing!r} is not one of {', '.join(TIMINGS)}")
        if self.fault_reset not in FAULT_RESET_POLICIES:
            raise ValueError(f"fault_reset: {self.fault_reset!r} is not one of {', '.join(FAULT_RESET_POLICIES)}")


def attempt_all(*actions: Callable[[], object]) -> None:
    """Run every action even when an earlier one fails (a stop sequence); then raise one LinkError for all."""
    errors = []
    for action in actions:
        try:
            action()
        except LinkError as exc:
            errors.append(str(exc))
    if errors:
        raise LinkError("; ".join(errors))


@dataclass(frozen=True)
class DriveIdentity:
    vendor_id: int
    product_code: int
    revision: int
    serial: int
    device_name: str
    firmware_version: str
    has_trace_recorder: bool


@dataclass(frozen=True)
class LiveSample:
    """One decimated live sample; t_s is the drive's own clock."""

    t_s: float
    values: dict[str, float]


@dataclass
class DriveStatus:
    state: str                  # CiA 402 state name, e.g. "OPERATION ENABLED", "FAULT"
    fault: bool
    heartbeat_ok: bool
    emcy: list[tuple[int, str]] = field(default_factory=list)  # (error code, text) received since last call
    warning: bool = False       # CiA 402 statusword bit 7: the drive warns (temperature, limits...) and runs on
    control_lost: str | None = None   # statusword bit 9 (remote) or a [drive] enable bit dropped while powered
    bus_drop: str | None = None       # the bus dropped for a moment (no frame at all), the drive still operational


class UnitsProfile(Protocol):
    """What the bench checks of a drive's units before motion (drivers.canopen.profile.DriveProfile gives it)."""
    kind: str                       # "cia402" (the drive's own units) | "drivebench"
    unread: tuple[str, ...]         # velocity factors the drive did not report: stated in the config or CiA default
    units_confirmed: str | None     # the bench config's word on how the stated ones were checked


class DriveLink(Protocol):
    """A drive link subclasses DriveLink. The members with a body are features a drive may lack: the body is what
    the bench gets from a drive without the feature (a link overrides what its drive has)."""

    report: dict[str, Any]                   # what the link read from the drive and set in it, for the record
    profile: UnitsProfile | None = None      # a CiA 402 drive's resolved profile; None: a drivebench protocol drive
    control_period_s: float | None = None    # the drive's control period (trace rows: decimation x this), once open
    time_base: str = "receive time"          # how live samples are placed: "drive clock" | "sync count" |
                                             # "sync answered" | "receive time"

    def measured_signals(self) -> frozenset[str] | None:
        """The signals the drive's live data carry, which must keep coming (feedback lost); None: every signal, and
        nothing to check."""
        return None

    def sync_report(self) -> dict[str, Any] | None:
        """SYNC interval statistics at the bench and how samples were placed in time; None: nothing to report."""
        return None

    def now_s(self) -> float | None:
        """The drive time of the last SYNC sent, on the drive's clock; None: the link does not know it."""
        return None

    def set_reference_speed(self, speed: Callable[[], float | None]) -> None:
        """A reference sensor's shaft speed, for a drive that checks its units against it at first motion; a drive
        without the check ignores it."""
        return None

    def drill(self, before_withhold: Callable[[], None] | None = None) -> dict[str, Any] | None:
        """The comm-loss drill: withhold the bench's traffic and observe the drive's own reaction (the record's
        comm_loss drive entry); `before_withhold` is called just before. None: the link cannot drill, so the
        bench's death cannot be shown safe."""
        return None

    def secure(self) -> str | None:
        """After the safe stop: the drive confirmed disabled, else the last resort (drivers.contract.last_resort: its
        comm-loss reaction left armed and let act, the shaft watched); the one line to show, None when nothing was
        needed. close() restores the drive's settings only when this ended with the drive disabled."""
        return None

    def keepalive(self) -> None:
        """One request now, for a drive whose watchdog sees only requests (while the load machine is drilled); a
        drive with a heartbeat consumer needs nothing."""
        return None

    def interrupt(self) -> None:
        """From another thread: a call in progress ends at once (the run loop is being abandoned, the safe stop
        follows)."""
        return None

    def open(self) -> DriveIdentity: ...
    def configure(self, live_signals: Sequence[str], trace_signals: Sequence[str], trace_decimation: int) -> None: ...
    def enable_velocity_mode(self) -> None: ...
    def set_speed_ref(self, speed_mech_rad_s: float) -> None: ...
    def write_parameter(self, name: str, value: float) -> None:
        """Write a named manufacturer object (test hook, firmware parameter, simulator plant injection)."""
        ...
    def sync(self) -> list[LiveSample]:
        """Lockstep: send one SYNC and return its samples. Real time: return samples received since last call."""
        ...
    def fetch_trace(self) -> dict[str, np.ndarray] | None:
        """New trace-recorder rows since the last call (columns: t_s + signals); None without a recorder."""
        ...
    def status(self) -> DriveStatus: ...
    def begin_quick_stop(self) -> None:
        """The quick-stop command alone, confirmed, without waiting for standstill (the safe stop gives it before it
        touches the load machine); quick_stop() then only waits."""
        ...
    def quick_stop(self) -> None: ...
    def disable(self) -> None: ...
    def close(self) -> None: ...


@dataclass(frozen=True)
class LoadFeedback:
    speed_mech_rad_s: float
    torque_nm: float
    enabled: bool
    fault: bool


class LoadLink(Protocol):
    """A load link subclasses LoadLink; members with a body as in DriveLink."""

    report: dict[str, Any]                   # what the link read from the machine and set in it, for the record
    map: Any = None                          # its register map (drivers.contract.load_map.LoadMap), for the record; None: none
    modes: tuple[LoadMode, ...] = ()         # the modes the machine has; empty: every LoadMode

    def drill(self) -> dict[str, Any] | None:
        """The load machine's comm-loss drill (the record's comm_loss load entry); None: it cannot drill."""
        return None

    def interrupt(self) -> None:
        """From another thread: a call in progress ends at once (the run is being abandoned)."""
        return None

    def open(self) -> str: ...
    def set_load(self, mode: LoadMode, value: float) -> None: ...
    def enable(self, on: bool) -> None: ...
    def feedback(self) -> LoadFeedback: ...
    def zero_and_disable(self) -> None: ...
    def close(self) -> None: ...
