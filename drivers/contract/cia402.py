"""The CiA 402 drive profile (IEC 61800-7-201) written once, as data, for the bench's links and the simulated drive.

- `State`, `decode`, `state_name`: the power drive state machine's states and their statusword patterns (Table 30).
- `Command`, `command_of`, `next_state`: controlword commands (Table 28) and the device-side transitions
  (Figure 40), used by the simulated drive.
- `Mode`, `supported_modes`: modes of operation (0x6060/0x6061) and the supported-modes bits (0x6502).
- `enable_operation`, `quick_stop`, `disable_voltage`, `fault_reset`: the bench-side sequences over a two-call
  transport surface (`Cia402Port`), so CANopen, serial and any later transport step a drive the same way.
"""

from __future__ import annotations

import enum
import time
from typing import Callable, Protocol

from drivers.contract.errors import LinkError

FAULT_RESET_POLICIES = ("never", "once")     # a drive found in FAULT at enable: reset it once, or never


class State(enum.Enum):
    """Value = the statusword bits that identify the state (bits 0-3, 5, 6)."""

    NOT_READY_TO_SWITCH_ON = 0x00
    SWITCH_ON_DISABLED = 0x40
    READY_TO_SWITCH_ON = 0x21
    SWITCHED_ON = 0x23
    OPERATION_ENABLED = 0x27
    QUICK_STOP_ACTIVE = 0x07
    FAULT_REACTION_ACTIVE = 0x0F
    FAULT = 0x08

    @property
    def label(self) -> str:
        return self.name.replace("_", " ")


# (mask, pattern, state): CiA 402 Table 30; bit 5 (quick stop) is "don't care" in four states
_PATTERNS: tuple[tuple[int, int, State], ...] = (
    (0x4F, 0x00, State.NOT_READY_TO_SWITCH_ON), (0x4F, 0x40, State.SWITCH_ON_DISABLED),
    (0x6F, 0x21, State.READY_TO_SWITCH_ON), (0x6F, 0x23, State.SWITCHED_ON), (0x6F, 0x27, State.OPERATION_ENABLED),
    (0x6F, 0x07, State.QUICK_STOP_ACTIVE), (0x4F, 0x0F, State.FAULT_REACTION_ACTIVE), (0x4F, 0x08, State.FAULT),
)

FAULT_STATES = frozenset({State.FAULT, State.FAULT_REACTION_ACTIVE})
POWERED_STATES = frozenset({State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE})   # the power stage switches


class StatusBit(enum.IntFlag):
    READY_TO_SWITCH_ON = 1 << 0
    SWITCHED_ON = 1 << 1
    OPERATION_ENABLED = 1 << 2
    FAULT = 1 << 3
    VOLTAGE_ENABLED = 1 << 4
    QUICK_STOP = 1 << 5            # 0 = quick stop active
    SWITCH_ON_DISABLED = 1 << 6
    WARNING = 1 << 7
    REMOTE = 1 << 9
    TARGET_REACHED = 1 << 10
    INTERNAL_LIMIT_ACTIVE = 1 << 11


def decode(statusword: int) -> State | None:
    for mask, pattern, state in _PATTERNS:
        if statusword & mask == pattern:
            return state
    return None


def state_name(statusword: int) -> str:
    state = decode(statusword)
    return state.label if state is not None else f"UNKNOWN (statusword 0x{statusword:04X})"


def statusword(state: State, *, target_reached: bool = False, remote: bool = True) -> int:
    """The statusword a drive in `state` reports (device side)."""
    word = state.value
    if state not in (State.SWITCH_ON_DISABLED, State.NOT_READY_TO_SWITCH_ON, State.FAULT):
        word |= StatusBit.VOLTAGE_ENABLED
    if remote:
        word |= StatusBit.REMOTE
    if target_reached:
        word |= StatusBit.TARGET_REACHED
    return int(word)


class Command(enum.IntEnum):
    """Controlword values of the device control commands (CiA 402 Table 28), as the bench writes them."""

    DISABLE_VOLTAGE = 0x0000
    QUICK_STOP = 0x0002
    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007             # also "disable operation" from OPERATION ENABLED
    ENABLE_OPERATION = 0x000F
    FAULT_RESET = 0x0080           # acts on the rising edge of bit 7


FAULT_RESET_BIT = 0x0080


def command_of(controlword: int) -> Command:
    """The command a controlword means (bits 0-3 and 7; Table 28's don't-care bits ignored)."""
    if controlword & FAULT_RESET_BIT:
        return Command.FAULT_RESET
    if not controlword & 0x02:
        return Command.DISABLE_VOLTAGE
    if controlword & 0x06 == 0x02:
        return Command.QUICK_STOP
    if controlword & 0x07 == 0x06:
        return Command.SHUTDOWN
    if controlword & 0x0F == 0x07:
        return Command.SWITCH_ON
    return Command.ENABLE_OPERATION


