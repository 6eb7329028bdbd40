"""Server side of socketcand's ASCII protocol (raw mode), bridging TCP clients onto a python-can bus.

What python-can's `socketcand` interface (can/interfaces/socketcand/socketcand.py) sends and expects:
    server: "< hi >"                 client: "< open can0 >"    server: "< ok >"
    client: "< rawmode >"            server: "< ok >"
    client: "< send 601 8 40 0 10 0 0 0 0 0 >"     (id hex, dlc hex, data bytes hex without padding)
    server: "< frame 581 1700000000.123456 4B001000AABB0000 >"   (id, seconds.micros, data as one hex string)
Each client gets its own python-can `virtual` bus on the simulator's channel, so a client hears every
node and every other client but never its own frames (python-can's `virtual` semantics, like a real
socketcand bound to a CAN interface with loopback of own frames off).
"""

from __future__ import annotations

import errno
import logging
import queue
import select
import socket
import threading
import time
from typing import Any

import can

from drivers.contract.ratelog import RateLimitedLog

log = logging.getLogger(__name__)

HANDSHAKE_TIMEOUT_S = 5.0
MAX_COMMAND_BYTES = 1024   # the longest command python-can sends is ~40 bytes; more without '>' is not socketcand
MAX_QUEUED_FRAMES = 10_000 # frames waiting for a client that does not read: beyond, the client is dropped
SEND_TIMEOUT_S = 2.0       # a send to a client that stopped reading: the client is dropped, the bus goes on
ACCEPT_BACKOFF_S = (0.05, 1.0)   # out of file descriptors: wait, then accept again (a later client must get in)
FORWARD_HOLD_S = 0.05   # after "< ok >" to rawmode: python-can's client reads that reply with one recv(), so
                        # frames must not share its TCP segment


def format_frame(msg: can.Message) -> str:
    can_id = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
    return f"< frame {can_id} {msg.timestamp:.6f} {bytes(msg.data).hex().upper()} >"


def parse_send(command: str) -> can.Message:
    """'< send 601 8 40 0 10 0 0 0 0 0 >' -> Message; ValueError on anything else."""
    parts = command.strip("<> \t\r\n").split()
    if len(parts) < 3 or parts[0] != "send":
        raise ValueError(f"not a send command: {command!r}")
    can_id, dlc = int(parts[1], 16), int(parts[2], 16)
    data = bytes(int(b, 16) for b in parts[3:])
    if dlc != len(data) or dlc > 8:
        raise ValueError(f"send command with dlc {dlc} and {len(data)} data bytes: {command!r}")
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=len(parts[1]) > 3)


class _DroppingQueue(queue.Queue):
    """A client's receive queue that never blocks the bus: with MAX_QUEUED_FRAMES waiting, a frame is dropped and
    the client marked (its forwarder then drops it). python-can's own queue is unbounded: a client that never reads
    grew the server without limit."""

    def __init__(self, maxsize: int):
        super().__init__(maxsize)
        self.overflowed = False

    def put(self, item, block: bool = True, timeout: float | None = None) -> None:
        with self.mutex:
            if self._qsize() >= self.maxsize:
                self.overflowed = True
                return
            self._put(item)
            self.unfinished_tasks += 1
            self.not_empty.notify()


