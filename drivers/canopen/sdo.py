"""SDO access for the link: expedited/segmented reads and writes through canopen's client with LinkErrors that name
the object, and the block-upload client (CiA 301 7.2.4.3.9-15) that canopen's client does not make fast enough."""

from __future__ import annotations

import binascii
import struct
import threading
import time
from typing import Any, Callable

import canopen
import numpy as np
from canopen import objectdictionary
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from drivers.canopen.dispatch import RunReceiver
from drivers.contract.errors import LinkError
from drivers.contract import objects as o


NO_SUCH_OBJECT = (o.ABORT_NOT_IN_OD, 0x06090011)     # object / subindex does not exist
_RAISE = object()     # _transfer: no "missing" value given


def abort_text(exc: SdoAbortedError) -> str:
    text = str(exc)
    return text.split(", ", 1)[1] if ", " in text else text


class SdoAccess:
    """Reads and writes of one node's objects; every failure is a LinkError naming index, subindex and name.

    One SDO transfer at a time per node (`lock`): a CANopen node has one SDO server channel, and the command thread
    (parameters, the state machine) and the telemetry thread (trace uploads) share it."""

    def __init__(self, node: canopen.RemoteNode, eds_name: str, timeout_s: float,
                 lock: threading.RLock | None = None):
        self.node = node
        self.eds_name = eds_name
        self.timeout_s = timeout_s
        self.where = f"node {node.id}"
        self.lock = lock or threading.RLock()

    def has(self, index: int, subindex: int | None = None) -> bool:
        od = self.node.object_dictionary
        if index not in od:
            return False
        obj = od[index]
        return subindex is None or isinstance(obj, objectdictionary.ODVariable) or subindex in obj

    def var(self, index: int, subindex: int = 0) -> objectdictionary.ODVariable:
        try:
            obj = self.node.object_dictionary[index]
            return obj if isinstance(obj, objectdictionary.ODVariable) else obj[subindex]
        except KeyError:
            raise LinkError(f"{self.where}: object 0x{index:04X}:{subindex:02X} is not in {self.eds_name}") from None

    def _failed(self, verb: str, index: int, subindex: int, name: str, exc: Exception) -> LinkError:
        label = f"{self.where}: SDO {verb} of 0x{index:04X}:{subindex:02X}" + (f" ({name})" if name else "")
        if isinstance(exc, SdoAbortedError):
            return LinkError(f"{label} aborted with 0x{exc.code:08X} ({abort_text(exc)})")
        return LinkError(f"{label}: {exc} within {self.timeout_s} s")

    def read(self, index: int, subindex: int = 0) -> Any:
        var = self.var(index, subindex)
        return var.decode_raw(self._transfer("read", index, subindex, var.name,
                                             lambda: self.node.sdo.upload(index, subindex)))

    def write(self, index: int, subindex: int, value: Any) -> None:
        var = self.var(index, subindex)
        data = var.encode_raw(value)
        self._transfer("write", index, subindex, var.name, lambda: self.node.sdo.download(index, subindex, data))

    def upload(self, index: int, subindex: int = 0) -> bytes:
        """Raw read of any index, with or without an EDS entry."""
        return self._transfer("read", index, subindex, "", lambda: self.node.sdo.upload(index, subindex))

    def download(self, index: int, subindex: int, data: bytes) -> None:
        """Raw write of any index, with or without an EDS entry."""
        self._transfer("write", index, subindex, "", lambda: self.node.sdo.download(index, subindex, data))

    def read_standard(self, index: int, subindex: int = 0, signed: bool = False) -> int | None:
        """A standard integer object read from the device itself (the EDS may lack it, the device may have it);
        None when the device says it has no such object."""
        data = self._transfer("read", index, subindex, "", lambda: self.node.sdo.upload(index, subindex),
                              missing=None)
        return None if data is None else int.from_bytes(data, "little", signed=signed)

    def write_standard(self, index: int, subindex: int, value: int, size: int, signed: bool = False) -> bool:
        """Write a standard integer object; False when the device has no such object."""
        data = value.to_bytes(size, "little", signed=signed)
        return self._transfer("write", index, subindex, "",
                              lambda: self.node.sdo.download(index, subindex, data) or True, missing=False)

    def _transfer(self, verb: str, index: int, subindex: int, name: str, call: Callable[[], Any],
                  missing: Any = _RAISE) -> Any:
        """call() under the link's lock; an abort or timeout becomes a LinkError, except that an abort saying the
        object does not exist returns `missing` where one is given."""
        try:
            with self.lock:
                return call()
        except SdoAbortedError as exc:
            if missing is not _RAISE and exc.code in NO_SUCH_OBJECT:
                return missing
            raise self._failed(verb, index, subindex, name, exc) from None
        except SdoCommunicationError as exc:
            raise self._failed(verb, index, subindex, name, exc) from None


