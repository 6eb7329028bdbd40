"""Fit the motor that explains a recorded run: least squares over the twin's replay (scipy.optimize.least_squares).

Parameters are the motor file's own dotted keys ([plant] and [mechanics]; the drive's [firmware] is the drive's and
stays as it is). They are fitted as log(value / start) (positive, comparable steps), with a forward-difference
Jacobian of the replay. Residuals: for every signal the run recorded among `FIT_SIGNALS`, (twin - recorded) / sigma
on every `decimate`-th row, sigma = the signal's own sample-to-sample noise (median absolute second difference,
floored at a twentieth of its tube tolerance, so a noiseless encoder does not outweigh everything else). A coordinate
scan (each parameter x0.8 and x1.25 in turn, a lower cost kept) gives least_squares its start.

Confidence intervals (95 %): covariance (J^T J)^-1 s^2 with s^2 the residual variance (sum r^2 / (m - n)), inflated by
(1 + rho) / (1 - rho), rho the residuals' lag-1 autocorrelation (clamped to [0, 0.999]: neighbouring rows of a closed
loop need not be independent; on the PMSM identification run rho came out <= 0, no inflation). A parameter is reported not identified
when its interval is wider than its value, when it sits on a bound, or when it carries a direction of the Jacobian
(columns scaled to unit norm: collinearity, not sensitivity) whose singular value is below 1e-3 of the largest (the
run cannot tell it apart from the others it moves with).
"""

from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.ndimage import uniform_filter1d
from scipy.optimize import least_squares

from drivers.contract.errors import InputError
from sim_backend.twin import RecordedRun, build_drive, get_key, read_motor, replay, with_values
from sim_backend.twin_tube import BLIND_SPEED, ESTIMATES, TOLERANCES, blind_rows

PARAMS: dict[str, tuple[str, ...]] = {
    "pmsm": ("plant.rs_ohm", "plant.ls_h", "plant.flux_wb", "mechanics.inertia_kgm2", "mechanics.viscous_nm_s_rad"),
    "spim": ("plant.rsd_ohm", "plant.rsq_ohm", "plant.rr_ohm", "plant.lsd_h", "plant.lsq_h", "plant.lr_h",
             "plant.msrd_h", "plant.msrq_h", "mechanics.inertia_kgm2", "mechanics.viscous_nm_s_rad"),
}
# the compared signals and the drive's voltage commands (u = R i + L di/dt + back-EMF: R_s, L_s and psi_m)
FIT_SIGNALS: dict[str, dict[str, float]] = {kind: {**tol, "u_sx_v": 1.0, "u_sy_v": 1.0}
                                             for kind, tol in TOLERANCES.items()}
BOUND_FACTOR = 5.0              # each parameter within [start / 5, start * 5]
SINGULAR_RATIO = 1e-3
# before the gradient steps: each parameter tried at these factors of its value, one at a time, a better cost kept.
# A closed loop's replay is smooth at large scale and rough at small (the SPIM's 100 Hz torque pulsation, dead-time
# compensation switching): from the paper motor the SPIM fit's first Jacobian pointed R_sd the wrong way (-1 % for a
# +20 % motor) while the cost at R_sd x1.2 was 38 % lower.
SCAN_FACTORS = (0.8, 1.25)
# residuals of moving averages over this time (s): the SPIM's torque and currents pulsate at twice the stator frequency,
# and a pointwise comparison of two pulsations makes the cost swing with their phase (B x0.95 doubled it, x1.05 six
# times, x0.6 lower than x0.8: measured on the lab SPIM rig); 20 ms covers a pulsation period from 25 Hz stator up
SMOOTH_S = {"pmsm": 0.0, "spim": 0.02}
Z95 = 1.959964
# On an instruments rig (twin.Instruments with a dyno inertia) the replayed load is the transducer's reading minus
# J_dyno dw/dt taken from the 10 ms encoder readings: through the ramps it is a reconstruction, and the parameters
# the run sees only through small voltage terms take its error up. Measured on sim-pmsm-lab-instruments, pmsm-identify
# from the paper motor: L_s -9.3 % (true value unchanged, 95 % interval -12 % .. -6 %) with every tube inside; the
# cost at the true motor (98.9k) above the fitted one (84.9k). Such a parameter is reported not identified there.
LOAD_RECONSTRUCTION_SENSITIVE = {"pmsm": ("plant.ls_h",), "spim": ()}


