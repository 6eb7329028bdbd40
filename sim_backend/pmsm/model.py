"""PmsmDrive: the simulated PMSM drive (plant + inverter + MRAS/IRFOC firmware + reference sensor + load
machine) meeting sim_backend.drive_model.DriveModel."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from drivers.contract.signals import SIGNAL_NAMES
from drivers.contract.parameters import ParamKind, checked, names_for
from sim_backend.three_phase_inverter import adc_lsb, draw_measurement_noise
from drivers.contract.errors import ContentError
from sim_backend.mechanics import LOAD_BRAKE, LOAD_TORQUE, LOAD_VISCOUS
from sim_backend.pmsm import firmware as fw
from sim_backend.pmsm import kernel as kn
from sim_backend.pmsm import plant as pl

_FW_OVERRIDES = {"fw_rs_ohm": fw.F_RS, "fw_ls_h": fw.F_LS, "fw_flux_wb": fw.F_FLUX, "fw_inertia_kgm2": fw.F_INERTIA,
                 "fw_isx_ref_a": fw.F_ISX_REF, "fw_deadtime_comp_v": fw.F_DEADTIME_COMP_V}
_INVERTER_VALUES = {"inverter_dead_time_s": kn.I_DEAD_TIME, "inverter_device_drop_v": kn.I_DEVICE_DROP}
_PLANT_FACTORS = {"plant_rs": pl.P_RS, "plant_ls": pl.P_LS, "plant_flux": pl.P_FLUX, "plant_inertia": pl.P_INERTIA}


def _get(cfg: dict, section: str, key: str, default: Any = None) -> Any:
    sec = cfg.get(section)
    if not isinstance(sec, dict):
        raise ContentError(f"[{section}] missing")
    if key not in sec:
        if default is not None:
            return default
        raise ContentError(f"[{section}] {key}: missing")
    return sec[key]


def _num(cfg: dict, section: str, key: str, default: float | None = None, positive: bool = False) -> float:
    value = _get(cfg, section, key, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ContentError(f"[{section}] {key}: expected a number, got {value!r}")
    if positive and not value > 0:
        raise ContentError(f"[{section}] {key}: must be > 0, got {value!r}")
    return float(value)


# [firmware] keys that must be given, > 0; speed_est_ki_over_kp (a number or "a1") is read apart
_FIRMWARE_POSITIVE = {
    "control_period_s": fw.F_PERIOD,
    "rs_ohm": fw.F_RS,
    "ls_h": fw.F_LS,
    "flux_wb": fw.F_FLUX,
    "inertia_kgm2": fw.F_INERTIA,
    "speed_est_kp": fw.F_SPEED_EST_KP,
    "flux_est_kp": fw.F_FLUX_EST_KP,
    "flux_est_ki_over_kp": fw.F_FLUX_EST_KI_OVER_KP,
    "flux_est_min_speed_elec_rad_s": fw.F_FLUX_EST_MIN_SPEED,
    "flux_est_min_fraction": fw.F_FLUX_EST_MIN_FRACTION,
    "flux_est_max_fraction": fw.F_FLUX_EST_MAX_FRACTION,
    "speed_loop_bandwidth_rad_s": fw.F_SPEED_BW,
    "speed_pi_zero_fraction": fw.F_SPEED_ZERO_FRACTION,
    "current_loop_bandwidth_rad_s": fw.F_CURRENT_BW,
    "current_limit_a": fw.F_I_MAX,
    "overcurrent_trip_a": fw.F_I_TRIP,
    "speed_ramp_mech_rad_s2": fw.F_RAMP,
    "voltage_limit_fraction": fw.F_VOLTAGE_FRACTION,
}
# [firmware] keys that may be left out: (parameter, default)
_FIRMWARE_DEFAULTS = {
    "flux_est_standstill_relax_s": (fw.F_FLUX_HOLD_RELAX_S, 0.0),
    "delay_comp_periods": (fw.F_DELAY_COMP, 1.5),
    "deadtime_comp_v": (fw.F_DEADTIME_COMP_V, 0.0),
    "deadtime_comp_width_a": (fw.F_DEADTIME_COMP_WIDTH, 0.05),
    "isx_ref_a": (fw.F_ISX_REF, 0.0),
}


class PmsmDrive:
    kind = "pmsm"

    def __init__(self, plant_nominal: np.ndarray, initial_angle: float, fw_params: np.ndarray,
                 inv_params: np.ndarray, seed: int, noise: bool):
        self.control_period_s = float(fw_params[fw.F_PERIOD])
        self.time_s = 0.0
        self._steps = 0
        self._plant_nominal = plant_nominal.copy()
        self._plant_factors = np.ones(pl.N_PARAMS)
        self._plant_p = plant_nominal.copy()
        self._x = pl.initial_state(plant_nominal[pl.P_FLUX], initial_angle)
        self._fw_p = fw_params.copy()
        self._fw_p_nominal = fw_params.copy()
        self._fw_s = fw.new_state(fw_params[fw.F_FLUX])
        self._inv_p = inv_params.copy()
        self._inv_s = np.zeros(kn.N_INV_STATE)
        self._rng = np.random.default_rng(seed)
        self._noise = noise
        self._no_noise = np.zeros((1, kn.NOISE_CHANNELS))
        self._load_mode = LOAD_TORQUE
        self._load_value = 0.0
        self._load_enabled = False

    # ---- construction ----
    @classmethod
    def from_config(cls, cfg: dict, seed: int, *, noise: bool = True) -> "PmsmDrive":
        kind = _get(cfg, "motor", "kind")
        if kind != "pmsm":
            raise ContentError(f"[motor] kind: expected 'pmsm', got {kind!r}")
        pole_pairs = _num(cfg, "motor", "pole_pairs", positive=True)
        plant = np.zeros(pl.N_PARAMS)
        plant[pl.P_RS] = _num(cfg, "plant", "rs_ohm", positive=True)
        plant[pl.P_LS] = _num(cfg, "plant", "ls_h", positive=True)
        plant[pl.P_FLUX] = _num(cfg, "plant", "flux_wb", positive=True)
        plant[pl.P_INERTIA] = _num(cfg, "mechanics", "inertia_kgm2", positive=True)
        plant[pl.P_VISCOUS] = _num(cfg, "mechanics", "viscous_nm_s_rad", 0.0)
        plant[pl.P_POLE_PAIRS] = pole_pairs
        angle0 = _num(cfg, "plant", "initial_angle_elec_rad", 0.0)

        inv = np.zeros(kn.N_INV_PARAMS)
        inv[kn.I_VDC] = _num(cfg, "inverter", "vdc_v", positive=True)
        inv[kn.I_DEAD_TIME] = _num(cfg, "inverter", "dead_time_s", 0.0)
        inv[kn.I_DEVICE_DROP] = _num(cfg, "inverter", "device_drop_v", 0.0)
        inv[kn.I_ERROR_WIDTH] = _num(cfg, "inverter", "error_current_width_a", 0.05)
        inv[kn.I_CURRENT_NOISE] = _num(cfg, "measurement", "current_noise_a", 0.0)
        inv[kn.I_CURRENT_FULL_SCALE] = _num(cfg, "measurement", "current_full_scale_a", positive=True)
        inv[kn.I_CURRENT_LSB] = adc_lsb(int(_num(cfg, "measurement", "current_adc_bits", 0.0)),
                                        inv[kn.I_CURRENT_FULL_SCALE], True)
        inv[kn.I_VDC_NOISE] = _num(cfg, "measurement", "vdc_noise_v", 0.0)
        inv[kn.I_VDC_FULL_SCALE] = _num(cfg, "measurement", "vdc_full_scale_v", positive=True)
        inv[kn.I_VDC_LSB] = adc_lsb(int(_num(cfg, "measurement", "vdc_adc_bits", 0.0)), inv[kn.I_VDC_FULL_SCALE], False)
        inv[kn.I_SUBSTEPS] = _num(cfg, "plant", "substeps", 2.0, positive=True)

        f = np.zeros(fw.N_PARAMS)
        s = "firmware"
        for key, index in _FIRMWARE_POSITIVE.items():
            f[index] = _num(cfg, s, key, positive=True)
        for key, (index, default) in _FIRMWARE_DEFAULTS.items():
            f[index] = _num(cfg, s, key, default)
        f[fw.F_POLE_PAIRS] = pole_pairs
        if _get(cfg, s, "speed_est_ki_over_kp") == "a1":
            f[fw.F_SPEED_EST_KI_OVER_KP] = 0.0
        else:
            f[fw.F_SPEED_EST_KI_OVER_KP] = _num(cfg, s, "speed_est_ki_over_kp", positive=True)
        fw.derive_gains(f)
        return cls(plant, angle0, f, inv, seed, noise)

    # ---- DriveModel ----
    def step(self, n: int) -> np.ndarray:
        out = np.empty((n, len(SIGNAL_NAMES)))
        noise = draw_measurement_noise(self._rng, n, kn.NOISE_CHANNELS) if self._noise else self._no_noise
        mode, value = (self._load_mode, self._load_value) if self._load_enabled else (LOAD_TORQUE, 0.0)
        kn.run_steps(n, self._steps, self._x, self._plant_p, mode, value, self._inv_p, self._inv_s,
                     self._fw_s, self._fw_p, noise, self._noise, out)
        self._steps += n
        self.time_s = self._steps * self.control_period_s
        return out

    def set_enabled(self, on: bool) -> None:
        self._fw_s[fw.S_ENABLE_CMD] = 1.0 if on else 0.0

    def set_speed_ref(self, speed_mech_rad_s: float) -> None:
        self._fw_s[fw.S_SPEED_REF_CMD] = float(speed_mech_rad_s)

    def set_load(self, mode: int, value: float, enabled: bool = True) -> None:
        if int(mode) not in (LOAD_TORQUE, LOAD_VISCOUS, LOAD_BRAKE):
            raise ValueError(f"load mode {mode!r}: expected 0 (torque), 1 (viscous) or 2 (brake)")
        self._load_mode = int(mode)
        self._load_value = float(value)
        self._load_enabled = bool(enabled)

    def load_feedback(self) -> tuple[float, float]:
        mode, value = (self._load_mode, self._load_value) if self._load_enabled else (LOAD_TORQUE, 0.0)
        return float(self._x[pl.X_W_MECH]), float(pl.load_torque(self._x, mode, value))

    def set_hook(self, name: str, value: float) -> None:
        value = float(value)
        if name == "flux_est_scale":
            fw.scale_flux_estimate(self._fw_s, value)
        elif name == "pos_est_offset_rad":
            fw.offset_angle_estimate(self._fw_s, value)
        elif name == "freeze_speed_est":
            self._fw_s[fw.S_FREEZE_SPEED] = 1.0 if value else 0.0
        elif name == "freeze_flux_est":
            self._fw_s[fw.S_FREEZE_FLUX] = 1.0 if value else 0.0
        elif name in _FW_OVERRIDES:
            self._fw_p[_FW_OVERRIDES[name]] = checked(name, self.kind, value)
            fw.derive_gains(self._fw_p)
        else:
            raise KeyError(f"unknown hook {name!r} for a pmsm drive; known: {', '.join(self.hook_names())}")

    def hook_names(self) -> tuple[str, ...]:
        return names_for(self.kind, ParamKind.TEST_HOOK, ParamKind.FIRMWARE)

    def set_plant_param(self, name: str, factor: float) -> None:
        if name in _INVERTER_VALUES:                  # absolute values, not factors
            self._inv_p[_INVERTER_VALUES[name]] = checked(name, self.kind, factor)
            return
        if name not in _PLANT_FACTORS:
            raise KeyError(f"unknown plant parameter {name!r}; known: {', '.join(self.plant_param_names())}")
        factor = checked(name, self.kind, factor)
        idx = _PLANT_FACTORS[name]
        self._plant_factors[idx] = factor
        self._plant_p[idx] = self._plant_nominal[idx] * factor
        if idx == pl.P_FLUX:  # the magnet flux vector keeps its angle, changes its length
            ratio = self._plant_p[idx] / math.hypot(self._x[pl.X_PSI_D], self._x[pl.X_PSI_Q])
            self._x[pl.X_PSI_D] *= ratio
            self._x[pl.X_PSI_Q] *= ratio

    def plant_param_names(self) -> tuple[str, ...]:
        return names_for(self.kind, ParamKind.PLANT)

    def fault_code(self) -> int:
        return int(self._fw_s[fw.S_FAULT])

    def reset_fault(self) -> None:
        self._fw_s[fw.S_FAULT] = 0.0

    # ---- inspection for tests and tools (not part of DriveModel) ----
    @property
    def plant_state(self) -> np.ndarray:
        return self._x

    @property
    def firmware_state(self) -> np.ndarray:
        return self._fw_s

    @property
    def firmware_params(self) -> np.ndarray:
        return self._fw_p
