"""Config checks every reader of a person's files shares (bench and simulator): a Problems collector that gathers
`file: field: reason` lines and raises them as one InputError, typed getters, the TOML reader with its file prefix,
and the path rule (absolute, else from the repository root, else next to the file)."""

from __future__ import annotations

import difflib
import math
from pathlib import Path
from typing import Any

from drivers.contract.errors import ContentError, InputError, one_line
from drivers.contract.toml_file import read_toml_file


class Problems:
    """Collects `file: field: reason` lines while a file is validated, then raises them all at once."""

    def __init__(self, file: str | Path):
        self.file = str(file)
        self.lines: list[str] = []

    def add(self, field: str, reason: str) -> None:
        self.lines.append(one_line(f"{self.file}: {field or '(file)'}: {reason}"))

    def extend(self, lines: list[str]) -> None:
        self.lines.extend(lines)

    def raise_if_any(self) -> None:
        if self.lines:
            raise InputError(self.lines)

    # Typed getters: report and return None when the value is missing or unusable.

    def unknown_keys(self, table: dict, allowed: set[str] | tuple[str, ...], where: str) -> None:
        for key in table:
            if key not in allowed:
                close = difflib.get_close_matches(str(key), [str(a) for a in allowed], n=1, cutoff=0.75)
                hint = f"; did you mean {close[0]!r}?" if close else ""
                self.add(_join(where, key), f"unknown key{hint} (allowed: {', '.join(sorted(allowed))})")

    def number(self, table: dict, key: str, where: str, *, required: bool = True, default: float | None = None,
               min_value: float | None = None, positive: bool = False) -> float | None:
        field = _join(where, key)
        if key not in table:
            if required:
                self.add(field, "missing (a number is required)")
            return default
        value = table[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.add(field, f"must be a number, got {_type_name(value)} {value!r}")
            return None
        value = float(value)
        if not math.isfinite(value):
            self.add(field, f"must be finite, got {value}")
            return None
        if positive and value <= 0:
            self.add(field, f"must be > 0, got {value:g}")
            return None
        if min_value is not None and value < min_value:
            self.add(field, f"must be >= {min_value:g}, got {value:g}")
            return None
        return value

    def integer(self, table: dict, key: str, where: str, *, required: bool = True, default: int | None = None,
                min_value: int | None = None, max_value: int | None = None) -> int | None:
        field = _join(where, key)
        if key not in table:
            if required:
                self.add(field, "missing (an integer is required)")
            return default
        value = table[key]
        if isinstance(value, bool) or not isinstance(value, int):
            self.add(field, f"must be an integer, got {_type_name(value)} {value!r}")
            return None
        if min_value is not None and value < min_value:
            self.add(field, f"must be >= {min_value}, got {value}")
            return None
        if max_value is not None and value > max_value:
            self.add(field, f"must be <= {max_value}, got {value}")
            return None
        return value

    def string(self, table: dict, key: str, where: str, *, required: bool = True, default: str | None = None,
               choices: tuple[str, ...] | None = None) -> str | None:
        field = _join(where, key)
        if key not in table:
            if required:
                self.add(field, "missing (a string is required)")
            return default
        value = table[key]
        if not isinstance(value, str):
            self.add(field, f"must be a string, got {_type_name(value)} {value!r}")
            return None
        if choices is not None and value not in choices:
            self.add(field, f"must be one of {', '.join(repr(c) for c in choices)}, got {value!r}")
            return None
        return value

    def boolean(self, table: dict, key: str, where: str, *, required: bool = True,
                default: bool | None = None) -> bool | None:
        field = _join(where, key)
        if key not in table:
            if required:
                self.add(field, "missing (true or false is required)")
            return default
        value = table[key]
        if not isinstance(value, bool):
            self.add(field, f"must be true or false, got {_type_name(value)} {value!r}")
            return None
        return value

    def table(self, parent: dict, key: str, where: str, *, required: bool = True) -> dict | None:
        field = _join(where, key)
        if key not in parent:
            if required:
                self.add(field, "missing table")
            return None
        value = parent[key]
        if not isinstance(value, dict):
            self.add(field, f"must be a table, got {_type_name(value)}")
            return None
        return value


def _join(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def _type_name(value: Any) -> str:
    return {bool: "boolean", int: "integer", float: "number", str: "string", list: "array",
            dict: "table"}.get(type(value), type(value).__name__)


def find_repo_root(start: str | Path | None = None) -> Path:
    """The directory holding pyproject.toml above `start` (a file or directory), else above this package, else cwd."""
    candidates: list[Path] = []
    if start is not None:
        p = Path(start).resolve()
        candidates.append(p if p.is_dir() else p.parent)
    candidates.append(Path(__file__).resolve().parent)
    for base in candidates:
        for d in (base, *base.parents):
            if (d / "pyproject.toml").is_file():
                return d
    return Path.cwd()


def read_toml(path: str | Path) -> dict[str, Any]:
    """A TOML input file parsed; InputError `file: (file): reason` when it cannot be used."""
    return read_toml_with_bytes(path)[0]


def read_toml_with_bytes(path: str | Path) -> tuple[dict[str, Any], bytes]:
    try:
        return read_toml_file(path)
    except ContentError as exc:
        raise InputError([f"{path}: (file): {exc}"]) from None


def resolve_path(value: str, root: Path, also: Path | None = None) -> Path | None:
    """An existing file for `value`: absolute, else under the repo root, else under `also`."""
    if not value.strip():
        return None
    try:
        p = Path(value).expanduser()
        if p.is_absolute():
            return p if p.is_file() else None
        for base in (root, also):
            if base is not None and (base / p).is_file():
                return (base / p).resolve()
    except (OSError, ValueError, RuntimeError):   # a name too long for the file system, no such user (~x)
        return None
    return None


def existing_path(problems: Problems, field: str, value: str, root: Path, also: Path | None = None) -> str | None:
    """The absolute path of an existing file for `value`, or None with a `field: file not found` problem."""
    found = resolve_path(value, root, also)
    if found is None:
        problems.add(field, f"file not found: {value!r} (relative paths are taken from the repo root {root})")
        return None
    return str(found)
