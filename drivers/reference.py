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
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from drivers.api import LoadFeedback

SOURCES = ("load", "drive", "none")
LOAD_SIGNALS = ("speed_true_mech_rad_s", "torque_load_nm")


@dataclass(frozen=True)
class ReferenceConfig:
    source: str | None = None                  # None: not stated (the drive decides)

    def signals(self, has_load: bool) -> tuple[str, ...]:
        """What the bench itself adds to every sample (the drive's own signals come from its profile)."""
        return LOAD_SIGNALS if self.source == "load" and has_load else ()

    def as_record(self, has_load: bool) -> dict[str, Any]:
        return {"source": self.source or "drive (not stated)", "bench_signals": list(self.signals(has_load))}


def values_from_load(feedback: LoadFeedback) -> dict[str, float]:
    """The load machine's feedback as reference signals (torque positive opposing positive rotation)."""
    return {"speed_true_mech_rad_s": feedback.speed_mech_rad_s, "torque_load_nm": feedback.torque_nm}


def check_section(table: Any, has_load: bool) -> tuple[ReferenceConfig | None, list[tuple[str, str]]]:
    if table is None:
        return ReferenceConfig(), []
    if not isinstance(table, dict):
        return None, [("reference", "must be a table: [reference] source = \"load\" | \"drive\" | \"none\"")]
    problems = [(f"reference.{key}", "unknown key (allowed: source)") for key in table if key != "source"]
    source = table.get("source")
    if source not in SOURCES:
        problems.append(("reference.source", f"must be one of {', '.join(repr(s) for s in SOURCES)}, got {source!r}"))
    elif source == "load" and not has_load:
        problems.append(("reference.source", "'load' needs a load machine ([load]) and this bench has none"))
    return (None if problems else ReferenceConfig(source)), problems
