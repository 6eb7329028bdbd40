"""`drivebench compare RUN_A RUN_B`: two runs side by side — what differs in what ran (scenario, seed, bench, drive
firmware, software revision, verdict), each criterion's value in both with the delta, and each signal's difference
over the drive-clock span both cover (B interpolated onto A's clock), plus a plot of the signals overlaid."""

from __future__ import annotations

import hashlib
import math
from pathlib import Path
from typing import Any

import numpy as np

from bench.inputs.criteria import is_angle, wrap_angle
from bench.outputs.run_files import load_run
from drivers.contract.signals import SIGNALS

IDENTITY: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("scenario", ("scenario", "name")), ("scenario sha256", ("scenario", "sha256")), ("seed", ("seed",)),
    ("bench", ("bench", "name")), ("drive", ("drive", "identity", "device_name")),
    ("firmware", ("drive", "firmware_version")), ("software", ("software", "version")),
    ("revision", ("software", "git_revision")), ("verdict", ("verdict",)), ("abort reason", ("abort_reason",)),
)
PLOT_SIGNALS = ("speed_ref_mech_rad_s", "speed_est_mech_rad_s", "speed_true_mech_rad_s", "pos_err_elec_rad",
                "flux_est_wb", "i_sx_a", "i_sy_a", "torque_load_nm")


def _get(record: dict, path: tuple[str, ...]) -> Any:
    value: Any = record
    for key in path:
        value = value.get(key) if isinstance(value, dict) else None
    return value


def _finite(x: Any) -> float | None:
    return float(x) if isinstance(x, (int, float)) and math.isfinite(x) else None


def compare_runs(run_a: str | Path, run_b: str | Path) -> dict[str, Any]:
    """The comparison as a JSON-able dict: identity (each field with both values and `same`), criteria (by name,
    in A's order then B's own), signals (rms and max |B - A| over the common span)."""
    rec_a, cols_a, _ = load_run(Path(run_a))
    rec_b, cols_b, _ = load_run(Path(run_b))
    identity = [{"field": name, "a": _get(rec_a, path), "b": _get(rec_b, path),
                 "same": _get(rec_a, path) == _get(rec_b, path)} for name, path in IDENTITY]
    by_b = {c["name"]: c for c in rec_b.get("criteria") or []}
    criteria = []
    for c in rec_a.get("criteria") or []:
        other = by_b.pop(c["name"], None)
        criteria.append(_criterion_row(c, other))
    criteria += [_criterion_row(None, c) for c in by_b.values()]
    return {"a": str(run_a), "b": str(run_b), "identity": identity, "criteria": criteria,
            "scenario": scenario_differences(rec_a, rec_b), "signals": _signal_rows(cols_a, cols_b)}


def _criterion_row(a: dict | None, b: dict | None) -> dict[str, Any]:
    any_ = a or b or {}
    va, vb = _finite((a or {}).get("value")), _finite((b or {}).get("value"))
    from bench.outputs.report import unit_of        # records written before criteria carried their unit

    return {"name": any_.get("name"), "signal": any_.get("signal"), "unit": any_.get("unit") or unit_of(any_),
            "value_a": va, "value_b": vb, "delta": vb - va if va is not None and vb is not None else None,
            "limit_a": (a or {}).get("limit"), "limit_b": (b or {}).get("limit"),
            "window_a": (a or {}).get("window_s"), "window_b": (b or {}).get("window_s"),
            "changed": [what for what, key in (("limit", "limit"), ("window", "window_s"), ("kind", "kind"))
                        if a is not None and b is not None and a.get(key) != b.get(key)],
            "status_a": (a or {}).get("status") or ("absent" if a is None else ""),
            "status_b": (b or {}).get("status") or ("absent" if b is None else "")}


