"""Design check of the MRAS estimators: closed-loop poles of the 2x2 MIMO system, PMSM paper eq. (13).

    det(I + diag(Gc_w, Gc_psi) G) = (1 + Gc_w G_ww)(1 + Gc_psi G_psipsi) - Gc_w Gc_psi G_wpsi G_psiw = 0
with eq. (9):  G_ww = (s^2 + a1 s + w^2)/(s D),  G_wpsi = w F/(psi D),  G_psiw = -a1 psi/(w s D),
               G_psipsi = 1/D,  F = s + a1,  D = F^2 + w^2,
and Gc_w = (kp_w s + ki_w)/s, Gc_psi = (kp_psi s + ki_psi)/s. Multiplying by s^3 D^2 gives the polynomial
    (s^2 D + N_w P)(s D + N_psi) + a1 F N_w N_psi = 0,   N = kp s + ki,  P = s^2 + a1 s + w^2,
of degree 7: the paper's seven poles. D divides it (at D = 0 it reduces to N_w N_psi (P + a1 F) =
N_w N_psi D), so two of the seven are always -a1 +- j w: the stator-current error modes, which the
adaptation cannot move; the other five are the estimator loops. psi^ cancels; w enters only as w^2; i_sx, i_sy enter only the
disturbance paths G_wa1, G_psia1 and so not the poles (the paper's "for any value of i_sx and i_sy").
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from drivers.contract.errors import InputError
from sim_backend.drive import load_motor_config


def estimator_gains(cfg: dict) -> dict[str, float]:
    try:
        return _estimator_gains(cfg)
    except KeyError as exc:
        raise InputError(f"[firmware] {exc.args[0]}: missing") from None
    except (TypeError, ValueError) as exc:
        raise InputError(f"[firmware] estimator gains: {exc}") from None


def _estimator_gains(cfg: dict) -> dict[str, float]:
    fw = cfg["firmware"]
    a1 = float(fw["rs_ohm"]) / float(fw["ls_h"])
    ratio = fw["speed_est_ki_over_kp"]
    kp_w = float(fw["speed_est_kp"])
    kp_psi = float(fw["flux_est_kp"])
    return {
        "a1": a1,
        "kp_w": kp_w,
        "ki_w": kp_w * (a1 if ratio == "a1" else float(ratio)),
        "kp_psi": kp_psi,
        "ki_psi": kp_psi * float(fw["flux_est_ki_over_kp"]),
    }


def characteristic_polynomial(speed_elec_rad_s: float, a1: float, kp_w: float, ki_w: float,
                              kp_psi: float, ki_psi: float) -> np.ndarray:
    """Coefficients (highest power first) of eq. (13) cleared of denominators."""
    w2 = speed_elec_rad_s ** 2
    F = np.array([1.0, a1])
    D = np.polyadd(np.polymul(F, F), [w2])
    P = np.array([1.0, a1, w2])
    n_w = np.array([kp_w, ki_w])
    n_psi = np.array([kp_psi, ki_psi])
    s = np.array([1.0, 0.0])
    speed_loop = np.polyadd(np.polymul(np.polymul(s, s), D), np.polymul(n_w, P))
    flux_loop = np.polyadd(np.polymul(s, D), n_psi)
    coupling = a1 * np.polymul(F, np.polymul(n_w, n_psi))
    return np.polyadd(np.polymul(speed_loop, flux_loop), coupling)


def default_speeds() -> np.ndarray:
    """The paper's Fig. 6 range: +-0.1 to +-314 elect. rad/s, log-spaced."""
    magnitudes = np.logspace(np.log10(0.1), np.log10(314.0), 60)
    return np.concatenate([-magnitudes[::-1], magnitudes])


def run_design_check(motor_config_path: str | Path, speeds: Any = None, i_sx: float = 0.0,
                     i_sy: float = 2.0) -> dict:
    """Poles over the speed range; i_sx, i_sy are recorded (they do not move the poles, see module doc)."""
    cfg = load_motor_config(motor_config_path)
    if cfg["motor"]["kind"] != "pmsm":
        raise InputError(f"{motor_config_path}: [motor] kind: the design check is eq. (13) of the PMSM "
                               f"paper and needs kind = 'pmsm', got {cfg['motor']['kind']!r}")
    try:
        gains = estimator_gains(cfg)
    except InputError as exc:
        raise InputError(f"{motor_config_path}: {exc}") from None
    speeds = default_speeds() if speeds is None else np.asarray(speeds, dtype=float)
    per_speed = []
    worst: tuple[float, float, complex] | None = None
    for w in speeds:
        poly = characteristic_polynomial(float(w), **gains)
        poles = np.roots(poly)
        poles = poles[np.lexsort((poles.imag, poles.real))]
        per_speed.append({"speed_elec_rad_s": float(w),
                          "poles": [[float(p.real), float(p.imag)] for p in poles]})
        p_max = poles[np.argmax(poles.real)]
        if worst is None or p_max.real > worst[0]:
            worst = (float(p_max.real), float(w), complex(p_max))
    assert worst is not None
    return {
        "motor_config": str(motor_config_path),
        "gains": gains,
        "operating_point": {"i_sx_a": i_sx, "i_sy_a": i_sy},
        "pole_count": len(per_speed[0]["poles"]),
        "max_real_part": worst[0],
        "stable": worst[0] < 0.0,
        "least_stable": {"speed_elec_rad_s": worst[1], "pole": [worst[2].real, worst[2].imag]},
        "per_speed": per_speed,
    }


def format_table(result: dict) -> str:
    g = result["gains"]
    lines = [
        f"MRAS estimator design check, eq. (13): {result['motor_config']}",
        f"a1 = {g['a1']:.2f} 1/s  kp_w = {g['kp_w']:g}  ki_w = {g['ki_w']:.6g}  "
        f"kp_psi = {g['kp_psi']:g}  ki_psi = {g['ki_psi']:.6g}",
        f"{result['pole_count']} closed-loop poles per speed (two are always -a1 +- j w_e; i_sx, i_sy do not move them)",
        f"{'w_e [rad/s]':>12}  {'max Re(s)':>10}  poles (re+im j)",
    ]
    for entry in result["per_speed"]:
        poles = entry["poles"]
        re_max = max(p[0] for p in poles)
        text = "  ".join(f"{p[0]:.4g}{p[1]:+.4g}j" for p in poles)
        lines.append(f"{entry['speed_elec_rad_s']:12.4g}  {re_max:10.4g}  {text}")
    ls = result["least_stable"]
    verdict = "all poles in the left half plane" if result["stable"] else "UNSTABLE: a pole with Re >= 0"
    lines.append(f"max real part {result['max_real_part']:.6g} 1/s at w_e = {ls['speed_elec_rad_s']:.4g} "
                 f"elect. rad/s: {verdict}")
    return "\n".join(lines)
