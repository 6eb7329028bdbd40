"""pytest plugin: the `drivebench` fixture runs scenarios from a test and attaches the records to the report.

    def test_start_reversal(drivebench):
        result = drivebench.run("scenarios/examples/pmsm-start-reversal.toml")
        assert result.verdict == "pass"

Every run adds user properties (drivebench_run_dir, drivebench_verdict, drivebench_criteria as JSON: they
land in pytest's JUnit XML) and a report section with the criteria table. Options: --drivebench-out DIR (default runs),
--drivebench-bench CONFIG (override every scenario's bench), --drivebench-rerun MODE (default save).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest

_RESULTS = pytest.StashKey[list]()


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("drivebench", "drivebench hardware-in-the-loop bench")
    group.addoption("--drivebench-out", default="runs", metavar="DIR", help="where run directories go (default runs)")
    group.addoption("--drivebench-bench", default=None, metavar="CONFIG",
                    help="bench config for every scenario (default: the one each scenario names)")
    group.addoption("--drivebench-rerun", default="save", choices=("spawn", "connect", "save", "off"),
                    help="Rerun mode of the runs (default save: run.rrd only)")


class DriveBench:
    """What the `drivebench` fixture gives a test."""

    def __init__(self, node: pytest.Item, out_root: str, bench: str | None, rerun_mode: str):
        self.node = node
        self.out_root = out_root
        self.bench = bench
        self.rerun_mode = rerun_mode
        self.results: list[Any] = node.stash.setdefault(_RESULTS, [])

    def run(self, scenario: str | Path, *, bench: str | Path | None = None, seed: int | None = None,
            rerun_mode: str | None = None, rerun_url: str | None = None):
        """Run one scenario; returns bench.run.orchestrator.RunResult (run_dir, verdict, record, criteria)."""
        from bench.run.orchestrator import run_scenario

        result = run_scenario(scenario, bench if bench is not None else self.bench, out_root=self.out_root,
                              seed=seed, rerun_mode=rerun_mode or self.rerun_mode, rerun_url=rerun_url)
        self.results.append(result)
        self.node.user_properties.append(("drivebench_run_dir", str(result.run_dir)))
        self.node.user_properties.append(("drivebench_verdict", result.verdict))
        self.node.user_properties.append(("drivebench_criteria", json.dumps([
            {k: c.get(k) for k in ("name", "signal", "window_s", "value", "limit", "passed", "status", "known_gap")}
            for c in result.record.get("criteria", [])])))
        return result


@pytest.fixture
def drivebench(request: pytest.FixtureRequest) -> DriveBench:
    config = request.config
    return DriveBench(request.node, config.getoption("--drivebench-out"), config.getoption("--drivebench-bench"),
                      config.getoption("--drivebench-rerun"))


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return "n/a" if math.isnan(value) else f"{value:.4g}"
    return str(value)


def format_result(result) -> str:
    record = result.record
    lines = [f"run dir: {result.run_dir}", f"verdict: {result.verdict}"]
    if record.get("abort_reason"):
        lines.append(f"reason:  {record['abort_reason']}")
    rows = [("criterion", "signal", "window_s", "value", "limit", "result")]
    for c in record.get("criteria", []):
        outcome = ("pass" if c.get("passed") else "not judged" if c.get("status") == "not_judged"
                   else "known gap" if c.get("known_gap") else "FAIL")
        rows.append((str(c.get("name")), str(c.get("signal")), _fmt(c.get("window_s")), _fmt(c.get("value")),
                     _fmt(c.get("limit")), outcome))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    lines += ["  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip() for row in rows]
    return "\n".join(lines)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call):
    outcome = yield
    report = outcome.get_result()
    if report.when != "call":
        return
    for n, result in enumerate(item.stash.get(_RESULTS, []), start=1):
        name = (result.record.get("scenario") or {}).get("name") or Path(str(result.run_dir)).name
        report.sections.append((f"drivebench run {n}: {name}", format_result(result)))
