"""The simulated load machine's Modbus server (TCP on 127.0.0.1, RTU on a pty), on pymodbus 3.16.

It serves drivebench's own register map, config/load-machines/drivebench-sim.toml, read with drivers.contract.load_map like
any map (the file is the single description of the machine's registers). pymodbus >= 3.13 has no datastore
get/setValues hooks; its SimDevice `action` callback runs before every register access: writes are validated and
applied to SimulatedDevice.set_load there, reads refresh the feedback registers from DriveModel.load_feedback().
Every request feeds the machine's communication watchdog. The server's asyncio loop runs in its own thread.
"""

from __future__ import annotations

import asyncio
import math
import os
import select
import socket
import threading
import tty
from pathlib import Path

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.contract.load_map import LoadMode
from drivers.contract.load_map import LoadMap, read_load_map, Reg
from sim_backend.device import SimulatedDevice

MAP_FILE = Path(__file__).resolve().parent.parent / "config" / "load-machines" / "drivebench-sim.toml"
IDENTITY = "drivebench-sim load machine"
TORQUE_LIMIT_NM = 200.0
VISCOUS_LIMIT = 10.0          # N*m/(rad/s)
START_TIMEOUT_S = 10.0
READ_FUNCTIONS = (3, 4, 6, 16, 23)     # 6, 16, 23 read back after their write
WRITE_FUNCTIONS = (6, 16, 23)
READ_ONLY = ("speed", "torque", "status", "fault_code", "version", "identity")
DATATYPES = {"uint16": DataType.UINT16, "int16": DataType.INT16, "uint32": DataType.UINT32,
             "int32": DataType.INT32, "float32": DataType.FLOAT32, "string": DataType.STRING}


def load_map() -> LoadMap:
    return read_load_map(MAP_FILE)


def _sim_data(regs: LoadMap) -> list[SimData]:
    initial = {"version": regs["version"].extra.get("expect", 0) if regs.has("version") else 0,
               "identity": IDENTITY.ljust(2 * regs["identity"].count, "\0") if regs.has("identity") else ""}
    return [SimData(r.address, values=initial.get(r.role, 0.0 if r.type == "float32" else 0),
                    datatype=DATATYPES[r.type], readonly=r.role in READ_ONLY)
            for r in sorted(regs.registers.values(), key=lambda r: r.address)]


