"""One reader for every TOML input (scenarios, bench configs, load-machine maps, motor and serve configs).

Only a regular file of bounded size is opened (a FIFO, a device such as /dev/zero or a directory would block or
exhaust memory); it must be UTF-8 TOML nested at most MAX_DEPTH deep. ContentError carries the reason alone; each
caller prefixes the file (and field "(file)"), so every problem stays one `file: field: reason` line.

The parsed table of a small document is kept, keyed by its bytes: the same bytes parse to the same table, so a
service validating each submission against its rigs' bench configs (a dozen files a submission) pays tomllib once per
content, and an edited file is parsed again whatever its timestamps say. Each caller gets a copy of its own."""

from __future__ import annotations

import os
import stat
import threading
import tomllib
from pathlib import Path
from typing import Any, Sequence

from drivers.contract.errors import ContentError

MAX_TOML_BYTES = 1 << 20      # 1 MiB: a scenario or config is a few kB
MAX_DEPTH = 32
PARSED_KEPT = 64              # documents whose parsed table is kept, keyed by their bytes (a service's submissions)
PARSED_KEPT_MAX_BYTES = 64 << 10
_parsed: dict[bytes, dict[str, Any]] = {}
_parsed_lock = threading.Lock()


def read_toml_file(path: str | Path, max_bytes: int = MAX_TOML_BYTES) -> tuple[dict[str, Any], bytes]:
    """(parsed table, the file's bytes) or ContentError."""
    path = Path(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise ContentError("not found") from None
    except OSError as exc:
        raise ContentError(f"cannot read: {exc.strerror or exc}") from None
    if stat.S_ISDIR(st.st_mode):
        raise ContentError("is a directory, not a TOML file")
    if not stat.S_ISREG(st.st_mode):
        raise ContentError("not a regular file (a pipe, socket or device cannot be a TOML file)")
    if st.st_size > max_bytes:
        raise ContentError(f"{st.st_size} bytes, larger than {max_bytes} bytes: not a config file")
    try:
        with open(path, "rb") as f:
            data = f.read(max_bytes + 1)
    except OSError as exc:
        raise ContentError(f"cannot read: {exc.strerror or exc}") from None
    return parse_toml_bytes(data, max_bytes), data


def parse_toml_bytes(data: bytes, max_bytes: int = MAX_TOML_BYTES) -> dict[str, Any]:
    """The parsed table of a TOML document already in memory (an uploaded scenario), checked like a file's."""
    if len(data) > max_bytes:
        raise ContentError(f"larger than {max_bytes} bytes: not a config file")
    kept = _parsed.get(data) if isinstance(data, bytes) else None
    if kept is not None:
        return _copy(kept)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise ContentError("not valid TOML: not UTF-8 text") from None
    if "\0" in text:
        raise ContentError("not valid TOML: binary data")
    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ContentError(f"not valid TOML: {' '.join(str(exc).split())}") from None
    except RecursionError:
        raise ContentError(f"not valid TOML: nested deeper than this reader allows ({MAX_DEPTH} levels)") from None
    if _depth(table) > MAX_DEPTH:
        raise ContentError(f"nested deeper than {MAX_DEPTH} levels: not a config file")
    if isinstance(data, bytes) and len(data) <= PARSED_KEPT_MAX_BYTES:
        kept = _copy(table)
        with _parsed_lock:
            while len(_parsed) >= PARSED_KEPT:
                del _parsed[next(iter(_parsed))]
            _parsed[data] = kept
    return table


def _copy(value: Any) -> Any:
    """A parsed TOML table's own copy: its tables and arrays new, its values (str, numbers, dates) immutable."""
    if isinstance(value, dict):
        return {k: _copy(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_copy(v) for v in value]
    return value


def known_entries(table: dict, known: Sequence[str], prefix: str, kind: str, problems: list[tuple[str, str]]):
    """(key, value, where) for each entry of a config table whose key is known; an unknown key is a problem
    `(prefix.key, "unknown KIND (known: ...)")` and is skipped."""
    for key, value in table.items():
        where = f"{prefix}.{key}"
        if key not in known:
            problems.append((where, f"unknown {kind} (known: {', '.join(known)})"))
            continue
        yield key, value, where


def _depth(value: Any, level: int = 0) -> int:
    if level > MAX_DEPTH:
        return level
    if isinstance(value, dict):
        return max((_depth(v, level + 1) for v in value.values()), default=level + 1)
    if isinstance(value, list):
        return max((_depth(v, level + 1) for v in value), default=level + 1)
    return level
