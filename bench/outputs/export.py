"""`drivebench export RUN_DIR --format mf4|csv [--out FILE]`: a run's telemetry in files other tools open.

- mf4: ASAM MDF 4.10 through asammdf (what asammdf, CANape, INCA and DIAdem read): one channel group, the drive
  clock `t_s` as the master channel, one channel per signal the run measured (a signal that is NaN throughout, not
  measured on that bench, is left out and named in the file comment), units and descriptions from
  drivers/contract/signals.py, the run's identity in the header comment and record.json attached (embedded), so the file
  carries its verdict. The lab instruments' records (captures, analyser readings) follow, a channel group each with
  its own master on the drive clock (bench.outputs.export_instruments).
- csv: `t_s` and one column per measured signal (names carry their units), through pyarrow's CSV writer; empty
  cells where a sample is missing.
"""

from __future__ import annotations

import json
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np

from drivers.contract.errors import InputError
from bench.outputs.run_files import load_run
from drivers.contract.signals import SIGNALS

FORMATS = ("mf4", "csv")


def _measured(columns: dict[str, np.ndarray]) -> tuple[list[str], list[str]]:
    """(signals with at least one finite sample, signals NaN throughout), in the catalogue's order."""
    kept, dropped = [], []
    for s in SIGNALS:
        if s.name in columns:
            (kept if np.isfinite(np.asarray(columns[s.name], dtype=float)).any() else dropped).append(s.name)
    return kept, dropped


def export_run(run_dir: str | Path, fmt: str, out: str | Path | None = None) -> Path:
    """Write the run's telemetry as `fmt`; the path written (default: RUN_DIR/telemetry.<fmt>)."""
    run_dir = Path(run_dir)
    if fmt not in FORMATS:
        raise InputError([f"--format: must be one of {', '.join(FORMATS)}, got {fmt!r}"])
    record, columns, _ = load_run(run_dir)
    target = Path(out) if out is not None else run_dir / f"telemetry.{fmt}"
    if target.is_dir():
        raise InputError([f"{target}: --out: is a directory; name the file to write"])
    if not target.parent.is_dir():
        raise InputError([f"{target}: --out: the directory {target.parent} does not exist"])
    t = np.asarray(columns.get("t_s", np.zeros(0)), dtype=np.float64)
    kept, dropped = _measured(columns)
    if fmt == "mf4":
        _write_mf4(target, record, t, columns, kept, dropped, run_dir)
    else:
        _write_csv(target, t, columns, kept)
    return target


def _write_mf4(path: Path, record: dict, t: np.ndarray, columns: dict[str, np.ndarray], kept: list[str],
               dropped: list[str], run_dir: Path) -> None:
    try:
        from asammdf import MDF, Signal
    except ImportError:
        raise InputError([f"{path}: --format mf4: needs asammdf: pip install 'drivebench[export]'"]) from None

    units = {s.name: (s.unit.replace("N*m", "N·m"), s.description) for s in SIGNALS}
    mdf = MDF(version="4.10")
    scenario = record.get("scenario") or {}
    drive = record.get("drive") or {}
    software = record.get("software") or {}
    lines = [f"drivebench run {scenario.get('name')}: verdict {record.get('verdict')}",
             f"scenario {scenario.get('path')} sha256 {scenario.get('sha256')}, seed {record.get('seed')}",
             f"bench {(record.get('bench') or {}).get('name')}, drive {drive.get('firmware_version')}",
             f"software {software.get('version')} {software.get('git_revision')}",
             f"started {record.get('started_utc')}, ended {record.get('ended_utc')}",
             "master channel t_s: the drive clock (s)"]
    if dropped:
        lines.append("not measured on this bench (NaN throughout, left out): " + ", ".join(dropped))
    started = _utc(record.get("started_utc"))
    if started is not None:       # the measurement's start is the run's, not the export's
        mdf.header.start_time = started
    signals = [Signal(np.asarray(columns[name], dtype=np.float64), t, name=name, unit=units[name][0],
                      comment=units[name][1], master_metadata=("t_s", 1)) for name in kept]
    if signals:
        mdf.append(signals, comment=f"drivebench {scenario.get('name')}", common_timebase=True)
    from bench.outputs.export_instruments import append_instrument_groups
    lines += append_instrument_groups(mdf, run_dir, record)     # the lab instruments' records, a group each
    mdf.header.comment = f"<HDcomment><TX>{escape(chr(10).join(lines))}</TX></HDcomment>"
    mdf.attach(json.dumps(record, indent=1, default=str).encode(), "record.json", comment="the run's record.json",
               embedded=True, mime="application/json")
    written = Path(mdf.save(path.with_name(path.stem + ".partial.mf4"), overwrite=True))  # asammdf keeps .mf4
    mdf.close()
    written.replace(path)


def _utc(text) -> "datetime | None":
    from datetime import datetime, timezone

    try:
        value = datetime.fromisoformat(str(text).replace("Z", "+00:00"))
    except ValueError:
        return None
    return value if value.tzinfo else value.replace(tzinfo=timezone.utc)


def _write_csv(path: Path, t: np.ndarray, columns: dict[str, np.ndarray], kept: list[str]) -> None:
    import pyarrow as pa
    import pyarrow.csv as pacsv

    arrays = [pa.array(t)] + [pa.array(np.asarray(columns[name], dtype=np.float64), from_pandas=True)
                              for name in kept]       # from_pandas: NaN -> null -> an empty cell
    tmp = path.with_name(path.name + ".tmp")
    pacsv.write_csv(pa.table(arrays, names=["t_s", *kept]), tmp)
    tmp.replace(path)