class _Client:
    def __init__(self, server: "SocketcandServer", conn: socket.socket, addr):
        self.server, self.conn, self.addr = server, conn, addr
        self.bus: can.BusABC | None = None
        self.closed = threading.Event()
        self.frames_in = self.frames_out = 0
        self.who = f"socketcand client {addr[0]}:{addr[1]}"
        self.session_open = False
        conn.settimeout(SEND_TIMEOUT_S)      # recv only after select; a send that blocks this long drops the client
        self.thread = threading.Thread(target=self._run, name=f"socketcand-{addr[1]}", daemon=True)
        self.thread.start()

    def _send_text(self, text: str) -> None:
        self.conn.sendall(text.encode("ascii"))

    def _too_long(self, buf: bytearray) -> bool:
        if b">" not in buf and len(buf) > MAX_COMMAND_BYTES:
            self.server.count("dropped_long_line")
            return True
        return False

    def _read_command(self, buf: bytearray, deadline: float) -> str | None:
        while b">" not in buf:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or self.closed.is_set() or self._too_long(buf):
                return None
            ready, _, _ = select.select([self.conn], [], [], min(remaining, 0.2))
            if ready:
                chunk = self.conn.recv(4096)
                if not chunk:
                    return None
                buf += chunk
        end = buf.index(b">") + 1
        start = buf.find(b"<")
        command = buf[start:end].decode("ascii", "replace") if 0 <= start < end else ""
        del buf[:end]
        return command

    def _run(self) -> None:
        buf = bytearray()
        try:
            self._send_text("< hi >")
            deadline = time.monotonic() + HANDSHAKE_TIMEOUT_S
            command = self._read_command(buf, deadline)
            if command is None:
                return
            words = command.strip("<> ").split()
            if words[:1] != ["open"] or len(words) != 2 or words[1] != self.server.can_name:
                self._send_text(f"< error could not open bus {' '.join(words[1:])} >")
                return
            self._send_text("< ok >")
            command = self._read_command(buf, deadline)
            if command is None or command.strip("<> ") != "rawmode":
                self._send_text("< error expected rawmode >")
                return
            from sim_backend.canopen.virtual_bus import FastVirtualBus
            self.bus = FastVirtualBus(channel=self.server.channel, receive_own_messages=False)
            bounded = _DroppingQueue(MAX_QUEUED_FRAMES)
            self.bus.channel[self.bus.channel.index(self.bus.queue)] = bounded
            self.bus.queue = bounded
            self._send_text("< ok >")
            forwarder = threading.Thread(target=self._forward, name=f"socketcand-fwd-{self.addr[1]}", daemon=True)
            forwarder.start()
            self._receive(buf)
        except OSError as exc:
            log.info("socketcand client %s: %s", self.addr, exc)
        finally:
            self.close()

    def _receive(self, buf: bytearray) -> None:
        while not self.closed.is_set():
            while b">" in buf:
                end = buf.index(b">") + 1
                start = buf.find(b"<")
                command = buf[start:end].decode("ascii", "replace") if 0 <= start < end else ""
                del buf[:end]
                if command.startswith("< send "):
                    if not self._admitted():
                        return
                    try:
                        self.bus.send(parse_send(command))
                        self.frames_in += 1
                    except ValueError as exc:
                        log.warning("socketcand client %s: %s", self.addr, exc)
                elif command:
                    log.info("socketcand client %s: ignored %r", self.addr, command)
            if self._too_long(buf):
                return
            ready, _, _ = select.select([self.conn], [], [], 0.2)
            if ready:
                chunk = self.conn.recv(65536)
                if not chunk:
                    return
                buf += chunk

    def _admitted(self) -> bool:
        """A served rig admits one bench at a time: a client becomes the bench with the first frame it sends (a
        listener that only receives, like candump, is never gated); a second sender is refused and closed."""
        sessions = self.server.sessions
        if sessions is None or self.session_open:
            return True
        holder = sessions.open(self.who)
        if holder is None:
            self.session_open = True
            return True
        self.server.count("refused_busy")
        self._send_text(f"< error rig busy: another bench ({holder}) is connected; one bench at a time >")
        return False

    def _forward(self) -> None:
        time.sleep(FORWARD_HOLD_S)
        try:
            while not self.closed.is_set():
                msg = self.bus.recv(0.2)
                if msg is None:
                    continue
                if self.bus.queue.overflowed:
                    self.server.count("dropped_slow_client")
                    log.warning("socketcand client %s: %d frames queued, not reading: dropped", self.addr,
                                MAX_QUEUED_FRAMES)
                    return
                lines = [format_frame(msg)]
                while len(lines) < 256:          # batch what is queued into one send
                    more = self.bus.recv(0)
                    if more is None:
                        break
                    lines.append(format_frame(more))
                self._send_text("".join(lines))
                self.frames_out += len(lines)
        except socket.timeout:
            self.server.count("dropped_slow_client")       # it stopped reading for SEND_TIMEOUT_S
            log.warning("socketcand client %s: not reading for %.1f s: dropped", self.addr, SEND_TIMEOUT_S)
        except (OSError, can.CanError) as exc:
            if not self.closed.is_set():
                log.info("socketcand client %s: %s", self.addr, exc)
        finally:
            self.close()

    def close(self) -> None:
        if self.closed.is_set():
            return
        self.closed.set()
        try:
            self.conn.close()
        except OSError:
            pass
        if self.bus is not None:
            self.bus.shutdown()
        if self.session_open:
            self.server.sessions.close(self.who)
        self.server._forget(self)


