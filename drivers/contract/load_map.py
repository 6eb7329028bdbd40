"""A load machine (dynamometer) described by data: its Modbus register map as a TOML file.

    [machine]       name, byte_order ("big"), word_order ("big": high word at the lower address), read_function
                    (3 holding | 4 input registers)
    [registers.X]   address (0-based, as on the wire), type (uint16 int16 uint32 int32 float32 string), and per role:
      enable        on, off                         the machine takes torque / free-wheels
      setpoint      scale                           register value x scale = N*m (torque/brake), N*m/(rad/s) (viscous)
      mode          torque, viscous, brake          (optional) the value of each mode it has; without it: torque only
      speed         unit ("rad/s" | "rpm"), scale   shaft speed from the machine's encoder (the rig's reference)
      torque        scale                           shaft torque from its transducer, N*m, opposing positive rotation
      status        enabled_bit, fault_bit
      fault_code    -                               (optional)
      fault_reset   value                           (optional) written to clear a latched fault
      watchdog      unit ("ms" | "s"), timeout_ms   (optional) communication watchdog, armed with timeout_ms at
                                                    connect: no request for that long -> torque off, disabled
      version       expect                          (optional) the map version the machine must report
      identity      count                           (optional, string) the machine's name
Required: enable, setpoint, speed, torque, status. config/load-machines/ holds drivebench's own simulated machine and
an example of a third-party map.
"""

from __future__ import annotations

import enum
import math
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from drivers.contract.errors import ContentError
from drivers.contract.toml_file import known_entries, read_toml_file

TYPES = {"uint16": (1, ">H"), "int16": (1, ">h"), "uint32": (2, ">I"), "int32": (2, ">i"), "float32": (2, ">f")}
ROLES = ("enable", "setpoint", "mode", "speed", "torque", "status", "fault_code", "fault_reset", "watchdog",
         "version", "identity")
REQUIRED = ("enable", "setpoint", "speed", "torque", "status")
ROLE_KEYS = {"enable": {"on", "off"}, "setpoint": {"scale"}, "mode": {"torque", "viscous", "brake"},
             "speed": {"unit", "scale"}, "torque": {"scale"}, "status": {"enabled_bit", "fault_bit"},
             "fault_code": set(), "fault_reset": {"value"}, "watchdog": {"unit", "timeout_ms"},
             "version": {"expect"}, "identity": {"count"}}
SPEED_UNITS = {"rad/s": 1.0, "rpm": math.pi / 30.0}
MAX_MAP_BYTES = 256 * 1024


class LoadMode(enum.IntEnum):
    """Load machine modes (Modbus register map in config/od/load-machine-registers.toml).

    Sign convention everywhere: the load torque T_L opposes positive rotation,
    J*dw/dt = T_e - T_L - B*w.
    """

    TORQUE = 0      # active: T_L = value, keeps its sign whatever the speed (hanging mass on a drum)
    VISCOUS = 1     # T_L = value * w, value in N*m/(rad/s) (DC generator into a resistor)
    BRAKE = 2       # passive: T_L = value * sign(w), zero at standstill (powder brake, friction)


@dataclass(frozen=True)
class Reg:
    role: str
    address: int
    type: str
    count: int                      # registers
    extra: dict[str, Any] = field(default_factory=dict)
    description: str = ""           # the map's words for it (the record names a reference signal's instrument by it)

    def encode(self, value: float, word_order: str) -> list[int]:
        if self.type == "string":
            raw = str(value).encode()[:2 * self.count].ljust(2 * self.count, b"\0")
            return [raw[i] << 8 | raw[i + 1] for i in range(0, len(raw), 2)]
        n, fmt = TYPES[self.type]
        raw = struct.pack(fmt, value if self.type == "float32" else int(round(value)))
        words = [raw[i] << 8 | raw[i + 1] for i in range(0, len(raw), 2)]
        return words if word_order == "big" else words[::-1]

    def decode(self, words: list[int], word_order: str) -> Any:
        if self.type == "string":
            return b"".join(struct.pack(">H", w) for w in words).rstrip(b"\0").decode(errors="replace")
        n, fmt = TYPES[self.type]
        words = list(words[:n]) if word_order == "big" else list(words[:n])[::-1]
        return struct.unpack(fmt, b"".join(struct.pack(">H", w) for w in words))[0]


@dataclass(frozen=True)
class LoadMap:
    path: Path
    name: str
    word_order: str
    read_function: int
    registers: dict[str, Reg]

    def __getitem__(self, role: str) -> Reg:
        return self.registers[role]

    def has(self, role: str) -> bool:
        return role in self.registers

    @property
    def modes(self) -> tuple[LoadMode, ...]:
        """The load modes the machine has (a machine without a mode register: torque only)."""
        if "mode" not in self.registers:
            return (LoadMode.TORQUE,)
        extra = self.registers["mode"].extra
        return tuple(m for m in LoadMode if m.name.lower() in extra)

    def mode_value(self, mode: LoadMode) -> int:
        return int(self.registers["mode"].extra[mode.name.lower()])

    @property
    def speed_factor(self) -> float:
        """Register value x this = mechanical rad/s."""
        reg = self.registers["speed"]
        return float(reg.extra.get("scale", 1.0)) * SPEED_UNITS[reg.extra.get("unit", "rad/s")]

    @property
    def watchdog_timeout_ms(self) -> int | None:
        reg = self.registers.get("watchdog")
        return int(reg.extra["timeout_ms"]) if reg is not None else None


