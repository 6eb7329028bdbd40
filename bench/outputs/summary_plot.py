"""summary.png: the run and its judgement in one figure over drive time — speed, position error, flux, currents,
torque; each criterion's window shaded on its signal's panel in its result's colour (green pass, red fail, amber not
judged or known gap) with its limit band where the limit is in the signal's own unit; trips and injections as
vertical markers. The same figure serves the record, `drivebench report` and the service's run page."""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

PANELS: tuple[tuple[str, str, tuple[tuple[str, str], ...]], ...] = (
    ("speed", "rad/s (mech)", (("speed_ref_mech_rad_s", "reference"), ("speed_est_mech_rad_s", "estimated"),
                               ("speed_true_mech_rad_s", "true (reference sensor)"))),
    ("position error", "rad (elec)", (("pos_err_elec_rad", "true - estimated"),)),
    ("flux", "Wb", (("flux_est_wb", "estimated"), ("flux_true_wb", "true"))),
    ("currents", "A", (("i_sx_a", "i_sx"), ("i_sy_a", "i_sy"), ("i_sx_ref_a", "i_sx ref"), ("i_sy_ref_a", "i_sy ref"))),
    ("torque", "N*m", (("torque_load_nm", "load (transducer)"), ("torque_est_nm", "drive's estimate"))),
)
PLOT_SIGNALS: tuple[str, ...] = tuple(dict.fromkeys(sig for _, _, lines in PANELS for sig, _ in lines))
BUCKETS = 1500  # per line: min and max of each bucket are drawn, so spikes survive the decimation
COLOURS = {"pass": "tab:green", "fail": "tab:red", "not_judged": "tab:orange", "known_gap": "tab:orange"}
# kinds whose limit bounds the signal itself around a centre (0, `expected` or `target`): drawn as a band
BAND_KINDS = {"peak_abs", "pos_error_max", "mean"}


def envelope(t: np.ndarray, y: np.ndarray, buckets: int = BUCKETS) -> tuple[np.ndarray, np.ndarray]:
    """Min-max decimation: for each of `buckets` equal slices, its min and max (at the slice's time)."""
    n = len(t) // buckets
    if n < 2:
        return t, y
    m = n * buckets
    tb = t[:m].reshape(buckets, n)
    yb = y[:m].reshape(buckets, n)
    with warnings.catch_warnings():          # a bucket with no finite value stays NaN: a gap in the line
        warnings.simplefilter("ignore", RuntimeWarning)
        lo = np.nanmin(yb, axis=1) if np.isnan(yb).any() else yb.min(axis=1)
        hi = np.nanmax(yb, axis=1) if np.isnan(yb).any() else yb.max(axis=1)
    tt = np.repeat(tb[:, 0], 2)
    yy = np.empty(2 * buckets)
    yy[0::2], yy[1::2] = lo, hi
    return np.concatenate([tt, t[m:]]), np.concatenate([yy, y[m:]])


