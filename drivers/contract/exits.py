"""How every `drivebench` command ends: exit 0 passed, 1 failed or aborted, 2 bad input or an error; bad input
reported as one line per problem on stderr without a traceback (the bench's commands and the simulator's alike)."""

from __future__ import annotations

import os
import tomllib
import traceback
from typing import Any, Callable

import click

from drivers.contract.errors import InputError, LinkError

EXIT_PASS, EXIT_FAIL, EXIT_ERROR = 0, 1, 2


def bad_input_types() -> tuple[type[BaseException], ...]:
    return (InputError, FileNotFoundError, tomllib.TOMLDecodeError, LinkError)


def problem_lines(exc: BaseException) -> list[str]:
    if isinstance(exc, InputError):
        return exc.problems or [str(exc)]
    if isinstance(exc, FileNotFoundError):
        return [f"{exc.filename}: (file): not found"]
    if isinstance(exc, tomllib.TOMLDecodeError):
        return [f"not valid TOML: {exc}"]
    if isinstance(exc, LinkError):
        return [f"cannot connect: {exc}"]
    return [f"{type(exc).__name__}: {exc}"]


def fail(exc: BaseException) -> int:
    """One line per problem on stderr; a bug (not bad input) also gets a hint how to see its traceback."""
    for line in problem_lines(exc):
        click.echo(line, err=True)
    if not isinstance(exc, bad_input_types()):
        if os.environ.get("DRIVEBENCH_DEBUG"):
            traceback.print_exc()
        else:
            click.echo("(set DRIVEBENCH_DEBUG=1 to see the traceback)", err=True)
    return EXIT_ERROR


def guarded(fn: Callable[[], int]) -> int:
    """fn()'s exit code; any exception reported as `fail` does (exit 2)."""
    try:
        return fn()
    except Exception as exc:
        return fail(exc)


def json_default(value: Any) -> Any:
    """json.dumps default for numpy values and complex numbers (everything else as its str)."""
    try:
        import numpy as np

        if isinstance(value, np.ndarray):
            return value.tolist()
        if isinstance(value, np.generic):
            return value.item()
    except ImportError:
        pass
    if isinstance(value, complex):
        return [value.real, value.imag]
    return str(value)
