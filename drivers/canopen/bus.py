"""The CAN bus under the link: python-can arguments from a [drive] table, bus-load arithmetic, bus health."""

from __future__ import annotations

import collections
import logging
import queue
import re
import socket
import threading
import time
from typing import Any, Callable

import can
from can.interfaces.virtual import VirtualBus

log = logging.getLogger(__name__)

ERROR_PASSIVE_LEVEL = 128    # CAN receive error counter at which a controller goes error passive (ISO 11898-1)

# [drive] keys the link itself reads; every other key passes through to python-can's Bus(...)
LINK_KEYS = frozenset({"transport", "sync_period_s", "heartbeat_timeout_s", "trace_decimation", "trace_signals",
                       "node_id", "eds", "sdo_timeout_s", "interface", "channel", "bitrate", "can", "profile",
                       "velocity_unit", "encoder_increments_per_rev", "gear_ratio", "rated_torque_nm",
                       "rated_current_a", "signals", "pdo", "comm_loss", "consumer_time_ms", "abort_option",
                       "error_behaviour", "bench_node_id", "standstill_mech_rad_s", "stop_timeout_s",
                       "boot_timeout_s", "velocity_mode"})


def frame_bits(n_data_bytes: int) -> int:
    """Bits of a CAN 2.0A data frame on the wire, with worst-case bit stuffing (ISO 11898-1)."""
    unstuffed = 47 + 8 * n_data_bytes
    return unstuffed + (34 + 8 * n_data_bytes - 1) // 4


def bus_kwargs(section: dict) -> dict[str, Any]:
    """python-can Bus(...) arguments from a [drive] table.

    python-can's own options (fd, data_bitrate, app_name, serial, host, port, ...) pass through from the [drive.can]
    table, verbatim; the channel may be a name or a number, as the interface wants it. For socketcand the endpoint
    may also be written in the channel as `can0@127.0.0.1:29536`. A socketcand connection is tuned for latency
    (`tcp_tune = true`) unless [drive.can] says `tcp_tune = false`.
    """
    kwargs: dict[str, Any] = {"interface": section["interface"], "channel": section["channel"]}
    if section.get("bitrate"):
        kwargs["bitrate"] = section["bitrate"]
    kwargs.update({k: v for k, v in section.items() if k not in LINK_KEYS})
    kwargs.update(section.get("can") or {})
    channel = str(kwargs["channel"])
    if kwargs["interface"] == "socketcand" and "@" in channel and "host" not in kwargs:
        name, _, endpoint = channel.partition("@")
        host, _, port = endpoint.rpartition(":")
        kwargs.update(channel=name, host=host, port=int(port))
    if kwargs["interface"] == "virtual":
        kwargs.setdefault("receive_own_messages", False)
    if kwargs["interface"] == "socketcand":
        # python-can's client leaves Nagle on unless told: SYNCs and commands then leave in bursts of up to 40 ms.
        # tcp_tune = TCP_NODELAY (+ TCP_QUICKACK); python-can drops it on Windows with a warning.
        kwargs.setdefault("tcp_tune", True)
    return kwargs


CONNECT_TIMEOUT_S = 5.0   # opening a CAN interface (a socketcand TCP connection and its handshake) at most this long


