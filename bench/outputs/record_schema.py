"""The run record's schema and the names of the files in a run directory.

runs/<UTC time>-<scenario name>/
  record.json        written at start (verdict "running"), rewritten atomically (tmp + os.replace) on every change
  telemetry.arrows   append-only Arrow IPC stream journal, flushed at least every flush interval (wall time);
                     a SIGKILLed run keeps every batch flushed so far. Removed once telemetry.parquet is written.
  telemetry.parquet  at finish: t_s (drive clock) + one float64 column per signal, catalogue names
  junit.xml          at finish: one testcase per criterion
The recorder keeps at most one flush interval of rows in memory; finish() streams the journal into Parquet.
"""

from __future__ import annotations

from typing import Any, TypedDict


class RunRecord(TypedDict, total=False):
    """record.json: the one schema of a run's record (what finish() returns, what `show`, the service and campaigns
    read). Written at the start, kept current while the run goes on, complete at the end."""
    # always there, from the start
    verdict: str                    # "running" until the end, then one of VERDICTS
    complete: bool                  # False while running, after a crash, or when writing failed
    scenario: dict[str, Any]        # path, sha256, name, duration_s, requirements
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
    load_emulation: dict[str, Any]  # modes the bench emulated from the measured speed (bench/run/load_emulation.py)
    rerun: dict[str, Any]
    data_source: str                # "trace" (the drive's recorder) or "pdo"
    trace_signals: list[str]
    signature_draws: dict[str, Any]  # a drawn signature's points and predictions (bench/signatures/run.py)
    trace_decimation: int
    live_signals: list[str]
    measured_signals: list[str]
    unit_check: dict[str, Any]
    drive_clock_start_s: float
    injections_applied: list[dict[str, Any]]
    overrides: dict[str, Any]       # a campaign point's axes: injections at 0 s on top of the file (bench/inputs/prepared.py)
    drive_settings: dict[str, Any]  # what the link configured and read from the drive (units, comm-loss reaction)
    load_settings: dict[str, Any]
    comm_loss: dict[str, Any]       # the bench-death drill before motion (bench.run.drill): verified, drive, load
    comm_loss_unverified: str       # one line where the config states an external stop chain instead
    drive_warnings: list[dict[str, Any]]   # statusword bit 7 changes: t_s, warning, utc
    lab_instruments: dict[str, Any]  # [[instruments]]: identities, errors, analyser files, captures (instrument_session)
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
PARQUET = "telemetry.parquet"
JUNIT = "junit.xml"
