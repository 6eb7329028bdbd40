"""The lab instruments' records in a run's MDF4 export (bench.outputs.export): one channel group per instrument
record — each scope/DAQ capture and each power analyser's readings — with its own master channel `t_s` on the drive
clock (as the run placed it, docs/instruments.md), channels named `<instrument>:<signal>` as criteria name them,
units as the bench config wired them, the sample rate and the placement's stated uncertainty in the group comment.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape

import numpy as np

_UNITS = {"N*m": "N·m"}


def instrument_records(run_dir: Path, record: dict) -> list[tuple[str, dict, dict[str, np.ndarray]]]:
    """(instrument name, its summary in record.json, its columns) for every record the run stored."""
    import pyarrow.parquet as pq

    lab = record.get("lab_instruments") or {}
    out = []
    for section in ("captures", "analysers"):
        for name, summary in sorted((lab.get(section) or {}).items()):
            path = run_dir / str(summary.get("file", ""))
            if summary.get("file") and path.is_file():
                out.append((name, summary, {k: np.asarray(v, dtype=np.float64)
                                            for k, v in pq.read_table(path).to_pydict().items()}))
    return out


def run_records(run_dir: Path, record: dict) -> tuple[dict[str, dict[str, np.ndarray]], tuple]:
    """A recorded run's instrument records by instrument name, and its bench's [[instruments]] (units, ranges and
    stated accuracy; () when the bench config the record names cannot be read): for re-judging offline."""
    records = {name: columns for name, _, columns in instrument_records(run_dir, record)}
    instruments: tuple = ()
    path = (record.get("bench") or {}).get("path")
    if records and path:
        try:
            from bench.inputs.benchconfig import load_bench_config
            instruments = load_bench_config(path).instruments
        except Exception:
            instruments = ()
    return records, instruments


def append_instrument_groups(mdf: Any, run_dir: Path, record: dict) -> list[str]:
    """Append a channel group per instrument record to `mdf` (asammdf.MDF); the header lines describing them."""
    from asammdf import Signal

    lines = []
    for name, summary, columns in instrument_records(run_dir, record):
        t = columns.pop("t_s")
        if not t.size:
            continue
        units = summary.get("units") or {}
        rate = summary.get("sample_rate_hz") or summary.get("rate_hz_drive_clock")
        how = (f"placed by its trigger at drive time {summary.get('forced_at_drive_s')} s, uncertainty "
               f"{summary.get('placement_uncertainty_s')} s" if "forced_at_drive_s" in summary
               else "each reading stamped with the drive time of the SYNC it was read at")
        comment = f"instrument {name}: {rate} S/s on the drive clock (master t_s), {how}"
        not_judged = summary.get("not_judged") or {}
        signals = [Signal(values, t, name=f"{name}:{signal}", unit=_UNITS.get(units.get(signal, ""),
                                                                             units.get(signal, "")),
                          comment=f"{name} {signal}" + (f"; not judged: {not_judged[signal]}"
                                                        if signal in not_judged else ""),
                          master_metadata=("t_s", 1))
                   for signal, values in columns.items()]
        if signals:
            mdf.append(signals, comment=escape(comment), common_timebase=True)
            lines.append(f"channel group {name}: {len(signals)} channels, {t.size} samples, {comment}")
    return lines
