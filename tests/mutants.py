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

import numpy as np
import pytest

Edit = tuple[str, str]


@dataclass(frozen=True)
class Mutant:
    name: str
    drive: str                                 # "pmsm" or "spim"
    what: str                                  # what the mutant firmware does, for docs/validation.md
    firmware: list[Edit] = field(default_factory=list)
    kernel: list[Edit] = field(default_factory=list)
    cheat: tuple[tuple[str, float], ...] = ()  # settings of the generic cheat block (CHEAT_SLOTS), issue 36
    kind: str = ""                             # the cheat's class, for the kill table


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

# --- cheats a vendor under schedule pressure might ship (issue 36) -----------------------------------------------
# One edit set per drive: a generic block decides each control period how much of the sensor the loops use
# (0 = the estimator, 1 = the sensor, between = a blend of the speed feedback); the mutant's settings (mode, alpha,
# threshold, window) are written into CHEAT_SLOTS extra firmware-state values, so the variants of a drive share one
# compilation. HOOKS counts the hook and parameter writes the drive has received (tests/mutants.py _cheat_state).
CHEAT_SLOTS = ("MODE", "ALPHA", "THRESH", "WINDOW", "RUN_T", "LAST_REF", "SINCE_REF", "HOOKS", "HOOKS_SEEN",
               "SINCE_HOOK")
ALWAYS, LOW_SPEED, AFTER_ENABLE, AFTER_REF_CHANGE, WATCHDOG, TEST_AWARE, TEST_AWARE_WINDOW, REPORT_BLEND, \
    HIGH_LOAD, START_AND_RAMPS = range(1, 11)

_CHEAT_FUNCTION = """
X_MODE, X_ALPHA, X_THRESH, X_WINDOW, X_RUN_T, X_LAST_REF, X_SINCE_REF, X_HOOKS, X_HOOKS_SEEN, X_SINCE_HOOK = \\
    range(N_CHEAT_BASE, N_CHEAT_BASE + 10)


@njit(cache=True)
def _cheat_use(s, sensor_mech, load_a, ref_cmd, ramping, ts):
    mode = s[X_MODE]
    s[X_RUN_T] += ts
    if ref_cmd != s[X_LAST_REF]:
        s[X_LAST_REF] = ref_cmd
        s[X_SINCE_REF] = 0.0
    else:
        s[X_SINCE_REF] += ts
    if s[X_HOOKS] != s[X_HOOKS_SEEN]:
        s[X_HOOKS_SEEN] = s[X_HOOKS]
        s[X_SINCE_HOOK] = 0.0
    else:
        s[X_SINCE_HOOK] += ts
    a = s[X_ALPHA]
    th = s[X_THRESH]
    win = s[X_WINDOW]
    if mode == 1.0:
        return a
    if mode == 2.0:
        return a if abs(sensor_mech) < th else 0.0
    if mode == 3.0:
        return 1.0 if s[X_RUN_T] < win else 0.0
    if mode == 4.0:
        return 1.0 if (ramping or s[X_SINCE_REF] < win) else 0.0
    if mode == 6.0:
        return 1.0 if s[X_HOOKS_SEEN] == 0.0 else 0.0
    if mode == 7.0:
        return 0.0 if s[X_SINCE_HOOK] < win else 1.0
    if mode == 9.0:
        return 1.0 if abs(load_a) > th else 0.0
    if mode == 10.0:
        return 1.0 if (ramping or s[X_RUN_T] < win) else 0.0
    return 0.0


"""

