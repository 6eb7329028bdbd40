"""Criteria on what a lab's instruments recorded, judged at the instrument's own rate (docs/instruments.md).

A criterion's signal (or its `reference`) may name an instrument's record instead of a telemetry signal:
`"<instrument>:<signal>"`, the instrument's name in the bench's [[instruments]] and the signal its channel gives —
`scope:speed_scope_mech_rad_s` (the capture around the marked moment, 50 kS/s on the simulated rigs),
`daq:i_a_a` (the DAQ's record of the run), `analyser:eff_drive_pct` (the analyser's readings at poll_hz). Every
existing kind works on it unchanged (a rise time, an overshoot, a ripple); the record's time axis, placed on the
drive clock, replaces the telemetry's rows, and its sample period is the row period the window is checked against.

Kinds added here, for any signal (telemetry or record), sampled uniformly over the window:
- `harmonic_pct`: the amplitude of harmonic `order` of `fundamental_hz` in % of |mean| (torque ripple per order)
  or, with `of_fundamental = true`, of the fundamental's amplitude (a current's harmonic);
- `thd_pct`: total harmonic distortion up to `max_order`, in % of the fundamental (current ripple); the
  fundamental from the signal's zero crossings unless `fundamental_hz` is given;
- `ripple_rms_pct`: rms of (signal - mean) in % of |mean| (the torque ripple factor).
Both Fourier kinds use the largest whole number of fundamental periods in the window.

Not judged, never a number: an instrument absent from this bench or its run (not opened, faulted, not triggered),
a signal it does not give, a window its record does not cover, or a sample in the window that was over-range or
clipped (NaN in the record).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any, Iterable, Mapping

import numpy as np

from bench.inputs.capture_names import _CAPTURE, is_capture_signal, split_capture_signal  # noqa: F401
from bench.inputs.criteria import (KINDS, CriterionResult, CriterionSpec, Kind, Param, _Unusable, _Window,
                                   evaluate)

def reads_capture(spec: CriterionSpec) -> bool:
    """True when the criterion reads an instrument's record (its signal or a signal parameter)."""
    return is_capture_signal(spec.signal) or any(is_capture_signal(v) for v in spec.params.values())


def capture_signals_of(instruments: Iterable[Any]) -> frozenset[str]:
    """`<instrument>:<signal>` for every channel of a bench's [[instruments]]: what its criteria may name."""
    return frozenset(f"{cfg.name}:{ch.signal}" for cfg in instruments for ch in cfg.channels)


def capture_units(instruments: Iterable[Any]) -> dict[str, str]:
    return {f"{cfg.name}:{ch.signal}": ch.unit for cfg in instruments for ch in cfg.channels}


def capture_accuracy(instruments: Iterable[Any]) -> dict[str, tuple[float, float, float]]:
    """(reading %, range %, range in the signal's units) of each signal whose instrument states its accuracy."""
    return {f"{cfg.name}:{ch.signal}": (cfg.accuracy_reading_pct, cfg.accuracy_range_pct, abs(ch.range * ch.scale))
            for cfg in instruments if getattr(cfg, "accuracy_reading_pct", None) is not None
            for ch in cfg.channels}


# --- kinds -----------------------------------------------------------------------------------------------------

def _whole_periods(w: _Window, spec: CriterionSpec) -> tuple[np.ndarray, np.ndarray, float, int]:
    """The window's samples over its largest whole number of periods of the fundamental: `fundamental_hz`, or
    (when not given) measured from the signal's rising zero crossings around its mean."""
    x, t = w.signal(spec.signal), w.t
    f = float(spec.params["fundamental_hz"]) if spec.params.get("fundamental_hz") is not None else _measured_hz(t, x)
    if not f > 0:
        raise _Unusable(f"fundamental_hz must be > 0, got {f:g}")
    dt = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    periods = math.floor((t[-1] - t[0] + dt) * f + 1e-9)
    if periods < 1:
        raise _Unusable(f"the window holds less than one period of {f:g} Hz")
    keep = t < t[0] + periods / f - 0.5 * dt
    return t[keep], x[keep], f, periods


