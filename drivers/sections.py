"""The keys every [drive] and every [load] table has, whatever the transport; each transport's config class
(drivers.transports) adds its own."""

from __future__ import annotations

from dataclasses import dataclass

from drivers.contract import cia402
from drivers.contract.control_watch import enable_bits_problem
from drivers.contract.sections import Section, key
from drivers.contract.signals import SIGNAL_NAMES


def signal_list(value: object) -> str | None:
    if not isinstance(value, (list, tuple)) or not value or not all(isinstance(v, str) for v in value):
        return "must be a non-empty list of signal names"
    unknown = [v for v in value if v not in SIGNAL_NAMES]
    if unknown:
        return f"unknown signal(s) {', '.join(unknown)}; known: {', '.join(SIGNAL_NAMES)}"
    return None


@dataclass(frozen=True)
class DriveSection(Section):
    """[drive]: the drive under test. Comm-loss keys left None take drivers.contract.comm_loss.CommLossConfig's
    defaults."""

    SECTION = "drive"
    transport: str | None = key(None, kind="string", required=True)
    sync_period_s: float = key(0.001, kind="number", positive=True)
    heartbeat_timeout_s: float = key(0.5, kind="number", positive=True)
    trace_decimation: int = key(1, kind="integer", min=1)
    trace_signals: tuple[str, ...] | None = key(None, check=signal_list)
    eds: str | None = key(None, kind="path")       # CANopen: the object dictionary; serial: optional, its parameters
    # how the drive is told to stop itself when the bench dies (drivers.contract.comm_loss checks them)
    comm_loss: str | None = None
    external_stop: str | None = None
    consumer_time_ms: int | None = None
    abort_option: int | None = None
    drill_margin_ms: int | None = None
    standstill_mech_rad_s: float = cia402.STANDSTILL_MECH_RAD_S   # the drive counts as stopped below this
    stop_timeout_s: float = cia402.STOP_TIMEOUT_S                 # how long a stop may take
    # manufacturer statusword bits (8, 14, 15) the drive sets while it obeys the bench, watched with bit 9 (remote)
    enable_bits: tuple[int, ...] | None = key(None, check=enable_bits_problem)
    # the drive's own velocity filter time constant on its reported speed (0x606C), for the first-motion unit check
    velocity_filter_s: float | None = key(None, kind="number", min=0, max=2.0)


@dataclass(frozen=True)
class LoadSection(Section):
    """[load]: the load machine (a rig without one, a free shaft, has no [load])."""

    SECTION = "load"
    transport: str | None = key(None, kind="string", required=True)
    map: str | None = key(None, kind="path", required=True)     # its register map (config/load-machines/)
    unit_id: int = key(1, kind="integer", min=0, max=247)
    timeout_s: float = key(0.5, kind="number", positive=True)
    retries: int = key(1, kind="integer", min=0)               # resent this many times after a timeout
    comm_loss: str = key("watchdog", kind="string", choices=("watchdog", "external"))
    external_stop: str | None = None
    drill_margin_ms: int | None = key(None, kind="integer", min=10, max=10000)
