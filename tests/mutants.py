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

ALL_MUTANTS = PMSM_MUTANTS + SPIM_MUTANTS


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


def build(mutant: Mutant):
    """The mutant's run_steps (compiled on its first call)."""
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
