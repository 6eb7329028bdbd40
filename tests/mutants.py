"""Firmware mutants: the simulated drives' firmware with one function changed, to show the acceptance suite rejects a
firmware that is not sensorless or not the paper's estimator.

A mutant is a list of source edits (exact text, found exactly once, so a mutant cannot silently turn into the
original when the firmware changes) to the firmware module and, for the cheats that read the plant, to the kernel
that calls it. The edited modules are compiled afresh (numba, no on-disk cache) and their `run_steps` replaces the
kernel's for the duration of a `with mutant_kernel(...)` block: the simulator then runs the mutant firmware through
the same CANopen stack and bench as the real one.
"""

from __future__ import annotations

import contextlib
import importlib
import re
import types
from dataclasses import dataclass, field
from pathlib import Path

import pytest

Edit = tuple[str, str]


@dataclass(frozen=True)
class Mutant:
    name: str
    drive: str                                 # "pmsm" or "spim"
    what: str                                  # what the mutant firmware does, for docs/validation.md
    firmware: list[Edit] = field(default_factory=list)
    kernel: list[Edit] = field(default_factory=list)


PMSM_MUTANTS = [
    Mutant("position_from_reference", "pmsm",
           "rho^ integrates the speed reference instead of the MRAS speed estimate (open-loop angle)",
           firmware=[("s[S_THETA] = _wrap(s[S_THETA] + w * T)                                   # (5c)",
                      "s[S_THETA] = _wrap(s[S_THETA] + p[F_POLE_PAIRS] * s[S_SPEED_REF_RAMPED] * T)")]),
    Mutant("frozen_speed_estimate", "pmsm", "w^ never updated by (8a): stays 0 from the enable",
           firmware=[("if s[S_FREEZE_SPEED] == 0.0:", "if False:")]),
    Mutant("speed_estimate_frozen_after_1s", "pmsm", "w^ updated by (8a) for the first second of drive time, then held",
           firmware=[("        i_xy = _update_estimators(s, p, i_ab)",
                      "        if t >= 1.0:\n            s[S_FREEZE_SPEED] = 1.0\n"
                      "        i_xy = _update_estimators(s, p, i_ab)")]),
    Mutant("frozen_flux_estimate", "pmsm", "psi^ never updated by (8b): stays at the nominal flux",
           firmware=[("if s[S_FREEZE_FLUX] == 0.0 and abs(w) < w_min:", "if False:"),
                     ("elif s[S_FREEZE_FLUX] == 0.0:", "elif False:")]),
    Mutant("encoder_cheat", "pmsm",
           "rho^ and w^ from the plant (an encoder): the frame is the true rotor flux angle, the flux estimator kept",
           firmware=[("if s[S_FREEZE_SPEED] == 0.0:", "if False:")],
           # the firmware advances rho^ by w^ T before use (5c): set so that it lands on the true angle
           kernel=[("        fw.firmware_step(fw_s, fw_p, ia_m, ib_m, vdc_m, t, row)",
                    "        fw_s[fw.S_OMEGA] = plant_p[pl.P_POLE_PAIRS] * x[pl.X_W_MECH]\n"
                    "        fw_s[fw.S_THETA] = math.atan2(x[pl.X_PSI_Q], x[pl.X_PSI_D]) - fw_s[fw.S_OMEGA] * period\n"
                    "        fw.firmware_step(fw_s, fw_p, ia_m, ib_m, vdc_m, t, row)")]),
]

# --- sensor-in-the-loop and detuned-estimator mutants (issue 24): the drive reports its estimator's output, but
# controls on an encoder (always, or only at low speed), or runs the estimator with its gains 10x off.
# The kernel hands the encoder to the firmware through two telemetry slots it overwrites afterwards.
_PMSM_ENCODER_INPUT = [
    ("C_VDC = SIGNAL_INDEX[\"vdc_v\"]\n",
     "C_VDC = SIGNAL_INDEX[\"vdc_v\"]\n"
     "C_ENC_SPEED_MECH = SIGNAL_INDEX[\"speed_true_mech_rad_s\"]   # mutant: encoder speed, from the kernel\n"
     "C_ENC_ANGLE_ELEC = SIGNAL_INDEX[\"pos_err_elec_rad\"]        # mutant: encoder angle (elec), from the kernel\n"),
]
_PMSM_ENCODER_KERNEL = [
    ("        fw.firmware_step(fw_s, fw_p, ia_m, ib_m, vdc_m, t, row)",
     "        row[C_SPEED_TRUE] = x[pl.X_W_MECH]\n"
     "        row[C_POS_ERR] = math.atan2(x[pl.X_PSI_Q], x[pl.X_PSI_D])\n"
     "        fw.firmware_step(fw_s, fw_p, ia_m, ib_m, vdc_m, t, row)"),
]