def read_load_map(path: str | Path) -> LoadMap:
    """Parse and check a map file; ContentError lists every problem as (field, reason)."""
    path = Path(path)
    try:
        raw, _ = read_toml_file(path, MAX_MAP_BYTES)
    except ContentError as exc:
        raise ContentError([("(file)", str(exc))]) from None
    problems: list[tuple[str, str]] = []
    machine = raw.get("machine", {})
    if not isinstance(machine, dict):
        machine, problems = {}, [("machine", "must be a table")]
    word_order = machine.get("word_order", "big")
    if word_order not in ("big", "little"):
        problems.append(("machine.word_order", f"must be 'big' or 'little', got {word_order!r}"))
    if machine.get("byte_order", "big") != "big":
        problems.append(("machine.byte_order", "Modbus registers are big-endian: only 'big'"))
    read_function = machine.get("read_function", 3)
    if read_function not in (3, 4):
        problems.append(("machine.read_function", f"must be 3 (holding) or 4 (input registers), got {read_function!r}"))
    table = raw.get("registers", {})
    registers: dict[str, Reg] = {}
    if not isinstance(table, dict):
        problems.append(("registers", "must be a table of [registers.ROLE] tables"))
        table = {}
    for role, spec, where in known_entries(table, ROLES, "registers", "role", problems):
        if not isinstance(spec, dict):
            problems.append((where, "must be a table"))
            continue
        reg = _register(role, spec, where, problems)
        if reg is not None:
            registers[role] = reg
    for role in REQUIRED:
        if role not in registers and not any(f.startswith(f"registers.{role}") for f, _ in problems):
            problems.append((f"registers.{role}", "missing (required: " + ", ".join(REQUIRED) + ")"))
    spans = sorted((r.address, r.address + r.count, r.role) for r in registers.values())
    for (a0, e0, r0), (a1, _, r1) in zip(spans, spans[1:]):
        if a1 < e0:
            problems.append((f"registers.{r1}", f"address {a1} overlaps registers.{r0} ({a0}..{e0 - 1})"))
    if problems:
        raise ContentError(problems)
    return LoadMap(path, str(machine.get("name", path.stem)), word_order, read_function, registers)


def _register(role: str, spec: dict, where: str, problems: list[tuple[str, str]]) -> Reg | None:
    allowed = {"address", "type", "description", "access"} | ROLE_KEYS[role] | ({"count"} if role == "identity" else set())
    unknown = sorted(set(spec) - allowed)
    if unknown:
        problems.append((f"{where}.{unknown[0]}", f"unknown key (allowed: {', '.join(sorted(allowed))})"))
        return None
    address, kind = spec.get("address"), spec.get("type", "string" if role == "identity" else None)
    if not isinstance(address, int) or isinstance(address, bool) or not 0 <= address <= 0xFFFF:
        problems.append((f"{where}.address", f"must be an integer 0..65535, got {address!r}"))
        return None
    if kind not in (*TYPES, "string") or (kind == "string") != (role == "identity"):
        problems.append((f"{where}.type", f"must be one of {', '.join(TYPES)}" + (" or string" if role == "identity"
                                                                                  else "") + f", got {kind!r}"))
        return None
    count = spec.get("count", 1) if kind == "string" else TYPES[kind][0]
    if not isinstance(count, int) or count < 1 or count > 125:
        problems.append((f"{where}.count", f"must be an integer 1..125, got {count!r}"))
        return None
    extra = {k: v for k, v in spec.items() if k in ROLE_KEYS[role]}
    for key, value in extra.items():
        if key == "unit":
            units = SPEED_UNITS if role == "speed" else {"ms": 1, "s": 1000}
            if value not in units:
                problems.append((f"{where}.unit", f"must be one of {', '.join(units)}, got {value!r}"))
                return None
        elif isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            problems.append((f"{where}.{key}", f"must be a number, got {value!r}"))
            return None
        elif key == "scale" and value == 0:
            problems.append((f"{where}.scale", "must not be 0"))
            return None
    if role == "watchdog" and not isinstance(extra.get("timeout_ms"), int):
        problems.append((f"{where}.timeout_ms", "missing: the timeout the bench arms the watchdog with (ms)"))
        return None
    if role == "status" and not {"enabled_bit", "fault_bit"} <= set(extra):
        problems.append((where, "needs enabled_bit and fault_bit"))
        return None
    if role == "mode" and "torque" not in extra:
        problems.append((f"{where}.torque", "missing: the value of torque mode"))
        return None
    return Reg(role, address, kind, count, extra, str(spec.get("description", "")))