_S = State
# (state, command) -> next state; CiA 402 Figure 40, transitions 2-12 and 16 (3+4 for "switch on + enable").
TRANSITIONS: dict[tuple[State, Command], State] = {
    (_S.SWITCH_ON_DISABLED, Command.SHUTDOWN): _S.READY_TO_SWITCH_ON,                 # 2
    (_S.READY_TO_SWITCH_ON, Command.SWITCH_ON): _S.SWITCHED_ON,                       # 3
    (_S.READY_TO_SWITCH_ON, Command.ENABLE_OPERATION): _S.OPERATION_ENABLED,          # 3 + 4
    (_S.SWITCHED_ON, Command.ENABLE_OPERATION): _S.OPERATION_ENABLED,                 # 4
    (_S.OPERATION_ENABLED, Command.SWITCH_ON): _S.SWITCHED_ON,                        # 5
    (_S.SWITCHED_ON, Command.SHUTDOWN): _S.READY_TO_SWITCH_ON,                        # 6
    (_S.READY_TO_SWITCH_ON, Command.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,          # 7
    (_S.READY_TO_SWITCH_ON, Command.QUICK_STOP): _S.SWITCH_ON_DISABLED,               # 7
    (_S.OPERATION_ENABLED, Command.SHUTDOWN): _S.READY_TO_SWITCH_ON,                  # 8
    (_S.OPERATION_ENABLED, Command.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,           # 9
    (_S.SWITCHED_ON, Command.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,                 # 10
    (_S.SWITCHED_ON, Command.QUICK_STOP): _S.SWITCH_ON_DISABLED,                      # 10
    (_S.OPERATION_ENABLED, Command.QUICK_STOP): _S.QUICK_STOP_ACTIVE,                 # 11
    (_S.QUICK_STOP_ACTIVE, Command.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,           # 12
    (_S.QUICK_STOP_ACTIVE, Command.ENABLE_OPERATION): _S.OPERATION_ENABLED,           # 16
}


def next_state(state: State, controlword: int, previous_controlword: int, fault_active: bool) -> State:
    """Device side: the state after `controlword` is written. A fault is left only on a rising edge of bit 7 once
    its cause has cleared (transition 15); the fault-reset bit otherwise masks the command."""
    if state is State.FAULT:
        rising = bool(controlword & FAULT_RESET_BIT) and not previous_controlword & FAULT_RESET_BIT
        return State.SWITCH_ON_DISABLED if rising and not fault_active else state
    command = command_of(controlword)
    if command is Command.FAULT_RESET:
        return state
    return TRANSITIONS.get((state, command), state)


class Mode(enum.IntEnum):
    """Modes of operation (0x6060 / 0x6061)."""

    PROFILE_POSITION = 1
    VELOCITY = 2
    PROFILE_VELOCITY = 3
    PROFILE_TORQUE = 4
    HOMING = 6
    INTERPOLATED_POSITION = 7
    CYCLIC_SYNC_POSITION = 8
    CYCLIC_SYNC_VELOCITY = 9
    CYCLIC_SYNC_TORQUE = 10


def supported_modes(bits: int) -> tuple[Mode, ...]:
    """0x6502 Supported drive modes: bit n-1 for mode n (bits 0-9)."""
    return tuple(mode for mode in Mode if bits >> (mode.value - 1) & 1)


def modes_bits(modes: tuple[Mode, ...] | list[Mode]) -> int:
    return sum(1 << (mode.value - 1) for mode in set(modes))


# -- bench side: the sequences ---------------------------------------------------------------------------------


class Cia402Port(Protocol):
    """What the sequences need from a transport. write_controlword may return the statusword the drive answered
    with (the serial protocol does); None means: read it."""

    def write_controlword(self, word: int) -> int | None: ...
    def read_statusword(self) -> int: ...


def wait_state(port: Cia402Port, wanted: frozenset[State] | set[State], what: str, timeout_s: float,
               first: int | None = None, where: str = "drive", poll_s: float = 0.002) -> State:
    """Poll the statusword until the drive is in one of `wanted`; LinkError naming the state it stayed in."""
    deadline = time.monotonic() + timeout_s
    word = port.read_statusword() if first is None else first
    while True:
        state = decode(word)
        if state in wanted:
            return state
        if time.monotonic() > deadline:
            expected = " or ".join(sorted(s.label for s in wanted))
            raise LinkError(f"{where}: {what}: drive stayed in {state_name(word)} (statusword 0x{word:04X}), "
                            f"expected {expected}")
        time.sleep(poll_s)
        word = port.read_statusword()


def command(port: Cia402Port, cmd: Command, wanted: frozenset[State] | set[State], what: str, timeout_s: float,
            where: str = "drive") -> State:
    return wait_state(port, wanted, what, timeout_s, port.write_controlword(int(cmd)), where)


def fault_reset(port: Cia402Port, timeout_s: float, where: str = "drive") -> None:
    """Bit 7 low, then its rising edge; FAULT -> SWITCH ON DISABLED; bit 7 low again."""
    port.write_controlword(Command.DISABLE_VOLTAGE)
    command(port, Command.FAULT_RESET, {State.SWITCH_ON_DISABLED}, "fault reset", timeout_s, where)
    port.write_controlword(Command.DISABLE_VOLTAGE)


def enable_operation(port: Cia402Port, *, fault_reset_policy: str, timeout_s: float, where: str = "drive",
                     select_mode: Callable[[], None] | None = None,
                     fault_detail: Callable[[], str] | None = None,
                     bring_to_rest: Callable[[], None] | None = None) -> None:
    """From whatever state the drive is in to OPERATION ENABLED.

    A drive in FAULT is reset only when the policy is "once"; with "never" it stays in FAULT and the run does not
    start. A drive found powered (left running, or in quick stop) is disabled first, so every run starts from
    SWITCH ON DISABLED; `bring_to_rest` (where the transport has it) first stops a drive found powered and waits for
    standstill, so the run never enables onto a turning shaft. `select_mode` runs while the power stage is off (mode
    of operation, target zero); `fault_detail` says what the fault is (error code) when a fault stops the enable."""
    if fault_reset_policy not in FAULT_RESET_POLICIES:
        raise ValueError(f"fault_reset: {fault_reset_policy!r} is not one of {FAULT_RESET_POLICIES}")
    word = port.read_statusword()
    state = decode(word)
    if state in FAULT_STATES:
        if fault_reset_policy == "never":
            detail = f" ({fault_detail()})" if fault_detail is not None else ""
            raise LinkError(f"{where}: drive is in {state_name(word)}{detail} and the fault-reset policy is 'never'")
        fault_reset(port, timeout_s, where)
    elif state in POWERED_STATES:
        if bring_to_rest is not None:
            bring_to_rest()
        command(port, Command.DISABLE_VOLTAGE, {State.SWITCH_ON_DISABLED}, "disable voltage before enabling",
                timeout_s, where)
    if select_mode is not None:
        select_mode()
    command(port, Command.SHUTDOWN, {State.READY_TO_SWITCH_ON}, "shutdown", timeout_s, where)
    command(port, Command.SWITCH_ON, {State.SWITCHED_ON}, "switch on", timeout_s, where)
    command(port, Command.ENABLE_OPERATION, {State.OPERATION_ENABLED}, "enable operation", timeout_s, where)


QUICK_STOPPED = frozenset({State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED, State.FAULT})
DISABLED = frozenset({State.SWITCH_ON_DISABLED, State.FAULT})


def quick_stop(port: Cia402Port, timeout_s: float, where: str = "drive") -> State:
    return command(port, Command.QUICK_STOP, QUICK_STOPPED, "quick stop", timeout_s, where)


STANDSTILL_MECH_RAD_S = 0.5  # below this the shaft counts as stopped (the safe stop disables only then)
STOP_TIMEOUT_S = 5.0         # at most this long waiting for standstill after a quick stop


LOCKSTEP_WALL_FACTOR = 6.0


def wait_standstill(advance: Callable[[], None], speed: Callable[[], float | None], threshold_mech_rad_s: float,
                    timeout_s: float, max_advances: int | None = None,
                    stopped: Callable[[], bool] | None = None) -> dict:
    """After a quick stop: let the drive brake until |speed| <= threshold, bounded in time, so the power stage goes off
    at standstill and not at speed. `advance` lets drive time pass (lockstep: one SYNC; real time: a short sleep);
    `speed` is the drive's speed in mech rad/s (None: unknown, stop waiting). A link error ends the wait: the
    disable step comes next whatever happened. `max_advances` bounds the wait in drive time too (lockstep: a
    simulated drive runs many times faster than the wall clock, and its trace recorder must not overrun while the
    bench waits). `stopped` says the drive has ended its quick stop itself (QUICK STOP ACTIVE -> SWITCH ON DISABLED,
    0x605A options 1-3: at standstill by its own judgement), which needs no unit: after a unit trip the bench's
    conversion of the drive's speed is the thing in doubt. Returns what happened, for the record."""
    started = time.monotonic()
    current = None
    advances = 0
    # lockstep: drive time bounds the wait (max_advances); the wall clock only guards against a link that crawls,
    # so a loaded bench PC (SYNC round trips of ms) still lets the drive brake for its full stop time
    wall_s = timeout_s if max_advances is None else LOCKSTEP_WALL_FACTOR * timeout_s
    while time.monotonic() - started < wall_s and (max_advances is None or advances < max_advances):
        advances += 1
        try:
            advance()
            current = speed()
            if current is None or abs(current) <= threshold_mech_rad_s:
                break
            by_itself = stopped is not None and stopped()
        except LinkError:
            break
        if by_itself:
            return {"standstill": True, "by": "the drive: QUICK STOP ACTIVE ended in SWITCH ON DISABLED (0x605A)",
                    "speed_at_disable_mech_rad_s": abs(current), "wait_s": round(time.monotonic() - started, 4)}
    return {"standstill": current is not None and abs(current) <= threshold_mech_rad_s,
            "speed_at_disable_mech_rad_s": None if current is None else abs(current),
            "wait_s": round(time.monotonic() - started, 4)}


def disable_voltage(port: Cia402Port, timeout_s: float, where: str = "drive") -> State:
    return command(port, Command.DISABLE_VOLTAGE, DISABLED, "disable voltage", timeout_s, where)