def _measured_hz(t: np.ndarray, x: np.ndarray) -> float:
    y = x - np.mean(x)
    k = np.flatnonzero((y[:-1] < 0) & (y[1:] >= 0))
    if k.size < 2:
        raise _Unusable("fewer than two rising zero crossings in the window: give fundamental_hz")
    crossings = t[k] - y[k] * (t[k + 1] - t[k]) / (y[k + 1] - y[k])
    return float((crossings.size - 1) / (crossings[-1] - crossings[0]))


def _amplitude(t: np.ndarray, x: np.ndarray, hz: float) -> float:
    phase = 2.0 * np.pi * hz * (t - t[0])
    return float(2.0 * math.hypot(np.mean(x * np.cos(phase)), np.mean(x * np.sin(phase))))


def _nyquist(t: np.ndarray, hz: float) -> None:
    rate = (t.size - 1) / (t[-1] - t[0]) if t.size > 1 and t[-1] > t[0] else 0.0
    if hz >= rate / 2:
        raise _Unusable(f"{hz:g} Hz is beyond half the sample rate ({rate:g} S/s)")


def _order(spec: CriterionSpec, key: str, default: float | None = None) -> int:
    n = float(spec.params.get(key, default))
    if n < 1 or n != int(n):
        raise _Unusable(f"{key} must be a whole number >= 1, got {n:g}")
    return int(n)


