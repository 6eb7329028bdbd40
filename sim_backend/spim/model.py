"""SpimDrive: the simulated single-phase induction motor drive (asymmetric plant + three-leg inverter + ADC +
sensorless ISFOC firmware + reference sensor + load machine) meeting sim_backend.drive_model.DriveModel."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from drivers.contract.signals import SIGNAL_NAMES
from drivers.contract.parameters import ParamKind, checked, names_for
from drivers.contract.errors import ContentError
from sim_backend.numerics import wrap_angle
from sim_backend.mechanics import LOAD_BRAKE, LOAD_TORQUE, LOAD_VISCOUS
from sim_backend.spim import firmware as fw
from sim_backend.spim import inverter as inv
from sim_backend.spim import kernel as kn
from sim_backend.spim import plant as pl

NOISE_BLOCK = 4096
_PLANT_KEYS = ("rsd_ohm", "rsq_ohm", "rr_ohm", "lsd_h", "lsq_h", "lr_h", "msrd_h", "msrq_h")
_INVERTER_KEYS = ("vdc_v", "pwm_frequency_hz", "dead_time_s", "device_drop_v", "zero_crossing_band_a")
_MEASUREMENT_KEYS = ("current_noise_a", "current_lsb_a", "vdc_noise_v", "vdc_lsb_v")
_FIRMWARE_NUMBERS = (
    "control_period_s", "pole_pairs", "stator_flux_ref_wb", "current_kp_v_per_a", "current_ki_v_per_as",
    "flux_kp_a_per_wb", "flux_ki_a_per_wbs", "slip_kp", "slip_ki", "speed_kp_nm_s_rad", "speed_ki_nm_rad",
    "torque_max_nm", "current_max_a", "overcurrent_trip_a", "speed_ramp_rad_s2", "speed_filter_rad_s",
    "emf_feedforward_filter_rad_s", "flux_min_wb", "modulation_max", "dead_time_comp_v",
    "dead_time_comp_band_a", "magnetising_time_s", "flux_current_model_gain_rad_s", "demagnetising_time_s")
# the firmware's motor model: the catalogue's firmware parameters but the compensation voltage (dead_time_comp_v)
_FW_MODEL_NAMES = tuple(n for n in names_for("spim", ParamKind.FIRMWARE) if n != "fw_deadtime_comp_v")
_FIRMWARE_NUMBERS += _FW_MODEL_NAMES
_INVERTER_VALUES = {"inverter_dead_time_s": inv.I_DEADTIME_S, "inverter_device_drop_v": inv.I_VDROP}
_MAY_BE_ZERO = {"dead_time_s", "device_drop_v", "current_noise_a", "current_lsb_a", "vdc_noise_v", "vdc_lsb_v",
                "dead_time_comp_v", "emf_feedforward_filter_rad_s", "flux_kp_a_per_wb", "flux_ki_a_per_wbs",
                "slip_kp", "speed_kp_nm_s_rad", "magnetising_time_s", "viscous_nm_s_rad",
                "flux_current_model_gain_rad_s", "demagnetising_time_s"}


def _section(cfg: dict, name: str) -> dict:
    sec = cfg.get(name)
    if not isinstance(sec, dict):
        raise ContentError(f"[{name}] missing")
    return sec


def _numbers(cfg: dict, section: str, keys: tuple[str, ...]) -> dict[str, float]:
    sec = _section(cfg, section)
    out = {}
    for key in keys:
        if key not in sec:
            raise ContentError(f"[{section}] {key}: missing")
        value = sec[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ContentError(f"[{section}] {key}: expected a finite number, got {value!r}")
        if value < 0 or (value == 0 and key not in _MAY_BE_ZERO):
            raise ContentError(f"[{section}] {key}: must be > 0, got {value!r}")
        out[key] = float(value)
    return out


class SpimDrive:
    kind = "spim"

    def __init__(self, plant: dict[str, float], mech: dict[str, float], substeps: int, inv_cfg: dict,
                 meas: dict, fw_cfg: dict, seed: int, noise: bool):
        self._plant_cfg = plant
        self._mech_cfg = mech
        self._substeps = int(substeps)
        self._fw_cfg = dict(fw_cfg)
        self._fw_model = {name: fw_cfg[name] for name in _FW_MODEL_NAMES}
        self.control_period_s = float(fw_cfg["control_period_s"])
        self.time_s = 0.0
        self._steps = 0
        self._plant_factors: dict[str, float] = {}
        self._load_mode = LOAD_TORQUE
        self._load_value = 0.0
        self._load_enabled = False
        self._pp = pl.plant_params(plant, mech, self._plant_factors)
        self._x = np.zeros(pl.N_PLANT_STATE)
        self._ip = inv.inverter_params(inv_cfg, meas)
        self._fp = fw.firmware_params(self._fw_model, self._fw_cfg)
        self._fs = fw.new_state()
        self._ks = np.array([0.0, 0.5, 0.5, 0.5])
        self._rng = np.random.default_rng(seed)
        self._noise = bool(noise)
        self._no_noise = np.zeros((1, kn.NOISE_CHANNELS))
        # standard-normal samples drawn in fixed blocks: the telemetry does not depend on how step() is chunked
        self._noise_buf = np.zeros((NOISE_BLOCK, kn.NOISE_CHANNELS))
        self._noise_pos = NOISE_BLOCK

    @classmethod
    def from_config(cls, cfg: dict, seed: int, *, noise: bool = True) -> "SpimDrive":
        kind = _section(cfg, "motor").get("kind")
        if kind != "spim":
            raise ContentError(f"[motor] kind: expected 'spim', got {kind!r}")
        pole_pairs = _numbers(cfg, "motor", ("pole_pairs",))["pole_pairs"]
        plant = _numbers(cfg, "plant", _PLANT_KEYS)
        plant["pole_pairs"] = pole_pairs
        substeps = _section(cfg, "plant").get("substeps", 2)
        if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
            raise ContentError(f"[plant] substeps: expected an integer >= 1, got {substeps!r}")
        mech = _numbers(cfg, "mechanics", ("inertia_kgm2", "viscous_nm_s_rad"))
        inv_cfg = _numbers(cfg, "inverter", _INVERTER_KEYS)
        meas = _numbers(cfg, "measurement", _MEASUREMENT_KEYS)
        fw_cfg: dict[str, Any] = _numbers(cfg, "firmware", _FIRMWARE_NUMBERS)
        common = _section(cfg, "firmware").get("common_leg", "centred")
        if common not in ("centred", "fixed"):
            raise ContentError(f"[firmware] common_leg: expected 'centred' or 'fixed', got {common!r}")
        fw_cfg["common_leg"] = common
        if fw_cfg["pole_pairs"] != pole_pairs:
            raise ContentError("[firmware] pole_pairs: differs from [motor] pole_pairs")
        return cls(plant, mech, substeps, inv_cfg, meas, fw_cfg, seed, noise)

    # ---- DriveModel ----
    def step(self, n: int) -> np.ndarray:
        out = np.empty((n, len(SIGNAL_NAMES)))
        done = 0
        while done < n:
            if self._noise and self._noise_pos == len(self._noise_buf):
                self._noise_buf = self._rng.standard_normal((NOISE_BLOCK, kn.NOISE_CHANNELS))
                self._noise_pos = 0
            m = n - done if not self._noise else min(n - done, NOISE_BLOCK - self._noise_pos)
            noise = self._noise_buf[self._noise_pos:self._noise_pos + m] if self._noise else self._no_noise
            kn.run_steps(m, self._x, self._pp, self._ip, self._fs, self._fp, self._ks, noise, self._noise,
                         self._substeps, out[done:done + m])
            done += m
            if self._noise:
                self._noise_pos += m
        self._steps += n
        self.time_s = self._steps * self.control_period_s
        return out

    def set_enabled(self, on: bool) -> None:
        self._fs[fw.S_ENABLED] = 1.0 if on else 0.0

    def set_speed_ref(self, speed_mech_rad_s: float) -> None:
        self._fs[fw.S_SPEED_TARGET] = float(speed_mech_rad_s)

    def set_load(self, mode: int, value: float, enabled: bool = True) -> None:
        if int(mode) not in (LOAD_TORQUE, LOAD_VISCOUS, LOAD_BRAKE):
            raise ValueError(f"load mode {mode!r}: expected 0 (torque), 1 (viscous) or 2 (brake)")
        self._load_mode, self._load_value, self._load_enabled = int(mode), float(value), bool(enabled)
        self._update_plant()

    def load_feedback(self) -> tuple[float, float]:
        open_d, open_q = self._x[pl.X_OPEN_D] != 0.0, self._x[pl.X_OPEN_Q] != 0.0
        i = pl.currents(self._x[pl.X_PSD], self._x[pl.X_PSQ], self._x[pl.X_PRD], self._x[pl.X_PRQ], self._pp,
                        open_d, open_q)
        te = pl.torque(*i, self._pp) - self._pp[pl.P_FRICTION] * self._x[pl.X_WM]
        return float(self._x[pl.X_WM]), float(kn.load_torque_now(self._x, self._pp, te))

    def set_hook(self, name: str, value: float) -> None:
        value = float(value)
        if not math.isfinite(value):
            raise ValueError(f"{name}: must be finite, got {value!r}")
        if name == "flux_est_scale":
            self._fs[fw.S_PHI] *= value
        elif name == "pos_est_offset_rad":
            self._fs[fw.S_THETA] = wrap_angle(self._fs[fw.S_THETA] + value)
        elif name == "freeze_speed_est":
            if value and self._fs[fw.S_FREEZE_SLIP] == 0.0:
                self._fs[fw.S_SLIP] = self._fs[fw.S_SLIP_INT]
            self._fs[fw.S_FREEZE_SLIP] = 1.0 if value else 0.0
        elif name == "freeze_flux_est":
            self._fs[fw.S_FREEZE_FLUX] = 1.0 if value else 0.0
        elif name == "fw_deadtime_comp_v":
            self._fw_cfg["dead_time_comp_v"] = checked(name, self.kind, value)
            self._fp = fw.firmware_params(self._fw_model, self._fw_cfg)
        elif name in self._fw_model:
            self._fw_model[name] = checked(name, self.kind, value)
            self._fp = fw.firmware_params(self._fw_model, self._fw_cfg)
        else:
            raise KeyError(f"unknown hook {name!r} for a spim drive; known: {', '.join(self.hook_names())}")

    def hook_names(self) -> tuple[str, ...]:
        return names_for(self.kind, ParamKind.TEST_HOOK, ParamKind.FIRMWARE)

    def set_plant_param(self, name: str, factor: float) -> None:
        if name in _INVERTER_VALUES:                  # absolute values, not factors
            self._ip[_INVERTER_VALUES[name]] = checked(name, self.kind, factor)
            return
        if name not in names_for(self.kind, ParamKind.PLANT):
            raise KeyError(f"unknown plant parameter {name!r}; known: {', '.join(self.plant_param_names())}")
        self._plant_factors[name] = checked(name, self.kind, factor)
        self._update_plant()

    def plant_param_names(self) -> tuple[str, ...]:
        return names_for(self.kind, ParamKind.PLANT)

    def fault_code(self) -> int:
        return int(self._fs[fw.S_FAULT])

    def reset_fault(self) -> None:
        self._fs[fw.S_FAULT] = 0.0

    # ---- internals and inspection (tests, tools; not part of DriveModel) ----
    def _update_plant(self) -> None:
        mode, value = (self._load_mode, self._load_value) if self._load_enabled else (LOAD_TORQUE, 0.0)
        self._pp[:] = pl.plant_params(self._plant_cfg, self._mech_cfg, self._plant_factors, mode, value)

    @property
    def plant_state(self) -> np.ndarray:
        return self._x

    @property
    def plant_params(self) -> np.ndarray:
        return self._pp

    @property
    def firmware_state(self) -> np.ndarray:
        return self._fs

    @property
    def firmware_params(self) -> np.ndarray:
        return self._fp
