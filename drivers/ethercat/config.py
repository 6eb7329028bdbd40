"""[drive] transport = "ethercat": the EtherCAT drive link's settings (drivers.ethercat.link.EthercatDriveLink).

The comm-loss keys of every [drive] apply: consumer_time_ms is the SM (process-data) watchdog time the bench writes
to the slave's 0x0420, abort_option the drive's 0x6007 reaction to it."""

from __future__ import annotations

from dataclasses import dataclass

from drivers.contract.sections import key
from drivers.sections import DriveSection


@dataclass(frozen=True)
class EthercatDriveConfig(DriveSection):
    interface: str | None = key(None, kind="string", required=True)   # the network port the drive is on, e.g. enp3s0
    slave: int = key(1, kind="integer", min=1)                        # position on the bus (1: next to the master)
    esi: str | None = key(None, kind="path")                         # the drive's ESI file: its identity is checked
    cycle_s: float = key(0.001, kind="number", positive=True)         # free-run process-data cycle (real time)
    sdo_timeout_s: float = key(1.0, kind="number", positive=True)
    state_timeout_s: float = key(3.0, kind="number", positive=True)   # each AL state change
    velocity_unit: str | None = key(None, kind="string")             # stated where the drive has no 0x60A9
