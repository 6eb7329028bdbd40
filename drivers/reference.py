"""The rig's reference sensor: where the bench's "true" signals come from (speed_true_mech_rad_s, torque_load_nm).

A sensorless drive's own speed is an estimate; what the shaft really does comes from a sensor the drive's firmware
does not use. The bench config's [reference] table says which:

    source = "load"     the load machine's encoder and torque transducer (its register map's speed/torque), read
                        with every SYNC (lockstep) or batch of samples (real time) and stamped with that sample's time
    source = "drive"    objects of the drive itself, for a sensored drive: map them in [drive.signals]
                        (e.g. speed_true_mech_rad_s = { object = "0x2F10", factor = 0.001 })
    source = "none"     no reference: criteria on true signals are not judged on this bench

Without [reference]: a drive carrying drivebench's extension reports the simulated rig encoder itself ("drive");
any other drive has none. A signal the bench cannot measure (true flux on a real rig) is "not measured", and a
criterion on it is reported as not judged — never a pass.

With source "load" or "none" the drive is not a source of rig truth at all: the signals drivers.contract.signals marks as
`reference` (true speed, position error, true flux, load torque) are never taken from the drive, whatever it offers;
the load machine gives speed_true_mech_rad_s and torque_load_nm, the rest is not measured. Its readings come at the
SYNC rate; on a drive with a trace recorder they are interpolated onto the trace's rows (onto_rows).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from drivers.api import LoadFeedback
from drivers.contract.sections import Section, key
from drivers.contract.signals import SIGNALS

SOURCES = ("load", "drive", "none")
LOAD_SIGNALS = ("speed_true_mech_rad_s", "torque_load_nm")
RIG_TRUTH = tuple(s.name for s in SIGNALS if s.reference)    # what only a rig's instruments (or a simulator) know


@dataclass(frozen=True)
class ReferenceConfig(Section):
    """[reference]: where the bench's true signals come from."""

    SECTION = "reference"
    source: str | None = key(None, kind="string", required=True, choices=SOURCES)   # None: not stated (the drive's)

    def signals(self, has_load: bool) -> tuple[str, ...]:
        """What the bench itself adds to every sample (the drive's own signals come from its profile)."""
        return LOAD_SIGNALS if self.source == "load" and has_load else ()

    def as_record(self, has_load: bool) -> dict[str, Any]:
        return {"source": self.source or "drive (not stated)", "bench_signals": list(self.signals(has_load))}

    def not_from_drive(self) -> frozenset[str]:
        """Signals the bench never takes from the drive: all rig truth once the reference is stated elsewhere."""
        return frozenset(RIG_TRUTH) if self.source in ("load", "none") else frozenset()

    def instruments(self, has_load: bool, load_map: Any = None, drive: str = "the drive") -> dict[str, str]:
        """Which instrument each rig-truth signal comes from, for the record (`load_map`: drivers.contract.load_map.LoadMap)."""
        out: dict[str, str] = {}
        for name in RIG_TRUTH:
            if name in self.signals(has_load):
                role = "speed" if name == "speed_true_mech_rad_s" else "torque"
                out[name] = _register_note(load_map, role)
            elif name in self.not_from_drive():
                out[name] = "not measured: no instrument on this rig gives it"
            else:
                out[name] = f"{drive}'s own report (reference source: {self.source or 'drive, not stated'})"
        return out


def _register_note(load_map: Any, role: str) -> str:
    if load_map is None:
        return f"load machine {role} feedback"
    reg = load_map[role]
    unit = f"{reg.extra.get('unit', 'rad/s')} x {reg.extra.get('scale', 1.0)}" if role == "speed" \
        else f"N*m x {reg.extra.get('scale', 1.0)}"
    what = f": {reg.description}" if reg.description else ""
    return f"{load_map.name}, {role} register {reg.address} ({reg.type}, {unit}) via Modbus{what}"


def values_from_load(feedback: LoadFeedback) -> dict[str, float]:
    """The load machine's feedback as reference signals (torque positive opposing positive rotation)."""
    return {"speed_true_mech_rad_s": feedback.speed_mech_rad_s, "torque_load_nm": feedback.torque_nm}


def onto_rows(t_rows: np.ndarray, readings: Sequence[tuple[float, dict[str, float]]],
              names: Sequence[str]) -> dict[str, np.ndarray]:
    """Reference readings [(t_s, values)] (time order) interpolated linearly onto rows at t_rows; held after the last
    reading, NaN before the first (the bench had no reading yet)."""
    t = np.asarray(t_rows, dtype=np.float64)
    if not readings:
        return {name: np.full(t.size, np.nan) for name in names}
    tr = np.array([r[0] for r in readings], dtype=np.float64)
    out = {}
    for name in names:
        v = np.array([r[1].get(name, np.nan) for r in readings], dtype=np.float64)
        col = np.interp(t, tr, v)
        col[t < tr[0] - 1e-9] = np.nan
        out[name] = col
    return out
