"""The verdict of a finished run: the time axis checked, the criteria evaluated on the in-test rows, the outcome
decided — error > aborted > fail > incomplete > pass — and an incomplete safe stop never leaving a pass."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from bench.inputs.capture_criteria import judge_with_records
from bench.inputs.criteria import CriterionResult, evaluate, incomplete_reason, time_axis, verdict as decide
import bench.inputs.capture_criteria  # noqa: F401  (registers the kinds judged on instruments' records)


@dataclass(frozen=True)
class Judged:
    verdict: str
    reason: str | None
    results: list[CriterionResult]
    time_axis: dict[str, Any]
    error: str | None


def judge_run(scenario, t: np.ndarray, columns: dict[str, np.ndarray], *, measured: frozenset[str] | None,
              row_period_s: float | None, tolerance: float, abort_reason: str | None, error: str | None,
              stop_errors: list[str], holes: dict | None = None, records: dict | None = None,
              instruments: tuple = ()) -> Judged:
    """`t` and `columns`: the recorded rows the criteria need (rows after duration_s, the stop, are not judged);
    `holes`: time_axis() of every in-test row (default: of `t`); `records`: the instruments' records on the drive
    clock, for criteria naming `<instrument>:<signal>` (bench.inputs.capture_criteria)."""
    in_test = t <= float(scenario.duration_s) + 1e-9
    if holes is None:
        holes = time_axis(t[in_test], row_period_s, tolerance)
    try:
        results = judge_with_records(
            scenario.criteria, lambda specs: evaluate(specs, t[in_test], {k: v[in_test] for k, v in columns.items()},
                                                      measured=measured, row_period_s=row_period_s,
                                                      tolerance=tolerance),
            records or {}, instruments)
    except Exception as exc:
        results = []
        if error is None:
            error = f"criteria evaluation failed: {type(exc).__name__}: {exc}"
    if error is not None:
        verdict, reason = "error", error
    else:
        verdict = decide(results, aborted=abort_reason is not None, holes=holes)
        reason = abort_reason or (incomplete_reason(results, holes) if verdict == "incomplete" else None)
    if stop_errors:
        reason = "; ".join(filter(None, [reason, "safe stop incomplete: " + "; ".join(stop_errors)]))
        if verdict in ("pass", "incomplete"):
            verdict = "error"
    return Judged(verdict, reason, results, holes, error)