@dataclass
class FittedParam:
    key: str
    start: float
    value: float
    low: float
    high: float
    identified: bool
    reason: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"value": self.value, "interval": [self.low, self.high], "start": self.start,
                "change_pct": 100.0 * (self.value / self.start - 1.0), "identified": self.identified,
                **({"reason": self.reason} if self.reason else {})}


@dataclass
class FitResult:
    kind: str
    params: list[FittedParam]
    signals: list[str]
    rows: int
    residuals: int
    cost_start: float
    cost: float
    nfev: int                   # the optimiser's evaluations (without its Jacobians)
    replays: int                # every replay the fit ran, Jacobians and the start included
    time_s: float
    autocorrelation: float
    singular_values: list[float]
    message: str
    notes: list[str] = field(default_factory=list)

    @property
    def values(self) -> dict[str, float]:
        return {p.key: p.value for p in self.params}

    def to_dict(self) -> dict[str, Any]:
        return {"fitted": {p.key: p.to_dict() for p in self.params},
                "not_identified": {p.key: p.reason for p in self.params if not p.identified},
                "fit": {"signals": self.signals, "rows": self.rows, "residuals": self.residuals,
                        "cost_start": self.cost_start, "cost": self.cost, "evaluations": self.nfev,
                        "replays": self.replays,
                        "time_s": self.time_s, "residual_lag1_autocorrelation": self.autocorrelation,
                        "singular_values": self.singular_values, "message": self.message, "notes": self.notes}}


def _noise_sigma(y: np.ndarray, floor: float) -> float:
    d2 = np.diff(y[np.isfinite(y)], 2)
    if d2.size < 10:
        return floor
    return max(1.4826 * float(np.median(np.abs(d2 - np.median(d2)))) / math.sqrt(6.0), floor)


