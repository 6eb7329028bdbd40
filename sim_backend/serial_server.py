"""The simulated drive's serial protocol server (docs/serial-protocol.md), over TCP or a pty.

One thread per server; it serves one client at a time, like a point-to-point serial line (over TCP a second
client is answered ERROR BUSY and closed while the first holds the line). The protocol handler (SerialProtocolHandler,
sim_backend/serial_protocol.py) is transport-free so tests can feed it frames directly. sim_backend.rig puts these
servers in front of a device.
"""

from __future__ import annotations

import array
import errno
import fcntl
import logging
import os
import select
import socket
import termios
import threading
import time
import tty
from typing import Any

from drivers.contract.serial_frames import RESPONSE_FLAG, Cmd, ErrorCode, FrameDecoder, encode_frame, error_payload
from drivers.contract.ratelog import RateLimitedLog
from sim_backend.device import SimulatedDevice
from sim_backend.serial_protocol import SerialProtocolHandler

log = logging.getLogger(__name__)

WRITE_TIMEOUT_S = 5.0
MAX_REQUEST_PAYLOAD = 1024 # the largest request (PARAM_WRITE_NAME) is under 100 bytes: a longer LEN is line noise
IDLE_TIMEOUT_S = 60.0      # a client that sends nothing for this long gives the line up
MAX_REFUSING = 8           # newcomers being answered BUSY at once
REFUSE_WAIT_S = 1.0        # how long a refused newcomer has to send its first request
ACCEPT_BACKOFF_S = (0.05, 1.0)
STALE_FRAME_S = 0.2        # a partial frame with no new byte for this long is resynchronised past


class _Session:
    """Decoder + handler for one connection; counts what it threw away."""

    def __init__(self, device: SimulatedDevice, stats: dict[str, int]):
        self.decoder = FrameDecoder(MAX_REQUEST_PAYLOAD)
        self.handler = SerialProtocolHandler(device)
        self.stats = stats

    @property
    def idle_timeout(self) -> float | None:
        return STALE_FRAME_S if self.decoder.buffer else None

    def feed(self, data: bytes) -> bytes:
        """Bytes from the line; b"" means the line stayed quiet for idle_timeout."""
        before = self.decoder.crc_errors
        frames = self.decoder.feed(data) if data else self.decoder.resync()
        self.stats["crc_errors"] += self.decoder.crc_errors - before
        out = b"".join(self.handler.handle(f) for f in frames)
        self.stats["frames"] += len(frames)
        return out


def _waiting(conn: socket.socket) -> bool:
    """Bytes from the client wait unread (the server thread has not run since they came); a closed connection has
    none (FIONREAD: nothing is consumed, nothing waits)."""
    count = array.array("i", [0])
    try:
        fcntl.ioctl(conn.fileno(), termios.FIONREAD, count, True)
    except (OSError, ValueError):
        return False
    return count[0] > 0


def _left(conn: socket.socket) -> bool:
    """The client closed or reset its side (without waiting)."""
    try:
        readable, _, _ = select.select([conn], [], [], 0)
        return bool(readable) and conn.recv(1, socket.MSG_PEEK) == b""
    except OSError:
        return True


