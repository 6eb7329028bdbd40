"""One test's result: its CiA reference, what the drive answered, what was measured, and the outcome.

Outcomes: "pass" (the drive did what the clause says), "note" (allowed by the standard but a lab must know: a mode it
lacks, a fixed mapping, a slow boot), "fail" (a finding: the drive deviates from the clause), "not_run" (the test could
not be run here; `detail` says why and which test it waits on). Only "fail" makes the suite fail.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Any

OUTCOMES = ("pass", "note", "fail", "not_run")


@dataclass
class Check:
    what: str
    expected: str
    answer: str
    ok: bool | None                     # None: observed, not judged
    time_ms: float | None = None


@dataclass
class TestResult:
    name: str
    clause: str
    title: str
    outcome: str = "pass"
    detail: str = ""
    checks: list[Check] = field(default_factory=list)
    measured: dict[str, Any] = field(default_factory=dict)
    findings: list[str] = field(default_factory=list)
    duration_s: float = 0.0
    safe_end: str = ""                  # how the test left the drive

    def check(self, what: str, expected: str, answer: str, ok: bool | None, time_ms: float | None = None) -> bool:
        self.checks.append(Check(what, expected, answer, ok, None if time_ms is None else round(time_ms, 2)))
        if ok is False:
            self.fail(f"{what}: expected {expected}, the drive answered {answer}")
        return bool(ok)

    def fail(self, finding: str) -> None:
        self.findings.append(f"{self.clause}: {finding}")
        self.outcome = "fail"

    def note(self, text: str) -> None:
        self.findings.append(f"{self.clause}: {text}")
        if self.outcome == "pass":
            self.outcome = "note"

    def not_run(self, why: str) -> None:
        self.outcome, self.detail = "not_run", why

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class Timer:
    def __enter__(self) -> "Timer":
        self.start = time.monotonic()
        return self

    def __exit__(self, *exc) -> None:
        self.ms = (time.monotonic() - self.start) * 1e3