def _pmsm_sensor_control(condition: str) -> list[Edit]:
    """The MRAS runs and is reported (speed, angle, flux estimates, the frame the position error is taken in);
    the speed and current loops run on the encoder while `condition` holds."""
    return _PMSM_ENCODER_INPUT + [(
        "        i_xy = _update_estimators(s, p, i_ab)\n"
        "        i_ref = complex(p[F_ISX_REF], _speed_controller(s, p))\n"
        "        u_xy = _current_controller(s, p, i_xy, i_ref, vdc)\n"
        "        # the command takes effect next period: rotate with the angle at the middle of that period\n"
        "        advance = p[F_DELAY_COMP] * s[S_OMEGA] * p[F_PERIOD]\n"
        "        from_frame = complex(s[S_TO_FRAME_RE], -s[S_TO_FRAME_IM]) * _small_rotation(advance)\n"
        "        u_ab = u_xy * from_frame\n",
        "        i_xy = _update_estimators(s, p, i_ab)\n"
        "        est_omega, est_re, est_im = s[S_OMEGA], s[S_TO_FRAME_RE], s[S_TO_FRAME_IM]\n"
        f"        if {condition}:\n"
        "            s[S_OMEGA] = p[F_POLE_PAIRS] * row[C_ENC_SPEED_MECH]\n"
        "            s[S_TO_FRAME_RE] = math.cos(row[C_ENC_ANGLE_ELEC])\n"
        "            s[S_TO_FRAME_IM] = -math.sin(row[C_ENC_ANGLE_ELEC])\n"
        "            i_xy = i_ab * complex(s[S_TO_FRAME_RE], s[S_TO_FRAME_IM])\n"
        "        i_ref = complex(p[F_ISX_REF], _speed_controller(s, p))\n"
        "        u_xy = _current_controller(s, p, i_xy, i_ref, vdc)\n"
        "        advance = p[F_DELAY_COMP] * s[S_OMEGA] * p[F_PERIOD]\n"
        "        from_frame = complex(s[S_TO_FRAME_RE], -s[S_TO_FRAME_IM]) * _small_rotation(advance)\n"
        "        u_ab = u_xy * from_frame\n"
        "        s[S_OMEGA], s[S_TO_FRAME_RE], s[S_TO_FRAME_IM] = est_omega, est_re, est_im\n")]


def _pmsm_estimator_gains(factor: float) -> list[Edit]:
    return [("        kp_w = p[F_SPEED_EST_KP]\n        ki_w = p[F_KI_W]\n",
             f"        kp_w = {factor!r} * p[F_SPEED_EST_KP]\n        ki_w = {factor!r} * p[F_KI_W]\n"),
            ("        kp_psi = p[F_FLUX_EST_KP]\n        ki_psi = p[F_KI_PSI]\n",
             f"        kp_psi = {factor!r} * p[F_FLUX_EST_KP]\n        ki_psi = {factor!r} * p[F_KI_PSI]\n")]


PMSM_SENSOR_MUTANTS = [
    Mutant("encoder_control_mras_reported", "pmsm",
           "speed and current loops on the encoder; the MRAS runs beside it and its estimates are reported",
           firmware=_pmsm_sensor_control("True"), kernel=_PMSM_ENCODER_KERNEL),
    Mutant("encoder_below_5rads", "pmsm",
           "encoder in the loops below 5 mech rad/s (a hybrid drive), the MRAS above; the MRAS always reported",
           firmware=_pmsm_sensor_control("abs(row[C_ENC_SPEED_MECH]) < 5.0"), kernel=_PMSM_ENCODER_KERNEL),
    Mutant("estimator_gains_x0.1", "pmsm", "both MRAS PI controllers (8a), (8b) with their gains x0.1",
           firmware=_pmsm_estimator_gains(0.1)),
    Mutant("estimator_gains_x10", "pmsm", "both MRAS PI controllers (8a), (8b) with their gains x10",
           firmware=_pmsm_estimator_gains(10.0)),
]

