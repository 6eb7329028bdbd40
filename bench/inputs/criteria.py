"""Acceptance criteria: one number per criterion from telemetry arrays, compared with a limit.

Every kind computes a `value` where smaller is better; a criterion passes when value <= limit. Its status is
"pass", "fail" or "not_judged" (never raises):
- not judged: a signal it needs is not measured on this bench, or data is missing in its window (no telemetry, the
  telemetry does not cover the window, rows missing from the drive clock); the bench could not see, so it neither
  passes nor fails, and the run's verdict is at best "incomplete";
- fail: the value is over the limit, or a measured signal is NaN/inf in the window (a drive putting out NaN is
  broken, not unmeasured), or the criterion cannot be computed (a zero base for a percentage).
`detail` says why. Angles (names ending in `_rad`) are compared through wrapped differences and averaged on the
circle.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Callable

import numpy as np

from drivers.contract.checks import Problems
from drivers.contract.signals import SIGNAL_NAMES


@dataclass(frozen=True)
class CriterionSpec:
    name: str
    kind: str
    signal: str
    window_s: tuple[float, float]
    limit: float
    params: dict = field(default_factory=dict)
    known_gap: str | None = None


@dataclass
class CriterionResult:
    name: str
    kind: str
    signal: str
    window_s: tuple[float, float]
    value: float
    limit: float
    passed: bool
    known_gap: str | None
    detail: str
    status: str = ""               # "pass" | "fail" | "not_judged"
    unit: str = ""                 # of value and limit ("%", "s", the signal's unit); "" where it has none

    def __post_init__(self) -> None:
        if not self.status:
            self.status = "pass" if self.passed else "fail"

    @property
    def judged(self) -> bool:
        return self.status != "not_judged"

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["window_s"] = list(self.window_s)
        return d


class _Unusable(Exception):
    """The criterion cannot be computed from this telemetry; the message becomes the result's detail."""


class _NotJudged(_Unusable):
    """The bench could not see what the criterion needs (unmeasured signal, missing data): not judged."""


@dataclass(frozen=True)
class Param:
    type: str                 # "signal" | "number" | "bool"
    default: Any = None
    required: bool = False
    help: str = ""


@dataclass(frozen=True)
class Kind:
    compute: Callable[["_Window", CriterionSpec], tuple[float, str]]
    unit: str                 # unit of value and limit; "signal" = the unit of the criterion's signal
    params: dict[str, Param]
    help: str
    exclusive: tuple[tuple[str, ...], ...] = ()   # at most one of each group
    one_of: tuple[str, ...] = ()                  # exactly one of these is required


