"""SCPI over raw TCP (a VISA `TCPIP::host::port::SOCKET` resource) on 127.0.0.1: one thread per connection.

The served instrument is an object with `answer(command: str) -> str | bytes | None` (None: a command without an
answer). Commands end with a newline; several may share a line separated by ';' (IEEE 488.2 program message units).
Quirks a real instrument has, for the fault tests (`ScpiServer.quirks`):
    silent     reads and never answers (a hung instrument, an unplugged LAN cable)
    garbage    answers every query with bytes that are no SCPI answer
    slow_s     answers each query this much later
    drop_after closes the connection after this many queries (a LAN glitch, an instrument rebooting)
"""

from __future__ import annotations

import socket
import threading
import time
from dataclasses import dataclass
from typing import Any

LOOPBACK = "127.0.0.1"


@dataclass
class Quirks:
    silent: bool = False
    garbage: bool = False
    slow_s: float = 0.0
    drop_after: int | None = None


class ScpiServer:
    def __init__(self, instrument: Any, host: str = LOOPBACK, port: int = 0):
        self.instrument = instrument
        self.quirks = Quirks()
        self._sock = socket.create_server((host, port))
        self.host, self.port = self._sock.getsockname()[:2]
        self.resource = f"TCPIP::{self.host}::{self.port}::SOCKET"
        self._stop = threading.Event()
        self._queries = 0
        self._conns: list[socket.socket] = []
        self._thread = threading.Thread(target=self._accept, name=f"scpi-{self.port}", daemon=True)
        self._thread.start()

    def dead(self) -> str | None:
        return None if self._thread.is_alive() or self._stop.is_set() else f"SCPI server {self.resource} stopped"

    def stop(self) -> None:
        self._stop.set()
        _close(self._sock)                 # shutdown wakes the accept() blocked on it
        for conn in list(self._conns):
            _close(conn)
        self._thread.join(timeout=2.0)

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._conns.append(conn)
            threading.Thread(target=self._serve, args=(conn,), name=f"scpi-{self.port}-conn", daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        buffer = b""
        try:
            while not self._stop.is_set():
                data = conn.recv(65536)
                if not data:
                    return
                buffer += data
                while b"\n" in buffer:
                    line, buffer = buffer.split(b"\n", 1)
                    for command in line.decode("ascii", "replace").split(";"):
                        command = command.strip()
                        if command and not self._one(conn, command):
                            return
        except OSError:
            return
        finally:
            _close(conn)
            if conn in self._conns:
                self._conns.remove(conn)

    def _one(self, conn: socket.socket, command: str) -> bool:
        """Run one command; False: the connection is to be dropped."""
        answer = self.instrument.answer(command)
        if answer is None:
            return True
        self._queries += 1
        q = self.quirks
        if q.drop_after is not None and self._queries > q.drop_after:
            return False
        if q.silent:
            return True
        if q.slow_s:
            time.sleep(q.slow_s)
        if q.garbage:
            answer = "\x7fZZ?@#garbage"
        payload = answer if isinstance(answer, bytes) else answer.encode("ascii")
        conn.sendall(payload + b"\n")
        return True


def _close(conn: socket.socket) -> None:
    try:
        conn.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    try:
        conn.close()
    except OSError:
        pass