SPIM_MUTANTS = [
    Mutant("slip_ignored", "spim", "rotor speed = stator-flux speed: the estimated slip is not subtracted",
           firmware=[("speed_raw = (ws - slip) / f[F_NP]", "speed_raw = ws / f[F_NP]")]),
    Mutant("frozen_slip_estimate", "spim", "the slip estimator (eqs. 35-42) never updated: slip stays 0",
           firmware=[("if s[S_FREEZE_SLIP] == 0.0:", "if False:")]),
    Mutant("frozen_flux_estimate", "spim", "the voltage-model stator flux never integrated",
           firmware=[("if s[S_FREEZE_FLUX] == 0.0:\n        s[S_PHI] = max(", "if False:\n        s[S_PHI] = max(")]),
    Mutant("true_speed_cheat", "spim", "the speed estimate read from the plant (a tachometer), estimators kept",
           firmware=[("s[S_SPEED_EST] += a_sp * (speed_raw - s[S_SPEED_EST])", "pass")],
           kernel=[("        gates_next, da, db, dc = fw.firmware_step(fs, fp, isd_m, isq_m, vdc_m, row)",
                    "        fs[fw.S_SPEED_EST] = x[pl.X_WM]\n"
                    "        gates_next, da, db, dc = fw.firmware_step(fs, fp, isd_m, isq_m, vdc_m, row)")]),
]

# The SPIM kernel hands the tachometer and the plant's stator flux (angle, magnitude) to the firmware through
# telemetry slots it overwrites afterwards.
_SPIM_SENSOR_KERNEL = [
    ("        gates_next, da, db, dc = fw.firmware_step(fs, fp, isd_m, isq_m, vdc_m, row)",
     "        row[fw.C_SPEED_TRUE] = x[pl.X_WM]\n"
     "        psq1_m = pp[pl.P_LSD] * isq / k_true + pp[pl.P_MSRD] * irq\n"
     "        row[fw.C_FLUX_TRUE] = math.sqrt(x[pl.X_PSD] * x[pl.X_PSD] + psq1_m * psq1_m)\n"
     "        row[fw.C_POS_ERR] = math.atan2(psq1_m, x[pl.X_PSD])\n"
     "        gates_next, da, db, dc = fw.firmware_step(fs, fp, isd_m, isq_m, vdc_m, row)"),
]


def _spim_tach_control(condition: str) -> list[Edit]:
    """The speed loop runs on the tachometer while `condition` holds; the estimate is computed and reported."""
    return [("    speed_est = s[S_SPEED_EST]\n",
             f"    speed_est = row[C_SPEED_TRUE] if {condition} else s[S_SPEED_EST]\n"),
            ("    row[C_SPEED_EST] = speed_est\n", "    row[C_SPEED_EST] = s[S_SPEED_EST]\n")]


def _spim_slip_gains(factor: float) -> list[Edit]:
    return [("        s[S_SLIP_INT] += f[F_KI_W] * ts * eps\n        s[S_SLIP] = f[F_KP_W] * eps + s[S_SLIP_INT]\n",
             f"        s[S_SLIP_INT] += {factor!r} * f[F_KI_W] * ts * eps\n"
             f"        s[S_SLIP] = {factor!r} * f[F_KP_W] * eps + s[S_SLIP_INT]\n")]


