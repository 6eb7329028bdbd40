"""The one protocol between `drivebench serve` and its run processes (bench/service/worker.py), versioned.

Transport: JSON lines. The service writes one `RunRequest` on the run process's stdin; the run process answers on its
stdout, a pipe that carries nothing else (the worker points the run's own stdout at its stderr, which the service keeps
as the run's service.log): `Progress` while the run goes, a `Trip` as one happens, `Log` lines of its own, and last
either `Finished` (the run directory, its record.json and verdict) or `Failed` (why no run was made). Every message
carries `"v": PROTOCOL_VERSION` and its `"type"`; a message of another version, an unknown type or a missing or unknown
field is refused with a `ProtocolError` that says which. Standard library only (imported by every run process).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields
from typing import Any, Union

PROTOCOL_VERSION = 1
MAX_LINE_BYTES = 1 << 20      # one message; a longer line is refused, not buffered without bound


class ProtocolError(ValueError):
    """A message the reader cannot take: its text is the one line the run's reason shows."""


@dataclass(frozen=True)
class RunRequest:
    """service -> run process: what `drivebench run` would take on its command line, and how to behave as the
    service's child."""
    run_id: int
    scenario_file: str
    bench: str
    out_dir: str                      # the run directory is made inside it
    seed: int | None = None
    recording_id: str | None = None   # the run's Rerun recording id ("run-N")
    recording_name: str | None = None # its name as the run page shows it (the live view, bench.service.live)
    rerun_interval_s: float | None = None  # how often run.rrd is written (serve --live: often); None: the default
    nice: int = 0                     # added to the run process's CPU niceness before the run starts (API first)
    drill_proofs: tuple[dict, ...] = ()   # comm-loss drills passed in earlier runs of this service (bench.run.drill)


@dataclass(frozen=True)
class Progress:
    t_s: float                        # drive time reached [s]
    duration_s: float                 # the scenario's drive time [s]


@dataclass(frozen=True)
class Trip:
    reason: str                       # the trip's kind: overcurrent, drive_link, ...
    t_s: float | None                 # drive time of the trip [s]
    message: str


@dataclass(frozen=True)
class Log:
    line: str


@dataclass(frozen=True)
class Finished:
    """The run made a record: the service indexes it from `record_path`."""
    run_dir: str
    record_path: str
    verdict: str                      # the record's verdict: pass, fail, incomplete, aborted, error
    abort_reason: str | None = None
    drill_proofs: tuple[dict, ...] = ()   # drills this process passed, for the service's next runs


@dataclass(frozen=True)
class Failed:
    """No record was made (bad input, an error before the run directory existed, a refused request)."""
    reason: str
    exit_code: int | None = None


Message = Union[RunRequest, Progress, Trip, Log, Finished, Failed]
TYPES: dict[str, type] = {"run_request": RunRequest, "progress": Progress, "trip": Trip, "log": Log,
                          "finished": Finished, "failed": Failed}
NAMES = {cls: name for name, cls in TYPES.items()}


def encode(message: Message) -> bytes:
    """One JSON line (ends with a newline)."""
    body = {"v": PROTOCOL_VERSION, "type": NAMES[type(message)], **asdict(message)}
    return (json.dumps(body, default=str, allow_nan=False) + "\n").encode("utf-8")


def decode(line: bytes | str) -> Message:
    """The message a JSON line carries; ProtocolError (one line) for anything else."""
    if len(line) > MAX_LINE_BYTES:
        raise ProtocolError(f"run protocol: a message of {len(line)} bytes (at most {MAX_LINE_BYTES})")
    try:
        data = json.loads(line)
    except ValueError as exc:
        shown = line[:60] if isinstance(line, str) else line[:60].decode("utf-8", "replace")
        raise ProtocolError(f"run protocol: not a JSON message: {shown!r} ({exc})") from None
    if not isinstance(data, dict):
        raise ProtocolError(f"run protocol: a message must be a JSON object, got {type(data).__name__}")
    version = data.pop("v", None)
    if version != PROTOCOL_VERSION:
        raise ProtocolError(f"run protocol: version {version!r} refused: this service speaks version "
                            f"{PROTOCOL_VERSION} (run process and service from different drivebench installs?)")
    kind = data.pop("type", None)
    cls = TYPES.get(kind) if isinstance(kind, str) else None
    if cls is None:
        raise ProtocolError(f"run protocol: unknown message type {kind!r} (one of {', '.join(TYPES)})")
    known = {f.name for f in fields(cls)}
    if unknown := sorted(set(data) - known):
        raise ProtocolError(f"run protocol: {kind}: unknown field(s) {', '.join(unknown)}")
    try:
        message = cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in data.items()})
    except TypeError as exc:
        raise ProtocolError(f"run protocol: {kind}: {exc}") from None
    _check_types(kind, message)
    return message


_SCALARS: dict[str, tuple[type, ...]] = {"int": (int,), "str": (str,), "float": (int, float), "bool": (bool,)}


def _check_types(kind: str, message: Any) -> None:
    """Field types as annotated (`int | None`, `float`, `tuple[dict, ...]`): a wrong type is refused, not carried."""
    for f in fields(message):
        value = getattr(message, f.name)
        spec = str(f.type)
        if value is None and "None" in spec:
            continue
        if spec.startswith("tuple"):
            ok = isinstance(value, tuple) and all(isinstance(v, dict) for v in value)
        else:
            base = spec.split("|")[0].strip()
            allowed = _SCALARS.get(base, (object,))
            ok = isinstance(value, allowed) and not (isinstance(value, bool) and bool not in allowed)
        if not ok:
            raise ProtocolError(f"run protocol: {kind}: {f.name}: {type(value).__name__} where {spec} was expected")