MIN_FRAMES_PER_S = 1000.0   # the slowest transfer rate a block upload may take before its deadline
MAX_STALLED_SUBBLOCKS = 3    # sub-blocks in a row that bring no new segment: the transfer is dead


def block_upload(network: canopen.Network, node_id: int, index: int, subindex: int, timeout_s: float,
                 send: Callable[[int, bytes], None], cancel: threading.Event | None = None) -> bytes:
    """SDO block upload, client side, with CRC. Segments are collected on the receive thread and handed over once
    per sub-block, which is what makes ~50k frames/s possible in Python. b"" when the server has no data.

    Bounded whatever the bus does: an abort frame (0x80: never a valid segment, whose sequence numbers start at 1)
    ends the transfer wherever it comes; each wait has timeout_s; sub-blocks that bring nothing new end it after
    MAX_STALLED_SUBBLOCKS; the whole transfer has a deadline of timeout_s plus the announced size at
    MIN_FRAMES_PER_S; `cancel` set by another thread ends it at once (the bench's safe stop needs the bus)."""
    rx = o.SDO_TX + node_id
    collector = _BlockCollector(cancel)
    saved = network.subscribers.get(rx, [])
    network.subscribers[rx] = [RunReceiver(collector.on_frame, collector.on_frames)]
    where = f"node {node_id}: block upload of 0x{index:04X}:{subindex:02X}"

    def request(data: bytes) -> None:
        send(o.SDO_RX + node_id, data.ljust(8, b"\0"))

    def fail(message: str, abort_code: int | None = o.ABORT_TIMEOUT) -> LinkError:
        if abort_code is not None:
            try:
                request(struct.pack("<BHBL", o.SDO_ABORT, index, subindex, abort_code))
            except LinkError:
                pass
        return LinkError(f"{where}: {message}")

    def aborted(frame: bytearray) -> LinkError:
        code = struct.unpack_from("<L", frame, 4)[0]
        return fail(f"aborted with 0x{code:08X} ({abort_text(SdoAbortedError(code))})", None)

    try:
        collector.expect(1)
        request(struct.pack("<BHBBB", o.BLOCK_UPLOAD_INITIATE | o.BLOCK_CRC_SUPPORTED, index, subindex,
                            o.MAX_BLOCK_SIZE, 0))
        frames = collector.wait(timeout_s)
        if frames is None:
            raise fail(f"no answer within {timeout_s} s")
        head = frames[0]
        if head[0] == o.SDO_ABORT:
            if struct.unpack_from("<L", head, 4)[0] == o.ABORT_NO_DATA:
                return b""
            raise aborted(head)
        if head[0] & 0xE1 != o.BLOCK_RESPONSE_INITIATE or struct.unpack_from("<HB", head, 1) != (index, subindex):
            raise fail(f"unexpected answer {bytes(head).hex()}", o.ABORT_COMMAND)
        size = struct.unpack_from("<L", head, 4)[0] if head[0] & o.BLOCK_SIZE_INDICATED else None
        crc_on = bool(head[0] & o.BLOCK_CRC_SUPPORTED)
        frames_expected = (size or 0) / 7 + 2
        deadline = time.monotonic() + timeout_s + frames_expected / MIN_FRAMES_PER_S
        chunks: list[bytes] = []
        stalled = 0
        collector.expect_block(o.MAX_BLOCK_SIZE)
        request(bytes([o.BLOCK_UPLOAD_START]))
        while True:
            frames = collector.wait(min(timeout_s, max(0.0, deadline - time.monotonic())))
            if frames is None:
                if collector.cancelled:
                    raise fail("cancelled by the bench (safe stop)", o.ABORT_GENERAL)
                if time.monotonic() >= deadline:
                    raise fail(f"not finished within its deadline ({len(chunks)} sub-blocks received)")
                raise fail(f"block segments stopped arriving (timeout {timeout_s} s)")
            abort = find_abort(frames)
            if abort is not None:
                raise aborted(abort)
            ackseq, last, data = accept_segments(frames)
            stalled = 0 if ackseq else stalled + 1
            if stalled >= MAX_STALLED_SUBBLOCKS:
                raise fail(f"{stalled} sub-blocks in a row without a valid segment", o.ABORT_SEQUENCE)
            if time.monotonic() >= deadline:
                raise fail(f"not finished within its deadline ({len(chunks)} sub-blocks received)")
            chunks.append(data)
            if last:
                collector.expect(1)
            else:
                collector.expect_block(o.MAX_BLOCK_SIZE)
            request(bytes([o.BLOCK_UPLOAD_ACK, ackseq, o.MAX_BLOCK_SIZE]))
            if last:
                break
        frames = collector.wait(timeout_s)
        if frames is None:
            raise fail(f"no end of transfer within {timeout_s} s")
        if frames[0][0] == o.SDO_ABORT:
            raise aborted(frames[0])
        end = frames[0]
        if end[0] & 0xE1 != o.BLOCK_RESPONSE_END:
            raise fail(f"unexpected end {bytes(end).hex()}", o.ABORT_COMMAND)
        unused = (end[0] >> 2) & 0x07
        data = b"".join(chunks)
        data = data[:len(data) - unused]
        if crc_on and struct.unpack_from("<H", end, 1)[0] != binascii.crc_hqx(data, 0):
            raise fail("CRC mismatch", o.ABORT_CRC)
        if size is not None and size != len(data):
            raise fail(f"got {len(data)} bytes, the server announced {size}", o.ABORT_TIMEOUT)
        request(bytes([o.BLOCK_UPLOAD_END]))
        return data
    finally:
        network.subscribers[rx] = saved


