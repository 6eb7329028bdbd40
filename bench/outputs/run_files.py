"""Reading a run directory back: record.json, telemetry.parquet, or a killed run's journal."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from bench.inputs.criteria import VERDICTS
from drivers.contract.errors import InputError
from bench.outputs.memory import RELEASING_POOL
from bench.outputs.record_schema import JOURNAL, PARQUET, RECORD
from drivers.contract.signals import SIGNAL_NAMES, TIME_COLUMN


def empty_schema() -> pa.Schema:
    return pa.schema([pa.field(k, pa.float64()) for k in (TIME_COLUMN, *SIGNAL_NAMES)])


def read_journal(path: Path):
    """(schema or None, generator of complete batches); stops quietly at a truncated or missing tail."""
    f = open(path, "rb")
    try:
        reader = pa.ipc.open_stream(f, memory_pool=RELEASING_POOL)
    except (pa.ArrowInvalid, OSError, EOFError):
        f.close()
        return None, iter(())

    def batches():
        try:
            while True:
                try:
                    yield reader.read_next_batch()
                except StopIteration:
                    return
                except (pa.ArrowInvalid, OSError, EOFError):
                    return   # the batch being written when the run was killed
        finally:
            f.close()

    return reader.schema, batches()



def _check_record_shape(path: Path, record: Any) -> None:
    """What show/evaluate rely on; anything else is a file this bench did not write."""
    if not isinstance(record, dict):
        raise InputError([f"{path}: (file): not a run record (a JSON object is expected, got {type(record).__name__})"])
    expected = {"verdict": (str, type(None)), "criteria": (list,), "scenario": (dict,), "telemetry": (dict,),
                "abort_reason": (str, type(None)), "drive": (dict,)}
    problems = [f"{path}: {key}: expected {' or '.join(t.__name__ for t in types)}, got {type(record[key]).__name__}"
                for key, types in expected.items() if key in record and not isinstance(record[key], types)]
    problems += [f"{path}: criteria[{i}]: expected an object, got {type(c).__name__}"
                 for i, c in enumerate(record.get("criteria") or []) if not isinstance(c, dict)]
    if problems:
        raise InputError(problems)


def _float_columns(path: Path, table: pa.Table) -> dict[str, np.ndarray]:
    if TIME_COLUMN not in table.column_names:
        raise InputError([f"{path}: {TIME_COLUMN}: column missing: not drivebench telemetry"])
    try:
        return {name: table.column(name).to_numpy().astype(np.float64, copy=False) for name in table.column_names}
    except (TypeError, ValueError, pa.ArrowException) as e:
        raise InputError([f"{path}: (file): not numeric telemetry: {e}"]) from None


def load_run(run_dir) -> tuple[dict, dict[str, np.ndarray], bool]:
    """(record, columns incl. t_s, complete). A killed run is recovered from its journal with complete=False."""
    run_dir = Path(run_dir)
    record_path = run_dir / RECORD
    try:
        record = json.loads(record_path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError([f"{run_dir}: {RECORD}: not found (not a run directory?)"]) from None
    except (OSError, ValueError) as e:   # ValueError: bad JSON, bad UTF-8, a number of more than 4,300 digits
        raise InputError([f"{record_path}: (file): unreadable: {' '.join(str(e).split())[:200]}"]) from None
    _check_record_shape(record_path, record)
    parquet, journal = run_dir / PARQUET, run_dir / JOURNAL
    complete = bool(record.get("complete")) and record.get("verdict") in VERDICTS
    if parquet.exists():
        try:
            table = pq.read_table(parquet)
        except (OSError, pa.ArrowException) as e:
            raise InputError([f"{parquet}: (file): not a readable Parquet file: {' '.join(str(e).split())[:200]}"]) \
                from None
        columns = _float_columns(parquet, table)
        return record, columns, complete
    if journal.exists():
        try:
            schema, batches = read_journal(journal)
            batches = list(batches)
            if schema is None:
                schema = empty_schema()
            table = pa.Table.from_batches(batches, schema=schema)
        except (OSError, pa.ArrowException) as e:
            raise InputError([f"{journal}: (file): not a readable journal: {' '.join(str(e).split())[:200]}"]) \
                from None
        return record, _float_columns(journal, table), False
    return record, {name: np.zeros(0) for name in (TIME_COLUMN, *SIGNAL_NAMES)}, False
