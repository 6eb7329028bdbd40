"""Typed config sections: each section of a config file is one frozen dataclass whose fields are the section's keys,
with their defaults, read and checked in one place.

    @dataclass(frozen=True)
    class SerialDriveConfig(Section):
        port: str | None = key(None, kind="string", required=True)
        baudrate: int = key(115200, kind="integer", min=1)

`Cls.read(table, problems, where, root)` checks a file's table (every problem one `file: field: reason` line, an
unknown key refused with the allowed list) and returns the instance, or None with the problems recorded;
`Cls.from_mapping(table)` builds one from a table code hands over (a link constructed in a test, a simulator
starter's plain tables), refusing unknown keys. A section also reads as a mapping of the keys it states (value not
None), so a [services] starter gets plain tables (`dict(section)`) and `section.get(key)` works where a key is
optional; None means "not stated" (a default decided elsewhere, e.g. by CommLossConfig, applies).
"""

from __future__ import annotations

import math
from dataclasses import Field, dataclass, field, fields
from pathlib import Path
from typing import Any, Callable, ClassVar, Iterator, TypeVar

from drivers.contract.checks import Problems, existing_path

KINDS = ("any", "number", "integer", "string", "boolean", "path", "table", "strings")
S = TypeVar("S", bound="Section")


def key(default: Any = None, *, kind: str = "any", required: bool = False, choices: tuple | None = None,
        min: float | None = None, max: float | None = None, positive: bool = False,
        check: Callable[[Any], str | None] | None = None) -> Any:
    """A key of a section: its default, what kind of value it takes, and its bounds. `check(value)` returns a reason
    when a value of the right kind is still unusable."""
    assert kind in KINDS, kind
    meta = {"kind": kind, "required": required, "choices": choices, "min": min, "max": max, "positive": positive,
            "check": check}
    if isinstance(default, (dict, list)):
        return field(default_factory=lambda: type(default)(default), metadata=meta)
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class Section:
    """Base of every typed section (see the module doc)."""

    SECTION: ClassVar[str] = ""          # the table's name in the file: "drive", "load", "simulator", ...

    @classmethod
    def keys_allowed(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))

    @classmethod
    def read(cls: type[S], table: dict, problems: Problems, where: str | None = None,
             root: Path | None = None, also: Path | None = None) -> S | None:
        """The section from a file's table; None (problems recorded) when a value cannot be used. Paths: absolute,
        else under `root` (the repository), else under `also` (the file's directory)."""
        where = cls.SECTION if where is None else where
        before = len(problems.lines)
        problems.unknown_keys(table, cls.keys_allowed(), where)
        values: dict[str, Any] = {}
        for f in fields(cls):
            if f.name in table:
                value = _checked(f, table[f.name], f"{where}.{f.name}" if where else f.name, problems, root, also)
                if value is not None:
                    values[f.name] = value
            elif f.metadata.get("required"):
                problems.add(f"{where}.{f.name}" if where else f.name, f"missing ({_kind_text(f)} is required)")
        if len(problems.lines) > before:
            return None
        return cls(**values)

    @classmethod
    def from_mapping(cls: type[S], table: Any) -> S:
        """An instance from a table handed over by code (not checked beyond its keys)."""
        if isinstance(table, cls):
            return table
        unknown = sorted(set(table) - set(cls.keys_allowed()))
        if unknown:
            raise ValueError(f"[{cls.SECTION}] {', '.join(unknown)}: unknown key "
                             f"(allowed: {', '.join(sorted(cls.keys_allowed()))})")
        return cls(**{k: v for k, v in table.items() if v is not None})

    # -- the mapping view: the keys this section states -----------------------------------------------------------

    def keys(self) -> list[str]:
        return [f.name for f in fields(self) if getattr(self, f.name) is not None]

    def __getitem__(self, name: str) -> Any:
        value = getattr(self, name, None) if name in self.keys_allowed() else None
        if value is None:
            raise KeyError(name)
        return value

    def get(self, name: str, default: Any = None) -> Any:
        try:
            return self[name]
        except KeyError:
            return default

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and self.get(name) is not None

    def __iter__(self) -> Iterator[str]:
        return iter(self.keys())

    def __len__(self) -> int:
        return len(self.keys())

    def items(self) -> list[tuple[str, Any]]:
        return [(k, getattr(self, k)) for k in self.keys()]

    def values(self) -> list[Any]:
        return [getattr(self, k) for k in self.keys()]


def _kind_text(f: Field) -> str:
    return {"number": "a number", "integer": "an integer", "string": "a string", "boolean": "true or false",
            "path": "a file path", "table": "a table",
            "strings": "a list of strings"}.get(f.metadata["kind"], "a value")


def _type_name(value: Any) -> str:
    return {bool: "boolean", int: "integer", float: "number", str: "string", list: "array",
            dict: "table"}.get(type(value), type(value).__name__)


def _checked(f: Field, value: Any, where: str, problems: Problems, root: Path | None,
             also: Path | None) -> Any:
    m = f.metadata
    kind = m.get("kind", "any")
    bad: str | None = None
    if kind in ("number", "integer"):
        if isinstance(value, bool) or not isinstance(value, (int, float) if kind == "number" else int):
            bad = f"must be {_kind_text(f)}, got {_type_name(value)} {value!r}"
        else:
            value = float(value) if kind == "number" else value
            if kind == "number" and not math.isfinite(value):
                bad = f"must be finite, got {value}"
            elif m["positive"] and value <= 0:
                bad = f"must be > 0, got {value:g}"
            elif m["min"] is not None and value < m["min"]:
                bad = f"must be >= {m['min']:g}, got {value:g}"
            elif m["max"] is not None and value > m["max"]:
                bad = f"must be <= {m['max']:g}, got {value:g}"
    elif kind in ("string", "path"):
        if not isinstance(value, str):
            bad = f"must be a string, got {_type_name(value)} {value!r}"
        elif kind == "path":
            found = existing_path(problems, where, value, root or Path.cwd(), also)
            if found is None:
                return None
            value = found
    elif kind == "boolean" and not isinstance(value, bool):
        bad = f"must be true or false, got {_type_name(value)} {value!r}"
    elif kind == "table" and not isinstance(value, dict):
        bad = f"must be a table, got {_type_name(value)}"
    elif kind == "strings" and (not isinstance(value, list) or not all(isinstance(v, str) for v in value)):
        bad = f"must be a list of strings, got {value!r}"
    if bad is None and m.get("choices") is not None and value not in m["choices"]:
        bad = f"must be one of {', '.join(repr(c) for c in m['choices'])}, got {value!r}"
    if bad is None and m.get("check") is not None:
        bad = m["check"](value)
    if bad is not None:
        problems.add(where, bad)
        return None
    return value
