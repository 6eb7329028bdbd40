"""Names of the firmware test hooks, firmware parameter overrides and simulator plant injections.

These names are the contract between the drive models, the object dictionaries (EDS ParameterName of the
manufacturer objects) and scenario files. A model accepts exactly the names listed for its kind.
"""

from __future__ import annotations

# One-shot or latched test hooks a lab's test firmware has (both drive kinds).
TEST_HOOKS: tuple[str, ...] = (
    "flux_est_scale",       # write f: estimated flux magnitude <- f * estimated flux, once (PMSM paper Fig. 7)
    "pos_est_offset_rad",   # write a: estimated field angle <- estimated angle + a, once (PMSM paper Fig. 10)
    "freeze_speed_est",     # 1: hold the speed (PMSM) / slip (SPIM) estimator output; 0: release
    "freeze_flux_est",      # 1: hold the flux-magnitude estimator output; 0: release
)

# Firmware model parameters a scenario may override (absolute values, SI units), per drive kind.
FIRMWARE_PARAMS: dict[str, tuple[str, ...]] = {
    "pmsm": ("fw_rs_ohm", "fw_ls_h", "fw_flux_wb", "fw_inertia_kgm2"),
    "spim": ("fw_rsd_ohm", "fw_rsq_ohm", "fw_rr_ohm", "fw_lsd_h", "fw_lsq_h", "fw_lr_h",
             "fw_msrd_h", "fw_msrq_h", "fw_inertia_kgm2"),
}

# Simulator-only plant injections: the value written is a factor on the nominal plant parameter.
PLANT_PARAMS: dict[str, tuple[str, ...]] = {
    "pmsm": ("plant_rs", "plant_ls", "plant_flux", "plant_inertia"),
    "spim": ("plant_rsd", "plant_rsq", "plant_rr", "plant_inertia"),
}


# Simulator-only fault injections (sim_backend/faults.py), both drive kinds. Handled by the simulated device and
# its protocol front ends, not by the drive model; refused like plant_* on a bench with plant_injections = false.
FAULT_INJECTIONS: tuple[str, ...] = (
    "fault_drop_frames_rate",     # p in [0, 1]: the drive's CAN/serial output frames are dropped with probability p
    "fault_corrupt_frames_rate",  # p in [0, 1]: one bit of each output frame is flipped with probability p
    "fault_delay_frames_s",       # d >= 0: every output frame leaves d seconds late (wall clock)
    "fault_stop_heartbeat",       # 1: the node stops producing heartbeats (everything else keeps working)
    "fault_overcurrent",          # 1: the drive's own protection trips: FAULT, EMCY 0x2310, power stage off
    "fault_freeze_estimator",     # 1: speed and flux estimators hold their outputs (both freeze_* hooks)
    "fault_kill_endpoint",        # 1: the drive endpoint goes silent; 2: the load machine's; 3: both
    "fault_bus_error",            # 1: the drive's CAN controller floods error frames (bus heavy / error passive)
    "fault_load_machine",         # 1: the load machine faults: status fault bit set, torque off
)


def writable_names(kind: str) -> tuple[str, ...]:
    """What the drive model itself accepts."""
    return TEST_HOOKS + FIRMWARE_PARAMS[kind] + PLANT_PARAMS[kind]


def injectable_names(kind: str) -> tuple[str, ...]:
    """What a simulated drive accepts through its protocols: the model's names plus the fault injections."""
    return writable_names(kind) + FAULT_INJECTIONS


def is_simulator_only(name: str) -> bool:
    return name.startswith("plant_") or name in FAULT_INJECTIONS
