"""The contract every simulated drive model meets; the protocol servers only use this.

A model owns plant + inverter + firmware + reference sensor + load machine for one drive and steps them
in fixed control periods. It returns telemetry blocks whose columns are drivers.contract.signals.SIGNAL_NAMES.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np


class DriveModel(Protocol):
    control_period_s: float   # firmware step, 100 us by default
    time_s: float             # drive clock: steps taken * control_period_s

    def step(self, n: int) -> np.ndarray:
        """Advance n control periods; return an (n, len(SIGNAL_NAMES)) float64 block, row k after step k."""
        ...

    def set_enabled(self, on: bool) -> None:
        """Power stage on (firmware runs its controllers) or off (gates blocked, currents decay)."""
        ...

    def set_speed_ref(self, speed_mech_rad_s: float) -> None: ...

    def set_load(self, mode: int, value: float, enabled: bool = True) -> None:
        """Load machine: drivers.api.LoadMode and its value; disabled means zero torque."""
        ...

    def load_feedback(self) -> tuple[float, float]:
        """(speed_mech_rad_s, torque_nm) as the load machine's encoder and torque sensor read them."""
        ...

    def set_hook(self, name: str, value: float) -> None:
        """Firmware test hooks and parameter overrides; see hook_names()."""
        ...

    def hook_names(self) -> tuple[str, ...]: ...

    def set_plant_param(self, name: str, factor: float) -> None:
        """Simulator-only: multiply a plant parameter (rs, rr, flux, inertia...) by factor from now on."""
        ...

    def plant_param_names(self) -> tuple[str, ...]: ...

    def fault_code(self) -> int:
        """0 = no fault; otherwise a CiA 402 / EMCY error code (0x2310 overcurrent, 0x3210 DC-link overvoltage...)."""
        ...

    def reset_fault(self) -> None: ...
