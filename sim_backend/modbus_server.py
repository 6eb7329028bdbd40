"""The simulated load machine's Modbus server (TCP on 127.0.0.1, RTU on a pty), on pymodbus 3.16.

pymodbus >= 3.13 has no datastore get/setValues hooks; its SimDevice `action` callback runs before every
register access: writes are validated and applied to SimulatedDevice.set_load there, reads refresh the
feedback registers from DriveModel.load_feedback(). The server's asyncio loop runs in its own thread.
Register map: drivers.modbus_load (documented in config/od/load-machine-registers.toml).
"""

from __future__ import annotations

import asyncio
import math
import os
import select
import socket
import struct
import threading
import tty

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.api import LoadMode
from drivers.modbus_load import (
    MAP_VERSION, REG_ENABLE, REG_FAULT_CODE, REG_FAULT_RESET, REG_IDENTITY, REG_MAP_VERSION, REG_MODE,
    REG_SETPOINT, REG_SPEED, REG_STATUS, REG_TORQUE, REG_TORQUE_LIMIT, REG_VISCOUS_LIMIT, STATUS_ENABLED,
    STATUS_FAULT, float_to_regs, regs_to_float,
)
from sim_backend.device import SimulatedDevice

IDENTITY = "drivebench-sim load machine"
TORQUE_LIMIT_NM = 200.0
VISCOUS_LIMIT = 10.0          # N*m/(rad/s)
START_TIMEOUT_S = 10.0
READ_FUNCTIONS = (3, 4, 6, 16, 23)     # 6, 16, 23 read back after their write
WRITE_FUNCTIONS = (6, 16, 23)


def _sim_data() -> list[SimData]:
    u16 = DataType.UINT16
    return [
        SimData(REG_ENABLE.address, values=0, datatype=u16),
        SimData(REG_MODE.address, values=0, datatype=u16),
        SimData(REG_SETPOINT.address, values=0.0, datatype=DataType.FLOAT32),
        SimData(REG_FAULT_RESET.address, values=0, datatype=u16),
        SimData(REG_SPEED.address, values=0.0, datatype=DataType.FLOAT32, readonly=True),
        SimData(REG_TORQUE.address, values=0.0, datatype=DataType.FLOAT32, readonly=True),
        SimData(REG_STATUS.address, values=0, datatype=u16, readonly=True),
        SimData(REG_FAULT_CODE.address, values=0, datatype=u16, readonly=True),
        SimData(REG_MAP_VERSION.address, values=MAP_VERSION, datatype=u16, readonly=True),
        SimData(REG_TORQUE_LIMIT.address, values=TORQUE_LIMIT_NM, datatype=DataType.FLOAT32, readonly=True),
        SimData(REG_VISCOUS_LIMIT.address, values=VISCOUS_LIMIT, datatype=DataType.FLOAT32, readonly=True),
        SimData(REG_IDENTITY.address, values=IDENTITY.ljust(2 * REG_IDENTITY.count, "\0"),
                datatype=DataType.STRING, readonly=True),
    ]


class LoadMachineRegisters:
    """The action callback: the load machine's controller behind its registers."""

    def __init__(self, device: SimulatedDevice):
        self.device = device
        self.rejected: list[tuple[int, int, int]] = []   # (function, address, exception code) for tests/logs

    def _refresh(self, regs: list[int], base: int) -> None:
        dev = self.device
        with dev.lock:
            speed, torque = dev.model.load_feedback()
            load = dev.load
            regs[REG_SPEED.address - base:REG_SPEED.address - base + 2] = float_to_regs(speed)
            regs[REG_TORQUE.address - base:REG_TORQUE.address - base + 2] = float_to_regs(torque)
            regs[REG_STATUS.address - base] = (STATUS_ENABLED if load.enabled else 0) | (
                STATUS_FAULT if load.fault else 0)
            regs[REG_FAULT_CODE.address - base] = load.fault & 0xFFFF
            regs[REG_ENABLE.address - base] = int(load.enabled)

    def _write(self, regs: list[int], base: int, address: int, values: list[int]) -> ExcCodes | None:
        end = address + len(values)
        new = list(regs)
        new[address - base:end - base] = values

        def touched(reg) -> bool:
            return address < reg.address + reg.count and reg.address < end

        for reg in (REG_SETPOINT,):     # float pairs are written whole or not at all
            if touched(reg) and not (address <= reg.address and reg.address + reg.count <= end):
                return ExcCodes.ILLEGAL_ADDRESS
        enable = new[REG_ENABLE.address - base]
        mode = new[REG_MODE.address - base]
        value = regs_to_float(new[REG_SETPOINT.address - base:REG_SETPOINT.address - base + 2])
        if enable not in (0, 1) or new[REG_FAULT_RESET.address - base] not in (0, 1):
            return ExcCodes.ILLEGAL_VALUE
        if mode not in tuple(LoadMode) or not math.isfinite(value):
            return ExcCodes.ILLEGAL_VALUE
        if touched(REG_MODE) or touched(REG_SETPOINT):
            if LoadMode(mode) is LoadMode.TORQUE and abs(value) > TORQUE_LIMIT_NM:
                return ExcCodes.ILLEGAL_VALUE
            if LoadMode(mode) is LoadMode.BRAKE and not 0.0 <= value <= TORQUE_LIMIT_NM:
                return ExcCodes.ILLEGAL_VALUE
            if LoadMode(mode) is LoadMode.VISCOUS and not 0.0 <= value <= VISCOUS_LIMIT:
                return ExcCodes.ILLEGAL_VALUE
        dev = self.device
        with dev.lock:
            if touched(REG_FAULT_RESET) and new[REG_FAULT_RESET.address - base]:
                dev.load.fault = 0
                values[REG_FAULT_RESET.address - address] = 0      # a command, reads back 0
            if touched(REG_ENABLE) and enable and dev.load.fault:
                return ExcCodes.DEVICE_FAILURE                      # a faulted machine refuses to enable
            dev.set_load(mode=mode if touched(REG_MODE) else None,
                         value=value if touched(REG_SETPOINT) else None,
                         enabled=bool(enable) if touched(REG_ENABLE) else None)
        return None

    async def action(self, function_code: int, start_address: int, address: int, count: int,
                     registers: list[int], set_values: list[int] | list[bool] | None) -> ExcCodes | None:
        if set_values is None:
            if function_code not in READ_FUNCTIONS:
                result = ExcCodes.ILLEGAL_FUNCTION
            else:
                self._refresh(registers, start_address)
                return None
        elif function_code not in WRITE_FUNCTIONS:
            result = ExcCodes.ILLEGAL_FUNCTION
        else:
            result = self._write(registers, start_address, address, set_values)
            if result is None:
                return None
        self.rejected.append((function_code, address, int(result)))
        return result