def harmonic_pct(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    t, x, f, periods = _whole_periods(w, spec)
    n = _order(spec, "order")
    _nyquist(t, n * f)
    amp = _amplitude(t, x, n * f)
    if spec.params.get("of_fundamental", False):
        base, what = _amplitude(t, x, f), "the fundamental"
    else:
        base, what = abs(float(np.mean(x))), "|mean|"
    if base == 0:
        raise _Unusable(f"{what} is zero; a percentage is undefined")
    return amp / base * 100.0, (f"order {n} ({n * f:.6g} Hz) amplitude {amp:.4g} against {what} {base:.4g}, "
                                f"{t.size} samples over {periods} periods of {f:.6g} Hz")


def thd_pct(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    t, x, f, periods = _whole_periods(w, spec)
    top = _order(spec, "max_order", 40.0)
    rate = (t.size - 1) / (t[-1] - t[0]) if t[-1] > t[0] else 0.0
    top = max(1, min(top, int((rate / 2) // f) - 1))
    fundamental = _amplitude(t, x, f)
    if fundamental == 0:
        raise _Unusable("the fundamental is zero; THD is undefined")
    harmonics = [_amplitude(t, x, n * f) for n in range(2, top + 1)]
    thd = math.sqrt(sum(a * a for a in harmonics)) / fundamental * 100.0
    worst = int(np.argmax(harmonics)) + 2 if harmonics else 1
    return thd, (f"orders 2-{top} of {f:.6g} Hz ({periods} periods) against the fundamental {fundamental:.4g}; "
                 f"largest order {worst}"
                 + (f" ({harmonics[worst - 2] / fundamental * 100:.3g} %)" if harmonics else ""))


def ripple_rms_pct(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    x = w.signal(spec.signal)
    m = float(np.mean(x))
    if m == 0:
        raise _Unusable("the mean is zero; a ripple factor is undefined")
    return float(np.std(x)) / abs(m) * 100.0, f"rms of the ripple {np.std(x):.4g} around the mean {m:.4g}"


_FUNDAMENTAL = {"fundamental_hz": Param("number", required=True, help="the fundamental (electrical) frequency")}
_MEASURED = {"fundamental_hz": Param("number", help="the fundamental (default: from the signal's zero crossings)")}
NEW_KINDS: dict[str, Kind] = {
    "harmonic_pct": Kind(harmonic_pct, "%", {
        **_FUNDAMENTAL, "order": Param("number", required=True, help="harmonic order of fundamental_hz"),
        "of_fundamental": Param("bool", False, help="in % of the fundamental's amplitude instead of |mean|")},
        "amplitude of harmonic `order` of fundamental_hz in % of |mean| (or of the fundamental)"),
    "thd_pct": Kind(thd_pct, "%", {**_MEASURED, "max_order": Param("number", 40.0, help="highest order")},
                    "total harmonic distortion up to max_order in % of the fundamental"),
    "ripple_rms_pct": Kind(ripple_rms_pct, "%", {}, "rms of (signal - mean) in % of |mean|"),
}


def _register() -> None:
    smooth = KINDS["rise_time"].params["smooth_s"]
    for name, kind in NEW_KINDS.items():
        kind.params.setdefault("smooth_s", smooth)
        KINDS.setdefault(name, kind)


# --- judging on the records ---------------------------------------------------------------------------------------

def _not_judged(spec: CriterionSpec, why: str, unit: str) -> CriterionResult:
    return CriterionResult(spec.name, spec.kind, spec.signal, tuple(spec.window_s), math.nan, float(spec.limit),
                           False, spec.known_gap, why, "not_judged", unit)


def evaluate_on_records(specs: Iterable[CriterionSpec], records: Mapping[str, Mapping[str, np.ndarray]],
                        instruments: Iterable[Any] = ()) -> list[CriterionResult]:
    """Criteria reading instruments' records: `records` maps an instrument's name to its columns (`t_s` on the drive
    clock and a column per signal) as the run placed them; `instruments` the bench's [[instruments]] (units,
    ranges and stated accuracy of each `<instrument>:<signal>`)."""
    instruments = tuple(instruments)
    units, accuracy = capture_units(instruments), capture_accuracy(instruments)
    out = []
    for spec in specs:
        names = [spec.signal] + [v for v in spec.params.values() if is_capture_signal(v)]
        kind_unit = KINDS[spec.kind].unit if spec.kind in KINDS else ""
        unit = units.get(spec.signal, "") if kind_unit == "signal" and not spec.params.get("percent") else (
            "%" if spec.params.get("percent") else kind_unit)
        instruments = {split_capture_signal(n)[0] for n in names if is_capture_signal(n)}
        if len(instruments) != 1 or not all(is_capture_signal(n) for n in names):
            out.append(_not_judged(spec, "a criterion reads one instrument's record: every signal it names must "
                                         "be <instrument>:<signal> of the same instrument", unit))
            continue
        inst = instruments.pop()
        record = records.get(inst)
        if record is None or "t_s" not in record or not len(record["t_s"]):
            out.append(_not_judged(spec, f"no record from instrument {inst!r} in this run (not on this bench, not "
                                         f"opened, faulted or not triggered: see lab_instruments)", unit))
            continue
        missing = [n for n in names if split_capture_signal(n)[1] not in record]
        if missing:
            out.append(_not_judged(spec, f"{', '.join(missing)}: instrument {inst!r} records no such signal", unit))
            continue
        t = np.asarray(record["t_s"], dtype=np.float64)
        columns = {n: np.asarray(record[split_capture_signal(n)[1]], dtype=np.float64) for n in names}
        a, b = spec.window_s
        inside = (t >= a) & (t <= b)
        lost = {n: int(np.count_nonzero(~np.isfinite(c[inside]))) for n, c in columns.items()}
        lost = {n: k for n, k in lost.items() if k}
        if lost:
            out.append(_not_judged(spec, "; ".join(f"{n}: {k} samples over-range or clipped in the window"
                                                   for n, k in lost.items()), unit))
            continue
        period = float(np.median(np.diff(t))) if t.size > 1 else None
        stated = {n: accuracy[n] for n in names if n in accuracy}
        judged = replace(spec, params={**spec.params, "_accuracy": stated})
        result = evaluate([judged], t, columns, measured=None, row_period_s=period, tolerance=1.5)[0]
        rate = f"{1.0 / period:.6g} S/s" if period else "one sample"
        out.append(replace(result, unit=unit, detail=f"{result.detail} [{inst}'s record, {rate}]"))
    return out


def judge_with_records(specs, judge_rest, records, instruments=()) -> list[CriterionResult]:
    """The scenario's criteria in its order: those reading a record judged on it, the rest by `judge_rest(specs)`."""
    specs = list(specs)
    on_records = [s for s in specs if reads_capture(s)]
    rest = iter(judge_rest([s for s in specs if not reads_capture(s)]))
    recorded = iter(evaluate_on_records(on_records, records, instruments))
    return [next(recorded) if reads_capture(s) else next(rest) for s in specs]


_register()
import bench.inputs.efficiency_criteria  # noqa: E402,F401  (registers the loss and efficiency kinds)