def find_abort(frames: list[bytearray]) -> bytearray | None:
    """An SDO abort among a sub-block's frames (0x80 is never a segment: sequence numbers start at 1)."""
    if len(frames) > 16 and all(map((8).__eq__, map(len, frames))):      # every frame 8 bytes (no Python loop)
        heads = np.frombuffer(b"".join(frames), dtype=np.uint8)[::8]
        hits = np.flatnonzero(heads == o.SDO_ABORT)
        return frames[int(hits[0])] if hits.size else None
    return next((f for f in frames if len(f) == 8 and f[0] == o.SDO_ABORT), None)


def accept_segments(frames: list[bytearray]) -> tuple[int, bool, bytes]:
    """(ackseq, last, data) of one sub-block: segments in sequence from 1, up to the first gap or the last
    segment of the transfer (what follows a gap is dropped; the server repeats it after our ack)."""
    if not all(map((8).__eq__, map(len, frames))):
        ackseq, last, pieces = 0, False, []
        for frame in frames:
            if not frame or frame[0] & 0x7F != ackseq + 1:
                break
            ackseq += 1
            pieces.append(bytes(frame[1:8]))
            if frame[0] & o.BLOCK_LAST_SEGMENT:
                last = True
                break
        return ackseq, last, b"".join(pieces)
    segments = np.frombuffer(b"".join(frames), dtype=np.uint8).reshape(-1, 8)
    gaps = np.flatnonzero(segments[:, 0] & 0x7F != np.arange(1, len(segments) + 1))
    n = int(gaps[0]) if gaps.size else len(segments)
    ends = np.flatnonzero(segments[:n, 0] & o.BLOCK_LAST_SEGMENT)
    last = bool(ends.size)
    if last:
        n = int(ends[0]) + 1
    return n, last, segments[:n, 1:].tobytes()


class _BlockCollector:
    """Receives SDO server frames on the CAN thread; wakes the uploader per block, not per frame.

    Frames are appended without a lock (only the receive thread appends; list.append is atomic); the lock is
    taken once, to wake the uploader, which then takes the list. A frame outside the expected window (after
    the block's last segment, before the next request) may be dropped, as the protocol allows."""

    def __init__(self, cancel: threading.Event | None = None):
        self._cancel = cancel
        self.cancelled = False
        self._cond = threading.Condition()
        self._frames: list[bytearray] = []
        self._want = 1
        self._block = 0
        self._ready = False

    def expect(self, n_frames: int) -> None:
        with self._cond:
            self._frames, self._want, self._block, self._ready = [], n_frames, 0, False

    def expect_block(self, blksize: int) -> None:
        with self._cond:
            self._frames, self._want, self._block, self._ready = [], 0, blksize, False

    def on_frame(self, can_id, data, timestamp):
        frames = self._frames
        frames.append(data)
        block = self._block
        if (data[0] & 0x80 or (data[0] & 0x7F) >= block) if block else len(frames) >= self._want:
            self._wake(frames)

    def on_frames(self, run: list[tuple[int, bytes]], timestamp: float) -> None:
        """A run of frames at once (bus.FrameDispatch.burst): what one on_frame call per frame does."""
        frames = self._frames
        datas = [data for _, data in run]
        frames.extend(datas)
        block = self._block
        if block:
            complete = any(data[0] & 0x80 or (data[0] & 0x7F) >= block for data in reversed(datas))
        else:
            complete = len(frames) >= self._want
        if complete:
            self._wake(frames)

    def _wake(self, frames: list) -> None:
        with self._cond:
            if frames is self._frames:
                self._ready = True
                self._cond.notify()

    def wait(self, timeout: float) -> list[bytearray] | None:
        deadline = time.monotonic() + timeout
        with self._cond:
            while not self._ready:
                if self._cancel is not None and self._cancel.is_set():
                    self.cancelled = True
                    return None
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._cond.wait(min(remaining, 0.05) if self._cancel is not None else remaining)
            frames, self._frames, self._ready = self._frames, [], False
            return frames
