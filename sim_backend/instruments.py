"""A lab's instruments around a simulated drive: what an instruments rig (config/benches/sim-*-instruments.toml) gives.

On a lab rig nothing knows the plant's state: the drive's firmware reports its own estimates and measurements, the
shaft's speed comes from an encoder on the dynamometer and its torque from a transducer. `InstrumentedModel` wraps a
DriveModel so that the simulated rig gives exactly that:

- the drive's telemetry carries no rig truth: the columns of drivers.contract.signals marked `reference` (speed_true, pos_err,
  flux_true, torque_load) are NaN, as from a firmware without a position sensor (the drivebench extension as a lab's
  drive would carry it: drive clock, trace recorder, estimator telemetry, test hooks);
- load_feedback() (what the Modbus dynamometer serves) is the encoder's and the transducer's reading:
  * encoder: `counts_per_rev` counts (lines x 4), an alignment offset drawn once from the seed (unknown to the bench),
    Gaussian edge jitter of `noise_counts` (std, in counts) on every control period's count; speed = counts over the
    last `speed_gate_s` (M-method), so it is quantised to 2*pi / counts_per_rev / speed_gate_s and lags by half a gate;
  * torque transducer, in line between motor and dynamometer: it reads the shaft torque, the dynamometer's own torque
    plus what accelerates the dynamometer's rotor (`dyno_inertia_kgm2`, part of the plant's lumped inertia):
    T_shaft = T_L + J_dyno dw/dt; then a first-order low-pass of `bandwidth_hz` and Gaussian noise `noise_nm` (std).
Every random draw is made per control period from the model's own seeded generator (never per Modbus request, whose
number depends on the bench's timing), so the same seed gives the same readings bit for bit.

The settings are the bench config's [simulator.instruments] table (read by sim_backend only):

    [simulator.instruments]
    encoder_counts_per_rev = 4096
    encoder_noise_counts = 0.3
    encoder_speed_gate_s = 0.01
    torque_bandwidth_hz = 100.0
    torque_noise_nm = 0.005
    dyno_inertia_kgm2 = 5e-4
    encoder_offset_rad = 1.234      # optional: where the index sits on the shaft (a rig's, fixed); left out: drawn
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from scipy.signal import lfilter

from drivers.contract.signals import SIGNAL_INDEX, SIGNALS

TRUTH_COLUMNS = tuple(SIGNAL_INDEX[s.name] for s in SIGNALS if s.reference)
_SPEED = SIGNAL_INDEX["speed_true_mech_rad_s"]
_TORQUE = SIGNAL_INDEX["torque_load_nm"]
_SEED_SALT = 0x1257_E7C0          # the instruments' generator differs from the drive's (its noise stays as it was)


@dataclass(frozen=True)
class InstrumentSpec:
    encoder_counts_per_rev: int = 4096
    encoder_noise_counts: float = 0.3
    encoder_speed_gate_s: float = 0.01
    torque_bandwidth_hz: float = 100.0
    torque_noise_nm: float = 0.005
    dyno_inertia_kgm2: float = 0.0          # 0: the transducer reads the dynamometer's torque alone
    encoder_offset_rad: float = -1.0        # the index's place on the shaft, fixed for the rig; < 0: drawn from the seed

    @classmethod
    def from_table(cls, table: Any, where: str = "simulator.instruments") -> "InstrumentSpec":
        if not isinstance(table, dict):
            raise RuntimeError(f"{where}: must be a table")
        known = {f.name for f in fields(cls)}
        for key, value in table.items():
            if key not in known:
                raise RuntimeError(f"{where}.{key}: unknown key (known: {', '.join(sorted(known))})")
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise RuntimeError(f"{where}.{key}: must be a number >= 0, got {value!r}")
        spec = cls(**table)
        if int(spec.encoder_counts_per_rev) != spec.encoder_counts_per_rev or spec.encoder_counts_per_rev < 4:
            raise RuntimeError(f"{where}.encoder_counts_per_rev: must be an integer >= 4")
        if spec.encoder_speed_gate_s <= 0 or spec.torque_bandwidth_hz <= 0:
            raise RuntimeError(f"{where}: encoder_speed_gate_s and torque_bandwidth_hz must be > 0")
        return spec


class InstrumentedModel:
    """A DriveModel seen through a lab's instruments (see the module docstring); everything else is the model's."""

    def __init__(self, model: Any, spec: InstrumentSpec, seed: int):
        self._model = model
        self.instruments = spec
        self._rng = np.random.default_rng([int(seed), _SEED_SALT])
        dt = float(model.control_period_s)
        self._gate_steps = max(1, round(spec.encoder_speed_gate_s / dt))
        self._gate_s = self._gate_steps * dt
        self._counts_per_rad = spec.encoder_counts_per_rev / (2.0 * math.pi)
        # where the encoder's index sits against the rotor: unknown to the bench, fixed for the rig
        self.offset_rad = float(self._rng.uniform(0.0, 2.0 * math.pi))
        if spec.encoder_offset_rad >= 0.0:                        # a rig's fixed index (the draw is still made)
            self.offset_rad = float(spec.encoder_offset_rad)
        self._angle_rad = 0.0                                     # shaft angle, integrated from the plant's speed
        self._counts = np.full(self._gate_steps + 1, self._count_of(np.array([0.0]))[0])   # last gate + 1
        self._alpha = 1.0 - math.exp(-2.0 * math.pi * spec.torque_bandwidth_hz * dt)
        self._torque_filtered = 0.0
        self._last_speed = 0.0
        self._speed = 0.0
        self._torque = 0.0

    def __getattr__(self, name: str) -> Any:          # the wrapped model's attributes and methods
        return getattr(self._model, name)

    @property
    def time_s(self) -> float:
        return self._model.time_s

    def _count_of(self, angle_rad: np.ndarray) -> np.ndarray:
        jitter = self.instruments.encoder_noise_counts * self._rng.standard_normal(angle_rad.size)
        return np.floor((angle_rad + self.offset_rad) * self._counts_per_rad + jitter)

    def step(self, n: int) -> np.ndarray:
        block = self._model.step(n)
        dt = float(self._model.control_period_s)
        angles = self._angle_rad + np.cumsum(block[:, _SPEED]) * dt
        self._angle_rad = float(angles[-1])
        counts = self._count_of(angles)
        history = np.concatenate((self._counts, counts))[-(self._gate_steps + 1):]
        self._counts = history
        self._speed = float(history[-1] - history[0]) / self._counts_per_rad / self._gate_s
        speeds = block[:, _SPEED]
        shaft = block[:, _TORQUE] + self.instruments.dyno_inertia_kgm2 * np.diff(speeds, prepend=self._last_speed) / dt
        self._last_speed = float(speeds[-1])
        # first-order lag, one control period at a time: y[k] = y[k-1] + alpha (u[k] - y[k-1])
        filtered, _ = lfilter([self._alpha], [1.0, self._alpha - 1.0], shaft,
                              zi=[(1.0 - self._alpha) * self._torque_filtered])
        self._torque_filtered = float(filtered[-1])
        self._torque = self._torque_filtered + self.instruments.torque_noise_nm * float(self._rng.standard_normal())
        block[:, TRUTH_COLUMNS] = np.nan                      # the firmware has no position sensor
        return block

    def load_feedback(self) -> tuple[float, float]:
        """(speed_mech_rad_s, torque_nm) as the dynamometer's encoder and torque transducer read them."""
        return self._speed, self._torque

    def encoder_count(self) -> int:
        """The dynamometer encoder's raw count (angle = count / counts_per_rev * 2*pi + an unknown offset)."""
        return int(self._counts[-1])