PMSM_CHEAT_EDITS = _PMSM_ENCODER_INPUT + [
    ("N_STATE = 25\n", "N_STATE = 25\nN_CHEAT_BASE = 25\n"),
    ("def new_state(initial_flux_wb", _CHEAT_FUNCTION + "def new_state(initial_flux_wb"),
    ("        if s[S_RUNNING] == 0.0:\n            _start(s, p,",
     "        if s[S_RUNNING] == 0.0:\n            s[X_RUN_T] = 0.0\n            _start(s, p,"),
    ("        i_xy = _update_estimators(s, p, i_ab)\n"
     "        i_ref = complex(p[F_ISX_REF], _speed_controller(s, p))\n"
     "        u_xy = _current_controller(s, p, i_xy, i_ref, vdc)\n"
     "        # the command takes effect next period: rotate with the angle at the middle of that period\n"
     "        advance = p[F_DELAY_COMP] * s[S_OMEGA] * p[F_PERIOD]\n"
     "        from_frame = complex(s[S_TO_FRAME_RE], -s[S_TO_FRAME_IM]) * _small_rotation(advance)\n"
     "        u_ab = u_xy * from_frame\n",
     "        i_xy = _update_estimators(s, p, i_ab)\n"
     "        enc_w = p[F_POLE_PAIRS] * row[C_ENC_SPEED_MECH]\n"
     "        enc_th = row[C_ENC_ANGLE_ELEC]\n"
     "        ramping = s[S_SPEED_REF_RAMPED] != s[S_SPEED_REF_CMD]\n"
     "        use = _cheat_use(s, row[C_ENC_SPEED_MECH], i_xy.imag, s[S_SPEED_REF_CMD], ramping, p[F_PERIOD])\n"
     "        if s[X_MODE] == 5.0 and (abs(s[S_OMEGA] - enc_w) > p[F_POLE_PAIRS] * s[X_THRESH]\n"
     "                                  or abs(_wrap(s[S_THETA] - enc_th)) > s[X_ALPHA]):\n"
     "            s[S_THETA] = enc_th\n"
     "            s[S_OMEGA] = enc_w\n"
     "            s[S_INT_OMEGA] = enc_w\n"
     "            s[S_TO_FRAME_RE] = math.cos(enc_th)\n"
     "            s[S_TO_FRAME_IM] = -math.sin(enc_th)\n"
     "            i_xy = i_ab * complex(s[S_TO_FRAME_RE], s[S_TO_FRAME_IM])\n"
     "        est_omega, est_re, est_im = s[S_OMEGA], s[S_TO_FRAME_RE], s[S_TO_FRAME_IM]\n"
     "        if use >= 1.0:\n"
     "            s[S_OMEGA] = enc_w\n"
     "            s[S_TO_FRAME_RE] = math.cos(enc_th)\n"
     "            s[S_TO_FRAME_IM] = -math.sin(enc_th)\n"
     "            i_xy = i_ab * complex(s[S_TO_FRAME_RE], s[S_TO_FRAME_IM])\n"
     "        elif use > 0.0:\n"
     "            s[S_OMEGA] = (1.0 - use) * est_omega + use * enc_w\n"
     "        i_ref = complex(p[F_ISX_REF], _speed_controller(s, p))\n"
     "        u_xy = _current_controller(s, p, i_xy, i_ref, vdc)\n"
     "        advance = p[F_DELAY_COMP] * s[S_OMEGA] * p[F_PERIOD]\n"
     "        from_frame = complex(s[S_TO_FRAME_RE], -s[S_TO_FRAME_IM]) * _small_rotation(advance)\n"
     "        u_ab = u_xy * from_frame\n"
     "        s[S_OMEGA], s[S_TO_FRAME_RE], s[S_TO_FRAME_IM] = est_omega, est_re, est_im\n"),
    ("    row[C_SPEED_EST] = s[S_OMEGA] * p[F_INV_POLE_PAIRS]\n",
     "    row[C_SPEED_EST] = s[S_OMEGA] * p[F_INV_POLE_PAIRS]\n"
     "    if s[X_MODE] == 8.0 and want_run:\n"
     "        row[C_SPEED_EST] = (1.0 - s[X_ALPHA]) * row[C_SPEED_EST] + s[X_ALPHA] * row[C_ENC_SPEED_MECH]\n"),
]

SPIM_CHEAT_EDITS = [
    ("N_FW_STATE = 32\n", "N_FW_STATE = 32\nN_CHEAT_BASE = 32\n"),
    ("def new_state() -> np.ndarray:", _CHEAT_FUNCTION + "def new_state() -> np.ndarray:"),
    ("        reset_controllers(s)\n        s[S_RUNNING] = 1.0\n",
     "        reset_controllers(s)\n        s[S_RUNNING] = 1.0\n        s[X_RUN_T] = 0.0\n"),
    ("    speed_est = s[S_SPEED_EST]\n",
     "    tach = row[C_SPEED_TRUE]\n"
     "    if s[X_MODE] == 5.0 and abs(s[S_SPEED_EST] - tach) > s[X_THRESH]:\n"
     "        s[S_SPEED_EST] = tach\n"
     "        s[S_SLIP_INT] = ws - f[F_NP] * tach\n"
     "        s[S_SLIP] = s[S_SLIP_INT]\n"
     "    use = _cheat_use(s, tach, i_q, s[S_SPEED_TARGET], s[S_SPEED_REF] != s[S_SPEED_TARGET], ts)\n"
     "    speed_est = (1.0 - use) * s[S_SPEED_EST] + use * tach\n"),
    ("    row[C_SPEED_EST] = speed_est\n",
     "    row[C_SPEED_EST] = s[S_SPEED_EST]\n"
     "    if s[X_MODE] == 8.0:\n"
     "        row[C_SPEED_EST] = (1.0 - s[X_ALPHA]) * s[S_SPEED_EST] + s[X_ALPHA] * tach\n"),
]


