"""An efficiency map from runs judged on a power analyser: every `loss_pct` criterion of every run found under a
directory (a campaign's output, or one run) is an operating point — the shaft speed and torque the analyser read over
its window, the efficiency P_out/P_in, and its uncertainty from the criterion (the judged value is the upper bound:
losses + U) — drawn as a contour plot over speed x torque with the points marked, and written as a table.

    python -m bench.outputs.efficiency_map RUNS_DIR [--out PREFIX]     # PREFIX.png and PREFIX.csv (default RUNS_DIR/efficiency_map)

Points of several seeds at one operating point are averaged (the spread between seeds is in the table).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np


def map_points(root: Path) -> list[dict]:
    """One row per operating point (scenario and criterion name), over every run under `root`."""
    import pyarrow.parquet as pq

    found: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for record_path in sorted(root.rglob("record.json")):
        record = json.loads(record_path.read_text())
        analysers = (record.get("lab_instruments") or {}).get("analysers") or {}
        for c in record.get("criteria") or []:
            if c.get("kind") != "loss_pct" or c.get("status") == "not_judged" or ":" not in c.get("signal", ""):
                continue
            name = c["signal"].split(":")[0]
            summary = analysers.get(name)
            if not summary:
                continue
            a = pq.read_table(record_path.parent / summary["file"]).to_pydict()
            t = np.asarray(a["t_s"])
            sel = (t >= c["window_s"][0]) & (t <= c["window_s"][1])
            p_in, p_out = float(np.mean(np.asarray(a["p_dc_w"])[sel])), float(np.mean(np.asarray(a["p_shaft_w"])[sel]))
            eff = 100.0 * p_out / p_in
            found[((record.get("scenario") or {}).get("name", ""), c["name"])].append({
                "speed_mech_rad_s": float(np.mean(np.asarray(a["speed_shaft_mech_rad_s"])[sel])),
                "torque_nm": float(np.mean(np.asarray(a["torque_shaft_nm"])[sel])),
                "efficiency_pct": eff, "uncertainty_pct": float(c["value"] - (100.0 - eff)),
                "p_in_w": p_in, "p_out_w": p_out, "seed": record.get("seed")})
    rows = []
    for (scenario, name), runs in sorted(found.items()):
        eff = [r["efficiency_pct"] for r in runs]
        rows.append({"scenario": scenario, "point": name, "runs": len(runs),
                     **{k: float(np.mean([r[k] for r in runs])) for k in
                        ("speed_mech_rad_s", "torque_nm", "efficiency_pct", "uncertainty_pct", "p_in_w", "p_out_w")},
                     "seed_spread_pct": float(max(eff) - min(eff))})
    return rows


def write_map(rows: list[dict], prefix: Path) -> tuple[Path, Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pyarrow as pa
    import pyarrow.csv as pacsv

    csv = prefix.with_suffix(".csv")
    pacsv.write_csv(pa.Table.from_pylist(rows), csv)
    w = np.array([r["speed_mech_rad_s"] for r in rows])
    q = np.array([r["torque_nm"] for r in rows])
    eff = np.array([r["efficiency_pct"] for r in rows])
    fig, ax = plt.subplots(figsize=(8, 5.5))
    filled = ax.tricontourf(w, q, eff, levels=12, cmap="viridis")
    lines = ax.tricontour(w, q, eff, levels=filled.levels[::2], colors="white", linewidths=0.6)
    ax.clabel(lines, fmt="%.1f %%", fontsize=7)
    ax.scatter(w, q, c="k", s=12)
    for r in rows:
        ax.annotate(f"{r['efficiency_pct']:.1f}±{r['uncertainty_pct']:.1f}", (r["speed_mech_rad_s"], r["torque_nm"]),
                    textcoords="offset points", xytext=(4, 4), fontsize=7)
    span_w, span_q = max(np.ptp(w), 1e-9), max(np.ptp(q), 1e-9)
    ax.set_xlim(w.min() - 0.05 * span_w, w.max() + 0.15 * span_w)
    ax.set_ylim(q.min() - 0.05 * span_q, q.max() + 0.1 * span_q)
    fig.colorbar(filled, ax=ax, label="efficiency P_shaft / P_in, %")
    ax.set_xlabel("shaft speed, rad/s (analyser)")
    ax.set_ylabel("shaft torque, N·m (analyser)")
    ax.set_title(f"efficiency map: {len(rows)} points, ± the analyser's stated accuracy")
    png = prefix.with_suffix(".png")
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return png, csv


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.outputs.efficiency_map", description=__doc__.split("\n")[0])
    parser.add_argument("runs_dir", type=Path)
    parser.add_argument("--out", type=Path, help="PREFIX of PREFIX.png and PREFIX.csv")
    args = parser.parse_args(argv)
    if not args.runs_dir.is_dir():
        print(f"{args.runs_dir}: not a directory", file=sys.stderr)
        return 2
    rows = map_points(args.runs_dir)
    if len(rows) < 3:
        print(f"{args.runs_dir}: {len(rows)} judged loss_pct points on an analyser; a map needs at least 3",
              file=sys.stderr)
        return 2
    png, csv = write_map(rows, args.out or args.runs_dir / "efficiency_map")
    print(f"{png}\n{csv}\n{len(rows)} points, efficiency {min(r['efficiency_pct'] for r in rows):.2f}-"
          f"{max(r['efficiency_pct'] for r in rows):.2f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
