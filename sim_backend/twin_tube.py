"""The tube (`tube`): around each recorded signal, the band of all values within +-time_tol_s and +-value_tol of it:
lower(t) = min over |tau - t| <= time_tol_s of y(tau) - value_tol, upper likewise; the twin is inside where
lower <= twin <= upper, and `excess` = how far outside (0 inside). This is the rectangle tube of csv-compare and of
LBNL's funnel (pyfunnel) on a uniformly sampled reference. pyfunnel itself was tried and not used: its only interface
writes five CSV files per comparison into a directory and returns a status code (the errors are read back from
errors.csv), prints its warnings on stdout (which `--json` owns) and ships a prebuilt C library built for Python up to
3.12; the tube here is a sliding minimum and maximum (scipy.ndimage) on the recorded samples, in memory.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.ndimage import maximum_filter1d, minimum_filter1d

# signals compared inside a tube, and their default value tolerance (signal units); time tolerance for all.
# PMSM: a few times the recording's noise (5 mA current noise, ~0.05 rad/s on the speed estimate). SPIM: its
# single-phase torque pulsates at twice the supply frequency, and its current noise is 20 mA: twice as wide.
COMPARED: dict[str, float] = {
    "speed_true_mech_rad_s": 1.0,
    "speed_est_mech_rad_s": 1.0,
    "i_sx_a": 0.1,
    "i_sy_a": 0.1,
    "flux_est_wb": 0.01,
}
TOLERANCES: dict[str, dict[str, float]] = {"pmsm": COMPARED, "spim": {k: 2.0 * v for k, v in COMPARED.items()}}
TIME_TOL_S = 0.005
# Near zero speed a sensorless drive's estimates follow the ADC noise (the PMSM flux estimator, paper eq. (7b), divides
# by w^2; its speed estimate spikes by ~10 rad/s for a few ms when it crosses the firmware's threshold): a twin without
# the rig's noise cannot follow them there, whatever its motor. The drive's estimates are not compared within
# BLIND_TIME_S of the recorded or the twin's speed estimate being below BLIND_SPEED (mech rad/s); the rest is.
ESTIMATES = ("speed_est_mech_rad_s", "flux_est_wb")
BLIND_SPEED = 2.0
BLIND_TIME_S = 0.02


@dataclass
class TubeResult:
    signal: str
    value_tol: float
    time_tol_s: float
    inside: bool
    max_excess: float                    # largest distance outside the tube (signal unit), 0 when inside
    t_max_excess_s: float | None
    fraction_outside: float              # of the compared rows
    first_exit_s: float | None
    intervals_outside: list[tuple[float, float]]
    rms_difference: float                # twin - recorded, over the compared rows
    not_compared_s: float = 0.0          # drive seconds left out (the estimates near zero speed)

    def to_dict(self) -> dict[str, Any]:
        return {"signal": self.signal, "value_tol": self.value_tol, "time_tol_s": self.time_tol_s,
                "not_compared_s": self.not_compared_s,
                "inside": self.inside, "max_excess": self.max_excess, "t_max_excess_s": self.t_max_excess_s,
                "fraction_outside": self.fraction_outside, "first_exit_s": self.first_exit_s,
                "intervals_outside": [list(iv) for iv in self.intervals_outside[:20]],
                "intervals_outside_count": len(self.intervals_outside), "rms_difference": self.rms_difference}


def tube_bounds(t: np.ndarray, y: np.ndarray, time_tol_s: float, value_tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bound of the tube around y(t) (uniform sampling assumed for the window width)."""
    dt = float(np.median(np.diff(t)))
    width = 2 * int(round(time_tol_s / dt)) + 1
    filled = np.where(np.isfinite(y), y, np.nan)
    lo = minimum_filter1d(np.where(np.isfinite(filled), filled, np.inf), width, mode="nearest") - value_tol
    hi = maximum_filter1d(np.where(np.isfinite(filled), filled, -np.inf), width, mode="nearest") + value_tol
    return lo, hi


def blind_rows(t: np.ndarray, speeds: list[np.ndarray], blind_speed: float = BLIND_SPEED,
               blind_time_s: float = BLIND_TIME_S) -> np.ndarray:
    """Rows within blind_time_s of any of the speed estimates being below blind_speed in magnitude."""
    slow = np.zeros(t.size, bool)
    for v in speeds:
        slow |= np.isfinite(v) & (np.abs(v) < blind_speed)
    if blind_speed <= 0 or not slow.any():
        return slow
    dt = float(np.median(np.diff(t)))
    return maximum_filter1d(slow.astype(np.int8), 2 * int(round(blind_time_s / dt)) + 1, mode="nearest") > 0


def tube(signal: str, t: np.ndarray, recorded: np.ndarray, twin: np.ndarray, time_tol_s: float,
         value_tol: float, ignore: np.ndarray | None = None) -> TubeResult:
    lo, hi = tube_bounds(t, recorded, time_tol_s, value_tol)
    ignore = np.zeros(t.size, bool) if ignore is None else ignore
    ok = np.isfinite(recorded) & np.isfinite(twin) & np.isfinite(lo) & np.isfinite(hi) & ~ignore
    excess = np.zeros_like(twin)
    excess[ok] = np.maximum(twin[ok] - hi[ok], 0.0) + np.maximum(lo[ok] - twin[ok], 0.0)
    twin_lost = np.isfinite(recorded) & ~np.isfinite(twin)       # the twin tripped or diverged: outside
    excess[twin_lost] = np.inf
    out = excess > 0
    compared = int((ok | twin_lost).sum())
    intervals: list[tuple[float, float]] = []
    if out.any():
        edges = np.flatnonzero(np.diff(np.concatenate(([0], out.astype(np.int8), [0]))))
        intervals = [(float(t[a]), float(t[b - 1])) for a, b in zip(edges[::2], edges[1::2])]
    k = int(np.argmax(excess)) if out.any() else None
    diff = (twin - recorded)[ok]
    return TubeResult(signal, value_tol, time_tol_s, not out.any(), float(excess[k]) if k is not None else 0.0,
                      float(t[k]) if k is not None else None, float(out.sum() / max(compared, 1)),
                      intervals[0][0] if intervals else None, intervals,
                      float(np.sqrt(np.mean(diff ** 2))) if diff.size else math.nan,
                      float(ignore.sum() * np.median(np.diff(t))))