SPIM_SENSOR_MUTANTS = [
    Mutant("tach_control_estimate_reported", "spim",
           "speed loop on a tachometer; the paper's speed estimator runs beside it and is reported",
           firmware=_spim_tach_control("True"), kernel=_SPIM_SENSOR_KERNEL),
    Mutant("tach_below_150rpm", "spim",
           "tachometer in the speed loop below 150 r/min (a hybrid drive), the estimate above; the estimate reported",
           firmware=_spim_tach_control("abs(row[C_SPEED_TRUE]) < 15.708"), kernel=_SPIM_SENSOR_KERNEL),
    Mutant("slip_from_plant", "spim", "the slip taken from the plant (stator-frame speed minus the true rotor speed)",
           firmware=[("    slip = s[S_SLIP]\n", "    slip = ws - f[F_NP] * row[C_SPEED_TRUE]\n")],
           kernel=_SPIM_SENSOR_KERNEL),
    Mutant("flux_from_plant", "spim", "the oriented stator flux (angle and magnitude) taken from the plant",
           firmware=[("    phi = s[S_PHI]\n    ws = eq / max(phi, f[F_PHI_MIN])\n",
                      "    s[S_PHI] = row[C_FLUX_TRUE]\n    phi = s[S_PHI]\n    ws = eq / max(phi, f[F_PHI_MIN])\n"),
                     ("    s[S_THETA] = wrap_angle(s[S_THETA] + ts * ws)\n",
                      "    s[S_THETA] = row[C_POS_ERR]\n")],
           kernel=_SPIM_SENSOR_KERNEL),
    Mutant("slip_gains_x0.1", "spim", "the slip PI (eqs. 40-42) with its gains x0.1", firmware=_spim_slip_gains(0.1)),
    Mutant("slip_gains_x10", "spim", "the slip PI (eqs. 40-42) with its gains x10", firmware=_spim_slip_gains(10.0)),
]

ALL_MUTANTS = PMSM_MUTANTS + SPIM_MUTANTS
SENSOR_MUTANTS = PMSM_SENSOR_MUTANTS + SPIM_SENSOR_MUTANTS


def _apply(source: str, edits: list[Edit], where: str) -> str:
    for old, new in edits:
        count = source.count(old)
        if count != 1:
            raise AssertionError(f"{where}: the mutant's edit target is found {count} times, not once: {old!r}")
        source = source.replace(old, new)
    return source


def _compile(module_name: str, source: str, names: dict) -> types.ModuleType:
    original = importlib.import_module(module_name)
    source = source.replace("cache=True", "cache=False")
    source = re.sub(r"^drop_stale_cache\(.*?\)\n", "", source, flags=re.S | re.M)
    module = types.ModuleType(f"{module_name}_mutant")
    module.__file__ = original.__file__
    module.__dict__.update(names)
    exec(compile(source, f"<mutant of {Path(original.__file__).name}>", "exec"), module.__dict__)
    return module


_BUILT: dict[tuple[str, str], object] = {}


def build(mutant: Mutant):
    """The mutant's run_steps (compiled on its first call), one per mutant and process: two tests of one mutant on
    the same pytest worker (xdist_group, `--dist loadgroup`) pay its numba compile once."""
    if (mutant.drive, mutant.name) not in _BUILT:
        _BUILT[(mutant.drive, mutant.name)] = _build(mutant)
    return _BUILT[(mutant.drive, mutant.name)]


def compile_group(mutant: Mutant) -> pytest.MarkDecorator:
    """The xdist group that keeps every test of this mutant on one worker (so its compile is shared)."""
    return pytest.mark.xdist_group(f"mutant-{mutant.drive}-{mutant.name}")


def _build(mutant: Mutant):
    pkg = f"sim_backend.{mutant.drive}"
    fw_src = Path(importlib.import_module(f"{pkg}.firmware").__file__).read_text()
    kn_src = Path(importlib.import_module(f"{pkg}.kernel").__file__).read_text()
    fw_mod = _compile(f"{pkg}.firmware", _apply(fw_src, mutant.firmware, f"{mutant.name}: firmware"), {})
    import_line = f"from {pkg} import firmware as fw\n"
    kn_src = _apply(kn_src, [(import_line, "")], f"{mutant.name}: kernel")
    kn_mod = _compile(f"{pkg}.kernel", _apply(kn_src, mutant.kernel, f"{mutant.name}: kernel"), {"fw": fw_mod})
    return kn_mod.run_steps


@contextlib.contextmanager
def mutant_kernel(mutant: Mutant, run_steps=None):
    """The simulator's kernel replaced by the mutant's for the block (in-process simulator only)."""
    kernel = importlib.import_module(f"sim_backend.{mutant.drive}.kernel")
    original = kernel.run_steps
    kernel.run_steps = run_steps or build(mutant)
    try:
        yield
    finally:
        kernel.run_steps = original