def fit(cfg: dict[str, Any], run: RecordedRun, keys: tuple[str, ...] | None = None, *, decimate: int = 4,
        signals: dict[str, float] | None = None, max_nfev: int = 60, diff_step: float = 2e-3,
        scan: tuple[float, ...] = SCAN_FACTORS, smooth_s: float | None = None) -> FitResult:
    kind = cfg["motor"]["kind"]
    keys = tuple(keys or PARAMS[kind])
    for key in keys:
        try:
            get_key(cfg, key)
        except (KeyError, ValueError, TypeError):
            raise InputError(f"motor: {key}: not a number in the motor file (--param names a dotted key)") \
                from None
    start = np.array([get_key(cfg, k) for k in keys])
    if np.any(start <= 0):
        raise InputError(f"motor: {keys[int(np.argmin(start))]}: the fit needs a start value > 0")
    fit_signals = {n: tol for n, tol in (signals or FIT_SIGNALS[kind]).items() if run.measured(n)}
    if not fit_signals:
        raise InputError(f"{run.run_dir}: telemetry.parquet: none of {', '.join(FIT_SIGNALS[kind])} is recorded")
    rows = np.arange(run.t.size)[::decimate]
    names = list(fit_signals)
    smooth_s = SMOOTH_S.get(kind, 0.0) if smooth_s is None else smooth_s
    width = max(1, int(round(smooth_s / float(np.median(np.diff(run.t)))))) if smooth_s > 0 else 1

    def smooth(y: np.ndarray) -> np.ndarray:
        return uniform_filter1d(y, width, mode="nearest") if width > 1 else y

    recorded = np.stack([smooth(run.columns[n])[rows] for n in names])
    sigma = np.array([_noise_sigma(run.columns[n], fit_signals[n] / 20.0) for n in names])
    valid = np.isfinite(recorded)
    est = "speed_est_mech_rad_s"
    if run.measured(est):      # the estimates near zero speed follow the rig's noise (twin.BLIND_SPEED): left out
        blind = blind_rows(run.t, [run.columns[est]], BLIND_SPEED)[rows]
        for i, name in enumerate(names):
            if name in ESTIMATES:
                valid[i] &= ~blind
    notes = [f"sigma {n} = {s:.3g}" for n, s in zip(names, sigma)]

    def residuals(x: np.ndarray) -> np.ndarray:
        trial = with_values(cfg, dict(zip(keys, start * np.exp(x))))
        twin = replay(trial, run)
        sim = np.stack([smooth(twin[n])[rows] for n in names])
        r = (sim - recorded) / sigma[:, None]
        r = np.where(valid, r, 0.0)
        # a twin that tripped or diverged: a large finite residual keeps the optimiser away from there
        return np.nan_to_num(r, nan=1e3, posinf=1e3, neginf=-1e3).ravel()

    t0 = time.perf_counter()
    build_drive(cfg).step(1)                         # compile outside the timing
    r0 = residuals(np.zeros(len(keys)))
    bound = math.log(BOUND_FACTOR)
    x0, scan_replays = _coordinate_scan(residuals, len(keys), float(r0 @ r0), scan)
    res = least_squares(residuals, x0, bounds=(-bound, bound), method="trf", diff_step=diff_step,
                        x_scale=1.0, max_nfev=max_nfev, xtol=1e-6, ftol=1e-8, gtol=1e-8)
    elapsed = time.perf_counter() - t0
    jac = res.jac
    m, n = jac.shape
    r = res.fun
    s2 = float(r @ r) / max(m - n, 1)
    rho = _lag1(r.reshape(len(names), -1))
    inflation = (1.0 + rho) / (1.0 - rho) if rho < 0.999 else 1e3
    # collinearity: the SVD of the Jacobian with unit-norm columns (a parameter the replay is merely less sensitive to
    # is told by its interval, not here)
    norms = np.linalg.norm(jac, axis=0)
    unit = jac / np.where(norms > 0, norms, 1.0)
    sv, vt = np.linalg.svd(unit, full_matrices=False)[1:]
    weak = (sv < SINGULAR_RATIO * sv[0]) if sv.size and sv[0] > 0 else np.ones(n, bool)
    weak |= norms.min() <= 0 if norms.size else False
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_sv2 = np.where(sv > 1e-12 * max(sv[0], 1e-300), 1.0 / sv ** 2, np.inf)
    cov_unit = (vt.T * inv_sv2) @ vt
    cov_x = cov_unit / np.outer(np.where(norms > 0, norms, np.nan), np.where(norms > 0, norms, np.nan)) * s2 * inflation
    values = start * np.exp(res.x)
    reconstructed = run.instruments is not None and run.instruments.dyno_inertia_kgm2 > 0
    if reconstructed:
        notes.append("instruments rig: the load replayed is the transducer's reading minus J_dyno dw/dt; the intervals "
                     "do not include that reconstruction's error (J came out 3.6 % low on the lab instruments rig, "
                     "its interval not covering the truth)")
    params = []
    for i, key in enumerate(keys):
        sd_x = math.sqrt(cov_x[i, i]) if np.isfinite(cov_x[i, i]) and cov_x[i, i] >= 0 else math.inf
        low, high = values[i] * math.exp(-Z95 * sd_x), values[i] * math.exp(Z95 * sd_x)
        reasons = []
        if not math.isfinite(sd_x) or high - low > values[i]:
            reasons.append("95 % interval wider than the value: the run does not excite it")
        if abs(abs(res.x[i]) - bound) < 1e-6:
            reasons.append(f"on the fit's bound (x{BOUND_FACTOR:g} or /{BOUND_FACTOR:g} of the start)")
        for j in np.flatnonzero(weak):
            if abs(vt[j, i]) > 0.3:
                partners = [keys[q] for q in range(n) if q != i and abs(vt[j, q]) > 0.3]
                reasons.append("near-singular Jacobian direction" +
                               (f" shared with {', '.join(partners)}" if partners else "") +
                               f" (singular value {sv[j] / sv[0]:.1e} of the largest, unit-norm columns)")
        if reconstructed and key in LOAD_RECONSTRUCTION_SENSITIVE.get(kind, ()):
            reasons.append(f"rests on the replayed load, which on this rig is the torque transducer's reading minus "
                           f"J_dyno dw/dt ({run.instruments.dyno_inertia_kgm2:g} kg m^2) from the "
                           f"{run.instruments.encoder_speed_gate_s * 1e3:g} ms encoder readings: its error through the "
                           f"ramps moves this value (on the lab instruments rig: -9 % for an unchanged L_s)")
        params.append(FittedParam(key, float(start[i]), float(values[i]), float(low) if math.isfinite(low) else 0.0,
                                  float(high) if math.isfinite(high) else math.inf, not reasons, "; ".join(reasons)))
    return FitResult(kind, params, names, int(rows.size), int(m), 0.5 * float(r0 @ r0), float(res.cost),
                     int(res.nfev), 1 + scan_replays + int(res.nfev) + int(res.njev or 0) * n, elapsed, float(rho), [float(v / sv[0]) for v in sv] if sv.size else [],
                     str(res.message), notes)


