"""A criterion's signal on an instrument's record: `<instrument>:<signal>` (bench.inputs.capture_criteria judges it).
Apart so that bench.inputs.criteria can tell such a name from a telemetry signal without importing the judging."""

from __future__ import annotations

import re

_CAPTURE = re.compile(r"^([a-z][a-z0-9_]*):([a-z][a-z0-9_]*)$")


def is_capture_signal(name: object) -> bool:
    return isinstance(name, str) and _CAPTURE.match(name) is not None


def split_capture_signal(name: str) -> tuple[str, str]:
    m = _CAPTURE.match(name)
    if m is None:
        raise ValueError(f"not an instrument signal: {name!r}")
    return m.group(1), m.group(2)
