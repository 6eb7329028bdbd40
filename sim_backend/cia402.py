"""CiA 402 power drive state machine (device side), shared by the simulated CANopen and serial drives."""

from __future__ import annotations

import enum
from dataclasses import dataclass


class State(enum.Enum):
    NOT_READY_TO_SWITCH_ON = 0x0000
    SWITCH_ON_DISABLED = 0x0040
    READY_TO_SWITCH_ON = 0x0021
    SWITCHED_ON = 0x0023
    OPERATION_ENABLED = 0x0027
    QUICK_STOP_ACTIVE = 0x0007
    FAULT_REACTION_ACTIVE = 0x000F
    FAULT = 0x0008


STATUS_VOLTAGE_ENABLED = 1 << 4
STATUS_REMOTE = 1 << 9
STATUS_TARGET_REACHED = 1 << 10
CONTROL_FAULT_RESET = 1 << 7

MODE_PROFILE_VELOCITY = 3


@dataclass
class Cia402Device:
    state: State = State.SWITCH_ON_DISABLED
    controlword: int = 0
    error_code: int = 0            # 0x603F
    target_reached: bool = False

    @property
    def power_enabled(self) -> bool:
        """The power stage switches (operation enabled, or braking in quick stop)."""
        return self.state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE)

    @property
    def statusword(self) -> int:
        word = self.state.value | STATUS_REMOTE
        if self.state not in (State.SWITCH_ON_DISABLED, State.NOT_READY_TO_SWITCH_ON, State.FAULT):
            word |= STATUS_VOLTAGE_ENABLED
        if self.state is State.SWITCH_ON_DISABLED:
            word &= ~0x20     # quick-stop bit is "don't care" (0) here
        if self.target_reached:
            word |= STATUS_TARGET_REACHED
        return word

    def fault(self, error_code: int) -> None:
        """A device fault: fault reaction (gates off), then FAULT."""
        self.error_code = error_code
        self.state = State.FAULT

    def write_controlword(self, word: int, fault_active: bool = False) -> None:
        rising_reset = bool(word & CONTROL_FAULT_RESET) and not self.controlword & CONTROL_FAULT_RESET
        self.controlword = word
        if self.state is State.FAULT:
            if rising_reset and not fault_active:
                self.error_code = 0
                self.state = State.SWITCH_ON_DISABLED
            return
        if word & CONTROL_FAULT_RESET:
            return
        command = word & 0x0F
        disable_voltage = not command & 0x02
        quick_stop = (command & 0x06) == 0x02
        shutdown = (command & 0x07) == 0x06
        switch_on = (command & 0x0F) == 0x07
        enable = (command & 0x0F) == 0x0F
        s = self.state
        if disable_voltage:
            self.state = State.SWITCH_ON_DISABLED
        elif quick_stop:
            self.state = State.QUICK_STOP_ACTIVE if s is State.OPERATION_ENABLED else (
                s if s is State.QUICK_STOP_ACTIVE else State.SWITCH_ON_DISABLED)
        elif shutdown:
            if s in (State.SWITCH_ON_DISABLED, State.SWITCHED_ON, State.OPERATION_ENABLED):
                self.state = State.READY_TO_SWITCH_ON
        elif switch_on:
            if s is State.READY_TO_SWITCH_ON:
                self.state = State.SWITCHED_ON
            elif s is State.OPERATION_ENABLED:
                self.state = State.SWITCHED_ON
        elif enable:
            if s in (State.SWITCHED_ON, State.READY_TO_SWITCH_ON):
                self.state = State.OPERATION_ENABLED
            elif s is State.QUICK_STOP_ACTIVE:
                self.state = State.OPERATION_ENABLED
