"""A trivial first-order drive model that meets sim_backend.drive_model.DriveModel.

For protocol and bench tests that need a drive but not its physics. Deterministic, no randomness.
"""

from __future__ import annotations

import math

import numpy as np

from drivers.contract.signals import SIGNAL_INDEX, SIGNAL_NAMES
from drivers.contract.parameters import ParamKind, names_for
from sim_backend.mechanics import LOAD_BRAKE, LOAD_TORQUE, LOAD_VISCOUS


class ToyDrive:
    """Speed follows its reference with a 50 ms lag; load torque shows in the torque-axis current."""

    kind = "pmsm"

    def __init__(self, control_period_s: float = 1e-4, tau_s: float = 0.05, torque_per_amp: float = 1.0):
        self.control_period_s = control_period_s
        self.time_s = 0.0
        self._steps = 0
        self._tau = tau_s
        self._kt = torque_per_amp
        self._enabled = False
        self._ref = 0.0
        self._speed = 0.0
        self._angle = 0.0
        self._load = (LOAD_TORQUE, 0.0, False)
        self.hooks: dict[str, float] = {}
        self.plant_factors: dict[str, float] = {}
        self._fault = 0

    def _load_torque(self) -> float:
        mode, value, enabled = self._load
        if not enabled:
            return 0.0
        if mode == LOAD_VISCOUS:
            return value * self._speed
        if mode == LOAD_BRAKE:
            return math.copysign(value, self._speed) if self._speed else 0.0
        return value

    def step(self, n: int) -> np.ndarray:
        out = np.zeros((n, len(SIGNAL_NAMES)))
        alpha = self.control_period_s / self._tau
        for k in range(n):
            self._steps += 1
            self.time_s = self._steps * self.control_period_s
            if self._enabled:
                self._speed += alpha * (self._ref - self._speed)
            else:
                self._speed *= 1.0 - alpha
            self._angle = (self._angle + 3 * self._speed * self.control_period_s + math.pi) % (2 * math.pi) - math.pi
            row = out[k]
            row[SIGNAL_INDEX["speed_ref_mech_rad_s"]] = self._ref
            row[SIGNAL_INDEX["speed_est_mech_rad_s"]] = self._speed
            row[SIGNAL_INDEX["speed_true_mech_rad_s"]] = self._speed
            row[SIGNAL_INDEX["pos_est_elec_rad"]] = self._angle
            row[SIGNAL_INDEX["flux_est_wb"]] = 0.26
            row[SIGNAL_INDEX["flux_true_wb"]] = 0.26
            torque = self._load_torque()
            row[SIGNAL_INDEX["i_sy_a"]] = torque / self._kt if self._enabled else 0.0
            row[SIGNAL_INDEX["torque_est_nm"]] = torque if self._enabled else 0.0
            row[SIGNAL_INDEX["torque_load_nm"]] = torque
            row[SIGNAL_INDEX["vdc_v"]] = 560.0
        return out

    def set_enabled(self, on: bool) -> None:
        self._enabled = on

    def set_speed_ref(self, speed_mech_rad_s: float) -> None:
        self._ref = speed_mech_rad_s

    def set_load(self, mode: int, value: float, enabled: bool = True) -> None:
        self._load = (mode, value, enabled)

    def load_feedback(self) -> tuple[float, float]:
        return self._speed, self._load_torque()

    def set_hook(self, name: str, value: float) -> None:
        if name not in self.hook_names():
            raise KeyError(name)
        self.hooks[name] = value

    def hook_names(self) -> tuple[str, ...]:
        return names_for(self.kind, ParamKind.TEST_HOOK, ParamKind.FIRMWARE)

    def set_plant_param(self, name: str, factor: float) -> None:
        if name not in names_for(self.kind, ParamKind.PLANT):
            raise KeyError(name)
        self.plant_factors[name] = factor

    def plant_param_names(self) -> tuple[str, ...]:
        return names_for(self.kind, ParamKind.PLANT)

    def fault_code(self) -> int:
        return self._fault

    def raise_fault(self, code: int) -> None:
        self._fault = code

    def reset_fault(self) -> None:
        self._fault = 0
