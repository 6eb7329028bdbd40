"""Run records: one directory per run, written as the run goes.

runs/<UTC time>-<scenario name>/
  record.json        written at start (verdict "running"), rewritten atomically (tmp + os.replace) on every change
  telemetry.arrows   append-only Arrow IPC stream journal, flushed at least every flush interval (wall time);
                     a SIGKILLed run keeps every batch flushed so far. Removed once telemetry.parquet is written.
  telemetry.parquet  at finish: t_s (drive clock) + one float64 column per signal, catalogue names
  junit.xml          at finish: one testcase per criterion
The recorder keeps at most one flush interval of rows in memory; finish() streams the journal into Parquet.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import dataclasses
import datetime as dt
import gc
import json
import math
import os
import re
import subprocess
import threading
import time
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Iterator, TypedDict
from xml.etree import ElementTree as ET

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from bench.criteria import CriterionResult
from drivers.contract.errors import InputError
from drivers.contract.checks import find_repo_root
from drivers.contract.signals import SIGNAL_NAMES, TIME_COLUMN

if TYPE_CHECKING:
    from bench.benchconfig import BenchConfig

class RunRecord(TypedDict, total=False):
    """record.json: the one schema of a run's record (what finish() returns, what `show`, the service and campaigns
    read). Written at the start, kept current while the run goes on, complete at the end."""
    # always there, from the start
    verdict: str                    # "running" until the end, then one of VERDICTS
    complete: bool                  # False while running, after a crash, or when writing failed
    scenario: dict[str, Any]        # path, sha256, name, duration_s
    seed: int
    bench: dict[str, Any]           # name, path, timing
    drive: dict[str, Any]           # identity (as the drive reported it), firmware_version
    software: dict[str, Any]        # drivebench version, revision, Python and library versions
    started_utc: str
    ended_utc: str | None
    abort_reason: str | None
    criteria: list[dict[str, Any]]  # CriterionResult.to_dict() per criterion
    telemetry: dict[str, Any]       # rows, t_first_s, t_last_s
    # noted by the orchestrator while the run goes on
    load_machine: str
    reference: dict[str, Any]
    instruments: dict[str, str]     # rig-truth signal -> the instrument it came from (or "not measured")
    load_emulation: dict[str, Any]  # modes the bench emulated from the measured speed (bench/load_emulation.py)
    rerun: dict[str, Any]
    data_source: str                # "trace" (the drive's recorder) or "pdo"
    trace_signals: list[str]
    trace_decimation: int
    live_signals: list[str]
    measured_signals: list[str]
    unit_check: dict[str, Any]
    drive_clock_start_s: float
    injections_applied: list[dict[str, Any]]
    drive_settings: dict[str, Any]  # what the link configured and read from the drive (units, comm-loss reaction)
    load_settings: dict[str, Any]
    comm_loss: dict[str, Any]       # the bench-death drill before motion (bench.drill): verified, drive, load
    comm_loss_unverified: str       # one line where the config states an external stop chain instead
    drive_warnings: list[dict[str, Any]]   # statusword bit 7 changes: t_s, warning, utc
    sync: dict[str, Any]            # SYNC intervals at the bench (p50/p99/max ms, late, skipped), time base, placement
    # at the end
    trips: list[dict[str, Any]]
    supervisor_trip: dict[str, Any]
    safe_stop: dict[str, Any]       # steps, errors
    time_axis: dict[str, Any]       # criteria.time_axis(): rows, gaps, missing_rows, duplicates
    signals_ignored_while_stopping: list[str]
    status_after_trip_error: str
    final_fetch_error: str
    live_tail: dict[str, Any]
    summary_png_error: str
    traceback: str


RECORD_KEYS = frozenset(RunRecord.__annotations__)

RECORD = "record.json"
JOURNAL = "telemetry.arrows"
RECORD_WRITE_S = 0.25        # a note reaches record.json within this (the flusher writes it, not the caller)
PARQUET = "telemetry.parquet"
JUNIT = "junit.xml"
from bench.criteria import VERDICTS  # noqa: E402  (pass fail incomplete aborted error)
_ROW_GROUP_ROWS = 1 << 14    # rows per Parquet row group: ~2 MB of a full record held at once when it is written
# reading the journal back and writing telemetry.parquet at the end of a run: the system allocator hands the buffers
# back to the OS (Arrow's default pool keeps them: +25-40 MB after every long run)
_END_POOL = pa.system_memory_pool()


def utc_now() -> str:
    return dt.datetime.now(dt.timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def software_identity() -> dict[str, Any]:
    try:
        version = metadata.version("drivebench")
    except metadata.PackageNotFoundError:
        version = None
    root = find_repo_root()
    revision, dirty = None, None
    try:
        revision = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True,
                                  timeout=5).stdout.strip() or None
        if revision:
            status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                                    capture_output=True, text=True, timeout=10)
            dirty = bool(status.stdout.strip()) if status.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        pass
    return {"version": version, "git_revision": revision, "git_dirty": dirty}


def json_safe(value: Any) -> Any:
    """Plain JSON: numpy scalars/arrays to Python, dataclasses to dicts, NaN/inf to null."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = dataclasses.asdict(value)
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return [json_safe(v) for v in value.tolist()]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return str(value)


