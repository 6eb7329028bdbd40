"""[load] transport = "modbus-tcp" | "modbus-rtu": the Modbus load link's settings (drivers.modbus_load)."""

from __future__ import annotations

from dataclasses import dataclass

from drivers.contract.sections import key
from drivers.sections import LoadSection


@dataclass(frozen=True)
class ModbusTcpConfig(LoadSection):
    host: str | None = key(None, kind="string", required=True)
    port: int | None = key(None, kind="integer", required=True, min=0, max=65535)


@dataclass(frozen=True)
class ModbusRtuConfig(LoadSection):
    port: str | None = key(None, kind="string", required=True)     # a serial device path or pyserial URL
    baudrate: int = key(19200, kind="integer", min=1)