class _ServerBase:
    def __init__(self, device: SimulatedDevice):
        self.device = device
        self.stats = {"crc_errors": 0, "frames": 0, "sessions": 0}
        self._wake_r, self._wake_w = socket.socketpair()
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._run_guarded, name=type(self).__name__, daemon=True)
        self.error: BaseException | None = None

    def _run_guarded(self) -> None:
        try:
            self._run()
        except BaseException as exc:  # the thread must not die silently: logged once, and dead() says so
            if not self._stopping.is_set():
                self.error = exc
                log.error("%s: endpoint stopped: %s: %s", type(self).__name__, type(exc).__name__, exc)

    def dead(self) -> str | None:
        """Why the endpoint no longer serves (its thread ended without stop()), or None while it serves; a supervisor
        (sim serve) polls it and exits non-zero, so a dead endpoint is a dead process."""
        if self._stopping.is_set() or self._thread.is_alive() or self._thread.ident is None:
            return None
        return f"{type(self).__name__}: {type(self.error).__name__}: {self.error}" if self.error else \
            f"{type(self).__name__}: its thread ended"

    def _run(self) -> None:
        raise NotImplementedError

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stopping.set()
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass
        self._thread.join(timeout_s)
        self._close_resources()
        self._wake_r.close()
        self._wake_w.close()

    def _close_resources(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


class SerialTcpServer(_ServerBase):
    """Serial protocol over TCP (pyserial URL socket://host:port). One client holds the line; a second one gets an
    ERROR BUSY reply to its first request and is closed (a client that connected for 0.2 s used to take the line
    from a running bench). With `sessions` (a served rig) the line is also refused while a bench holds the rig over
    another front end, and an admitted client finds the drive restarted."""

    def __init__(self, device: SimulatedDevice, host: str, port: int, sessions: Any = None):
        super().__init__(device)
        self.sessions = sessions
        self.stats.update(refused_busy=0, accept_errors=0, idle_dropped=0, client_errors=0)
        self._accept_log = RateLimitedLog(log, "serial endpoint: accept failed")
        self._listener = socket.create_server((host, port))
        self.host = host
        self.port = self._listener.getsockname()[1]
        self.url = f"socket://{host}:{self.port}"
        self.serial_port = self.url          # what a serial link opens: [drive] port
        self._refusing = threading.BoundedSemaphore(MAX_REFUSING)
        self._thread.start()

    def _run(self) -> None:
        backoff = ACCEPT_BACKOFF_S[0]
        while not self._stopping.is_set():
            ready, _, _ = select.select([self._listener, self._wake_r], [], [])
            if self._wake_r in ready:
                return
            conn, addr, backoff = self._accept(backoff)
            if conn is not None:
                self._hold(conn, addr)

    def _hold(self, conn: socket.socket, addr: Any) -> None:
        """One client on the line until it leaves; whatever it does, the endpoint goes on accepting."""
        who = f"serial client {addr[0]}:{addr[1]}" if isinstance(addr, tuple) and len(addr) >= 2 else "serial client"
        try:
            holder = self.sessions.open(who) if self.sessions is not None else None
        except Exception as exc:                 # the drive's restart failed: refuse this one, keep the endpoint
            self._client_error(who, exc)
            conn.close()
            return
        if holder is not None:
            self._refuse(conn, f"the rig is held by another bench ({holder}); one bench at a time")
            return
        try:
            self._serve(conn)
        except Exception as exc:                 # a reset, a bad descriptor, a handler bug: this client only
            self._client_error(who, exc)
        finally:
            conn.close()
            if self.sessions is not None:
                self.sessions.close(who)

    def _client_error(self, who: str, exc: BaseException) -> None:
        self.stats["client_errors"] += 1
        log.warning("%s: %s: %s (dropped; the endpoint goes on)", who, type(exc).__name__, exc)

    def _accept(self, backoff: float) -> tuple[socket.socket | None, Any, float]:
        try:
            conn, addr = self._listener.accept()
            conn.settimeout(WRITE_TIMEOUT_S)
        except OSError as exc:   # EMFILE/ENFILE: out of descriptors; ECONNABORTED: the client left at once
            self.stats["accept_errors"] += 1
            self._accept_log.note(exc)
            if exc.errno in (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM):
                self._stopping.wait(backoff)
                return None, None, min(backoff * 2, ACCEPT_BACKOFF_S[1])
            return None, None, backoff
        self.stats["sessions"] += 1
        return conn, addr, ACCEPT_BACKOFF_S[0]

    def _refuse(self, conn: socket.socket, reason: str) -> None:
        """Answer the newcomer's first request with ERROR BUSY (so its link reports why), then close it; on a thread
        of its own, at most MAX_REFUSING at once (beyond that a newcomer is closed at once)."""
        self.stats["refused_busy"] += 1
        if not self._refusing.acquire(blocking=False):
            conn.close()
            return

        def answer() -> None:
            try:
                decoder = FrameDecoder(MAX_REQUEST_PAYLOAD)
                deadline = time.monotonic() + REFUSE_WAIT_S
                conn.settimeout(0.1)
                while time.monotonic() < deadline:
                    try:
                        data = conn.recv(4096)
                    except socket.timeout:
                        continue
                    if not data:
                        return
                    frames = decoder.feed(data)
                    if frames:
                        f = frames[0]
                        conn.sendall(encode_frame(f.seq, Cmd.ERROR | RESPONSE_FLAG,
                                                  error_payload(f.cmd, ErrorCode.BUSY, reason)))
                        return
            except OSError:
                pass
            finally:
                conn.close()
                self._refusing.release()

        try:
            threading.Thread(target=answer, name="serial-refuse", daemon=True).start()
        except RuntimeError:                     # no thread to spare: closed at once
            conn.close()
            self._refusing.release()

    def _serve(self, conn: socket.socket) -> None:
        """Serve one client until it leaves, stays silent for IDLE_TIMEOUT_S, or the server stops. The holder's own
        bytes and its leaving are read before a newcomer is looked at, so a bench that reconnects right after closing
        finds the line free."""
        session = _Session(self.device, self.stats)
        last_byte = time.monotonic()
        self.device.master_watchdog.arrived = lambda: _waiting(conn)
        try:
            self._serve_loop(conn, session, last_byte)
        finally:
            self.device.master_watchdog.arrived = None

    def _serve_loop(self, conn: socket.socket, session: "_Session", last_byte: float) -> None:
        with conn:
            while True:
                timeout = session.idle_timeout or IDLE_TIMEOUT_S
                ready, _, _ = select.select([conn, self._listener, self._wake_r], [], [], timeout)
                if self._wake_r in ready:
                    return None
                if self._listener in ready and conn not in ready:
                    if _left(conn):                  # the holder left as the newcomer came: the newcomer gets the line
                        return None
                    newcomer, _, _ = self._accept(ACCEPT_BACKOFF_S[0])
                    if newcomer is not None:         # a second client while the line is held: refused
                        self._refuse(newcomer, "the serial line is held by another client; one bench at a time")
                    continue
                if conn in ready:
                    try:
                        data = conn.recv(65536)
                    except OSError:
                        return None
                    if not data:
                        return None
                    last_byte = time.monotonic()
                elif time.monotonic() - last_byte >= IDLE_TIMEOUT_S:
                    self.stats["idle_dropped"] += 1  # a half-open or forgotten client must not hold the line
                    return None
                else:
                    data = b""                       # quiet inside a frame
                reply = session.feed(data)
                if reply:
                    try:
                        conn.sendall(reply)
                    except OSError:
                        return None

    def _close_resources(self) -> None:
        self._listener.close()


class SerialPtyServer(_ServerBase):
    """Serial protocol on a pseudo-terminal: clients open .path like a serial port."""

    def __init__(self, device: SimulatedDevice):
        super().__init__(device)
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)          # no echo, no line discipline: a clean 8-bit line
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)
        self.serial_port = self.path         # what a serial link opens: [drive] port
        self._thread.start()

    def _run(self) -> None:
        session = _Session(self.device, self.stats)
        self.stats["sessions"] += 1
        while True:
            ready, _, _ = select.select([self._master, self._wake_r], [], [], session.idle_timeout)
            if self._wake_r in ready:
                return
            if self._master in ready:
                try:
                    data = os.read(self._master, 65536)
                except BlockingIOError:
                    continue
            else:
                data = b""                           # quiet inside a frame
            reply = session.feed(data)
            view = memoryview(reply)
            while view:
                _, writable, _ = select.select([], [self._master], [], WRITE_TIMEOUT_S)
                if not writable:
                    session.decoder.buffer.clear()   # nobody reads the line: drop the reply
                    break
                try:
                    view = view[os.write(self._master, view):]
                except BlockingIOError:
                    continue

    def _close_resources(self) -> None:
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass


def start_serial_tcp(device: SimulatedDevice, host: str = "127.0.0.1", port: int = 0,
                     sessions: Any = None) -> SerialTcpServer:
    return SerialTcpServer(device, host, port, sessions)


def start_serial_pty(device: SimulatedDevice) -> SerialPtyServer:
    return SerialPtyServer(device)
