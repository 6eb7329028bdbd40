"""Loads a torque-controlled dynamometer lacks, emulated by the bench from the measured shaft speed.

A lab's dynamometer in torque mode has no brake or viscous mode (its register map lists the modes it has,
drivers.contract.load_map). Where the bench measures the shaft's speed itself (`[reference] source = "load"`: the
dynamometer's encoder, read with every SYNC), it emulates them: at every SYNC it reads the speed, computes the load
torque the missing mode would give and sends it as a torque setpoint, held until the next SYNC. A crane is an active
torque (m g r) and needs no emulation. Where the machine has the mode natively (drivebench's simulated dynamometer),
the bench sends the mode itself and emulates nothing.

Laws (T_L opposes positive rotation, drivers.api.LoadMode):
- viscous: T_L = c * w;
- brake:   T_L = T_b * clip(w / BRAKE_BAND_MECH_RAD_S, -1, 1). A real brake's torque jumps at zero speed (Coulomb
  friction, zero at standstill); a torque source fed with a lagged speed and a jump would push the shaft through zero
  and chatter there. Inside |w| < BRAKE_BAND_MECH_RAD_S the emulated brake's torque follows the speed linearly, so it
  always opposes the measured motion, is zero at standstill and never drives a standing shaft.

Lag: the torque applied during one SYNC period comes from the speed read at its start, which the dynamometer measured
over its own window (the instruments rigs: counts over a 10 ms gate, i.e. the mean speed 5 ms before the reading). So
the torque follows the speed with a delay between gate/2 and T_sync + gate/2 (5-15 ms on the instruments rigs, 10 ms
on average), plus the Modbus write's transit on a real rig (about 1-5 ms over TCP; none in lockstep simulation).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

from drivers.contract.load_map import LoadMode
from drivers.contract.load_map import read_load_map

BRAKE_BAND_MECH_RAD_S = 0.5      # |w| below this: the emulated brake's torque is linear in w (see the docstring)
EMULABLE = (LoadMode.VISCOUS, LoadMode.BRAKE)
SPEED_SIGNAL = "speed_true_mech_rad_s"


def emulable(mode: LoadMode, native: Iterable[LoadMode], speed_measured: bool) -> bool:
    """The bench can give `mode` on a machine with the `native` modes: it lacks it, has torque mode, and the bench
    measures the shaft speed itself."""
    native = tuple(native)
    return mode not in native and mode in EMULABLE and LoadMode.TORQUE in native and speed_measured


def emulates_on(cfg, mode: LoadMode) -> bool:
    """Whether a run on bench config `cfg` (bench.inputs.benchconfig.BenchConfig) emulates `mode`."""
    if not cfg.load or not cfg.load.get("map"):
        return False
    return emulable(mode, read_load_map(cfg.load["map"]).modes, cfg.reference_source == "load")


def emulated_torque_nm(mode: LoadMode, value: float, speed_mech_rad_s: float) -> float:
    """The load torque (opposing positive rotation) of `mode` with its scenario `value` at the measured speed."""
    if mode == LoadMode.VISCOUS:
        return value * speed_mech_rad_s
    if mode == LoadMode.BRAKE:
        return value * max(-1.0, min(1.0, speed_mech_rad_s / BRAKE_BAND_MECH_RAD_S))
    raise ValueError(f"{mode.name.lower()} mode is not emulated")


def lag_bounds_s(sync_period_s: float, speed_window_s: float) -> tuple[float, float]:
    """Shortest and longest delay from the shaft's speed to the emulated torque (no Modbus transit included)."""
    return speed_window_s / 2.0, sync_period_s + speed_window_s / 2.0


@dataclass(frozen=True)
class LoadEmulation:
    """What a run emulates: the machine's native modes and whether the bench reads the shaft speed."""
    native: tuple[LoadMode, ...]
    speed_measured: bool
    sync_period_s: float

    def emulates(self, mode: LoadMode) -> bool:
        return emulable(mode, self.native, self.speed_measured)

    def setting(self, mode: LoadMode, value: float, speed_mech_rad_s: float) -> tuple[LoadMode, float]:
        """What to send the machine for the profile's (mode, value): itself, or the emulated torque."""
        if not self.emulates(mode):
            return mode, value
        return LoadMode.TORQUE, emulated_torque_nm(mode, value, speed_mech_rad_s)

    def as_record(self, modes: Iterable[LoadMode]) -> dict:
        used = sorted({m.name.lower() for m in modes if self.emulates(m)})
        return {"modes": used, "from": SPEED_SIGNAL, "period_s": self.sync_period_s,
                "brake_band_mech_rad_s": BRAKE_BAND_MECH_RAD_S,
                "lag": "torque from the speed read at the start of each SYNC period, held for it: delay T_sync + "
                       "half the dynamometer's speed window at most (+ the Modbus write on a real rig)"}
