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


def writable_names(kind: str) -> tuple[str, ...]:
    return TEST_HOOKS + FIRMWARE_PARAMS[kind] + PLANT_PARAMS[kind]
