"""[drive] transport = "canopen": the CANopen drive link's settings (drivers.canopen.link.CanopenDriveLink)."""

from __future__ import annotations

from dataclasses import dataclass

from drivers.contract.sections import key
from drivers.sections import DriveSection


def _channel(value: object) -> str | None:
    # python-can interfaces number their channels (pcan, kvaser) or name them
    if isinstance(value, bool) or not isinstance(value, (str, int)):
        return f"must be a string, got {type(value).__name__} {value!r}"
    return None


@dataclass(frozen=True)
class CanopenDriveConfig(DriveSection):
    """Profile, PDO and comm-loss keys are checked by drivers.canopen.profile.config_keys (and against the EDS by
    check_section); None: not stated, the drive or the profile decides."""

    eds: str | None = key(None, kind="path", required=True)      # the object dictionary the link loads
    interface: str | None = key(None, kind="string", required=True)
    channel: str | int | None = key(None, required=True, check=_channel)
    bitrate: int = key(1_000_000, kind="integer", min=1)
    node_id: int | None = key(None, kind="integer", required=True, min=1, max=127)
    sdo_timeout_s: float = key(0.5, kind="number", positive=True)
    can: dict | None = None                     # python-can Bus() options
    boot_timeout_s: float = 0.0                 # how long the drive may take to boot (0: up when the bench connects)
    velocity_mode: str = "auto"                 # "auto" | "pv" | "csv"
    pdo: str = "auto"                           # drivers.canopen.pdo.POLICIES
    # the drive profile (drivers.canopen.profile)
    profile: str = "auto"                       # "auto" | "cia402" | "drivebench"
    velocity_unit: str | None = None
    velocity_side: str | None = None
    units_confirmed: str | None = None
    encoder_increments_per_rev: float | None = None
    gear_ratio: tuple[float, float] | None = None
    rated_torque_nm: float | None = None
    rated_current_a: float | None = None
    signals: dict | None = None
    error_behaviour: int | None = None
    bench_node_id: int | None = None
    # the last resort's NMT command where the drive's manual says it stops the power stage (drivers.canopen.closing)
    last_resort_nmt: str = key("none", kind="string", choices=("none", "stop", "reset"))