class _LoopThread:
    """An asyncio loop in a daemon thread, with a clean stop."""

    def __init__(self, name: str):
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name=name, daemon=True)
        self.thread.start()

    def run(self, coro, timeout_s: float = START_TIMEOUT_S):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout_s)

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(START_TIMEOUT_S)
        if not self.thread.is_alive():
            self.loop.close()


class ModbusServerHandle:
    def __init__(self, device: SimulatedDevice, unit_id: int):
        self.device = device
        self.registers = LoadMachineRegisters(device)
        self.sim_device = SimDevice(unit_id, simdata=_sim_data(), action=self.registers.action)
        self._loop = _LoopThread(type(self).__name__)
        self.server = None
        self.port = 0
        self.path = ""

    def _start(self, make_server) -> None:
        async def start():
            self.server = make_server()
            await self.server.serve_forever(background=True)
        try:
            self._loop.run(start())
        except BaseException:
            self._loop.close()
            raise

    def stop(self) -> None:
        if self.server is not None:
            try:
                self._loop.run(self.server.shutdown())
            except (TimeoutError, RuntimeError):
                pass
            self.server = None
        self._loop.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


class ModbusTcpHandle(ModbusServerHandle):
    def __init__(self, device: SimulatedDevice, host: str, port: int, unit_id: int):
        super().__init__(device, unit_id)
        self._start(lambda: ModbusTcpServer(self.sim_device, address=(host, port)))
        self.host = host
        self.port = self.server.transport.sockets[0].getsockname()[1]


class NullModem:
    """Two pseudo-terminals joined back to back, like a null-modem cable: what one end writes the other reads.

    pymodbus's serial server must open a port by path, and so must the client; a single pty offers only one.
    """

    def __init__(self):
        self._fds: list[int] = []
        self.paths: list[str] = []
        self._masters: list[int] = []
        for _ in range(2):
            master, slave = os.openpty()
            tty.setraw(slave)
            os.set_blocking(master, False)
            self._masters.append(master)
            self._fds += [master, slave]             # keep the slave open: a master with no slave reads EIO
            self.paths.append(os.ttyname(slave))
        self._wake_r, self._wake_w = socket.socketpair()
        self._thread = threading.Thread(target=self._run, name="NullModem", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        a, b = self._masters
        pending = {a: bytearray(), b: bytearray()}      # bytes waiting to go out of each master
        while True:
            writers = [fd for fd, buf in pending.items() if buf]
            ready_r, ready_w, _ = select.select([a, b, self._wake_r], writers, [])
            if self._wake_r in ready_r:
                return
            for src, dst in ((a, b), (b, a)):
                if src in ready_r:
                    try:
                        pending[dst] += os.read(src, 65536)
                    except (BlockingIOError, OSError):
                        pass
            for fd in ready_w:
                try:
                    del pending[fd][:os.write(fd, pending[fd])]
                except (BlockingIOError, OSError):
                    pass

    def close(self) -> None:
        self._wake_w.send(b"x")
        self._thread.join(START_TIMEOUT_S)
        for fd in self._fds:
            try:
                os.close(fd)
            except OSError:
                pass
        self._wake_r.close()
        self._wake_w.close()


class ModbusRtuPtyHandle(ModbusServerHandle):
    def __init__(self, device: SimulatedDevice, unit_id: int, baudrate: int):
        super().__init__(device, unit_id)
        self.modem = NullModem()
        server_end, self.path = self.modem.paths
        try:
            self._start(lambda: ModbusSerialServer(self.sim_device, port=server_end, baudrate=baudrate))
        except BaseException:
            self.modem.close()
            raise

    def stop(self) -> None:
        super().stop()
        self.modem.close()


def start_modbus_tcp(device: SimulatedDevice, host: str = "127.0.0.1", port: int = 0,
                     unit_id: int = 1) -> ModbusTcpHandle:
    return ModbusTcpHandle(device, host, port, unit_id)


def start_modbus_rtu_pty(device: SimulatedDevice, unit_id: int = 1, baudrate: int = 115200) -> ModbusRtuPtyHandle:
    return ModbusRtuPtyHandle(device, unit_id, baudrate)
