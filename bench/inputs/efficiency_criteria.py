"""Losses and efficiency judged on a power analyser's readings, with the uncertainty budget of its stated accuracy
(IEC 61800-9-2 operating points, docs/instruments.md and docs/acceptance.md).

A criterion's signal is the input power (`analyser:p_dc_w`: the drive's; or a motor-terminal element), `output` the
output power (`analyser:p_shaft_w`; with `output_2`, `output_3` the sum of up to three elements: a CDM's losses
are P_dc - (P_a + P_b + P_c)), all readings of an analyser whose [[instruments]] entry states its accuracy
(`accuracy_reading_pct`, `accuracy_range_pct`). Over the window, with P the mean of the readings:

    U(P)      = reading_pct/100 * |P| + range_pct/100 * range          (the data sheet's limit, per element)
    loss      = P_in - P_out,                    U(loss)     = U(P_in) + U(P_out)
    loss in % = 100 (P_in - P_out) / P_in,       U(loss %)   = 100 P_out/P_in (U(P_in)/P_in + U(P_out)/P_out)

The errors are a calibrated instrument's, systematic within its spec: averaging readings does not shrink them, and
the elements' limits add (worst case; the root sum of squares is in the detail). The value judged is the upper
bound, measured + U: a point passes only when its losses are shown below the limit whatever the analyser's error
within its spec (ISO 14253-1's rule for proving conformance). `reference_loss_w` (the standard's reference PDS or
CDM losses for the rated power, from its tables) adds the class the measured losses indicate — IES2 below 80 %,
IES1 80-120 %, IES0 above 120 % of the reference (IE for a CDM) — stated as indicative: a class is certified by an
accredited test, not by a bench.

Only on instruments' records (bench.inputs.capture_criteria passes the accuracy); on telemetry or without a
stated accuracy: not judged.
"""

from __future__ import annotations

import math

import numpy as np

from bench.inputs.criteria import KINDS, CriterionSpec, Kind, Param, _NotJudged, _Unusable, _Window

ACCURACY = "_accuracy"       # injected by capture_criteria: signal -> (reading_pct, range_pct, range)


def _budget(w: _Window, spec: CriterionSpec) -> tuple[float, float, float, float, str]:
    accuracy = spec.params.get(ACCURACY) or {}
    outputs = [spec.params["output"]] + [spec.params[k] for k in ("output_2", "output_3") if spec.params.get(k)]
    names = [spec.signal, *outputs]
    missing = [n for n in names if n not in accuracy]
    if missing:
        raise _NotJudged(f"no stated accuracy for {', '.join(missing)}: give the analyser's accuracy_reading_pct "
                         "and accuracy_range_pct in its [[instruments]] entry")
    means = {n: float(np.mean(w.signal(n))) for n in names}
    limits = {n: accuracy[n][0] / 100 * abs(means[n]) + accuracy[n][1] / 100 * accuracy[n][2] for n in names}
    p_in, u_in = means[spec.signal], limits[spec.signal]
    p_out, u_out = sum(means[n] for n in outputs), sum(limits[n] for n in outputs)
    r, g, _ = accuracy[spec.signal]
    parts = f" ({len(outputs)} elements)" if len(outputs) > 1 else ""
    return p_in, p_out, u_in, u_out, (f"P_in {p_in:.5g} W ±{u_in:.3g}, P_out{parts} {p_out:.5g} W ±{u_out:.3g} over "
                                      f"{w.t.size} readings (±({r:g} % of reading + {g:g} % of range))")


def _indicative_class(spec: CriterionSpec, loss: float, u: float) -> str:
    ref = spec.params.get("reference_loss_w")
    if ref is None:
        return ""
    lo, hi = (loss - u) / ref * 100, (loss + u) / ref * 100

    def cls(pct: float) -> str:
        return "IES2" if pct < 80 else ("IES1" if pct <= 120 else "IES0")

    named = cls(loss / ref * 100)
    spread = "" if cls(lo) == cls(hi) else f", {cls(hi)}-{cls(lo)} within the uncertainty"
    return (f"; {loss / ref * 100:.1f} % of the reference losses {ref:g} W: class {named} indicative "
            f"(not a certification{spread})")


def loss_w(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    p_in, p_out, u_in, u_out, how = _budget(w, spec)
    loss, u = p_in - p_out, u_in + u_out
    return loss + u, (f"losses {loss:.4g} W ±{u:.3g} W (rss {math.hypot(u_in, u_out):.3g}), upper bound judged; "
                      f"{how}{_indicative_class(spec, loss, u)}")


def loss_pct(w: _Window, spec: CriterionSpec) -> tuple[float, str]:
    p_in, p_out, u_in, u_out, how = _budget(w, spec)
    if p_in <= 0 or p_out <= 0:
        raise _Unusable(f"P_in {p_in:.4g} W, P_out {p_out:.4g} W: an efficiency needs power flowing in and out")
    eta = p_out / p_in
    u = 100 * eta * (u_in / p_in + u_out / p_out)
    loss = 100 * (1 - eta)
    return loss + u, (f"efficiency {100 * eta:.3f} % ±{u:.3f} points, losses {loss:.3f} % of P_in (upper bound "
                      f"judged); {how}")


_POWER = {"output": Param("signal", required=True, help="output power (the criterion's signal is the input)"),
          "output_2": Param("signal", help="a second output element, added (a CDM's motor phases)"),
          "output_3": Param("signal", help="a third output element, added")}
NEW_KINDS: dict[str, Kind] = {
    "loss_w": Kind(loss_w, "W", {**_POWER, "reference_loss_w": Param(
        "number", help="the standard's reference losses: adds an indicative IES/IE class")},
        "mean(input - output power) + its uncertainty from the analyser's stated accuracy"),
    "loss_pct": Kind(loss_pct, "%", dict(_POWER),
                     "100 - efficiency (losses in % of the input) + its uncertainty from the stated accuracy"),
}


def _register() -> None:
    smooth = KINDS["rise_time"].params["smooth_s"]
    for name, kind in NEW_KINDS.items():
        kind.params.setdefault("smooth_s", smooth)
        KINDS.setdefault(name, kind)


_register()
