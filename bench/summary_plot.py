"""summary.png: one figure with speed, position error, flux and currents over drive time."""

from __future__ import annotations

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
MAX_POINTS = 20_000  # per line; a 10 kHz trace of a long run is decimated for drawing only


def write_summary_png(path: Path, t_s: np.ndarray, columns: Mapping[str, np.ndarray], title: str = "") -> Path:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    t_s = np.asarray(t_s, dtype=float)
    step = max(1, len(t_s) // MAX_POINTS)
    fig = Figure(figsize=(10, 9), layout="constrained")
    axes = fig.subplots(len(PANELS), 1, sharex=True)
    for ax, (name, unit, lines) in zip(axes, PANELS):
        for signal, label in lines:
            values = columns.get(signal)
            if values is None or len(values) != len(t_s) or not np.isfinite(values).any():
                continue
            ax.plot(t_s[::step], np.asarray(values)[::step], label=label, linewidth=0.8)
        ax.set_ylabel(f"{name}\n[{unit}]")
        ax.grid(True, alpha=0.3)
        if ax.get_lines():
            ax.legend(loc="upper right", fontsize="small")
    axes[-1].set_xlabel("drive time t_s [s]")
    if title:
        fig.suptitle(title)
    path = Path(path)
    fig.savefig(path, dpi=100)
    return path
