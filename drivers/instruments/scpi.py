"""One SCPI session over pyvisa (pyvisa-py backend: no vendor VISA to install).

Every query has the instrument's timeout; a silent instrument, a dropped connection or an answer that does not parse
raises InstrumentError with one line naming the instrument, the command and what happened.
"""

from __future__ import annotations

import threading
from typing import Sequence

import numpy as np

ERROR_QUERY_LIMIT = 32          # an error queue never drains beyond this: the instrument is babbling


class InstrumentError(RuntimeError):
    """An instrument did not answer, answered garbage, or reported an error: one line for people."""


class ScpiSession:
    def __init__(self, name: str, resource: str, timeout_s: float, error_query: str = ":SYSTem:ERRor?"):
        import pyvisa

        self.name = name
        self.resource = resource
        self.timeout_s = timeout_s
        self.error_query = error_query
        self._lock = threading.Lock()
        self._errors = (pyvisa.errors.VisaIOError, pyvisa.errors.InvalidSession, OSError, EOFError, ValueError)
        try:
            self._rm = pyvisa.ResourceManager("@py")
            self._inst = self._rm.open_resource(resource, open_timeout=int(timeout_s * 1000))
        except Exception as exc:          # pyvisa raises several types here (VisaIOError, OSError, ValueError)
            raise InstrumentError(f"instrument {name!r} at {resource}: cannot connect: {_why(exc)}") from None
        self._inst.timeout = int(timeout_s * 1000)
        self._inst.read_termination = "\n"
        self._inst.write_termination = "\n"

    def _fail(self, command: str, exc: BaseException) -> InstrumentError:
        return InstrumentError(f"instrument {self.name!r} at {self.resource}: {command!r}: {_why(exc, self.timeout_s)}")

    def write(self, command: str) -> None:
        with self._lock:
            try:
                self._inst.write(command)
            except self._errors as exc:
                raise self._fail(command, exc) from None

    def query(self, command: str) -> str:
        with self._lock:
            try:
                return self._inst.query(command).strip()
            except self._errors as exc:
                raise self._fail(command, exc) from None

    def query_floats(self, command: str, count: int | None = None) -> list[float]:
        answer = self.query(command)
        try:
            values = [float(v) for v in answer.split(",")]
        except ValueError:
            raise InstrumentError(f"instrument {self.name!r}: {command!r} answered garbage: {answer[:60]!r}") from None
        if count is not None and len(values) != count:
            raise InstrumentError(f"instrument {self.name!r}: {command!r} answered {len(values)} values, "
                                  f"{count} expected: {answer[:60]!r}")
        return values

    def query_block(self, command: str, datatype: str = "h") -> np.ndarray:
        """An IEEE 488.2 definite-length binary block (#<n><length><bytes>), little-endian values."""
        with self._lock:
            try:
                return self._inst.query_binary_values(command, datatype=datatype, is_big_endian=False,
                                                      container=np.array, expect_termination=True)
            except self._errors as exc:
                raise self._fail(command, exc) from None

    def errors(self) -> list[str]:
        """Drain the error queue; the errors it held ('0,"No error"' ends it)."""
        found = []
        for _ in range(ERROR_QUERY_LIMIT):
            answer = self.query(self.error_query)
            code = answer.split(",", 1)[0].strip()
            try:
                if int(code) == 0:
                    return found
            except ValueError:
                raise InstrumentError(f"instrument {self.name!r}: {self.error_query!r} answered garbage: "
                                      f"{answer[:60]!r}") from None
            found.append(answer)
        raise InstrumentError(f"instrument {self.name!r}: its error queue does not empty "
                              f"({ERROR_QUERY_LIMIT} errors read, last {found[-1]!r})")

    def check_errors(self, after: str) -> None:
        found = self.errors()
        if found:
            raise InstrumentError(f"instrument {self.name!r}: error after {after}: {'; '.join(found)}")

    def configure(self, commands: Sequence[str]) -> None:
        for command in commands:
            self.write(command)
        self.query("*OPC?")
        self.check_errors("configuration")

    def close(self) -> None:
        with self._lock:
            for closing in (self._inst.close, self._rm.close):
                try:
                    closing()
                except Exception:
                    pass


def _why(exc: BaseException, timeout_s: float | None = None) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    if "VI_ERROR_TMO" in text or "Timeout" in text:
        return f"no answer within {timeout_s:g} s" if timeout_s else "no answer (timeout)"
    return text[:160]