def is_angle(signal: str) -> bool:
    return signal.endswith("_rad")


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Wrap to [-pi, pi)."""
    return (np.asarray(a, dtype=np.float64) + np.pi) % (2.0 * np.pi) - np.pi


class _Window:
    """The samples of one criterion's time window, with coverage and NaN checks on access."""

    def __init__(self, t_s: np.ndarray, columns: dict[str, np.ndarray], window_s: tuple[float, float],
                 smooth_s: float | None = None, row_period_s: float | None = None, tolerance: float = 1.5):
        a, b = window_s
        t = np.asarray(t_s, dtype=np.float64)
        if t.size == 0:
            raise _NotJudged("no telemetry recorded")
        dt = row_period_s or (float(np.median(np.diff(t))) if t.size > 1 else 0.0)
        tol = tolerance * dt + 1e-9
        if t[-1] < b - tol:
            raise _NotJudged(f"telemetry ends at {t[-1]:.6g} s, before the window end {b:g} s")
        if t[0] > a + tol:
            raise _NotJudged(f"telemetry starts at {t[0]:.6g} s, after the window start {a:g} s")
        self.mask = (t >= a) & (t <= b)
        self.t = t[self.mask]
        if self.t.size == 0:
            raise _NotJudged(f"no samples in window [{a:g}, {b:g}] s")
        holes = time_axis(self.t, dt, tolerance)
        if holes["missing_rows"] or holes["duplicates"]:
            raise _NotJudged(f"{holes['missing_rows']} rows missing in the window ({holes['gaps']} gaps in the drive "
                             f"clock, largest {holes['largest_gap_s']:.6g} s), {holes['duplicates']} duplicates")
        self.columns = columns
        self.window_s = window_s
        idx = np.flatnonzero(self.mask)
        self.first, self.last = int(idx[0]), int(idx[-1])
        self.smooth_n = max(1, int(round(smooth_s / dt))) if smooth_s and dt > 0 else 1

    def signal(self, name: str) -> np.ndarray:
        if name not in self.columns:
            raise _NotJudged(f"signal {name} was not recorded")
        x = np.asarray(self.columns[name], dtype=np.float64)[self.mask]
        nans = int(np.count_nonzero(~np.isfinite(x)))
        if nans == x.size:
            raise _NotJudged(f"signal {name} is NaN throughout the window (not measured on this bench?)")
        if nans:
            raise _Unusable(f"signal {name} has {nans} NaN/inf samples in the window")
        if self.smooth_n > 1:
            x = self._smoothed(name, x.size)
        return x

    def _smoothed(self, name: str, n: int) -> np.ndarray:
        """Trailing moving average over smooth_n samples, using history before the window when it is finite."""
        full = np.asarray(self.columns[name], dtype=np.float64)
        start = max(0, self.first - (self.smooth_n - 1))
        seg = full[start:self.last + 1]
        bad = np.flatnonzero(~np.isfinite(seg[: self.first - start]))
        if bad.size:
            seg = seg[bad[-1] + 1:]
        if is_angle(name):
            return np.arctan2(_moving_mean(np.sin(seg), self.smooth_n), _moving_mean(np.cos(seg), self.smooth_n))[-n:]
        return _moving_mean(seg, self.smooth_n)[-n:]

    def after(self, spec: CriterionSpec) -> float:
        return float(spec.params.get("after_s", self.window_s[0]))


def _moving_mean(x: np.ndarray, k: int) -> np.ndarray:
    c = np.concatenate(([0.0], np.cumsum(x)))
    hi = np.arange(1, x.size + 1)
    lo = np.maximum(0, hi - k)
    return (c[hi] - c[lo]) / (hi - lo)


# --- helpers -------------------------------------------------------------------------------------------

def _difference(w: _Window, spec: CriterionSpec) -> np.ndarray:
    """signal - reference (signal) or - target (number), or the signal itself; wrapped for angles."""
    x = w.signal(spec.signal)
    ref = _reference(w, spec, required=False)
    d = x if ref is None else x - ref
    return wrap_angle(d) if is_angle(spec.signal) else d


def _reference(w: _Window, spec: CriterionSpec, required: bool = True) -> np.ndarray | None:
    p = spec.params
    if "reference" in p:
        return w.signal(p["reference"])
    if "target" in p:
        return np.full(w.t.size, float(p["target"]))
    if required:
        raise _Unusable("needs `reference` (a signal) or `target` (a number)")
    return None


def _settle_time(t: np.ndarray, inside: np.ndarray, t0: float) -> tuple[float, str]:
    """Time from t0 until `inside` holds at every later sample of the window; inf if it never does."""
    sel = t >= t0
    t, inside = t[sel], inside[sel]
    if t.size == 0:
        raise _Unusable(f"no samples after {t0:g} s in the window")
    if not inside[-1]:
        return math.inf, "never settles inside the band before the window end"
    outside = np.flatnonzero(~inside)
    t_in = t[0] if outside.size == 0 else t[outside[-1] + 1]
    return float(t_in - t0), f"inside the band from {t_in:.6g} s"


def _max_abs_error(w: _Window, e: np.ndarray, unit: str) -> tuple[float, str]:
    i = int(np.argmax(np.abs(e)))
    return float(abs(e[i])), f"max |error| {e[i]:+.4g}{unit} at {w.t[i]:.6g} s"


def _rms_error(e: np.ndarray, unit: str) -> tuple[float, str]:
    return float(np.sqrt(np.mean(e * e))), f"rms over {e.size} samples, mean {np.mean(e):+.4g}{unit}"


def _pct_band(spec: CriterionSpec, level: float, default_pct: float) -> float:
    if "band_abs" in spec.params:
        return float(spec.params["band_abs"])
    return float(spec.params.get("band_pct", default_pct)) / 100.0 * abs(level)