class LoadMachineRegisters:
    """The action callback: the load machine's controller behind its registers."""

    def __init__(self, device: SimulatedDevice, regs: LoadMap | None = None):
        self.device = device
        self.map = regs or load_map()
        self.rejected: list[tuple[int, int, int]] = []   # (function, address, exception code) for tests/logs

    def _put(self, words: list[int], base: int, reg: Reg, value) -> None:
        if reg.address >= base and reg.address + reg.count <= base + len(words):
            words[reg.address - base:reg.address - base + reg.count] = reg.encode(value, self.map.word_order)

    def _get(self, words: list[int], base: int, reg: Reg):
        return reg.decode(words[reg.address - base:reg.address - base + reg.count], self.map.word_order)

    def _refresh(self, regs: list[int], base: int) -> None:
        dev, m = self.device, self.map
        with dev.lock:
            speed, torque = dev.model.load_feedback()
            load = dev.load
            bits = m["status"].extra
            self._put(regs, base, m["speed"], speed / m.speed_factor)
            self._put(regs, base, m["torque"], torque / float(m["torque"].extra.get("scale", 1.0)))
            self._put(regs, base, m["status"], (int(load.enabled) << int(bits["enabled_bit"]))
                      | (int(bool(load.fault)) << int(bits["fault_bit"])))
            if m.has("fault_code"):
                self._put(regs, base, m["fault_code"], load.fault & 0xFFFF)
            self._put(regs, base, m["enable"], m["enable"].extra["on"] if load.enabled else m["enable"].extra["off"])

    def _write(self, regs: list[int], base: int, address: int, values: list[int]) -> ExcCodes | None:
        m = self.map
        end = address + len(values)
        new = list(regs)
        new[address - base:end - base] = values

        def touched(reg) -> bool:
            return address < reg.address + reg.count and reg.address < end

        for reg in m.registers.values():     # multi-register values are written whole or not at all
            if reg.count > 1 and touched(reg) and not (address <= reg.address and reg.address + reg.count <= end):
                return ExcCodes.ILLEGAL_ADDRESS
        def touched_role(role: str) -> bool:        # optional registers (mode, fault reset, watchdog) may be absent
            return m.has(role) and touched(m[role])

        enable = self._get(new, base, m["enable"])
        value = float(self._get(new, base, m["setpoint"])) * float(m["setpoint"].extra.get("scale", 1.0))
        reset = self._get(new, base, m["fault_reset"]) if m.has("fault_reset") else 0
        if enable not in (m["enable"].extra["on"], m["enable"].extra["off"]) or reset not in (0, 1):
            return ExcCodes.ILLEGAL_VALUE
        if m.has("mode"):
            modes = {m.mode_value(mode): mode for mode in m.modes}
            mode_value = self._get(new, base, m["mode"])
        else:                                        # a torque-only machine
            modes, mode_value = {int(LoadMode.TORQUE): LoadMode.TORQUE}, int(LoadMode.TORQUE)
        if mode_value not in modes or not math.isfinite(value):
            return ExcCodes.ILLEGAL_VALUE
        mode = modes[mode_value]
        if touched_role("mode") or touched(m["setpoint"]):
            if mode is LoadMode.TORQUE and abs(value) > TORQUE_LIMIT_NM:
                return ExcCodes.ILLEGAL_VALUE
            if mode is LoadMode.BRAKE and not 0.0 <= value <= TORQUE_LIMIT_NM:
                return ExcCodes.ILLEGAL_VALUE
            if mode is LoadMode.VISCOUS and not 0.0 <= value <= VISCOUS_LIMIT:
                return ExcCodes.ILLEGAL_VALUE
        dev = self.device
        with dev.lock:
            if touched_role("watchdog"):
                timeout = float(self._get(new, base, m["watchdog"]))
                dev.load_watchdog.arm(timeout / 1000.0)
                dev.load_watchdog.touch()
                if timeout:
                    dev.arm_watchdogs()
            if touched_role("fault_reset") and reset:
                dev.load.fault = 0
                values[m["fault_reset"].address - address] = 0      # a command, reads back 0
            is_on = enable == m["enable"].extra["on"]
            if touched(m["enable"]) and is_on and dev.load.fault:
                return ExcCodes.DEVICE_FAILURE                      # a faulted machine refuses to enable
            if touched_role("mode") or touched(m["setpoint"]) or touched(m["enable"]):
                dev.set_load(mode=int(mode) if touched_role("mode") else None,
                             value=value if touched(m["setpoint"]) else None,
                             enabled=is_on if touched(m["enable"]) else None)
        return None

    async def action(self, function_code: int, start_address: int, address: int, count: int,
                     registers: list[int], set_values: list[int] | list[bool] | None) -> ExcCodes | None:
        self.device.load_watchdog.touch()           # any request feeds the communication watchdog
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
    def __init__(self, device: SimulatedDevice, unit_id: int, regs: LoadMap | None = None):
        self.device = device
        self.registers = LoadMachineRegisters(device, regs)
        self.sim_device = SimDevice(unit_id, simdata=_sim_data(self.registers.map), action=self.registers.action)
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

    def dead(self) -> str | None:
        """Why the endpoint no longer serves (its loop ended without stop()), or None."""
        if self.server is not None and not self._loop.thread.is_alive():
            return f"{type(self).__name__}: its event loop ended"
        return None

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
    def __init__(self, device: SimulatedDevice, host: str, port: int, unit_id: int, regs: LoadMap | None = None):
        super().__init__(device, unit_id, regs)
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
    def __init__(self, device: SimulatedDevice, unit_id: int, baudrate: int, regs: LoadMap | None = None):
        super().__init__(device, unit_id, regs)
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
                     unit_id: int = 1, regs: LoadMap | None = None) -> ModbusTcpHandle:
    """regs: the machine's register map (default: drivebench-sim.toml)."""
    return ModbusTcpHandle(device, host, port, unit_id, regs)


def start_modbus_rtu_pty(device: SimulatedDevice, unit_id: int = 1, baudrate: int = 115200,
                         regs: LoadMap | None = None) -> ModbusRtuPtyHandle:
    return ModbusRtuPtyHandle(device, unit_id, baudrate, regs)
