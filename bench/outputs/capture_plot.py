"""A plot of an instrument's capture: one panel per signal on the drive clock, the marked moment, and the windows of
the criteria judged on it (green pass, red fail, amber not judged). Written as instruments/<name>.png after a run."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

MAX_POINTS = 50_000         # per signal: a long DAQ record is drawn from every n-th sample (a glance, not analysis)
COLOURS = {"pass": "tab:green", "fail": "tab:red", "not_judged": "orange"}


def write_capture_png(path: Path, name: str, record: Mapping[str, np.ndarray], summary: Mapping[str, Any],
                      criteria: Iterable[Mapping[str, Any]] = ()) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    t = np.asarray(record["t_s"], dtype=float)
    signals = [k for k in record if k != "t_s"]
    stride = max(1, t.size // MAX_POINTS)
    units = summary.get("units") or {}
    fig = Figure(figsize=(10, 1.5 * len(signals) + 1.2))
    axes = fig.subplots(len(signals), 1, sharex=True, squeeze=False)[:, 0]
    fig.subplots_adjust(left=0.12, right=0.98, bottom=0.08, top=0.92, hspace=0.12)
    moment = summary.get("forced_at_drive_s")
    mine = [c for c in criteria if str(c.get("signal", "")).startswith(f"{name}:")]
    for ax, signal in zip(axes, signals):
        ax.plot(t[::stride], np.asarray(record[signal], dtype=float)[::stride], linewidth=0.7)
        ax.set_ylabel(f"{signal}\n[{units.get(signal, '')}]", fontsize=7)
        ax.grid(True, alpha=0.3)
        if moment is not None and summary.get("marked_moment_s"):
            ax.axvline(float(moment), color="tab:purple", linestyle=":", linewidth=1.0)
        for c in mine:
            if c["signal"] == f"{name}:{signal}" and len(c.get("window_s") or ()) == 2:
                ax.axvspan(*map(float, c["window_s"]), color=COLOURS.get(c.get("status"), "grey"), alpha=0.1, lw=0)
    rate = summary.get("sample_rate_hz")
    axes[-1].set_xlabel(f"drive time t_s [s]   ({rate} S/s, placed within ±{summary.get('placement_uncertainty_s')} s; "
                        "dotted: the forced trigger; shaded: criteria windows)", fontsize=7)
    fig.suptitle(f"{name}: {t.size} samples from {t[0]:.4f} s", y=0.995, fontsize=9)
    fig.savefig(path, dpi=90)
    return Path(path)
