"""Reporters a process that runs `drivebench run` in-process may install (the service's run worker does, through
bench.service.child): progress, trips and the result of each run. None installed: a plain `drivebench run`, which
reports to nobody. The service imports this module, not the other way round."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Protocol


class Reporters(Protocol):
    def progress_reporter(self) -> Callable[[float, float], None] | None: ...

    def trip_reporter(self) -> Callable[[dict], None] | None: ...

    def result_reporter(self) -> Callable[[Path, str, dict[str, Any]], None] | None: ...


installed: Reporters | None = None


def install(reporters: Reporters | None) -> None:
    global installed
    installed = reporters
