"""The parameter catalogue: every named value a scenario may write into a drive, in one place.

One record per name: what kind of thing it is, its unit, its domain, which drive kinds have it and whether only a
simulator can honour it. The drivebench object dictionaries (EDS manufacturer objects), the serial protocol's
parameter list, the simulated drive's dispatch and scenario validation all read this catalogue; the order of the
records is the order of the objects in the EDS and of the serial parameter list.

Kinds:
- test hook: a debug object a lab's test firmware has (write once or latch);
- firmware parameter: an estimator/controller model parameter, absolute value in SI units;
- plant injection: a factor on a nominal plant parameter (only a simulator has a plant to change);
- device fault: the simulated drive or load machine faults on its own (only a simulator);
- wire fault: frames or bytes on the simulated drive's wire are dropped, corrupted, delayed or stopped (only a
  simulator whose front ends carry the fault wrappers).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

DRIVE_KINDS = ("pmsm", "spim")


class ParamKind(enum.Enum):
    TEST_HOOK = "test hook"
    FIRMWARE = "firmware parameter"
    PLANT = "plant injection"
    DEVICE_FAULT = "device fault"
    WIRE_FAULT = "wire fault"


class Capability(enum.Enum):
    """What a bench must declare before a scenario may use a parameter of this kind (beyond the drive offering it)."""

    NONE = "none"
    PLANT = "plant_injections"      # [bench] plant_injections = true: the bench can change its plant (a simulator)
    WIRE = "wire_faults"            # [bench] wire_faults = true: the simulator's front ends carry fault wrappers


CAPABILITY_OF = {ParamKind.TEST_HOOK: Capability.NONE, ParamKind.FIRMWARE: Capability.NONE,
                 ParamKind.PLANT: Capability.PLANT, ParamKind.DEVICE_FAULT: Capability.PLANT,
                 ParamKind.WIRE_FAULT: Capability.WIRE}


@dataclass(frozen=True)
class Domain:
    """Allowed values and how a problem is worded: "<name> <meaning> and must be <rule>, got <value>"."""

    meaning: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False          # low itself excluded
    choices: tuple[float, ...] = ()
    choice_text: str = ""           # e.g. "1 (hold) or 0 (release)"
    hint: str = ""

    def problem(self, name: str, value: float) -> str | None:
        if not math.isfinite(value):
            return f"{name} must be finite, got {value}"
        if self.choices:
            if value not in self.choices:
                return f"{name} takes {self.choice_text}, got {value:g}"
            return None
        if self.low is not None and (value <= self.low if self.low_open else value < self.low) \
                or self.high is not None and value > self.high:
            return f"{name} {self.meaning} and must be {self.rule}, got {value:g}{self.hint}"
        return None

    @property
    def rule(self) -> str:
        if self.choices:
            return self.choice_text
        if self.low is not None and self.high is not None:
            return f"within {self.low:g}..{self.high:g}"
        if self.low is not None:
            return f"{'>' if self.low_open else '>='} {self.low:g}"
        return "finite"


ANY = Domain("is a value")
SWITCH = Domain("is a switch", choices=(0.0, 1.0), choice_text="1 (on) or 0 (off)")
HOLD = Domain("is a latch", choices=(0.0, 1.0), choice_text="1 (hold) or 0 (release)")
POSITIVE_SI = Domain("is an absolute parameter value in SI units", low=0.0, low_open=True)
PLANT_FACTOR = Domain("is a factor on the nominal plant value", low=0.0, low_open=True, hint=" (0.8 means -20 %)")


@dataclass(frozen=True)
class Parameter:
    name: str
    kind: ParamKind
    unit: str                        # "1" for factors and switches
    domain: Domain
    drive_kinds: tuple[str, ...]
    description: str

    @property
    def simulator_only(self) -> bool:
        return self.kind in (ParamKind.PLANT, ParamKind.DEVICE_FAULT, ParamKind.WIRE_FAULT)

    @property
    def capability(self) -> Capability:
        return CAPABILITY_OF[self.kind]

    def problem(self, value: float) -> str | None:
        return self.domain.problem(self.name, value)


_BOTH = DRIVE_KINDS
_P, _S = ("pmsm",), ("spim",)
H, F, PL, DF, WF = (ParamKind.TEST_HOOK, ParamKind.FIRMWARE, ParamKind.PLANT, ParamKind.DEVICE_FAULT,
                    ParamKind.WIRE_FAULT)

CATALOGUE: tuple[Parameter, ...] = (
    # test hooks (both drive kinds)
    Parameter("flux_est_scale", H, "1", Domain("is a factor on the estimated flux", low=0.0, low_open=True), _BOTH,
              "estimated flux magnitude <- f * estimated flux, once (PMSM paper Fig. 7)"),
    Parameter("pos_est_offset_rad", H, "rad", ANY, _BOTH,
              "estimated field angle <- estimated angle + a, once (PMSM paper Fig. 10)"),
    Parameter("freeze_speed_est", H, "1", HOLD, _BOTH,
              "1: hold the speed estimator (PMSM: w^ as it is) / slip estimator (SPIM: w^_sl at its PI's integral)"),
    Parameter("freeze_flux_est", H, "1", HOLD, _BOTH, "1: hold the flux-magnitude estimator output"),
    # firmware model parameters (absolute values, SI units)
    Parameter("fw_rs_ohm", F, "ohm", POSITIVE_SI, _P, "stator resistance in the estimators"),
    Parameter("fw_ls_h", F, "H", POSITIVE_SI, _P, "stator inductance in the estimators"),
    Parameter("fw_flux_wb", F, "Wb", POSITIVE_SI, _P, "nominal rotor flux in the estimators"),
    Parameter("fw_inertia_kgm2", F, "kg*m^2", POSITIVE_SI, _P, "inertia in the speed controller design"),
    Parameter("fw_deadtime_comp_v", F, "V", Domain("is a compensation voltage in V", low=0.0, high=100.0), _BOTH,
              "per-phase dead-time and device-drop compensation voltage (V_dc t_d f_pwm + V_drop when exact)"),
    Parameter("fw_isx_ref_a", F, "A", Domain("is a field-axis current in A", low=-5.0, high=5.0), _P,
              "field-axis current reference i_sx* (paper III.D: 0; non-zero shows eq. (15a))"),
    Parameter("fw_rsd_ohm", F, "ohm", POSITIVE_SI, _S, "main winding resistance"),
    Parameter("fw_rsq_ohm", F, "ohm", POSITIVE_SI, _S, "auxiliary winding resistance"),
    Parameter("fw_rr_ohm", F, "ohm", POSITIVE_SI, _S, "rotor resistance"),
    Parameter("fw_lsd_h", F, "H", POSITIVE_SI, _S, "main winding self inductance"),
    Parameter("fw_lsq_h", F, "H", POSITIVE_SI, _S, "auxiliary winding self inductance"),
    Parameter("fw_lr_h", F, "H", POSITIVE_SI, _S, "rotor self inductance"),
    Parameter("fw_msrd_h", F, "H", POSITIVE_SI, _S, "main winding mutual inductance"),
    Parameter("fw_msrq_h", F, "H", POSITIVE_SI, _S, "auxiliary winding mutual inductance"),
    Parameter("fw_inertia_kgm2", F, "kg*m^2", POSITIVE_SI, _S, "inertia in the speed controller design"),
    # plant injections (factor on the nominal value)
    Parameter("plant_rs", PL, "1", PLANT_FACTOR, _P, "stator resistance"),
    Parameter("plant_ls", PL, "1", PLANT_FACTOR, _P, "stator inductance"),
    Parameter("plant_flux", PL, "1", PLANT_FACTOR, _P, "permanent-magnet flux"),
    Parameter("plant_inertia", PL, "1", PLANT_FACTOR, _P, "shaft inertia"),
    Parameter("plant_rsd", PL, "1", PLANT_FACTOR, _S, "main winding resistance"),
    Parameter("plant_rsq", PL, "1", PLANT_FACTOR, _S, "auxiliary winding resistance"),
    Parameter("plant_rr", PL, "1", PLANT_FACTOR, _S, "rotor resistance"),
    Parameter("plant_inertia", PL, "1", PLANT_FACTOR, _S, "shaft inertia"),
    # the simulated inverter's non-idealities (absolute values, from then on)
    Parameter("inverter_dead_time_s", PL, "s", Domain("is a dead time in s", low=0.0, high=1e-5), _BOTH,
              "the inverter's dead time (PMSM paper config: 0, ideally compensated)"),
    Parameter("inverter_device_drop_v", PL, "V", Domain("is an on-state drop in V", low=0.0, high=5.0), _BOTH,
              "the inverter's IGBT/diode on-state drop"),
    # faults of the simulated rig (both drive kinds)
    Parameter("fault_drop_frames_rate", WF, "1", Domain("is a probability per frame", low=0.0, high=1.0), _BOTH,
              "the drive's CAN/serial output frames are dropped with probability p"),
    Parameter("fault_corrupt_frames_rate", WF, "1", Domain("is a probability per frame", low=0.0, high=1.0), _BOTH,
              "one bit of each output frame is flipped with probability p"),
    Parameter("fault_delay_frames_s", WF, "s", Domain("is a delay in seconds", low=0.0, high=10.0), _BOTH,
              "every output frame leaves d seconds late (wall clock)"),
    Parameter("fault_stop_heartbeat", WF, "1", SWITCH, _BOTH, "the node stops producing heartbeats"),
    Parameter("fault_overcurrent", DF, "1", SWITCH, _BOTH, "the drive's own protection trips: FAULT, EMCY 0x2310"),
    Parameter("fault_freeze_estimator", DF, "1", SWITCH, _BOTH, "speed and flux estimators hold their outputs"),
    Parameter("fault_kill_endpoint", WF, "1",
              Domain("selects an endpoint", choices=(1.0, 2.0, 3.0), choice_text="1 (drive), 2 (load machine) or 3 (both)"),
              _BOTH, "the drive endpoint (1), the load machine's (2) or both (3) go silent"),
    Parameter("fault_bus_error", WF, "1", SWITCH, _BOTH, "the drive's CAN controller floods error frames"),
    Parameter("fault_load_machine", DF, "1", SWITCH, _BOTH, "the load machine faults: fault bit set, torque off"),
)


def parameters_for(drive_kind: str, *kinds: ParamKind) -> tuple[Parameter, ...]:
    """The records a drive of `drive_kind` has (of the given kinds; all kinds when none given), catalogue order."""
    return tuple(p for p in CATALOGUE if drive_kind in p.drive_kinds and (not kinds or p.kind in kinds))


def names_for(drive_kind: str, *kinds: ParamKind) -> tuple[str, ...]:
    return tuple(p.name for p in parameters_for(drive_kind, *kinds))


def lookup(name: str, drive_kind: str | None = None) -> Parameter | None:
    """The record for `name` (of that drive kind, when given)."""
    return next((p for p in CATALOGUE if p.name == name and (drive_kind is None or drive_kind in p.drive_kinds)),
                None)


def checked(name: str, drive_kind: str, value: float) -> float:
    """value as a float when it is in the record's domain; ValueError naming the rule otherwise."""
    record = lookup(name, drive_kind)
    if record is None:
        raise KeyError(f"unknown parameter {name!r} for a {drive_kind} drive")
    problem = record.problem(float(value))
    if problem:
        raise ValueError(problem)
    return float(value)


ALL_NAMES: frozenset[str] = frozenset(p.name for p in CATALOGUE)