def socketcand_greeting(host: str, port: int, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """A socketcand server greets with `< hi >` at once. python-can's client waits for it without a timeout: a port
    that accepts and never speaks (a typo pointing at the Modbus port, a hung server) would hang the bench. OSError
    (TimeoutError) with the reason when the greeting does not come."""
    with socket.create_connection((host, port), timeout=timeout_s) as sock:
        deadline = time.monotonic() + timeout_s
        got = b""
        while b">" not in got:
            sock.settimeout(max(0.01, deadline - time.monotonic()))
            try:
                chunk = sock.recv(64)
            except socket.timeout:
                raise TimeoutError(f"no socketcand greeting from {host}:{port} within {timeout_s:g} s "
                                   f"(is it a socketcand server?)") from None
            if not chunk:
                if got:
                    break
                raise ConnectionError(f"{host}:{port} closed the connection before greeting (not socketcand?)")
            got += chunk
            if len(got) > 64 or time.monotonic() > deadline:
                break
        if not got.startswith(b"< hi >"):
            raise ConnectionError(f"{host}:{port} is not a socketcand server (it said {got[:32]!r})")


class SocketcandRefusal:
    """Reads a socketcand server's `< error ... >` (a served rig refusing a second bench) as a refusal, not a frame.

    python-can's client parses every `< error ... >` as an error frame whose first word is a hex CAN id; the refusal's
    words are not, so its receive thread logged a traceback and died with another (54 lines). Wrapped around the
    bus's receive: the refusal text is kept in `.reason`, the bus goes quiet, and the link's first request fails with
    one line naming it."""

    PATTERN = re.compile(r"< error ([^<>]*)>")

    WAIT_S = 1.0      # a request that timed out: how long a refusal may still be on its way (a loaded server)

    def __init__(self, bus: can.BusABC):
        self.reason: str | None = None
        self.refused = threading.Event()
        self._bus = bus
        self._recv = bus._recv_internal
        bus._recv_internal = self._recv_internal
        # python-can's client warns on every TCP read that ends mid-message (normal at load) and logs a traceback for
        # what it cannot parse; the link reports what matters in one line
        logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.CRITICAL)

    def _pending_text(self) -> str:
        for name, value in vars(self._bus).items():      # python-can keeps the unparsed text in a private buffer
            if name.endswith("__receive_buffer") and isinstance(value, str):
                return value
        return ""

    def _recv_internal(self, timeout: float | None):
        if self.reason is not None:
            time.sleep(min(timeout or 0.0, 0.05))
            return None, False
        try:
            return self._recv(timeout)
        except can.CanError:
            found = self.PATTERN.search(self._pending_text())
            if found is None:
                raise
            self.reason = found.group(1).strip()
            self.refused.set()
            log.info("socketcand server refused this bench: %s", self.reason)
            return None, False


class BurstQueue(queue.Queue):
    """A QuickVirtualBus's receive queue: can.Message items, and bursts a sender hands over as one item
    (`put_burst`: standard-ID data frames (cob, payload), in order, sent at one instant) — the simulator's TPDOs of
    a SYNC, a block upload's sub-block — without a Message per frame; the receiving end takes them apart.

    What the thread `handled_by` puts does not wake the receive thread: that thread handles it itself once its send
    returns (HandlingNetwork); the receive thread takes what is left on its next poll."""

    handled_by: int | None = None

    def put(self, item: Any, block: bool = True, timeout: float | None = None) -> None:
        if self.handled_by != threading.get_ident():
            super().put(item, block, timeout)
            return
        with self.mutex:
            self.queue.append(item)
            self.unfinished_tasks += 1

    def put_burst(self, timestamp: float, frames: list[tuple[int, bytes]]) -> None:
        with self.mutex:
            self.queue.append((timestamp, frames))
            self.unfinished_tasks += 1
            if self.handled_by != threading.get_ident():
                self.not_empty.notify()


def burst_messages(burst: tuple[float, list[tuple[int, bytes]]], channel: Any) -> list[can.Message]:
    timestamp, frames = burst
    return [can.Message(timestamp=timestamp, arbitration_id=cob, is_extended_id=False, channel=channel,
                        dlc=len(payload), data=bytearray(payload), is_rx=True, check=False)
            for cob, payload in frames]


