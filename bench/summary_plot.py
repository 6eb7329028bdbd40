"""summary.png: one figure with speed, position error, flux and currents over drive time."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Mapping

import numpy as np

PANELS: tuple[tuple[str, str, tuple[tuple[str, str], ...]], ...] = (
    ("speed", "rad/s (mech)", (("speed_ref_mech_rad_s", "reference"), ("speed_est_mech_rad_s", "estimated"),
                               ("speed_true_mech_rad_s", "true"))),
    ("position error", "rad (elec)", (("pos_err_elec_rad", "true - estimated"),)),
    ("flux", "Wb", (("flux_est_wb", "estimated"), ("flux_true_wb", "true"))),
    ("currents", "A", (("i_sx_a", "i_sx"), ("i_sy_a", "i_sy"), ("i_sx_ref_a", "i_sx ref"), ("i_sy_ref_a", "i_sy ref"))),
)
PLOT_SIGNALS: tuple[str, ...] = tuple(dict.fromkeys(sig for _, _, lines in PANELS for sig, _ in lines))
BUCKETS = 1500  # per line: min and max of each bucket are drawn, so spikes survive the decimation


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


def write_summary_png(path: Path, t_s: np.ndarray, columns: Mapping[str, np.ndarray], title: str = "") -> Path:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    t_s = np.asarray(t_s, dtype=float)
    fig = Figure(figsize=(10, 9))  # fixed margins: constrained layout doubles the drawing time
    axes = fig.subplots(len(PANELS), 1, sharex=True)
    fig.subplots_adjust(left=0.1, right=0.98, bottom=0.06, top=0.95, hspace=0.12)
    for ax, (name, unit, lines) in zip(axes, PANELS):
        for signal, label in lines:
            values = columns.get(signal)
            if values is None or len(values) != len(t_s) or not np.isfinite(values).any():
                continue
            ax.plot(*envelope(t_s, np.asarray(values, dtype=float)), label=label, linewidth=0.8)
        ax.set_ylabel(f"{name}\n[{unit}]")
        ax.grid(True, alpha=0.3)
        if ax.get_lines():
            ax.legend(loc="upper right", fontsize="small")
    axes[-1].set_xlabel("drive time t_s [s]")
    if title:
        fig.suptitle(title)
    path = Path(path)
    try:
        # Agg draws a path in chunks of 500 points: a dense min-max envelope otherwise costs ~15 MB of scanline cells
        with matplotlib.rc_context({"agg.path.chunksize": 500}):
            fig.savefig(path, dpi=100, pil_kwargs={"compress_level": 1})  # fast zlib: the plot is written every run
    finally:
        fig.clear()         # a figure is a web of cycles: without this its canvas waits for the cyclic collector
        del fig, axes
    return path