def events_of(record: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Trips and applied injections of a record (or of the orchestrator's notes) as plot markers."""
    out: list[dict[str, Any]] = []
    for trip in record.get("trips") or []:
        if isinstance(trip, dict) and isinstance(trip.get("t_s"), (int, float)) and math.isfinite(trip["t_s"]):
            out.append({"t_s": float(trip["t_s"]), "kind": "trip", "label": str(trip.get("reason") or "trip")})
    for inj in record.get("injections_applied") or []:
        t = inj.get("applied_t_s", inj.get("at_s")) if isinstance(inj, dict) else None
        if isinstance(t, (int, float)):
            out.append({"t_s": float(t), "kind": "injection", "label": f"{inj.get('name')} = {inj.get('value')}"})
    return out


def _status(c: Mapping[str, Any]) -> str:
    if c.get("passed"):
        return "pass"
    if c.get("status") == "not_judged":
        return "not_judged"
    return "known_gap" if c.get("known_gap") else "fail"


def _band(c: Mapping[str, Any], params: Mapping[str, Any]) -> tuple[float, float] | None:
    """(low, high) of the signal the limit allows, where the limit is in the signal's unit and about a constant."""
    kind, limit = c.get("kind"), c.get("limit")
    if kind not in BAND_KINDS or not isinstance(limit, (int, float)) or params.get("reference"):
        return None
    if kind == "mean":
        centre = params.get("expected")
    else:
        centre = params.get("target", 0.0)
    if not isinstance(centre, (int, float)):
        return None
    return float(centre) - float(limit), float(centre) + float(limit)


def _fmt(v: Any) -> str:
    return "n/a" if not isinstance(v, (int, float)) or not math.isfinite(v) else f"{v:.3g}"


def write_summary_png(path: Path, t_s: np.ndarray, columns: Mapping[str, np.ndarray], title: str = "",
                      criteria: Iterable[Mapping[str, Any]] = (), params: Mapping[str, Mapping[str, Any]] | None = None,
                      events: Iterable[Mapping[str, Any]] = ()) -> Path:
    """`criteria`: CriterionResult.to_dict() rows (or record.json's); `params`: criterion name -> its scenario
    parameters (for the limit band's centre); `events`: events_of(record)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    t_s = np.asarray(t_s, dtype=float)
    panels = [p for p in PANELS if any(columns.get(s) is not None and len(columns[s]) == len(t_s)
                                       and np.isfinite(columns[s]).any() for s, _ in p[2])] or list(PANELS[:1])
    fig = Figure(figsize=(10, 1.9 * len(panels) + 1.3))  # fixed margins: constrained layout doubles the drawing time
    axes = fig.subplots(len(panels), 1, sharex=True, squeeze=False)[:, 0]
    fig.subplots_adjust(left=0.1, right=0.98, bottom=0.07, top=0.93 - 0.02 * (len(panels) < 4), hspace=0.14)
    panel_of = {sig: i for i, (_, _, lines) in enumerate(panels) for sig, _ in lines}
    for ax, (name, unit, lines) in zip(axes, panels):
        for signal, label in lines:
            values = columns.get(signal)
            if values is None or len(values) != len(t_s) or not np.isfinite(values).any():
                continue
            ax.plot(*envelope(t_s, np.asarray(values, dtype=float)), label=label, linewidth=0.8)
        ax.set_ylabel(f"{name}\n[{unit}]")
        ax.yaxis.set_major_locator(MaxNLocator(nbins=4))      # 1.9 in per panel: more ticks only cost drawing
        ax.grid(True, alpha=0.3)
    params = params or {}
    per_panel = [0] * len(panels)          # labels of one panel stacked, not drawn over each other
    for c in criteria:
        i = panel_of.get(str(c.get("signal")))
        window = c.get("window_s") or ()
        if i is None or len(window) != 2:
            continue
        ax, colour = axes[i], COLOURS[_status(c)]
        ax.axvspan(float(window[0]), float(window[1]), color=colour, alpha=0.08, lw=0)
        band = _band(c, params.get(str(c.get("name"))) or {})
        if band is not None:
            ax.hlines(band, float(window[0]), float(window[1]), colors=colour, linestyles="--", linewidth=0.9)
        unit_text = f" {c.get('unit')}" if c.get("unit") else ""
        ax.annotate(f"{c.get('name')}: {_fmt(c.get('value'))} / {_fmt(c.get('limit'))}{unit_text}",
                    (float(window[0]), 1.0), xycoords=("data", "axes fraction"), fontsize=6, color=colour,
                    va="top", ha="left", annotation_clip=True, xytext=(2, -2 - 7 * (per_panel[i] % 6)),
                    textcoords="offset points")
        per_panel[i] += 1
    for event in events:
        style = {"trip": ("tab:red", "-"), "injection": ("tab:purple", ":")}[event["kind"]]
        for ax in axes:
            ax.axvline(event["t_s"], color=style[0], linestyle=style[1], linewidth=1.0)
        axes[-1].annotate(event["label"], (event["t_s"], 0.03), xycoords=("data", "axes fraction"), fontsize=7,
                          color=style[0], rotation=90, va="bottom", ha="right")
    for ax in axes:
        if ax.get_lines():
            ax.legend(loc="lower right", fontsize="x-small")
    axes[-1].set_xlabel("drive time t_s [s]   (shaded: criterion windows, green pass / red fail / amber not judged or "
                        "known gap; dashed: limit; red line: trip; purple dotted: injection)", fontsize=7)
    if title:
        fig.suptitle(title, y=0.995)
    path = Path(path)
    try:
        # Agg draws a path in chunks of 500 points: a dense min-max envelope otherwise costs ~15 MB of scanline cells
        with matplotlib.rc_context({"agg.path.chunksize": 500}):
            fig.savefig(path, dpi=100, pil_kwargs={"compress_level": 1})  # fast zlib: the plot is written every run
    finally:
        del fig, axes       # a web of cycles: a run's end collects it at once (memory.release_freed_memory)
    return path
