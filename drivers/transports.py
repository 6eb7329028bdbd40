"""Transport name -> (its config class, its link class): the one registry a bench config's [drive] and [load]
tables are read through and their links built from. Link classes are named, not imported, so reading a config
does not load python-can, pyserial or pymodbus."""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any

from drivers.canopen.config import CanopenDriveConfig
from drivers.contract.sections import Section
from drivers.modbus_config import ModbusRtuConfig, ModbusTcpConfig
from drivers.serial_config import SerialDriveConfig


@dataclass(frozen=True)
class Transport:
    config: type[Section]
    link: str                   # "module:Class", constructed as Class(config, base_dir[, settings])

    def link_class(self) -> Any:
        module, _, name = self.link.partition(":")
        return getattr(importlib.import_module(module), name)


DRIVE_TRANSPORTS: dict[str, Transport] = {
    "canopen": Transport(CanopenDriveConfig, "drivers.canopen.link:CanopenDriveLink"),
    "serial": Transport(SerialDriveConfig, "drivers.serial_link:SerialDriveLink"),
}
LOAD_TRANSPORTS: dict[str, Transport] = {
    "modbus-tcp": Transport(ModbusTcpConfig, "drivers.modbus_load:ModbusLoadLink"),
    "modbus-rtu": Transport(ModbusRtuConfig, "drivers.modbus_load:ModbusLoadLink"),
}
