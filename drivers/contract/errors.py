"""The error types of drivebench, one small set for the bench, the drivers' clients and the simulator.

- InputError: a file or argument a person wrote cannot be used (scenario, bench config, motor config, run
  directory, command-line option). str(e) lists every problem, one `file: field: reason` line each; a command
  reports it as those lines and exit code 2, never a traceback.
- ContentError: a piece of content cannot be used (a TOML file, an EDS, a load-machine map, a velocity unit, a
  drive profile, a motor section). str(e) is the reason alone, `problems` the (field, reason) pairs where there are
  several; the caller, which knows the file and field, turns it into InputError lines or a refusal.
- LinkError: a device or its transport failed (timeout, abort, CRC error, lost heartbeat, refused drill); the
  message says which.

Subclasses exist only where code catches them specifically (bench.run.drill.DrillRefused).
"""

from __future__ import annotations


def one_line(text: str) -> str:
    """Control characters (a key with an escaped newline, a stray tab) shown escaped: one problem, one line."""
    return "".join(c if c.isprintable() or c == " " else repr(c)[1:-1] for c in text)


class InputError(Exception):
    """A scenario, bench config or run directory the bench cannot use. str(e) lists every problem, one per line."""

    def __init__(self, problems: list[str] | str):
        self.problems = [one_line(p) for p in ([problems] if isinstance(problems, str) else problems)]
        super().__init__("\n".join(self.problems))


class ContentError(ValueError):
    """Content that cannot be used; str(e) is the reason, `problems` the (field, reason) pairs behind it."""

    def __init__(self, reason: str | list[tuple[str, str]]):
        if isinstance(reason, str):
            self.problems = [("", reason)]
            super().__init__(reason)
        else:
            self.problems = list(reason)
            super().__init__("; ".join(f"{f}: {r}" if f else r for f, r in self.problems))


class LinkError(RuntimeError):
    """A protocol-level failure: timeout, abort, CRC error, lost heartbeat. The message says which."""