def _cheat(drive: str, kind: str, name: str, what: str, **settings: float) -> Mutant:
    if drive == "pmsm":
        return Mutant(name, "pmsm", what, firmware=PMSM_CHEAT_EDITS, kernel=_PMSM_ENCODER_KERNEL,
                      cheat=tuple(settings.items()), kind=kind)
    return Mutant(name, "spim", what, firmware=SPIM_CHEAT_EDITS, kernel=_SPIM_SENSOR_KERNEL,
                  cheat=tuple(settings.items()), kind=kind)


PARTIAL, TRANSIENT, REGION, TEST_AWARE_CLASS = ("partial sensor use", "sensor in transients only",
                                                 "sensor in a region only", "test-aware firmware")
CHEAT_MUTANTS = [
    _cheat("pmsm", PARTIAL, "blend_10pct", "speed feedback 90 % MRAS + 10 % encoder, always", MODE=ALWAYS, ALPHA=0.1),
    _cheat("pmsm", PARTIAL, "blend_30pct", "speed feedback 70 % MRAS + 30 % encoder, always", MODE=ALWAYS, ALPHA=0.3),
    _cheat("pmsm", PARTIAL, "blend_20pct_below_10rads", "speed feedback 20 % encoder below 10 mech rad/s",
           MODE=LOW_SPEED, ALPHA=0.2, THRESH=10.0),
    _cheat("pmsm", PARTIAL, "report_blend_20pct", "control on the MRAS; the reported speed estimate 20 % encoder",
           MODE=REPORT_BLEND, ALPHA=0.2),
    _cheat("pmsm", TRANSIENT, "encoder_0.5s_after_enable", "encoder in the loops for 0.5 s after each enable",
           MODE=AFTER_ENABLE, WINDOW=0.5),
    _cheat("pmsm", TRANSIENT, "encoder_0.3s_after_ref_change",
           "encoder in the loops while the ramp runs and for 0.3 s after each reference change",
           MODE=AFTER_REF_CHANGE, WINDOW=0.3),
    _cheat("pmsm", TRANSIENT, "watchdog_0.1rad", "estimator snapped to the encoder when the angles differ by "
           "> 0.1 elec rad or the speeds by > 2 mech rad/s", MODE=WATCHDOG, ALPHA=0.1, THRESH=2.0),
    _cheat("pmsm", TRANSIENT, "watchdog_0.3rad", "estimator snapped to the encoder when the angles differ by "
           "> 0.3 elec rad or the speeds by > 5 mech rad/s", MODE=WATCHDOG, ALPHA=0.3, THRESH=5.0),
    _cheat("pmsm", REGION, "encoder_above_2.5A", "encoder in the loops while abs(i_sy) > 2.5 A (high load)",
           MODE=HIGH_LOAD, THRESH=2.5),
    _cheat("pmsm", TEST_AWARE_CLASS, "honest_after_first_write",
           "encoder in the loops until the first hook or parameter write, the MRAS after it", MODE=TEST_AWARE),
    _cheat("pmsm", TEST_AWARE_CLASS, "honest_2s_after_each_write",
           "the MRAS for 2 s after each hook or parameter write, the encoder otherwise",
           MODE=TEST_AWARE_WINDOW, WINDOW=2.0),
    _cheat("spim", PARTIAL, "tach_blend_10pct", "speed feedback 90 % estimate + 10 % tachometer, always",
           MODE=ALWAYS, ALPHA=0.1),
    _cheat("spim", PARTIAL, "tach_blend_30pct", "speed feedback 70 % estimate + 30 % tachometer, always",
           MODE=ALWAYS, ALPHA=0.3),
    _cheat("spim", PARTIAL, "tach_blend_30pct_below_300rpm", "speed feedback 30 % tachometer below 300 r/min",
           MODE=LOW_SPEED, ALPHA=0.3, THRESH=31.416),
    _cheat("spim", PARTIAL, "report_blend_20pct", "control on the estimate; the reported estimate 20 % tachometer",
           MODE=REPORT_BLEND, ALPHA=0.2),
    _cheat("spim", TRANSIENT, "tach_1s_after_enable", "tachometer in the speed loop for 1 s after each enable",
           MODE=AFTER_ENABLE, WINDOW=1.0),
    _cheat("spim", TRANSIENT, "tach_0.5s_after_ref_change",
           "tachometer while the ramp runs and for 0.5 s after each reference change", MODE=AFTER_REF_CHANGE,
           WINDOW=0.5),
    _cheat("spim", TRANSIENT, "watchdog_1rads", "speed estimate and slip snapped to the tachometer when they "
           "differ by > 1 rad/s", MODE=WATCHDOG, THRESH=1.0),
    _cheat("spim", REGION, "tach_above_2A", "tachometer in the speed loop while abs(i_sq) > 2 A (high load)",
           MODE=HIGH_LOAD, THRESH=2.0),
    _cheat("spim", REGION, "tach_below_100rpm", "tachometer in the speed loop below 100 r/min (very low speed)",
           MODE=LOW_SPEED, ALPHA=1.0, THRESH=10.472),
    _cheat("spim", REGION, "tach_at_start_and_ramps",
           "tachometer for 1.5 s after the enable and while the speed ramp runs", MODE=START_AND_RAMPS, WINDOW=1.5),
    _cheat("spim", TEST_AWARE_CLASS, "honest_after_first_write",
           "tachometer until the first hook or parameter write, the estimate after it", MODE=TEST_AWARE),
    _cheat("spim", TEST_AWARE_CLASS, "honest_2s_after_each_write",
           "the estimate for 2 s after each hook or parameter write, the tachometer otherwise",
           MODE=TEST_AWARE_WINDOW, WINDOW=2.0),
]


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