class QuickVirtualBus(VirtualBus):
    """python-can's `virtual` interface, same channels and delivery, cheaper per frame at the link's end: a frame
    already queued is taken without the queue's lock and the receive log call (python-can logs every frame at level
    9), and a sent frame is copied field by field for each receiver instead of by deepcopy. Measured on the receive
    thread: ~30 % less CPU per frame of a block upload, the bulk of a lockstep run's frames.

    `inline_delivery` (lockstep links): a receiver on the channel that offers it (`put_inline`, an in-process node
    that handles a frame at once when idle) gets the frame handled in the sending thread, before send returns;
    the same frames in the same order, without a thread hand-off per request."""

    inline_delivery = False

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        if not self.queue.maxsize:
            burst_queue = BurstQueue()
            self.channel[self.channel.index(self.queue)] = burst_queue
            self.queue = burst_queue
        self._taken: collections.deque[can.Message] = collections.deque()   # a burst's frames not yet returned
        # held while a received frame is handled: by the receive thread from taking a frame until it comes for the
        # next, or by a sender handling what has arrived (handle_arrived); frames are handled one at a time, in order
        self._handling = threading.Lock()
        self._rx_holds = False

    def _plain_queue(self) -> bool:
        # one reader pops; writers append under the queue's lock (a deque's popleft and append are atomic); a bounded
        # queue (rx_queue_size) needs get() to wake a writer waiting for room; a receive wrapped for a purpose
        # (SocketcandRefusal) goes through it
        return self._filters is None and not self.queue.maxsize and self._open and "_recv_internal" not in vars(self)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        if self._rx_holds:                    # the frame returned last has been handled
            self._rx_holds = False
            self._handling.release()
        if not self._plain_queue():
            return super().recv(timeout)
        pending = self.queue.queue
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            if self._taken:
                self._handling.acquire()
                if self._taken:               # else a sender handled them meanwhile
                    self._rx_holds = True
                    return self._taken.popleft()
                self._handling.release()
            if not pending:
                with self.queue.not_empty:        # wait for a frame without taking it: a sender may handle it
                    while not pending:
                        remaining = None if deadline is None else deadline - time.monotonic()
                        if remaining is not None and remaining <= 0:
                            return None
                        self.queue.not_empty.wait(remaining)
            self._handling.acquire()              # a sender handling frames finishes first: the order stays
            try:
                item = pending.popleft()
            except IndexError:                    # the sender took them all
                self._handling.release()
                continue
            if isinstance(item, tuple):           # a burst: its frames one by one
                self._taken.extend(burst_messages(item, self.channel_id))
                item = self._taken.popleft()
            self._rx_holds = True
            return item

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        """python-can's receive (a bus with filters): a burst's frames one by one, as recv gives them."""
        if self._taken:
            return self._taken.popleft(), False
        item, filtered = super()._recv_internal(timeout)
        if isinstance(item, tuple):
            self._taken.extend(burst_messages(item, self.channel_id))
            item = self._taken.popleft()
        return item, filtered

    def handle_arrived(self, listeners: list[Callable[[can.Message], Any]],
                       on_burst: Callable[[float, list[tuple[int, bytes]]], None]) -> None:
        """Lockstep: hand the frames already here to `listeners` in this thread, as the receive thread (a notifier
        with these listeners) would, when it is not handling one itself — a burst to `on_burst(timestamp, frames)`,
        which does for its frames what the listeners would frame by frame; the answer an inline receiver gave during
        send is then in before the caller waits for it, without a thread hand-off."""
        if self._plain_queue() and self._handling.acquire(blocking=False):
            self._handle_taken_and_queued(listeners, on_burst)
        if self.queue.queue:             # left to the receive thread (or put meanwhile by a thread that does not
            with self.queue.not_empty:   # handle what it puts): wake it
                self.queue.not_empty.notify()

    def _handle_taken_and_queued(self, listeners: list[Callable[[can.Message], Any]],
                                 on_burst: Callable[[float, list[tuple[int, bytes]]], None]) -> None:
        try:
            items: list = list(self._taken)
            self._taken.clear()
            with self.queue.mutex:
                items.extend(self.queue.queue)
                self.queue.queue.clear()
            for item in items:
                if isinstance(item, tuple):
                    on_burst(item[0], item[1])
                else:
                    for listener in listeners:
                        listener(item)
        except Exception as exc:         # as on the receive thread: logged, never raised into the sender
            log.error("CAN receive listener: %s", exc)
        finally:
            self._handling.release()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._check_if_open()
        timestamp = msg.timestamp if self.preserve_timestamps else time.time()
        all_sent = True
        for bus_queue in self.channel:
            if bus_queue is self.queue and not self.receive_own_messages:
                continue
            copy = can.Message(timestamp=timestamp, arbitration_id=msg.arbitration_id,
                               is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                               is_error_frame=msg.is_error_frame, channel=self.channel_id, dlc=msg.dlc,
                               data=bytearray(msg.data), is_fd=msg.is_fd, is_rx=bus_queue is not self.queue,
                               bitrate_switch=msg.bitrate_switch, error_state_indicator=msg.error_state_indicator,
                               check=False)
            put_inline = getattr(bus_queue, "put_inline", None) if self.inline_delivery else None
            if put_inline is not None:
                put_inline(copy)
                continue
            try:
                bus_queue.put(copy, block=True, timeout=timeout)
            except queue.Full:
                all_sent = False
        if not all_sent:
            raise can.CanOperationError("Could not send message to one or more recipients")


