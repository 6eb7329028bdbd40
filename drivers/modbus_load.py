"""LoadLink to a load machine (dynamometer) over Modbus TCP or Modbus RTU, with pymodbus's sync clients.

Register map: config/od/load-machine-registers.toml (the constants below; a test keeps both equal).
One address space of holding registers: read with FC3 (FC4 reads the same), write with FC6/FC16.
float32 values take two registers, IEEE-754, high word first ("ABCD").

The [load] section: transport "modbus-tcp" (host, port) or "modbus-rtu" (port = device path, pty path or
pyserial URL; baudrate), unit_id, timeout_s, retries.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ModbusException
from pymodbus.pdu import ExceptionResponse

from drivers.api import LinkError, LoadFeedback, LoadMode, attempt_all


@dataclass(frozen=True)
class Register:
    name: str
    address: int
    kind: str          # "uint16" | "float32" | "string"
    access: str        # "rw" | "ro"
    count: int = 1     # registers


REG_ENABLE = Register("enable", 0, "uint16", "rw")
REG_MODE = Register("mode", 1, "uint16", "rw")
REG_SETPOINT = Register("setpoint", 2, "float32", "rw", 2)
REG_FAULT_RESET = Register("fault_reset", 4, "uint16", "rw")
REG_SPEED = Register("speed_mech_rad_s", 16, "float32", "ro", 2)
REG_TORQUE = Register("torque_nm", 18, "float32", "ro", 2)
REG_STATUS = Register("status", 20, "uint16", "ro")
REG_FAULT_CODE = Register("fault_code", 21, "uint16", "ro")
REG_MAP_VERSION = Register("map_version", 32, "uint16", "ro")
REG_TORQUE_LIMIT = Register("torque_limit_nm", 33, "float32", "ro", 2)
REG_VISCOUS_LIMIT = Register("viscous_limit_nm_s_per_rad", 35, "float32", "ro", 2)
REG_IDENTITY = Register("identity", 40, "string", "ro", 16)

REGISTERS: tuple[Register, ...] = (REG_ENABLE, REG_MODE, REG_SETPOINT, REG_FAULT_RESET, REG_SPEED, REG_TORQUE,
                                   REG_STATUS, REG_FAULT_CODE, REG_MAP_VERSION, REG_TORQUE_LIMIT,
                                   REG_VISCOUS_LIMIT, REG_IDENTITY)
STATUS_ENABLED = 1 << 0
STATUS_FAULT = 1 << 1
MAP_VERSION = 1

EXCEPTION_TEXT = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
                  4: "server device failure", 6: "server busy", 11: "gateway target failed to respond"}


def register_at(address: int) -> Register | None:
    return next((r for r in REGISTERS if r.address <= address < r.address + r.count), None)


def float_to_regs(value: float) -> list[int]:
    raw = struct.pack(">f", value)
    return [raw[0] << 8 | raw[1], raw[2] << 8 | raw[3]]


def regs_to_float(regs: list[int]) -> float:
    return struct.unpack(">f", struct.pack(">HH", regs[0], regs[1]))[0]


def regs_to_str(regs: list[int]) -> str:
    return b"".join(struct.pack(">H", r) for r in regs).rstrip(b"\0").decode(errors="replace")


class ModbusLoadLink:
    def __init__(self, section: dict, base_dir: Path):
        self.transport = section.get("transport", "modbus-tcp")
        if self.transport not in ("modbus-tcp", "modbus-rtu"):
            raise ValueError(f"[load] transport: '{self.transport}' is not 'modbus-tcp' or 'modbus-rtu'")
        self.unit_id = int(section.get("unit_id", 1))
        self.timeout_s = float(section.get("timeout_s", 0.5))
        self.retries = int(section.get("retries", 1))
        if not 0 <= self.unit_id <= 247:
            raise ValueError(f"[load] unit_id: {self.unit_id} outside 0..247")
        if self.timeout_s <= 0 or self.retries < 0:
            raise ValueError("[load] timeout_s must be > 0 and retries >= 0")
        if self.transport == "modbus-tcp":
            self.host = str(section.get("host", "127.0.0.1"))
            self.port = int(section.get("port", 502))
            self.where = f"modbus-tcp {self.host}:{self.port} unit {self.unit_id}"
        else:
            port = section.get("port")
            if not isinstance(port, str) or not port:
                raise ValueError("[load] port: a serial port path or URL is required for modbus-rtu")
            self.serial_port = port
            self.baudrate = int(section.get("baudrate", 19200))
            self.where = f"modbus-rtu {port} unit {self.unit_id}"
        self.base_dir = base_dir
        self._client: ModbusTcpClient | ModbusSerialClient | None = None

    def _connected_client(self) -> ModbusTcpClient | ModbusSerialClient:
        if self._client is None:
            raise LinkError(f"load machine {self.where}: link not open")
        return self._client

    def _call(self, request: str, address: int, **kwargs):
        client = self._connected_client()
        n = kwargs.get("count") or len(kwargs.get("values", [0]))
        names = list(dict.fromkeys(r.name if (r := register_at(a)) else "unmapped"
                                   for a in range(address, address + n)))
        span = f"register {address}" if n == 1 else f"registers {address}..{address + n - 1}"
        what = f"{request} of {span} ({', '.join(names)})"
        try:
            response = getattr(client, request)(address, device_id=self.unit_id, **kwargs)
        except ModbusException as exc:
            raise LinkError(f"load machine {self.where}: {what}: no valid reply within {self.timeout_s:g} s x {self.retries + 1}: {exc}") from None
        if isinstance(response, ExceptionResponse) or response.isError():
            code = getattr(response, "exception_code", 0)
            raise LinkError(f"load machine {self.where}: {what} refused: Modbus exception {code} ({EXCEPTION_TEXT.get(code, 'unknown')})")
        return response

    def read(self, reg: Register, count: int | None = None) -> list[int]:
        return list(self._call("read_holding_registers", reg.address, count=count or reg.count).registers)

    def open(self) -> str:
        if self.transport == "modbus-tcp":
            self._client = ModbusTcpClient(self.host, port=self.port, timeout=self.timeout_s, retries=self.retries)
        else:
            self._client = ModbusSerialClient(self.serial_port, baudrate=self.baudrate, timeout=self.timeout_s,
                                              retries=self.retries)
        if not self._client.connect():
            self._client = None
            raise LinkError(f"load machine {self.where}: cannot connect")
        try:
            (version,) = self.read(REG_MAP_VERSION)
            if version != MAP_VERSION:
                raise LinkError(f"load machine {self.where}: register map version {version}, this bench knows "
                                f"{MAP_VERSION}")
            return regs_to_str(self.read(REG_IDENTITY))
        except LinkError:
            self.close()
            raise

    def set_load(self, mode: LoadMode, value: float) -> None:
        self._call("write_registers", REG_MODE.address, values=[int(LoadMode(mode))] + float_to_regs(value))

    def enable(self, on: bool) -> None:
        self._call("write_register", REG_ENABLE.address, value=1 if on else 0)

    def reset_fault(self) -> None:
        self._call("write_register", REG_FAULT_RESET.address, value=1)

    def feedback(self) -> LoadFeedback:
        regs = self.read(REG_SPEED, REG_FAULT_CODE.address + 1 - REG_SPEED.address)
        status = regs[4]
        return LoadFeedback(speed_mech_rad_s=regs_to_float(regs[0:2]), torque_nm=regs_to_float(regs[2:4]),
                            enabled=bool(status & STATUS_ENABLED), fault=bool(status & STATUS_FAULT))

    def zero_and_disable(self) -> None:
        """Setpoint to zero, then disable; tries both whatever the first one did."""
        attempt_all(lambda: self._call("write_registers", REG_SETPOINT.address, values=float_to_regs(0.0)),
                    lambda: self.enable(False))

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None