_BUILT: dict[tuple, object] = {}


def build(mutant: Mutant):
    """The mutant's run_steps (compiled on its first call); mutants with the same edits share one compilation (the
    cheats of issue 36 differ only in their settings, written into the firmware state)."""
    key = (mutant.drive, tuple(mutant.firmware), tuple(mutant.kernel))
    if key not in _BUILT:
        _BUILT[key] = _build(mutant)
    return _BUILT[key]


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
        with _cheat_state(mutant):
            yield
    finally:
        kernel.run_steps = original


@contextlib.contextmanager
def _cheat_state(mutant: Mutant):
    """For a cheat (issue 36): the firmware state carries CHEAT_SLOTS more values (its settings and memories), and
    every hook or parameter write the drive receives is counted there, as a firmware sees its own SDO writes."""
    if not mutant.cheat:
        yield
        return
    firmware = importlib.import_module(f"sim_backend.{mutant.drive}.firmware")
    model = importlib.import_module(f"sim_backend.{mutant.drive}.model")
    cls = model.PmsmDrive if mutant.drive == "pmsm" else model.SpimDrive
    new_state, set_hook = firmware.new_state, cls.set_hook
    settings = dict(mutant.cheat)
    unknown = set(settings) - set(CHEAT_SLOTS)
    if unknown:
        raise AssertionError(f"{mutant.name}: unknown cheat settings {sorted(unknown)}")

    def extended(*args, **kwargs):
        s = new_state(*args, **kwargs)
        extra = [settings.get(name, 1e9 if name.startswith("SINCE") else 0.0) for name in CHEAT_SLOTS]
        return np.concatenate([s, np.array(extra, dtype=float)])

    def counting(self, name, value):
        set_hook(self, name, value)
        state = self._fw_s if mutant.drive == "pmsm" else self._fs
        state[len(state) - len(CHEAT_SLOTS) + CHEAT_SLOTS.index("HOOKS")] += 1.0

    firmware.new_state, cls.set_hook = extended, counting
    try:
        yield
    finally:
        firmware.new_state, cls.set_hook = new_state, set_hook
