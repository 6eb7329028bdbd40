"""The recorder: writes one run directory as the run goes (layout and schema: bench/outputs/record_schema.py).

The recorder keeps at most one flush interval of rows in memory in the append-only journal; a background thread
flushes it on time and keeps record.json current; finish() streams the journal into Parquet and writes junit.xml.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import json
import math
import os
import re
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Iterator

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from bench.outputs.atomic_write import json_safe, write_text_atomic
from bench.inputs.criteria import VERDICTS, CriterionResult
from drivers.contract.errors import InputError
from bench.outputs.junit import write_junit
from bench.outputs.memory import RELEASING_POOL, release_freed_memory
from bench.outputs.provenance import software_identity, utc_now
from bench.outputs.record_schema import JOURNAL, JUNIT, PARQUET, RECORD, RECORD_KEYS, RunRecord
from bench.outputs.run_files import empty_schema, read_journal
from drivers.contract.signals import SIGNAL_NAMES, TIME_COLUMN

if TYPE_CHECKING:
    from bench.inputs.benchconfig import BenchConfig

RECORD_WRITE_S = 0.25        # a note reaches record.json within this (the flusher writes it, not the caller)
_ROW_GROUP_ROWS = 1 << 14    # rows per Parquet row group: ~2 MB of a full record held at once when it is written


def _run_dir_name(name: str) -> str:
    stamp = dt.datetime.now(dt.timezone.utc).strftime("%Y%m%dT%H%M%S.%fZ")[:-4] + "Z"
    safe = re.sub(r"[^A-Za-z0-9._-]+", "-", name).strip("-.") or "scenario"
    return f"{stamp}-{safe}"


class RunRecorder:
    """Writes one run directory. append() is cheap; a background thread flushes the journal on time."""

    def __init__(self, out_root: Path, scenario, seed: int, bench_cfg: BenchConfig | None,
                 flush_interval_s: float = 0.5, flush_drive_s: float = 0.25):
        out_root = Path(out_root)
        out_root.mkdir(parents=True, exist_ok=True)
        base = _run_dir_name(scenario.name)
        for n in range(1000):
            candidate = out_root / (base if n == 0 else f"{base}-{n}")
            try:
                candidate.mkdir()
                break
            except FileExistsError:
                continue
        else:
            raise RuntimeError(f"cannot create a run directory under {out_root}")
        self.run_dir: Path = candidate
        self.flush_interval_s = float(flush_interval_s)
        # flushed at least every flush_interval_s of wall time and every flush_drive_s of drive time (a simulator
        # in lockstep runs many times faster than the wall clock: a SIGKILL must not lose seconds of drive time)
        self.flush_drive_s = float(flush_drive_s)
        self._t_flushed = -math.inf
        self.record: RunRecord = {
            "verdict": "running",
            "complete": False,
            "scenario": {"path": str(scenario.path), "sha256": scenario.sha256, "name": scenario.name,
                         "duration_s": scenario.duration_s,
                         **({"requirements": list(scenario.requirements)} if getattr(scenario, "requirements", ())
                            else {})},
            "seed": seed,
            "bench": {"name": bench_cfg.bench.name if bench_cfg else None,
                      "path": bench_cfg.path if bench_cfg else None},
            "drive": {"identity": None, "firmware_version": None},
            "software": software_identity(),
            "started_utc": utc_now(),
            "ended_utc": None,
            "abort_reason": None,
            "criteria": [],
            "telemetry": {"rows": 0, "t_first_s": None, "t_last_s": None},
        }
        self.write_errors: list[str] = []
        self.lost_rows = 0
        self._lock = threading.Lock()
        self._pending: dict[str, list[np.ndarray | None]] = {}   # per column, one entry per appended block
        self._pending_sizes: list[int] = []
        self._schema: pa.Schema | None = None
        self._journal_file = None
        self._writer: pa.ipc.RecordBatchStreamWriter | None = None
        self._rows = 0
        self._last_flush = time.monotonic()
        self._stop = threading.Event()
        self._closed = False
        self._record_dirty = False
        self._record_file_lock = threading.Lock()     # one writer of record.json at a time (flusher, finish)
        self._write_record()
        self._flusher = threading.Thread(target=self._flush_loop, name=f"journal-{self.run_dir.name}", daemon=True)
        self._flusher.start()

    # --- while running ---------------------------------------------------------------------------------

    def set_drive(self, identity: dict) -> None:
        identity = json_safe(identity)
        with self._lock:
            self.record["drive"] = {"identity": identity,
                                    "firmware_version": identity.get("firmware_version")
                                    if isinstance(identity, dict) else None}
            self._write_record()

    def note(self, key: str, value) -> None:
        """Into the record now; onto the disk by the flusher within flush_interval_s / 2 (the caller is the command
        thread: an fsync there paused a drive's request stream past a 300 ms comm-loss watchdog on a loaded host)."""
        if key not in RECORD_KEYS:
            raise ValueError(f"note(): {key!r} is not a field of RunRecord (bench/outputs/record_schema.py)")
        with self._lock:
            self.record[key] = json_safe(value)
            self._record_dirty = True

    def append(self, columns: dict[str, np.ndarray]) -> None:
        """Rows: "t_s" + signal columns, equal lengths. Signals not given are NaN in the record."""
        if TIME_COLUMN not in columns:
            raise ValueError(f"append(): the {TIME_COLUMN!r} column is missing")
        block = {k: np.array(v, dtype=np.float64).reshape(-1) for k, v in columns.items()}   # a copy
        n = block[TIME_COLUMN].size
        bad = [k for k, v in block.items() if v.size != n]
        if bad:
            raise ValueError(f"append(): columns {bad} do not have {n} rows like {TIME_COLUMN!r}")
        if n == 0:
            return
        with self._lock:
            if self._closed:
                raise RuntimeError("append() after finish()")
            if self._schema is None:
                extras = sorted(k for k in block if k != TIME_COLUMN and k not in SIGNAL_NAMES)
                names = [TIME_COLUMN, *SIGNAL_NAMES, *extras]
                self._schema = pa.schema([pa.field(k, pa.float64()) for k in names])
                self._pending = {k: [] for k in names}
            elif any(k not in self._pending for k in block):
                unknown = [k for k in block if k not in self._pending]
                raise ValueError(f"append(): columns {unknown} were not in the first block")
            for name, parts in self._pending.items():
                parts.append(block.get(name))
            self._pending_sizes.append(n)
            t_last = float(block[TIME_COLUMN][-1])
            due = (time.monotonic() - self._last_flush >= self.flush_interval_s
                   or not t_last - self._t_flushed < self.flush_drive_s)
        if due:
            self.flush()

    def flush(self) -> None:
        """Write pending rows to the journal as one record batch and push it to the OS."""
        with self._lock:
            self._flush_locked()

    def read_back(self, signals: Iterable[str] | None = None, t_min: float = -math.inf,
                  t_max: float = math.inf) -> dict[str, np.ndarray]:
        """The rows appended so far with t_min <= t_s <= t_max (t_s + the given signal columns, default all), read
        back from the journal after a flush: the caller evaluates criteria without keeping its own copy of the run,
        and only the rows it needs are ever in memory. A signal never recorded comes back as NaN."""
        names = None
        parts: dict[str, list[np.ndarray]] = {}
        for chunk in self.iter_back(signals, t_min, t_max):
            names = names or list(chunk)
            for n, values in chunk.items():
                parts.setdefault(n, []).append(values)
        if names is None:
            names = list(self._flushed_schema().names) if signals is None else [TIME_COLUMN, *dict.fromkeys(signals)]
        return {n: np.concatenate(parts[n]) if n in parts else np.zeros(0) for n in names}

    def iter_back(self, signals: Iterable[str] | None = None, t_min: float = -math.inf,
                  t_max: float = math.inf) -> Iterator[dict[str, np.ndarray]]:
        """read_back() one journal batch at a time (for a summary of the whole run in bounded memory)."""
        schema = self._flushed_schema()
        names = list(schema.names) if signals is None else [TIME_COLUMN, *dict.fromkeys(signals)]
        for batch in self._journal_batches():
            t = batch.column(0).to_numpy(zero_copy_only=False)
            mask = (t >= t_min) & (t <= t_max)
            if not mask.any():
                continue
            every = bool(mask.all())
            rows = int(mask.sum())
            chunk = {}
            for n in names:
                if n not in schema.names:
                    chunk[n] = np.full(rows, np.nan)
                    continue
                values = batch.column(schema.get_field_index(n)).to_numpy(zero_copy_only=False)
                # a copy: a view would keep the whole batch (every column of the record) alive
                chunk[n] = values.copy() if every else values[mask]
            yield chunk

    def read_back_envelope(self, signals: Iterable[str], buckets: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """For a plot of the whole run in bounded memory: per time bucket the minimum and maximum of each signal
        (t repeated, values min, max interleaved), computed batch by batch from the journal."""
        schema = self._flushed_schema()
        t0, t1 = self.record["telemetry"]["t_first_s"], self.record["telemetry"]["t_last_s"]
        names = [n for n in dict.fromkeys(signals) if n in schema.names]
        if t0 is None or t1 is None:
            return np.zeros(0), {}
        span = max(t1 - t0, 1e-12)
        lo = {n: np.full(buckets, np.inf) for n in names}
        hi = {n: np.full(buckets, -np.inf) for n in names}
        for batch in self._journal_batches():
            t = batch.column(0).to_numpy(zero_copy_only=False)
            idx = np.clip(((t - t0) / span * buckets).astype(np.int64), 0, buckets - 1)
            for n in names:
                v = batch.column(schema.get_field_index(n)).to_numpy(zero_copy_only=False)
                ok = np.isfinite(v)
                np.minimum.at(lo[n], idx[ok], v[ok])
                np.maximum.at(hi[n], idx[ok], v[ok])
        edges = t0 + span * np.arange(buckets) / buckets
        t_env = np.repeat(edges, 2)
        columns = {}
        for n in names:
            y = np.empty(2 * buckets)
            y[0::2], y[1::2] = lo[n], hi[n]
            y[~np.isfinite(y)] = np.nan
            columns[n] = y
        return t_env, columns

    def _flushed_schema(self) -> pa.Schema:
        with self._lock:
            self._flush_locked()
            if self._journal_file is not None and not self.write_errors:
                try:
                    self._journal_file.flush()
                except OSError as exc:
                    self._write_failed("telemetry.arrows", exc)
            return self._schema or empty_schema()

    def _journal_batches(self):
        journal = self.run_dir / JOURNAL
        return read_journal(journal)[1] if journal.exists() else ()

    # --- at the end --------------------------------------------------------------------------------------

    def finish(self, verdict: str, criteria: list[CriterionResult], abort_reason: str | None) -> RunRecord:
        """Close the journal, write telemetry.parquet, junit.xml and the final record.json; the record as written
        (JSON-safe: what record.json holds)."""
        if verdict not in VERDICTS:
            raise ValueError(f"verdict must be one of {VERDICTS}, got {verdict!r}")
        self._stop.set()
        self._flusher.join(timeout=5)
        with self._lock:
            self._flush_locked()
            self._closed = True
            results = [c.to_dict() if hasattr(c, "to_dict") else dict(c) for c in criteria]
            self.record.update(verdict=verdict, criteria=results, abort_reason=abort_reason,
                               ended_utc=utc_now(), complete=True)
            try:
                if self._writer is not None:
                    self._writer.close()
                    self._journal_file.flush()
                    os.fsync(self._journal_file.fileno())
                    self._journal_file.close()
                if not self.write_errors:
                    self._write_parquet()
                    write_junit(self.run_dir / JUNIT, self.record)
            except OSError as exc:
                self._write_failed("telemetry", exc)
            if self.write_errors:
                self.record.update(complete=False)   # the journal keeps what was written: show recovers it
            self._write_record()
            self.raise_write_errors()
            journal = self.run_dir / JOURNAL
            if journal.exists():
                journal.unlink()
            return json.loads(json.dumps(json_safe(self.record)))

    # --- internals ---------------------------------------------------------------------------------------

    def _flush_loop(self) -> None:
        while not self._stop.wait(min(self.flush_interval_s / 2, RECORD_WRITE_S)):
            with self._lock:
                if self._pending_sizes and time.monotonic() - self._last_flush >= self.flush_interval_s / 2:
                    self._flush_locked()
                text = self._record_text() if self._record_dirty else None
                self._record_dirty = False
            if text is not None:        # written outside the lock: note() never waits for a disk
                self._write_record_text(text)

    def _flush_locked(self) -> None:
        self._last_flush = time.monotonic()
        if not self._pending_sizes:
            return
        n = sum(self._pending_sizes)
        arrays = []
        for parts in self._pending.values():
            if any(p is None for p in parts):
                parts = [np.full(size, np.nan) if p is None else p for p, size in zip(parts, self._pending_sizes)]
            arrays.append(pa.array(np.concatenate(parts) if len(parts) > 1 else parts[0], type=pa.float64()))
        batch = pa.RecordBatch.from_arrays(arrays, schema=self._schema)
        try:
            if self.write_errors:
                raise OSError("an earlier write failed")
            if self._writer is None:
                self._journal_file = open(self.run_dir / JOURNAL, "wb")
                self._writer = pa.ipc.new_stream(self._journal_file, self._schema)
            self._writer.write_batch(batch)
            self._journal_file.flush()
        except OSError as exc:                 # the disk is full: the run goes on to its safe stop, rows are lost
            self._write_failed("telemetry.arrows", exc)
            self.lost_rows += n
            for parts in self._pending.values():
                parts.clear()
            self._pending_sizes.clear()
            return
        t = arrays[0]
        self._t_flushed = float(t[n - 1].as_py())
        tel = self.record["telemetry"]
        if tel["t_first_s"] is None:
            tel["t_first_s"] = float(t[0].as_py())
        tel["t_last_s"] = float(t[n - 1].as_py())
        self._rows += n
        tel["rows"] = self._rows
        for parts in self._pending.values():
            parts.clear()
        self._pending_sizes.clear()

    def _write_parquet(self) -> None:
        journal = self.run_dir / JOURNAL
        tmp = self.run_dir / (PARQUET + ".tmp")
        schema = self._schema or empty_schema()
        # no dictionary pages (noisy floats do not repeat), 64 KiB data pages: ~7 MB of buffers instead of ~18 MB
        with pq.ParquetWriter(tmp, schema, compression="zstd", memory_pool=RELEASING_POOL, use_dictionary=False,
                              data_page_size=1 << 16) as out:
            pending: list[pa.RecordBatch] = []
            pending_rows = 0
            for batch in read_journal(journal)[1] if journal.exists() else []:
                pending.append(batch)
                pending_rows += batch.num_rows
                if pending_rows >= _ROW_GROUP_ROWS:
                    out.write_table(pa.Table.from_batches(pending, schema=schema))
                    pending, pending_rows = [], 0
            if pending or pending_rows == 0:
                out.write_table(pa.Table.from_batches(pending, schema=schema))
        os.replace(tmp, self.run_dir / PARQUET)
        release_freed_memory(collect=False)

    def _write_record(self) -> None:
        """A full disk or a vanished directory must not end a run with the drive enabled: the error is kept (the
        record in memory stays current) and reported once the run is over (finish raises it)."""
        self._record_dirty = False
        self._write_record_text(self._record_text())

    def _record_text(self) -> str:
        return json.dumps(json_safe(self.record), indent=2, allow_nan=False) + "\n"

    def _write_record_text(self, text: str) -> None:
        with self._record_file_lock:
            try:
                write_text_atomic(self.run_dir / RECORD, text)
            except OSError as exc:
                self._write_failed("record.json", exc)

    def _write_failed(self, what: str, exc: OSError) -> None:
        if not self.write_errors:
            self.write_errors.append(f"{what}: {exc.strerror or exc}")
        with contextlib.suppress(OSError):
            (self.run_dir / (RECORD + ".tmp")).unlink(missing_ok=True)

    def raise_write_errors(self) -> None:
        if self.write_errors:
            raise InputError([f"{self.run_dir}: --out: cannot write the run record ({self.write_errors[0]}); "
                              f"{self._rows} rows were journaled before that, {self.lost_rows} after it lost; the "
                              f"run's safe stop was done"])