class SocketcandServer:
    """Serves one CAN bus (a python-can `virtual` channel) as `can_name` on host:port."""

    def __init__(self, channel: str, host: str = "127.0.0.1", port: int = 0, can_name: str = "can0",
                 sessions: Any = None):
        self.channel, self.can_name = channel, can_name
        self.sessions = sessions            # BenchSessions: one bench at a time (a served rig), None: a plain bus
        self.stats: dict[str, int] = {"accepted": 0, "dropped_long_line": 0, "dropped_slow_client": 0,
                                      "accept_errors": 0, "refused_busy": 0}
        self._listener = socket.create_server((host, port))
        self.host, self.port = host, self._listener.getsockname()[1]
        self.url = f"socketcand://{host}:{self.port}/{can_name}"
        self._clients: list[_Client] = []
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._accept_log = RateLimitedLog(log, "socketcand: accept failed")
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._accept_guarded, name="socketcand-accept", daemon=True)
        self._thread.start()

    def count(self, what: str) -> None:
        with self._lock:
            self.stats[what] = self.stats.get(what, 0) + 1

    def _accept_guarded(self) -> None:
        try:
            self._accept_loop()
        except BaseException as exc:        # logged once; dead() tells the supervisor
            if not self._stopping.is_set():
                self.error = exc
                log.error("socketcand: endpoint stopped: %s: %s", type(exc).__name__, exc)

    def dead(self) -> str | None:
        """Why the endpoint no longer accepts (its thread ended without stop()), or None."""
        if self._stopping.is_set() or self._thread.is_alive():
            return None
        return f"socketcand: {type(self.error).__name__}: {self.error}" if self.error else "socketcand: accept ended"

    def _accept_loop(self) -> None:
        backoff = ACCEPT_BACKOFF_S[0]
        while not self._stopping.is_set():
            ready, _, _ = select.select([self._listener], [], [], 0.2)
            if not ready or self._stopping.is_set():
                continue
            try:
                conn, addr = self._listener.accept()
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            except OSError as exc:
                if self._stopping.is_set():
                    return
                self.count("accept_errors")     # EMFILE/ENFILE: out of descriptors; a client that left at once
                self._accept_log.note(exc)
                if exc.errno in (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM):
                    self._stopping.wait(backoff)
                    backoff = min(backoff * 2, ACCEPT_BACKOFF_S[1])
                continue
            backoff = ACCEPT_BACKOFF_S[0]
            with self._lock:        # held while the client starts, so its _forget() comes after this
                self.stats["accepted"] += 1
                try:
                    self._clients.append(_Client(self, conn, addr))
                except RuntimeError as exc:     # no thread to spare for it: this client only
                    self.stats["accept_errors"] += 1
                    self._accept_log.note(exc)
                    conn.close()

    def _forget(self, client: _Client) -> None:
        with self._lock:
            if client in self._clients:
                self._clients.remove(client)

    @property
    def clients(self) -> int:
        with self._lock:
            return len(self._clients)

    def stop(self) -> None:
        self._stopping.set()
        self._thread.join(timeout=2.0)
        self._listener.close()
        with self._lock:
            clients = list(self._clients)
        for client in clients:
            client.close()
            client.thread.join(timeout=2.0)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def start_socketcand(channel: str, host: str = "127.0.0.1", port: int = 0, can_name: str = "can0",
                     sessions: Any = None) -> SocketcandServer:
    return SocketcandServer(channel, host, port, can_name, sessions)
