"""The telemetry catalogue: one name per signal from firmware to record to Rerun entity path.

Order matters: it is the column order of every telemetry block a drive model returns and of the
trace recorder's channels. Units are in the names; electrical vs mechanical is always explicit.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Signal:
    name: str
    unit: str
    description: str
    reference: bool = False  # from the rig's reference sensors (encoder, torque transducer), never used by control


SIGNALS: tuple[Signal, ...] = (
    Signal("speed_ref_mech_rad_s", "rad/s", "speed reference after the drive's ramp limiter"),
    Signal("speed_est_mech_rad_s", "rad/s", "estimated rotor speed"),
    Signal("speed_true_mech_rad_s", "rad/s", "rotor speed from the rig encoder", reference=True),
    Signal("pos_est_elec_rad", "rad", "angle of the controller's field frame, wrapped to [-pi, pi)"),
    Signal("pos_err_elec_rad", "rad", "true field angle minus estimated, wrapped to [-pi, pi)", reference=True),
    Signal("flux_est_wb", "Wb", "estimated flux magnitude (PMSM rotor flux, SPIM stator flux)"),
    Signal("flux_true_wb", "Wb", "true flux magnitude (simulator; NaN on a real rig)", reference=True),
    Signal("i_sx_a", "A", "measured current, field (x/d) axis of the controller frame"),
    Signal("i_sy_a", "A", "measured current, torque (y/q) axis of the controller frame"),
    Signal("i_sx_ref_a", "A", "field-axis current reference"),
    Signal("i_sy_ref_a", "A", "torque-axis current reference"),
    Signal("u_sx_v", "V", "commanded voltage, field axis"),
    Signal("u_sy_v", "V", "commanded voltage, torque axis"),
    Signal("torque_est_nm", "N*m", "electromagnetic torque estimated by the firmware"),
    Signal("torque_load_nm", "N*m", "shaft load torque from the rig torque transducer", reference=True),
    Signal("vdc_v", "V", "measured DC-link voltage"),
)

SIGNAL_NAMES: tuple[str, ...] = tuple(s.name for s in SIGNALS)
SIGNAL_INDEX: dict[str, int] = {name: i for i, name in enumerate(SIGNAL_NAMES)}
TIME_COLUMN = "t_s"  # drive clock, seconds