def write_json_atomic(path: Path, data: dict) -> None:
    write_text_atomic(path, json.dumps(json_safe(data), indent=2, allow_nan=False) + "\n")


def write_text_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


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
                         "duration_s": scenario.duration_s},
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
            raise ValueError(f"note(): {key!r} is not a field of RunRecord (bench/records.py)")
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
            return self._schema or _empty_schema()

    def _journal_batches(self):
        journal = self.run_dir / JOURNAL
        return _read_journal(journal)[1] if journal.exists() else ()

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
        schema = self._schema or _empty_schema()
        # no dictionary pages (noisy floats do not repeat), 64 KiB data pages: ~7 MB of buffers instead of ~18 MB
        with pq.ParquetWriter(tmp, schema, compression="zstd", memory_pool=_END_POOL, use_dictionary=False,
                              data_page_size=1 << 16) as out:
            pending: list[pa.RecordBatch] = []
            pending_rows = 0
            for batch in _read_journal(journal)[1] if journal.exists() else []:
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


_RUNS_STARTED = 0


def freeze_long_lived() -> None:
    """At the start of a process's second run: what is alive then (imports and JIT, paid by the first run; a test
    session's objects) is collected and moved out of the cyclic garbage collector's generations (gc.freeze), so
    the full collection after each later run's plot walks only what that run created. Once only: freezing before
    every run would keep each earlier run's cyclic garbage for good (+5 MB a run, measured). A process with one
    run (drivebench run) never pays it."""
    global _RUNS_STARTED
    _RUNS_STARTED += 1
    if _RUNS_STARTED == 2:
        gc.collect()
        gc.freeze()


def release_freed_memory(collect: bool = True) -> None:
    """After the end-of-run steps (the plot, Parquet): freed buffers go back to the OS instead of staying in the
    allocators' free lists, so a process that runs many runs (a campaign worker, a long session) stays flat.
    collect: first a full garbage collection (~25 ms; a matplotlib figure is a web of cycles)."""
    if collect:
        gc.collect()
    pa.default_memory_pool().release_unused()
    if _LIBC is not None:
        _LIBC.malloc_trim(0)


def _load_libc():
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return libc if hasattr(libc, "malloc_trim") else None      # glibc only
    except OSError:
        return None


_LIBC = _load_libc()


def _empty_schema() -> pa.Schema:
    return pa.schema([pa.field(k, pa.float64()) for k in (TIME_COLUMN, *SIGNAL_NAMES)])


def _read_journal(path: Path):
    """(schema or None, generator of complete batches); stops quietly at a truncated or missing tail."""
    f = open(path, "rb")
    try:
        reader = pa.ipc.open_stream(f, memory_pool=_END_POOL)
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