# --- kinds ---------------------------------------------------------------------------------------------

def _speed_error_pct(w: _Window, spec: CriterionSpec) -> np.ndarray:
    p = spec.params
    err = w.signal(spec.signal) - w.signal(p.get("true_signal", "speed_true_mech_rad_s"))
    if "base_mech_rad_s" in p:
        base = float(p["base_mech_rad_s"])
    elif "base_rpm" in p:
        base = float(p["base_rpm"]) * math.pi / 30.0
    else:
        base = float(np.max(np.abs(w.signal(p.get("ref_signal", "speed_ref_mech_rad_s")))))
    if base <= 0:
        raise _Unusable("the speed reference is zero in the window: give base_mech_rad_s or base_rpm")
    return err / base * 100.0


def speed_error_max_pct(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    return _max_abs_error(w, _speed_error_pct(w, spec), " %")


def speed_error_rms_pct(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    return _rms_error(_speed_error_pct(w, spec), " %")


def _pos_error(w: _Window, spec: CriterionSpec) -> np.ndarray:
    x = w.signal(spec.signal)
    if "reference" in spec.params:
        x = x - w.signal(spec.params["reference"])
    return wrap_angle(x)


def pos_error_max(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    return _max_abs_error(w, _pos_error(w, spec), " rad")


def pos_error_rms(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    return _rms_error(_pos_error(w, spec), " rad")


def _flux_error_pct(w: _Window, spec: CriterionSpec) -> np.ndarray:
    true = w.signal(spec.params.get("true_signal", "flux_true_wb"))
    if np.any(np.abs(true) <= 0):
        raise _Unusable("the true flux is zero in the window; a percentage is undefined")
    return (w.signal(spec.signal) - true) / np.abs(true) * 100.0


def flux_error_max_pct(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    return _max_abs_error(w, _flux_error_pct(w, spec), " %")


def flux_error_rms_pct(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    return _rms_error(_flux_error_pct(w, spec), " %")


def flux_recovery_time(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    e = _flux_error_pct(w, spec)
    band = float(spec.params.get("band_pct", 2.0))
    value, detail = _settle_time(w.t, np.abs(e) <= band, w.after(spec))
    return value, f"flux error within ±{band:g} %: {detail}"


def settling_time(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    ref = _reference(w, spec)
    band = _pct_band(spec, ref[-1], 2.0)
    err = _difference(w, spec)
    value, detail = _settle_time(w.t, np.abs(err) <= band, w.after(spec))
    return value, f"band ±{band:.4g}: {detail}"


def overshoot_pct(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    x = w.signal(spec.signal)
    final = float(_reference(w, spec)[-1])
    start = float(spec.params.get("from_value", x[0]))
    step = final - start
    if step == 0:
        raise _Unusable("the step is zero (final value equals the initial value)")
    beyond = (x - final) * math.copysign(1.0, step)
    i = int(np.argmax(beyond))
    pct = max(0.0, float(beyond[i])) / abs(step) * 100.0
    return pct, f"step {start:.4g} -> {final:.4g}, peak {x[i]:.4g} at {w.t[i]:.6g} s"


def steady_state_error(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    ref = _reference(w, spec)
    err = float(np.mean(_difference(w, spec)))
    if spec.params.get("percent", False):
        level = abs(float(np.mean(ref)))
        if level == 0:
            raise _Unusable("the mean reference is zero; a percentage is undefined")
        return abs(err) / level * 100.0, f"mean error {err:+.4g} = {err / level * 100:+.4g} % of {level:.4g}"
    return abs(err), f"mean error {err:+.4g}"


def peak_abs(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    d = _difference(w, spec)
    i = int(np.argmax(np.abs(d)))
    return float(abs(d[i])), f"peak {d[i]:+.4g} at {w.t[i]:.6g} s"


def rms(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    d = _difference(w, spec)
    return float(np.sqrt(np.mean(d * d))), f"rms over {d.size} samples"


def mean(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    d = _difference(w, spec)
    expected = float(spec.params["expected"])
    if is_angle(spec.signal):
        m = float(np.arctan2(np.mean(np.sin(d)), np.mean(np.cos(d))))
        dev = float(abs(wrap_angle(np.array(m - expected))))
    else:
        m = float(np.mean(d))
        dev = abs(m - expected)
    return dev, f"mean {m:+.6g}, expected {expected:+.6g}"


def _from_after(w: _Window, spec: CriterionSpec) -> tuple[float, np.ndarray, np.ndarray]:
    """(after_s, times, the signal) of the window's samples from after_s on."""
    x = w.signal(spec.signal)
    t0 = w.after(spec)
    sel = w.t >= t0
    if not np.any(sel):
        raise _Unusable(f"no samples after {t0:g} s in the window")
    return t0, w.t[sel], x[sel]


def reversal_time(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    t0, t, x = _from_after(w, spec)
    target = float(spec.params.get("target", -x[0]))
    if target == 0 or (x[0] != 0 and math.copysign(1.0, target) == math.copysign(1.0, x[0])):
        raise _Unusable(f"target {target:g} is not a reversal from {x[0]:.4g}")
    band = _pct_band(spec, target, 5.0)
    hit = np.flatnonzero(np.abs(x - target) <= band)
    if hit.size == 0:
        return math.inf, f"never reached {target:.4g} ±{band:.4g} (last {x[-1]:.4g})"
    return float(t[hit[0]] - t0), f"reached {target:.4g} ±{band:.4g} at {t[hit[0]]:.6g} s"


def _level(w: _Window, spec: CriterionSpec) -> float:
    """The final level a response is judged against: `target`, or the last value of `reference` in the window."""
    return float(_reference(w, spec)[-1])


def rise_time(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    t0, t, x = _from_after(w, spec)
    final = _level(w, spec)
    start = float(spec.params.get("from_value", x[0]))
    step = final - start
    if step == 0:
        raise _Unusable("the step is zero (final value equals the initial value)")
    lo, hi = float(spec.params.get("low_pct", 10.0)), float(spec.params.get("high_pct", 90.0))
    if not 0 <= lo < hi <= 100:
        raise _Unusable(f"needs 0 <= low_pct < high_pct <= 100, got {lo:g}, {hi:g}")
    progress = (x - start) / step * 100.0          # % of the step reached, whatever its sign
    hit_hi = np.flatnonzero(progress >= hi)
    if hit_hi.size == 0:
        return math.inf, f"never reached {hi:g} % of the step {start:.4g} -> {final:.4g} (max {progress.max():.3g} %)"
    before = np.flatnonzero(progress[:hit_hi[0] + 1] >= lo)
    t_lo, t_hi = t[before[0]], t[hit_hi[0]]
    return float(t_hi - t_lo), (f"{lo:g} % at {t_lo:.6g} s, {hi:g} % at {t_hi:.6g} s of the step "
                                f"{start:.4g} -> {final:.4g}")


def dip(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    x = w.signal(spec.signal)
    t0 = w.after(spec)
    sel = w.t >= t0
    if not np.any(sel):
        raise _Unusable(f"no samples after {t0:g} s in the window")
    level = _reference(w, spec)[sel]
    direction = np.where(level < 0, -1.0, 1.0)     # towards zero from the level (below it at level 0)
    drop = (level - x[sel]) * direction
    i = int(np.argmax(drop))
    value = max(0.0, float(drop[i]))
    detail = f"deepest {x[sel][i]:.4g} against {level[i]:.4g} at {w.t[sel][i]:.6g} s"
    if spec.params.get("percent", False):
        base = abs(float(np.mean(level)))
        if base == 0:
            raise _Unusable("the level is zero; a percentage is undefined")
        return value / base * 100.0, detail + f" ({value:.4g} = {value / base * 100:.4g} % of {base:.4g})"
    return value, detail


def ripple_pp(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    x = w.signal(spec.signal)
    i, j = int(np.argmin(x)), int(np.argmax(x))
    return float(x[j] - x[i]), f"min {x[i]:.4g} at {w.t[i]:.6g} s, max {x[j]:.4g} at {w.t[j]:.6g} s"


def ripple_std(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    x = w.signal(spec.signal)
    return float(np.std(x)), f"std over {x.size} samples around the mean {np.mean(x):.4g}"


_REF = {
    "reference": Param("signal", help="subtract this signal"),
    "target": Param("number", help="subtract this constant (signal units)"),
}
_AFTER = {"after_s": Param("number", help="measure from this time (default: window start)")}
_BAND = {"band_pct": Param("number", help="band half-width in % of the final reference"),
         "band_abs": Param("number", help="band half-width in signal units")}

KINDS: dict[str, Kind] = {
    "speed_error_max_pct": Kind(speed_error_max_pct, "%", {
        "true_signal": Param("signal", "speed_true_mech_rad_s", help="true speed"),
        "ref_signal": Param("signal", "speed_ref_mech_rad_s", help="reference whose max |value| is the base"),
        "base_mech_rad_s": Param("number", help="fixed base speed instead"),
        "base_rpm": Param("number", help="fixed base speed instead, rpm")},
        "max |signal - true| in % of the base (default: max |reference| in the window)",
        exclusive=(("base_mech_rad_s", "base_rpm"),)),
    "speed_error_rms_pct": Kind(speed_error_rms_pct, "%", {
        "true_signal": Param("signal", "speed_true_mech_rad_s"),
        "ref_signal": Param("signal", "speed_ref_mech_rad_s"),
        "base_mech_rad_s": Param("number"), "base_rpm": Param("number")},
        "RMS of (signal - true) in % of the base", exclusive=(("base_mech_rad_s", "base_rpm"),)),
    "pos_error_max": Kind(pos_error_max, "rad", {"reference": Param("signal", help="angle to subtract")},
                          "max |wrapped angle error|"),
    "pos_error_rms": Kind(pos_error_rms, "rad", {"reference": Param("signal")}, "RMS of the wrapped angle error"),
    "flux_error_max_pct": Kind(flux_error_max_pct, "%", {"true_signal": Param("signal", "flux_true_wb")},
                               "max |signal - true| / |true| in %"),
    "flux_error_rms_pct": Kind(flux_error_rms_pct, "%", {"true_signal": Param("signal", "flux_true_wb")},
                               "RMS of (signal - true) / |true| in %"),
    "flux_recovery_time": Kind(flux_recovery_time, "s", {
        "true_signal": Param("signal", "flux_true_wb"), "band_pct": Param("number", 2.0), **_AFTER},
        "time from after_s until the flux error stays within ±band_pct %"),
    "settling_time": Kind(settling_time, "s", {**_REF, **_BAND, **_AFTER},
                          "time from after_s until |signal - reference| stays within the band",
                          exclusive=(("band_pct", "band_abs"),), one_of=("reference", "target")),
    "overshoot_pct": Kind(overshoot_pct, "%", {**_REF, "from_value": Param("number", help="initial value")},
                          "overshoot beyond the final reference in % of the step", one_of=("reference", "target")),
    "steady_state_error": Kind(steady_state_error, "signal", {**_REF, "percent": Param("bool", False)},
                               "|mean(signal - reference)| (in % of |mean reference| with percent = true)",
                               one_of=("reference", "target")),
    "peak_abs": Kind(peak_abs, "signal", dict(_REF), "max |signal| (or |signal - reference|)",
                     exclusive=(("reference", "target"),)),
    "rms": Kind(rms, "signal", dict(_REF), "RMS of signal (or signal - reference)",
                exclusive=(("reference", "target"),)),
    "mean": Kind(mean, "signal", {**_REF, "expected": Param("number", required=True)},
                 "|mean(signal) - expected| (mean of signal - reference when given)",
                 exclusive=(("reference", "target"),)),
    "reversal_time": Kind(reversal_time, "s", {
        "target": Param("number", help="speed after the reversal (default: minus the speed at after_s)"),
        **_BAND, **_AFTER},
        "time from after_s until the signal reaches the reversed speed within the band (default 5 %)",
        exclusive=(("band_pct", "band_abs"),)),
    "rise_time": Kind(rise_time, "s", {
        **_REF, "from_value": Param("number", help="initial value (default: the signal at after_s)"),
        "low_pct": Param("number", 10.0, help="lower crossing, % of the step"),
        "high_pct": Param("number", 90.0, help="upper crossing, % of the step"), **_AFTER},
        "time from low_pct to high_pct of the step from the initial to the final reference (first crossings)",
        one_of=("reference", "target")),
    "dip": Kind(dip, "signal", {**_REF, "percent": Param("bool", False), **_AFTER},
                "largest excursion of the signal from the level towards zero (0 when none); % of |level| with "
                "percent = true", one_of=("reference", "target")),
    "ripple_pp": Kind(ripple_pp, "signal", {}, "peak to peak, max - min of the signal in the window"),
    "ripple_std": Kind(ripple_std, "signal", {}, "standard deviation of the signal in the window"),
}


_SMOOTH = Param("number", help="trailing moving average over this many seconds applied to every signal first")
for _kind in KINDS.values():
    _kind.params["smooth_s"] = _SMOOTH


def time_axis(t_s: np.ndarray, row_period_s: float | None, tolerance: float = 1.5) -> dict[str, Any]:
    """Rows, gaps (intervals over `tolerance` periods: 1.5 on a drive clock, more on receive-time stamps, which
    jitter), the rows they miss, and duplicated or backward stamps of a time axis."""
    t = np.asarray(t_s, dtype=np.float64)
    if not row_period_s and t.size > 1:
        row_period_s = float(np.median(np.diff(t)))
    axis = TimeAxis(row_period_s or 0.0, tolerance)
    axis.add(t)
    return axis.result()


@dataclass
class TimeAxis:
    """time_axis() over a time axis given in consecutive pieces (a run's journal, batch by batch): memory does not
    grow with the run. The row period must be known beforehand."""
    period: float
    tolerance: float = 1.5
    rows: int = 0
    gaps: int = 0
    missing_rows: int = 0
    largest_gap_s: float | None = None
    duplicates: int = 0
    _last: float | None = None

    def add(self, t: np.ndarray) -> None:
        if t.size == 0:
            return
        steps = np.diff(t) if self._last is None else np.diff(t, prepend=self._last)
        self._last = float(t[-1])
        self.rows += int(t.size)
        if steps.size == 0:
            return
        gaps = steps > self.tolerance * self.period if self.period > 0 else np.zeros(steps.size, dtype=bool)
        self.gaps += int(gaps.sum())
        if gaps.any():
            self.missing_rows += int(np.sum(np.round(steps[gaps] / self.period) - 1))
        largest = float(steps.max())
        self.largest_gap_s = largest if self.largest_gap_s is None else max(self.largest_gap_s, largest)
        self.duplicates += int(np.count_nonzero(steps <= 0))

    def result(self) -> dict[str, Any]:
        return {"rows": self.rows, "row_period_s": self.period, "tolerance": self.tolerance, "gaps": self.gaps,
                "missing_rows": self.missing_rows, "largest_gap_s": self.largest_gap_s or 0.0,
                "duplicates": self.duplicates}


def signals_of(spec: CriterionSpec) -> list[str]:
    """Every signal a criterion reads: its own, signal parameters given, and signal parameters' defaults."""
    kind = KINDS.get(spec.kind)
    names = [spec.signal]
    if kind is not None:
        for key, param in kind.params.items():
            if param.type == "signal":
                value = spec.params.get(key, param.default)
                if isinstance(value, str) and value in SIGNAL_NAMES and _reads_param(spec, key):
                    names.append(value)
    return list(dict.fromkeys(names))


def _reads_param(spec: CriterionSpec, key: str) -> bool:
    """A default signal parameter is read only when nothing given replaces it (a fixed base instead of ref_signal)."""
    if key == "ref_signal" and any(k in spec.params for k in ("base_mech_rad_s", "base_rpm")):
        return False
    return key in spec.params or KINDS[spec.kind].params[key].default is not None


def evaluate(specs, t_s: np.ndarray, columns: dict[str, np.ndarray], *, measured: frozenset[str] | None = None,
             row_period_s: float | None = None, tolerance: float = 1.5) -> list[CriterionResult]:
    """`measured`: the signals this bench measures (None: all); `row_period_s`: the period rows are expected at
    (None: the median interval) and `tolerance` the interval, in periods, beyond which rows count as missing."""
    results = []
    for spec in specs:
        status = ""
        try:
            unmeasured = [s for s in signals_of(spec) if measured is not None and s not in measured]
            if unmeasured:
                raise _NotJudged(f"signal {', '.join(unmeasured)} is not measured on this bench")
            with np.errstate(all="ignore"):   # overflow to inf fails the criterion like any large value
                window = _Window(t_s, columns, spec.window_s, spec.params.get("smooth_s"), row_period_s, tolerance)
                value, detail = KINDS[spec.kind].compute(window, spec)
                if window.smooth_n > 1:
                    detail += f" (moving average over {spec.params['smooth_s']:g} s)"
            passed = bool(value <= spec.limit)
        except _NotJudged as e:
            value, detail, passed, status = math.nan, str(e), False, "not_judged"
        except _Unusable as e:
            value, detail, passed = math.nan, str(e), False
        except KeyError:
            value, detail, passed = math.nan, f"unknown criterion kind {spec.kind!r}", False
        if not passed and math.isfinite(value):
            detail = f"value {value:.6g} > limit {spec.limit:g}; {detail}"
        results.append(CriterionResult(spec.name, spec.kind, spec.signal, tuple(spec.window_s), float(value),
                                       float(spec.limit), passed, spec.known_gap, detail, status, unit_of(spec)))
    return results


def unit_of(spec: CriterionSpec) -> str:
    """The unit of a criterion's value and limit: its kind's ("%", "s", "rad"), or its signal's (drivers.contract.signals),
    or "%" for a kind that judges in percent when asked (`percent = true`)."""
    from drivers.contract.signals import SIGNALS

    kind = KINDS.get(spec.kind)
    if kind is None:
        return ""
    if kind.unit != "signal":
        return kind.unit
    if spec.params.get("percent"):
        return "%"
    return next((s.unit for s in SIGNALS if s.name == spec.signal), "")


VERDICTS = ("pass", "fail", "incomplete", "aborted", "error")


def verdict(results, aborted: bool, holes: dict | None = None) -> str:
    """aborted > fail (a judged criterion over its limit, not a known gap) > incomplete (a criterion not judged: the
    bench could not see; or the telemetry misses rows anywhere in the run, `holes` from time_axis) > pass. A run with
    missing data never passes."""
    if aborted:
        return "aborted"
    if any(r.judged and not r.passed and not r.known_gap for r in results):
        return "fail"
    if any(not r.judged for r in results) or (holes and (holes["missing_rows"] or holes["duplicates"])):
        return "incomplete"
    return "pass"


def incomplete_reason(results, holes: dict | None) -> str | None:
    parts = []
    unjudged = [r.name for r in results if not r.judged]
    if unjudged:
        parts.append(f"{len(unjudged)} criteria not judged ({'; '.join(unjudged)})")
    if holes and (holes["missing_rows"] or holes["duplicates"]):
        parts.append(f"telemetry misses {holes['missing_rows']} rows in {holes['gaps']} gaps and has "
                     f"{holes['duplicates']} duplicated stamps")
    return ", ".join(parts) or None


__all__ = ["CriterionSpec", "CriterionResult", "KINDS", "evaluate", "verdict", "wrap_angle", "SIGNAL_NAMES"]


# -- parsing [[criteria]] tables (scenario files) ------------------------------------------------------------------

_CRITERION_KEYS = ("name", "kind", "signal", "window_s", "limit", "known_gap")


def parse_criteria(p: Problems, items: list[tuple[str, dict]], duration: float) -> tuple[CriterionSpec, ...]:
    """The [[criteria]] tables of a scenario, each checked against its kind's parameters; problems go to `p`."""
    out = []
    names: set[str] = set()
    for where, item in items:
        name = p.string(item, "name", where)
        if name is not None:
            if name in names:
                p.add(f"{where}.name", f"duplicate criterion name {name!r}")
            names.add(name)
        kind_name = p.string(item, "kind", where, choices=tuple(KINDS))
        signal = p.string(item, "signal", where)
        if signal is not None and not known_signal(signal):
            p.add(f"{where}.signal", f"unknown signal {signal!r} (signals: {', '.join(SIGNAL_NAMES)}; or an "
                                        f"instrument's <instrument>:<signal>)")
            signal = None
        window = _window(p, item, where, duration)
        limit = p.number(item, "limit", where, min_value=0.0)
        known_gap = p.string(item, "known_gap", where, required=False)
        if known_gap is not None and not known_gap.strip():
            p.add(f"{where}.known_gap", "give the reason for the known gap")
        params = None
        if kind_name is not None:
            params = _criterion_params(p, item, where, kind_name, window)
        if None in (name, kind_name, signal, window, limit, params):
            continue
        out.append(CriterionSpec(name, kind_name, signal, window, limit, params, known_gap))
    return tuple(out)


def known_signal(name: str) -> bool:
    """A telemetry signal, or an instrument's `<instrument>:<signal>` (bench.inputs.capture_criteria)."""
    from bench.inputs.capture_names import is_capture_signal
    return name in SIGNAL_NAMES or is_capture_signal(name)


def _window(p: Problems, item: dict, where: str, duration: float) -> tuple[float, float] | None:
    field_ = f"{where}.window_s"
    if "window_s" not in item:
        p.add(field_, "missing (give [start_s, end_s])")
        return None
    w = item["window_s"]
    if (not isinstance(w, list) or len(w) != 2
            or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in w)):
        p.add(field_, f"must be [start_s, end_s], two numbers, got {w!r}")
        return None
    a, b = float(w[0]), float(w[1])
    if not (math.isfinite(a) and math.isfinite(b)):
        p.add(field_, f"must be finite, got {w!r}")
    elif a < 0:
        p.add(field_, f"starts at a negative time {a:g} s")
    elif b <= a:
        p.add(field_, f"end {b:g} s must be after start {a:g} s")
    elif b > duration:
        p.add(field_, f"ends at {b:g} s, after the end of the run (duration_s = {duration:g})")
    else:
        return a, b
    return None


def _criterion_params(p: Problems, item: dict, where: str, kind_name: str,
                      window: tuple[float, float] | None) -> dict[str, Any] | None:
    kind = KINDS[kind_name]
    given = {k: v for k, v in item.items() if k not in _CRITERION_KEYS}
    ok = True
    for key in given:
        if key not in kind.params:
            allowed = ", ".join(sorted(kind.params)) or "none"
            p.add(f"{where}.{key}", f"unknown key for kind {kind_name!r} (its parameters: {allowed})")
            ok = False
    params: dict[str, Any] = {}
    for key, spec in kind.params.items():
        if key not in given:
            if spec.required:
                p.add(f"{where}.{key}", f"missing (required by kind {kind_name!r})")
                ok = False
            continue
        if spec.type == "signal":
            v = p.string(given, key, where)
            if v is not None and not known_signal(v):
                p.add(f"{where}.{key}", f"unknown signal {v!r}")
                v = None
        elif spec.type == "bool":
            v = p.boolean(given, key, where)
        else:
            v = p.number(given, key, where)
            if v is not None and (key.startswith(("band_", "base_", "smooth_")) and v <= 0):
                p.add(f"{where}.{key}", f"must be > 0, got {v:g}")
                v = None
        if v is None:
            ok = False
        params[key] = v
    for group in kind.exclusive:
        present = [k for k in group if k in given]
        if len(present) > 1:
            p.add(f"{where}.{present[1]}", f"give only one of {', '.join(group)}")
            ok = False
    if kind.one_of and sum(k in given for k in kind.one_of) != 1:
        p.add(where, f"kind {kind_name!r} needs exactly one of {', '.join(kind.one_of)}")
        ok = False
    if kind_name == "rise_time" and ok:
        lo, hi = params.get("low_pct", 10.0), params.get("high_pct", 90.0)
        if not 0 <= lo < hi <= 100:
            p.add(f"{where}.low_pct", f"needs 0 <= low_pct < high_pct <= 100, got {lo:g} and {hi:g}")
            ok = False
    after = params.get("after_s")
    if after is not None and window is not None and not (window[0] <= after < window[1]):
        p.add(f"{where}.after_s", f"{after:g} s is outside the window [{window[0]:g}, {window[1]:g}] s")
        ok = False
    return params if ok else None