MECHANICS = ("mechanics.inertia_kgm2", "mechanics.viscous_nm_s_rad")
MECHANICS_WINDOW_S = 0.05


def fit_mechanics(run: RecordedRun, torque_signal: str = "torque_est_nm", start: dict[str, float] | None = None,
                  window_s: float = MECHANICS_WINDOW_S) -> FitResult:
    """J and B of the shaft from what any drive and rig report, the drive's firmware a black box:
    J dw/dt + B w = T_e - T_L with w the reference sensor's shaft speed, T_e the drive's reported torque, T_L the
    measured load. Integrated over consecutive windows of window_s (no differentiation of a sampled speed):
    J (w(b) - w(a)) + B int_a^b w dt = int_a^b (T_e - T_L) dt, solved by linear least squares; intervals from
    (A^T A)^-1 s^2 as for the full fit. T_e is the drive's own figure: a torque constant or current scaling error in
    the drive moves J and B with it (docs/twin.md)."""
    t0 = time.perf_counter()
    needed = ("speed_true_mech_rad_s", torque_signal, "torque_load_nm")
    for name in needed:
        if not run.measured(name):
            raise InputError(f"{run.run_dir / 'telemetry.parquet'}: {name}: not recorded (the mechanics fit needs "
                                 f"the shaft speed, the drive's reported torque and the measured load)")
    t = run.t
    w = run.columns["speed_true_mech_rad_s"]
    net = run.columns[torque_signal] - run.columns["torque_load_nm"]
    ok = np.isfinite(w) & np.isfinite(net)
    t, w, net = t[ok], w[ok], net[ok]
    cum_w = np.concatenate(([0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))))
    cum_net = np.concatenate(([0.0], np.cumsum(0.5 * (net[1:] + net[:-1]) * np.diff(t))))
    edges = np.searchsorted(t, np.arange(t[0], t[-1], window_s))
    edges = np.unique(np.append(edges, t.size - 1))
    a, b = edges[:-1], edges[1:]
    design = np.column_stack([w[b] - w[a], cum_w[b] - cum_w[a]])
    target = cum_net[b] - cum_net[a]
    scale = np.abs(design).max(axis=0)
    scale[scale == 0] = 1.0
    coef, *_ = np.linalg.lstsq(design / scale, target, rcond=None)
    values = coef / scale
    resid = target - design @ values
    m, n = design.shape
    s2 = float(resid @ resid) / max(m - n, 1)
    rho = _lag1(resid[None, :])
    cov = np.linalg.pinv((design / scale).T @ (design / scale)) * s2 * ((1 + rho) / (1 - rho))
    sd = np.sqrt(np.clip(np.diag(cov), 0, None)) / scale
    sv = np.linalg.svd(design / scale, compute_uv=False)
    starts = start or {}
    params = []
    for i, key in enumerate(MECHANICS):
        low, high = values[i] - Z95 * sd[i], values[i] + Z95 * sd[i]
        reasons = []
        if values[i] <= 0:
            reasons.append("fitted value not positive")
        if high - low > abs(values[i]):
            reasons.append("95 % interval wider than the value: the run does not excite it")
        params.append(FittedParam(key, float(starts.get(key, values[i])), float(values[i]), float(low), float(high),
                                  not reasons, "; ".join(reasons)))
    cost = 0.5 * float(resid @ resid)
    return FitResult("mechanics", params, list(needed), int(t.size), int(m), 0.5 * float(target @ target), cost,
                     1, 0, time.perf_counter() - t0, float(rho), [float(v / sv[0]) for v in sv],
                     f"linear least squares over {m} windows of {window_s:g} s")