def make_bus(kwargs: dict[str, Any]) -> can.BusABC:
    """can.Bus(**kwargs) (python-can's `virtual` interface: QuickVirtualBus); for socketcand a client that reads the
    server's handshake replies as a prefix of what arrives: python-can's compares the whole read with `< ok >`, and a
    served drive's first frame in the same TCP segment (`< ok >< frame 701 ... >`, the more likely with TCP_NODELAY)
    made it refuse a healthy rig."""
    if kwargs.get("interface") == "virtual":
        return QuickVirtualBus(**{k: v for k, v in kwargs.items() if k != "interface"})
    if kwargs.get("interface") != "socketcand":
        return can.Bus(**kwargs)
    from can.interfaces.socketcand.socketcand import SocketCanDaemonBus, convert_ascii_message_to_can_message

    class HandshakeTolerantBus(SocketCanDaemonBus):
        def _expect_msg(self, msg: str) -> None:
            sock = self._SocketCanDaemonBus__socket
            text = ""
            while len(text) < len(msg):
                chunk = sock.recv(256).decode("ascii")
                if not chunk:
                    break
                text += chunk
            if not text.startswith(msg):
                raise can.CanError(f"Expected '{msg}' got: '{text}'")
            rest = text[len(msg):]
            while "<" in rest and ">" in rest:             # whole frames that came along: delivered first
                start, end = rest.index("<"), rest.index(">")
                frame = convert_ascii_message_to_can_message(rest[start:end + 1])
                if frame is not None:
                    frame.channel = self.channel if hasattr(self, "channel") else None
                    self._SocketCanDaemonBus__message_buffer.append(frame)
                rest = rest[end + 1:]
            self._SocketCanDaemonBus__receive_buffer += rest                  # a partial one: completed later

    return HandshakeTolerantBus(**{k: v for k, v in kwargs.items() if k != "interface"})


def open_bus(kwargs: dict[str, Any], connect: Callable[[], Any] | None = None,
             timeout_s: float = CONNECT_TIMEOUT_S) -> Any:
    """Open a CAN interface within timeout_s: connect() (default can.Bus(**kwargs)) runs on a helper thread so that
    no driver's handshake can block the bench for good; a socketcand endpoint is checked for its greeting first."""
    if kwargs.get("interface") == "socketcand":
        socketcand_greeting(str(kwargs.get("host", "127.0.0.1")), int(kwargs.get("port", 29536)), timeout_s)
    result: dict[str, Any] = {}

    def run() -> None:
        try:
            result["value"] = connect() if connect is not None else make_bus(kwargs)
        except BaseException as exc:         # handed to the caller's thread
            result["error"] = exc

    worker = threading.Thread(target=run, name="can-open", daemon=True)
    worker.start()
    worker.join(timeout_s)
    if worker.is_alive():
        raise TimeoutError(f"opening CAN interface {kwargs.get('interface')!r} channel {kwargs.get('channel')!r} "
                           f"took longer than {timeout_s:g} s")
    if "error" in result:
        raise result["error"]
    return result.get("value")


class BusErrorCounter(can.Listener):
    """Error frames as a receive error counter would count them (+8 per error frame, -1 per good frame), and
    the interface's own bus state where it reports one (python-can BusState; socketcan, pcan, ... do)."""

    def __init__(self):
        self.counter = 0
        self.error_frames = 0

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self.error_frames += 1
            self.counter += 8
        elif self.counter:
            self.counter -= 1

    def count_good(self, n_frames: int) -> None:
        """n_frames good frames in a row: what on_message_received does for each."""
        self.counter = max(0, self.counter - n_frames)

    def problem(self, bus: can.BusABC | None) -> str | None:
        try:
            state = bus.state if bus is not None else can.BusState.ACTIVE
        except (NotImplementedError, can.CanError, OSError):
            state = can.BusState.ACTIVE
        if state is can.BusState.ERROR:
            return "CAN bus off (the interface reports BusState.ERROR)"
        if state is can.BusState.PASSIVE:
            return "CAN controller error passive (the interface reports BusState.PASSIVE)"
        if self.counter >= ERROR_PASSIVE_LEVEL:
            return (f"CAN bus errors: {self.error_frames} error frames, receive error count ~{self.counter} "
                    f">= {ERROR_PASSIVE_LEVEL} (error passive)")
        return None
