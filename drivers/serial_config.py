"""[drive] transport = "serial": the serial drive link's settings (drivers.serial_link.SerialDriveLink)."""

from __future__ import annotations

from dataclasses import dataclass

from drivers.contract.sections import key
from drivers.sections import DriveSection


@dataclass(frozen=True)
class SerialDriveConfig(DriveSection):
    port: str | None = key(None, kind="string", required=True)     # a device path or a pyserial URL
    baudrate: int = key(115200, kind="integer", min=1)
    timeout_s: float = key(0.5, kind="number", positive=True)      # one attempt's wait for its reply
    retries: int = key(3, kind="integer", min=0)                   # resent this many times (docs/serial-protocol.md)