def _coordinate_scan(residuals, n: int, cost0: float, factors: tuple[float, ...]) -> tuple[np.ndarray, int]:
    """One pass of coordinate search over log-factors; returns the start for least_squares and the replays used."""
    x = np.zeros(n)
    best = cost0
    replays = 0
    for i in range(n):
        for f in factors:
            trial = x.copy()
            trial[i] = math.log(f)
            r = residuals(trial)
            replays += 1
            c = float(r @ r)
            if c < best:
                best, x = c, trial
    return x, replays


def _lag1(r: np.ndarray) -> float:
    """Lag-1 autocorrelation of the residuals, per signal row, pooled."""
    num = float(np.sum(r[:, 1:] * r[:, :-1]))
    den = float(np.sum(r * r))
    return max(0.0, min(num / den, 0.999)) if den > 0 else 0.0


_LINE = re.compile(r"^(\s*)([A-Za-z0-9_]+)(\s*=\s*)([^#\n]*?)(\s*)(#.*)?$")


def motor_toml(source: Path, result: FitResult, run_name: str) -> str:
    """The source motor file with the fitted values put in (layout, comments and [firmware] kept)."""
    lines = source.read_text(encoding="utf-8").splitlines()
    fitted = {p.key: p for p in result.params}
    section = ""
    out = []
    for line in lines:
        stripped = line.strip()
        if stripped.startswith("[") and stripped.endswith("]"):
            section = stripped.strip("[]").strip()
        m = _LINE.match(line)
        if m and f"{section}.{m.group(2)}" in fitted:
            p = fitted[f"{section}.{m.group(2)}"]
            if p.identified:
                value = f"{p.value:.6g}"
                comment = f"# twin fit of {run_name}: start {p.start:.6g}, 95 % interval [{p.low:.4g}, {p.high:.4g}]"
            else:       # a value the run does not determine is not written: the source's stays
                value = m.group(4).strip()
                comment = (f"# twin fit of {run_name}: NOT IDENTIFIED ({p.reason}); kept the source's value (the fit "
                           f"stopped at {p.value:.6g})")
            line = f"{m.group(1)}{m.group(2)}{m.group(3)}{value:<{max(len(m.group(4)), 1)}} {comment}"
        elif m and section == "motor" and m.group(2) == "name":
            line = f'{m.group(1)}name{m.group(3)}"twin fit of {run_name}" # was {m.group(4).strip()}'
        out.append(line)
    text = "\n".join(out) + "\n"
    header = (f"# Written by `drivebench twin --fit` from the run {run_name}, starting from {source.name}: the [plant] and\n"
              f"# [mechanics] values marked 'twin fit' are fitted (one NOT IDENTIFIED keeps the source's value);\n"
              f"# everything else is the source file's.\n")
    return header + text


def write_motor(source: Path, result: FitResult, run_name: str, path: Path) -> None:
    text = motor_toml(source, result, run_name)
    path.write_text(text, encoding="utf-8")
    build_drive(read_motor(path), where=str(path))      # usable at once by a simulated rig
