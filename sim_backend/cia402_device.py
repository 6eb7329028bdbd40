"""The simulated drive's CiA 402 power drive state machine: drivers.contract.cia402's transitions and statusword, kept in a
record the CANopen node, the serial server and the comm-loss reaction share."""

from __future__ import annotations

from dataclasses import dataclass

from drivers.contract.cia402 import POWERED_STATES, State, StatusBit, next_state, statusword


@dataclass
class Cia402Device:
    state: State = State.SWITCH_ON_DISABLED
    controlword: int = 0
    error_code: int = 0            # 0x603F
    target_reached: bool = False
    warning: bool = False          # statusword bit 7 (a drive warns and runs on: temperature, limits)
    remote: bool = True            # statusword bit 9: False = local control, the controlword is not obeyed

    @property
    def power_enabled(self) -> bool:
        """The power stage switches (operation enabled, or braking in quick stop)."""
        return self.state in POWERED_STATES

    @property
    def statusword(self) -> int:
        word = statusword(self.state, target_reached=self.target_reached, remote=self.remote)
        return int(word | StatusBit.WARNING) if self.warning else word

    def fault(self, error_code: int) -> None:
        """A device fault: fault reaction (gates off), then FAULT."""
        self.error_code = error_code
        self.state = State.FAULT

    def write_controlword(self, word: int, fault_active: bool = False) -> None:
        previous, self.controlword = self.controlword, word
        was_fault = self.state is State.FAULT
        self.state = next_state(self.state, word, previous, fault_active)
        if was_fault and self.state is not State.FAULT:
            self.error_code = 0