def write_junit(path: Path, record: dict) -> None:
    """One testcase per criterion (time: the drive seconds of its window, the part of the run it judges), a "run"
    testcase for an aborted, failed-to-run or incomplete run; the suite's time is the run's wall time, its
    properties say what ran on what (seed, scenario hash, bench, drive, firmware, software revision)."""
    scenario = record.get("scenario", {}).get("name") or "scenario"
    criteria = record.get("criteria", [])
    suite = ET.Element("testsuite", name=scenario)
    properties = ET.SubElement(suite, "properties")
    for name, value in _junit_properties(record):
        ET.SubElement(properties, "property", name=name, value=value)
    failures = skipped = errors = 0
    for c in criteria:
        window = c["window_s"]
        case = ET.SubElement(suite, "testcase", classname=f"drivebench.{scenario}", name=str(c["name"]),
                             time=f"{max(0.0, float(window[1]) - float(window[0])):.6g}")
        unit = f" {c['unit']}" if c.get("unit") else ""
        case_props = ET.SubElement(case, "properties")
        for name, value in (("kind", c["kind"]), ("signal", c["signal"]), ("unit", c.get("unit") or ""),
                            ("value", _fmt(c["value"])), ("limit", _fmt(c["limit"])),
                            ("status", c.get("status") or "")):
            ET.SubElement(case_props, "property", name=name, value=str(value))
        text = (f"{c['kind']} of {c['signal']} in [{window[0]:g}, {window[1]:g}] s: "
                f"value {_fmt(c['value'])}{unit}, limit {_fmt(c['limit'])}{unit}")
        if c.get("status") == "not_judged":
            skipped += 1
            ET.SubElement(case, "skipped", message=f"not judged: {c.get('detail', '')}").text = text
        elif not c["passed"] and c.get("known_gap"):
            skipped += 1
            ET.SubElement(case, "skipped", message=f"known gap: {c['known_gap']}").text = f"{text}; {c['detail']}"
        elif not c["passed"]:
            failures += 1
            ET.SubElement(case, "failure", message=text).text = c.get("detail", "")
        else:
            ET.SubElement(case, "system-out").text = f"{text}; {c.get('detail', '')}"
    if record.get("verdict") in ("aborted", "error"):
        errors += 1
        case = ET.SubElement(suite, "testcase", classname=f"drivebench.{scenario}", name="run")
        ET.SubElement(case, "error", message=f"run {record['verdict']}: {record.get('abort_reason') or 'no reason given'}")
    elif record.get("verdict") == "incomplete":      # a run that could not judge everything is not a pass in CI
        failures += 1
        case = ET.SubElement(suite, "testcase", classname=f"drivebench.{scenario}", name="run")
        unjudged = [c["name"] for c in criteria if c.get("status") == "not_judged"]
        ET.SubElement(case, "failure", message=f"run incomplete: {len(unjudged)} criteria not judged").text = \
            "; ".join(unjudged)
    wall = _wall_s(record)
    if wall is not None:
        suite.set("time", f"{wall:.3f}")
    suite.set("tests", str(len(criteria) + errors))
    suite.set("failures", str(failures))
    suite.set("errors", str(errors))
    suite.set("skipped", str(skipped))
    suite.set("timestamp", str(record.get("started_utc") or ""))
    root = ET.Element("testsuites")
    root.append(suite)
    ET.indent(root)
    tmp = path.with_name(path.name + ".tmp")
    ET.ElementTree(root).write(tmp, encoding="utf-8", xml_declaration=True)
    os.replace(tmp, path)


def _junit_properties(record: dict) -> list[tuple[str, str]]:
    scenario = record.get("scenario") or {}
    drive = record.get("drive") or {}
    identity = drive.get("identity") or {}
    software = record.get("software") or {}
    bench = record.get("bench") or {}
    pairs = [("verdict", record.get("verdict")), ("seed", record.get("seed")),
             ("scenario.path", scenario.get("path")), ("scenario.sha256", scenario.get("sha256")),
             ("bench.name", bench.get("name")), ("drive.device_name", identity.get("device_name")),
             ("drive.firmware_version", drive.get("firmware_version")),
             ("software.version", software.get("version")), ("software.git_revision", software.get("git_revision")),
             ("started_utc", record.get("started_utc")), ("ended_utc", record.get("ended_utc"))]
    return [(k, str(v)) for k, v in pairs if v is not None and v != ""]


def _wall_s(record: dict) -> float | None:
    import datetime as dt

    try:
        start, end = (dt.datetime.fromisoformat(str(record[k]).replace("Z", "+00:00"))
                      for k in ("started_utc", "ended_utc"))
    except (KeyError, TypeError, ValueError):
        return None
    return max(0.0, (end - start).total_seconds())


def _fmt(v) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "n/a"
    return f"{v:.6g}"


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
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError([f"{record_path}: (file): unreadable: {e}"]) from None
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
            schema, batches = _read_journal(journal)
            batches = list(batches)
            if schema is None:
                schema = _empty_schema()
            table = pa.Table.from_batches(batches, schema=schema)
        except (OSError, pa.ArrowException) as e:
            raise InputError([f"{journal}: (file): not a readable journal: {' '.join(str(e).split())[:200]}"]) \
                from None
        return record, _float_columns(journal, table), False
    return record, {name: np.zeros(0) for name in (TIME_COLUMN, *SIGNAL_NAMES)}, False
