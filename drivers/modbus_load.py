"""LoadLink to a load machine (dynamometer) over Modbus TCP or Modbus RTU, with pymodbus's sync clients, driven by
the machine's register map file (drivers.contract.load_map; config/load-machines/).

The [load] section: transport "modbus-tcp" (host, port) or "modbus-rtu" (port = device path, pty path or pyserial
URL; baudrate), map (the machine's register map file), unit_id, timeout_s, retries.

Where the map has a communication watchdog, it is armed at connect with the map's timeout and kept fed by a thread
of this process, so the machine takes its torque off by itself when the bench process dies.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Mapping
from datetime import datetime, timezone
from pathlib import Path

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ModbusException
from pymodbus.pdu import ExceptionResponse

from drivers.contract.errors import LinkError
from drivers.api import attempt_all, LoadFeedback, LoadLink
from drivers.contract.load_map import LoadMode
from drivers.contract.comm_loss import EXTERNAL_HINT
from drivers.modbus_config import ModbusRtuConfig, ModbusTcpConfig
from drivers.contract.load_map import LoadMap, read_load_map, Reg
from drivers.contract.errors import ContentError

EXCEPTION_TEXT = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
                  4: "server device failure", 6: "server busy", 11: "gateway target failed to respond"}
FEEDBACK = ("speed", "torque", "status")


class ModbusLoadLink(LoadLink):
    def __init__(self, config: ModbusTcpConfig | ModbusRtuConfig | Mapping[str, Any], base_dir: Path):
        self.transport = config.get("transport") or "modbus-tcp"
        if self.transport not in ("modbus-tcp", "modbus-rtu"):
            raise ValueError(f"[load] transport: '{self.transport}' is not 'modbus-tcp' or 'modbus-rtu'")
        section = (ModbusTcpConfig if self.transport == "modbus-tcp" else ModbusRtuConfig).from_mapping(
            {**config, "transport": self.transport})
        self.config = section
        self.unit_id = int(section.unit_id)
        self.timeout_s = float(section.timeout_s)
        self.retries = int(section.retries)
        if not 0 <= self.unit_id <= 247:
            raise ValueError(f"[load] unit_id: {self.unit_id} outside 0..247")
        if self.timeout_s <= 0 or self.retries < 0:
            raise ValueError("[load] timeout_s must be > 0 and retries >= 0")
        if not section.map:
            raise ValueError("[load] map: the load machine's register map file is required (config/load-machines/)")
        map_path = Path(section.map)
        map_path = map_path if map_path.is_absolute() else Path(base_dir) / map_path
        try:
            self.map: LoadMap = read_load_map(map_path)
        except ContentError as exc:
            raise ValueError(f"{map_path}: {exc}") from None
        if self.transport == "modbus-tcp":
            self.host = str(section.host or "127.0.0.1")
            self.port = int(section.port if section.port is not None else 502)
            self.where = f"modbus-tcp {self.host}:{self.port} unit {self.unit_id}"
        else:
            port = section.port
            if not isinstance(port, str) or not port:
                raise ValueError("[load] port: a serial port path or URL is required for modbus-rtu")
            self.serial_port = port
            self.baudrate = int(section.baudrate)
            self.where = f"modbus-rtu {port} unit {self.unit_id}"
        self.base_dir = base_dir
        self.comm_loss = section.comm_loss         # "external": the rig stops it by other means
        self.external_stop = str(section.external_stop or "")
        self.drill_margin_ms = section.drill_margin_ms
        self.report: dict = {"map": self.map.name, "modes": [m.name.lower() for m in self.map.modes]}
        self._client: ModbusTcpClient | ModbusSerialClient | None = None
        self._lock = threading.Lock()          # the watchdog thread and the bench share the client
        self._keepalive_stop = threading.Event()
        self._cancel = threading.Event()       # interrupt(): a drill in progress ends at once
        self._keepalive: threading.Thread | None = None

    @property
    def modes(self) -> tuple[LoadMode, ...]:
        return self.map.modes

    def _connected_client(self) -> ModbusTcpClient | ModbusSerialClient:
        if self._client is None:
            raise LinkError(f"load machine {self.where}: link not open")
        return self._client

    def _roles_at(self, address: int, n: int) -> str:
        names = [r.role for r in self.map.registers.values()
                 if address < r.address + r.count and r.address < address + n]
        return ", ".join(names) or "unmapped"

    def _call(self, request: str, address: int, **kwargs):
        client = self._connected_client()
        n = kwargs.get("count") or len(kwargs.get("values", [0]))
        span = f"register {address}" if n == 1 else f"registers {address}..{address + n - 1}"
        what = f"{request} of {span} ({self._roles_at(address, n)})"
        try:
            with self._lock:
                response = getattr(client, request)(address, device_id=self.unit_id, **kwargs)
        except (ModbusException, OSError) as exc:       # pymodbus lets a reset connection through as OSError
            raise LinkError(f"load machine {self.where}: {what}: no valid reply within {self.timeout_s:g} s x "
                            f"{self.retries + 1}: {exc}") from None
        if isinstance(response, ExceptionResponse) or response.isError():
            code = getattr(response, "exception_code", 0)
            raise LinkError(f"load machine {self.where}: {what} refused: Modbus exception {code} "
                            f"({EXCEPTION_TEXT.get(code, 'unknown')})")
        return response

    def _read_words(self, address: int, count: int) -> list[int]:
        request = "read_holding_registers" if self.map.read_function == 3 else "read_input_registers"
        return list(self._call(request, address, count=count).registers)

    def read(self, reg: Reg) -> object:
        return reg.decode(self._read_words(reg.address, reg.count), self.map.word_order)

    def _write(self, reg: Reg, value: float) -> None:
        words = reg.encode(value, self.map.word_order)
        if len(words) == 1:
            self._call("write_register", reg.address, value=words[0])
        else:
            self._call("write_registers", reg.address, values=words)

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
            if self.map.has("version"):
                version, expect = self.read(self.map["version"]), self.map["version"].extra.get("expect")
                if expect is not None and version != expect:
                    raise LinkError(f"load machine {self.where}: register map version {version}, the map file "
                                    f"{self.map.path.name} describes version {expect}")
            name = str(self.read(self.map["identity"])) if self.map.has("identity") else self.map.name
            self._arm_watchdog()
            return name
        except LinkError:
            self.close()
            raise

    def _arm_watchdog(self) -> None:
        timeout_ms = self.map.watchdog_timeout_ms
        if self.comm_loss == "external":
            self.report["watchdog"] = (f"not used: the rig stops the machine by other means ({self.external_stop}); "
                                       "unverified comm-loss reaction")
            return
        if not timeout_ms:
            raise LinkError(no_watchdog_refusal(self.where, self.map.path.name))
        reg = self.map["watchdog"]
        self._write(reg, timeout_ms if reg.extra.get("unit", "ms") == "ms" else timeout_ms / 1000.0)
        self.report["watchdog"] = f"armed: {timeout_ms} ms (register {reg.address})"
        self._keepalive_stop.clear()
        self._keepalive = threading.Thread(target=self._feed_watchdog, args=(timeout_ms / 4000.0,),
                                           name="load-watchdog-keepalive", daemon=True)
        self._keepalive.start()

    def _stop_feeding(self) -> None:
        self._keepalive_stop.set()
        if self._keepalive is not None:
            self._keepalive.join(timeout=2.0)
            self._keepalive = None

    @property
    def drill_margin(self) -> int:
        timeout_ms = self.map.watchdog_timeout_ms or 0
        return int(self.drill_margin_ms) if self.drill_margin_ms is not None else max(100, timeout_ms // 10)

    def drill(self) -> dict:
        """The bench-death drill: enabled at zero torque, the bench stops every request (its watchdog feed too) for
        the watchdog time plus a margin, then reads the status register once (any request feeds the watchdog, so one
        read is all there is: the reaction is bounded, not timed) and expects it disabled. Then re-arms and leaves it
        at zero torque and disabled. Returns the drill's record (`result`: passed / failed with `refusal` /
        unverified)."""
        if self.comm_loss == "external":
            return {"what": "load machine", "result": "unverified", "mode": "external",
                    "external_stop": self.external_stop,
                    "note": "not drilled: the bench config states the rig's own stop chain; nothing proves it"}
        timeout_ms = self.map.watchdog_timeout_ms
        if not timeout_ms:           # refused at open already; kept for links built without open()
            return {"what": "load machine", "result": "failed",
                    "refusal": no_watchdog_refusal(self.where, self.map.path.name)}
        margin = self.drill_margin
        self.set_load(LoadMode.TORQUE, 0.0)
        self.enable(True)
        before = self.feedback()
        report = {"what": "load machine", "mode": "watchdog", "timeout_ms": timeout_ms, "margin_ms": margin,
                  "enabled_before": before.enabled}
        self._stop_feeding()
        with self._lock:                       # nothing else may reach the machine while it is left alone
            report["withheld_utc"] = datetime.now(timezone.utc).isoformat(timespec="milliseconds")
            withheld = time.monotonic()
            if self._cancel.wait((timeout_ms + margin) / 1000.0):
                raise LinkError(f"load machine {self.where}: comm-loss drill abandoned: the run is stopping")
            silent_ms = (time.monotonic() - withheld) * 1e3
        after = self.feedback()
        report.update(silent_ms=round(silent_ms, 1), enabled_after=after.enabled,
                      torque_after_nm=round(after.torque_nm, 4),
                      disabled_within_ms=round(silent_ms, 1) if not after.enabled else None)
        if after.enabled:                       # it did not stop itself: the bench does (not zero_and_disable:
            self._write(self.map["setpoint"], 0.0)  # that is the end-of-run step, counted as such)
            self.enable(False)
        self._arm_watchdog()                   # armed and fed again
        if before.enabled and not after.enabled:
            report["result"] = "passed"
            return report
        report["result"] = "failed"
        why = ("it did not report itself enabled at zero torque, so its reaction cannot be seen" if not before.enabled
               else f"it was still enabled {silent_ms:.0f} ms after the bench's last request (watchdog "
                    f"{timeout_ms} ms + margin {margin} ms)")
        report["refusal"] = (f"load machine {self.where}: comm-loss drill failed: {why}; it would keep its torque if "
                             f"the bench died. Check its watchdog register in {self.map.path.name}, or where the rig "
                             f"stops it by other means write [load] {EXTERNAL_HINT}")
        return report

    def interrupt(self) -> None:
        """From another thread: the run is being abandoned; a drill in progress ends at once (the safe stop follows)."""
        self._cancel.set()

    def _feed_watchdog(self, period_s: float) -> None:
        """Any request feeds a Modbus watchdog: read the status register while this process lives."""
        while not self._keepalive_stop.wait(period_s):
            try:
                self.read(self.map["status"])
            except Exception:                         # LinkError, a reset connection: the bench's own calls
                pass                                  # will report a dead link

    def set_load(self, mode: LoadMode, value: float) -> None:
        mode = LoadMode(mode)
        if mode not in self.map.modes:
            raise LinkError(f"load machine {self.where}: has no {mode.name.lower()} mode (its map "
                            f"{self.map.path.name} lists {', '.join(m.name.lower() for m in self.map.modes)})")
        setpoint = self.map["setpoint"]
        raw = value / float(setpoint.extra.get("scale", 1.0))
        if not self.map.has("mode"):
            self._write(setpoint, raw)
            return
        mode_reg = self.map["mode"]
        words = setpoint.encode(raw, self.map.word_order)
        if mode_reg.address + mode_reg.count == setpoint.address:     # one request: never a half-changed load
            self._call("write_registers", mode_reg.address,
                       values=mode_reg.encode(self.map.mode_value(mode), self.map.word_order) + words)
        else:
            self._write(mode_reg, self.map.mode_value(mode))
            self._write(setpoint, raw)

    def enable(self, on: bool) -> None:
        reg = self.map["enable"]
        self._write(reg, reg.extra.get("on", 1) if on else reg.extra.get("off", 0))

    def reset_fault(self) -> None:
        if self.map.has("fault_reset"):
            self._write(self.map["fault_reset"], self.map["fault_reset"].extra.get("value", 1))

    def feedback(self) -> LoadFeedback:
        regs = [self.map[r] for r in FEEDBACK]
        start = min(r.address for r in regs)
        end = max(r.address + r.count for r in regs)
        if end - start <= 32:                          # one request when the feedback registers sit together
            words = self._read_words(start, end - start)
            value = {r.role: r.decode(words[r.address - start:r.address - start + r.count], self.map.word_order)
                     for r in regs}
        else:
            value = {r.role: self.read(r) for r in regs}
        status = int(value["status"])
        bits = self.map["status"].extra
        return LoadFeedback(speed_mech_rad_s=float(value["speed"]) * self.map.speed_factor,
                            torque_nm=float(value["torque"]) * float(self.map["torque"].extra.get("scale", 1.0)),
                            enabled=bool(status >> int(bits["enabled_bit"]) & 1),
                            fault=bool(status >> int(bits["fault_bit"]) & 1))

    def zero_and_disable(self) -> None:
        """Setpoint to zero, then disable; tries both whatever the first one did."""
        attempt_all(lambda: self._write(self.map["setpoint"], 0.0), lambda: self.enable(False))

    def close(self) -> None:
        self._stop_feeding()
        if self._client is not None:
            if self.map.watchdog_timeout_ms and self.comm_loss != "external":       # a normal end: the bench leaves politely, no reaction needed
                try:
                    self._write(self.map["watchdog"], 0)
                except LinkError:
                    pass
            self._client.close()
            self._client = None


def no_watchdog_refusal(where: str, map_name: str) -> str:
    return (f"load machine {where}: its register map {map_name} has no communication watchdog: it keeps its torque "
            f"when the bench dies, and nothing can prove otherwise. Add its watchdog register to the map, or where "
            f"the rig stops it by other means write [load] {EXTERNAL_HINT}")
