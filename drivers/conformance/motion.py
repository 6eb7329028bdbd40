"""The suite's hands on the drive, over a port: the CiA 402 state machine stepped by object access and confirmed on
the statusword, motion at a test speed, a stop measured on the reference sensor, and the safe end every test gets.

Time: every wait counts process-data cycles (lockstep: the drive's own time, period x cycles) and is also bounded
in wall time, so a drive that does not answer ends a test, never the suite.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from drivers.conformance.port import ConformancePort, CycleAnswer, ObjectAbort, PortError, ProcessDataPdo
from drivers.contract import objects as o
from drivers.contract.cia402 import POWERED_STATES, Mode, State, decode, state_name, supported_modes

HALT_BIT = 0x0100
STANDSTILL_FRACTION = 0.02
WALL_FACTOR = 20.0           # a wait of T drive seconds may take at most this x T (+1 s) of wall time


@dataclass(frozen=True)
class Settings:
    test_speed_mech_rad_s: float = 50.0
    standstill_mech_rad_s: float = 0.5
    stop_timeout_s: float = 5.0
    spin_up_timeout_s: float = 5.0
    consumer_time_ms: int = 500
    abort_option: int = 3
    gap_periods: int = 10
    continuity_periods: int = 150
    fault_reset: str = "never"           # [bench] fault_reset: a fault a test left is reset ("once") or ends the suite


@dataclass
class Context:
    port: ConformancePort
    reference: Callable[[], float | None]       # the shaft's speed, mech rad/s, from the reference sensor
    reference_name: str
    settings: Settings
    pdos: list[ProcessDataPdo] = field(default_factory=list)
    boot: dict[str, Any] = field(default_factory=dict)
    identity: dict[str, Any] = field(default_factory=dict)
    mode: int = Mode.PROFILE_VELOCITY
    cycles: int = 0
    last: CycleAnswer | None = None

    @property
    def period_s(self) -> float:
        return self.port.period_s

    # -- objects --------------------------------------------------------------------------------------------
    def statusword(self) -> int:
        return self.port.read(o.STATUSWORD)

    def state(self) -> State | None:
        return decode(self.statusword())

    def optional(self, index: int, sub: int = 0, signed: bool = False) -> int | None:
        """An object the drive may lack: None when it has none."""
        try:
            return self.port.read(index, sub, signed) if self.port.has(index, sub) else None
        except ObjectAbort:
            return None

    def cycle(self, sync: bool = True, command: bool = True) -> CycleAnswer:
        self.last = self.port.cycle(sync=sync, command=command)
        self.cycles += 1 if sync else 0
        return self.last

    # -- state machine --------------------------------------------------------------------------------------
    def command(self, word: int | None, wanted: set[State], timeout_s: float = 0.5) -> tuple[State | None, float]:
        """Controlword (None: none, only wait), then the statusword until the drive is in `wanted` (cycles pass
        meanwhile). (state, ms)."""
        started = time.monotonic()
        if word is not None:
            self.port.set_command(controlword=word)
        state = self.state()
        for _ in range(max(1, math.ceil(timeout_s / self.period_s))):
            if state in wanted or time.monotonic() - started > WALL_FACTOR * timeout_s + 1.0:
                break
            self.cycle()
            state = self.state()
        return state, (time.monotonic() - started) * 1e3

    def select_mode(self) -> None:
        bits = self.optional(o.SUPPORTED_DRIVE_MODES)
        have = supported_modes(bits) if bits is not None else (Mode.PROFILE_VELOCITY,)
        self.mode = Mode.PROFILE_VELOCITY if Mode.PROFILE_VELOCITY in have else Mode.CYCLIC_SYNC_VELOCITY
        self.port.set_command(target=0)
        self.port.write(o.MODES_OF_OPERATION, 0, int(self.mode), 1, signed=True)

    def wait_rest(self) -> bool:
        """Cycles until the reference sensor says standstill (the bench's threshold), bounded by the stop timeout in
        drive time: never enable onto a turning shaft (a sensorless drive may not catch it), never call a coasting shaft
        stopped."""
        started = time.monotonic()
        for _ in range(math.ceil(self.settings.stop_timeout_s / self.period_s)):
            speed = self.speed()
            if speed is None or abs(speed) <= self.settings.standstill_mech_rad_s:
                return True
            if time.monotonic() - started > WALL_FACTOR * self.settings.stop_timeout_s:
                break
            self.cycle()
        return False

    def enable(self) -> State | None:
        """SWITCH ON DISABLED -> OPERATION ENABLED at target 0 (transitions 2, 3, 4), the shaft at rest first."""
        self.wait_rest()
        self.select_mode()
        for word, wanted in ((0x06, State.READY_TO_SWITCH_ON), (0x07, State.SWITCHED_ON),
                             (0x0F, State.OPERATION_ENABLED)):
            state, _ = self.command(word, {wanted})
            if state is not wanted:
                return state
        return State.OPERATION_ENABLED

    def speed(self) -> float | None:
        value = self.reference()
        return None if value is None or not math.isfinite(value) else value

    def run_to(self, speed_mech_rad_s: float) -> tuple[bool, float | None]:
        """Target speed set; cycles until the reference sensor says within 5 % (bounded). (reached, speed)."""
        self.port.set_command(target=self.port.to_drive_velocity(speed_mech_rad_s))
        started = time.monotonic()
        speed = None
        for _ in range(math.ceil(self.settings.spin_up_timeout_s / self.period_s)):
            self.cycle()
            speed = self.speed()
            if speed is not None and abs(speed - speed_mech_rad_s) <= 0.05 * abs(speed_mech_rad_s):
                return True, speed
            if time.monotonic() - started > WALL_FACTOR * self.settings.spin_up_timeout_s:
                break
        return False, speed

    def measure_stop(self, done: Callable[[], bool] | None = None) -> dict[str, Any]:
        """After a stop command: cycles until the reference sensor says standstill (or `done`), with the time and the
        angle the shaft turned meanwhile (sum of |speed| x period: the distance on the reference sensor). Standstill:
        |speed| at most the bench's standstill threshold or 2 % of the speed the stop began from, whichever is larger
        (a shaft the drive let go at its own threshold may drift slowly on a reference sensor)."""
        distance, n, speed = 0.0, 0, self.speed()
        start_speed = speed
        threshold = max(self.settings.standstill_mech_rad_s, STANDSTILL_FRACTION * abs(start_speed or 0.0))
        limit = math.ceil(self.settings.stop_timeout_s / self.period_s)
        started = time.monotonic()
        while n < limit and time.monotonic() - started < WALL_FACTOR * self.settings.stop_timeout_s:
            if speed is not None and abs(speed) <= threshold and (done is None or done()):
                break
            self.cycle()
            n += 1
            speed = self.speed()
            distance += abs(speed or 0.0) * self.period_s
        stopped = speed is not None and abs(speed) <= threshold
        return {"from_mech_rad_s": None if start_speed is None else round(start_speed, 3),
                "stop_time_s": round(n * self.period_s, 4) if stopped else None,
                "stop_distance_rad": round(distance, 4), "standstill": stopped,
                "speed_at_end_mech_rad_s": None if speed is None else round(speed, 3),
                "standstill_below_mech_rad_s": round(threshold, 3),
                "state_at_end": state_name(self.statusword())}

    def safe_end(self) -> str:
        """Whatever the test left: a turning shaft stopped first (quick stop, standstill on the reference sensor),
        then voltage disabled; halt cleared, target 0. Returns one line for the report."""
        try:
            self.port.set_command(target=0)
            word = self.statusword()
            state = decode(word)
            speed = self.speed()
            turning = speed is not None and abs(speed) > self.settings.standstill_mech_rad_s
            if state in POWERED_STATES:
                if state is State.OPERATION_ENABLED and turning:
                    self.command(0x02, {State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED})
                    self.measure_stop()
                self.wait_rest()                            # still powered: the drive holds zero until rest
                self.command(0x00, {State.SWITCH_ON_DISABLED, State.FAULT})
            elif state not in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                self.command(0x00, {State.SWITCH_ON_DISABLED})
            self.wait_rest()                                # coasting with the power off: wait, bounded
            final = self.statusword()
            speed = self.speed()
            line = f"{state_name(final)}, shaft {'?' if speed is None else f'{speed:.2f}'} rad/s"
            if decode(final) in POWERED_STATES:
                return f"DRIVE STILL POWERED ({line}): the motor may still turn"
            return line
        except (ObjectAbort, PortError) as exc:
            return f"could not confirm the drive disabled ({exc}): the motor may still turn"