def _common(cols_a: dict, cols_b: dict, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(t, a, b on A's clock) over the span both runs cover with finite samples; None when they share none."""
    if name not in cols_a or name not in cols_b:
        return None
    ta, tb = np.asarray(cols_a["t_s"], float), np.asarray(cols_b["t_s"], float)
    a, b = np.asarray(cols_a[name], float), np.asarray(cols_b[name], float)
    ok_b = np.isfinite(b)
    if not ok_b.any() or not np.isfinite(a).any():
        return None
    lo, hi = max(ta[0], tb[ok_b][0]), min(ta[-1], tb[ok_b][-1])
    sel = (ta >= lo) & (ta <= hi) & np.isfinite(a)
    if not sel.any():
        return None
    return ta[sel], a[sel], np.interp(ta[sel], tb[ok_b], b[ok_b])


def _measured(cols: dict, name: str) -> bool:
    return name in cols and bool(np.isfinite(np.asarray(cols[name], float)).any())


def _signal_rows(cols_a: dict, cols_b: dict) -> list[dict[str, Any]]:
    """A row per signal both runs measured (its difference), and one per signal only one of them measured (said, so
    that a signal the other bench could not measure is not silently left out)."""
    rows = []
    for s in SIGNALS:
        in_a, in_b = _measured(cols_a, s.name), _measured(cols_b, s.name)
        if in_a != in_b:
            rows.append({"signal": s.name, "unit": s.unit, "only_in": "a" if in_a else "b", "span_s": None,
                         "rms_diff": None, "max_abs_diff": None, "at_s": None})
            continue
        common = _common(cols_a, cols_b, s.name)
        if common is None:
            continue
        t, a, b = common
        d = wrap_angle(b - a) if is_angle(s.name) else b - a     # angles: the short way round
        i = int(np.argmax(np.abs(d)))
        rows.append({"signal": s.name, "unit": s.unit, "span_s": [float(t[0]), float(t[-1])],
                     "rms_diff": float(np.sqrt(np.mean(d * d))), "max_abs_diff": float(abs(d[i])),
                     "at_s": float(t[i])})
    return rows


def scenario_differences(rec_a: dict, rec_b: dict, most: int = 40) -> list[dict[str, Any]]:
    """What differs between the two runs' scenario files, key by key (`limits.overcurrent_a`, `speed[1].end_s`, ...),
    read from the paths their records name where the file there still has the hash the record says; a side whose
    file is gone or changed is said as such. [] when both ran the same file content."""
    from drivers.contract.toml_file import parse_toml_bytes

    sides = []
    for rec in (rec_a, rec_b):
        scenario = rec.get("scenario") or {}
        try:
            data = Path(str(scenario.get("path"))).read_bytes()
        except OSError:
            return [{"key": "(file)", "a": None, "b": None, "note": f"{scenario.get('path')}: no longer readable"}]
        if hashlib.sha256(data).hexdigest() != scenario.get("sha256"):
            return [{"key": "(file)", "a": None, "b": None,
                     "note": f"{scenario.get('path')}: changed since the run (its sha256 differs)"}]
        sides.append(_flat(parse_toml_bytes(data)))
    if (rec_a.get("scenario") or {}).get("sha256") == (rec_b.get("scenario") or {}).get("sha256"):
        return []
    a, b = sides
    rows = [{"key": k, "a": a.get(k), "b": b.get(k), "note": ""} for k in sorted(set(a) | set(b), key=_key_order)
            if a.get(k) != b.get(k) and k not in ("name", "description")]
    return rows[:most]


def _flat(value: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(value, dict):
        out: dict[str, Any] = {}
        for k, v in value.items():
            out.update(_flat(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        out = {}
        for i, v in enumerate(value):
            out.update(_flat(v, f"{prefix}[{i}]"))
        return out
    return {prefix: value}


def _key_order(key: str) -> tuple:
    return (not key.startswith("limits"), key)


def write_plot(run_a: str | Path, run_b: str | Path, path: Path) -> Path | None:
    """The measured signals of both runs overlaid on the drive clock, a panel per signal (A solid, B dashed)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    rec_a, cols_a, _ = load_run(Path(run_a))
    rec_b, cols_b, _ = load_run(Path(run_b))
    units = {s.name: s.unit for s in SIGNALS}
    names = [n for n in PLOT_SIGNALS if _common(cols_a, cols_b, n) is not None]
    if not names:
        return None
    fig = Figure(figsize=(10, 1.7 * len(names) + 0.8), layout="constrained")
    axes = fig.subplots(len(names), 1, sharex=True, squeeze=False)[:, 0]
    label_a = f"A {Path(run_a).name} ({rec_a.get('verdict')})"
    label_b = f"B {Path(run_b).name} ({rec_b.get('verdict')})"
    for ax, name in zip(axes, names):
        for cols, label, style in ((cols_a, label_a, "-"), (cols_b, label_b, "--")):
            t, y = np.asarray(cols["t_s"], float), np.asarray(cols.get(name, np.full(len(cols["t_s"]), np.nan)))
            stride = max(1, len(t) // 4000)
            ax.plot(t[::stride], y[::stride], style, lw=0.9, label=label)
        ax.set_ylabel(f"{name}\n{units[name]}", fontsize=7)
        ax.grid(True, lw=0.3)
        ax.tick_params(labelsize=7)
    axes[0].legend(fontsize=7, loc="upper right")
    axes[-1].set_xlabel("drive time t_s, s", fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    return path
