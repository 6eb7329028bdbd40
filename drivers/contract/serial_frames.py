"""Framing of the drivebench serial drive protocol, shared by the client and the simulated drive.

Frame (docs/serial-protocol.md):

    A5 5A | LEN u16 LE | SEQ u8 | CMD u8 | HCRC u8 | PAYLOAD (LEN bytes) | CRC u32 LE

HCRC is CRC-8 (poly 0x07, init 0, CRC-8/SMBUS) over LEN, SEQ, CMD, so a corrupted length is caught
before the receiver waits for a payload that never comes. CRC is CRC-32 (IEEE 802.3, zlib.crc32)
over LEN..PAYLOAD (everything after the start bytes, without HCRC).
"""

from __future__ import annotations

import enum
import struct
import zlib
from dataclasses import dataclass

SOF = b"\xa5\x5a"
HEADER_SIZE = 7          # SOF(2) LEN(2) SEQ(1) CMD(1) HCRC(1)
TRAILER_SIZE = 4
OVERHEAD = HEADER_SIZE + TRAILER_SIZE
MAX_PAYLOAD = 65535

PROTOCOL_MAJOR = 1
PROTOCOL_MINOR = 1

RESPONSE_FLAG = 0x80     # a reply carries CMD | 0x80 and the request's SEQ


class Cmd(enum.IntEnum):
    HELLO = 0x01             # req: major u8, minor u8 -> major u8, minor u8, max_payload u16, period f64, n_signals u8
    IDENTITY = 0x02          # -> vendor u32, product u32, revision u32, serial u32, flags u8, name str8, fw str8
    CONTROLWORD = 0x10       # req: controlword u16 -> statusword u16
    STATUS = 0x11            # -> statusword u16, error_code u16, mode i8, step u64, n u8, n x emcy code u16
    MODE = 0x12              # req: mode of operation i8 -> mode displayed i8
    TARGET_VELOCITY = 0x13   # req: f64 rad/s (mechanical) -> (empty)
    WATCHDOG = 0x14          # req: timeout_ms u16 (0 off), reaction i16 (CiA 402 0x6007 code) -> (empty)
    PARAM_LIST = 0x20        # -> n u8, n x name str8
    PARAM_WRITE_INDEX = 0x21  # req: index u16, value f64 -> (empty)
    PARAM_WRITE_NAME = 0x22  # req: value f64, name (rest of payload, UTF-8) -> (empty)
    TRACE_CONFIGURE = 0x30   # req: mask u32, decimation u16, trigger u8 -> (empty)
    TRACE_START = 0x31
    TRACE_STOP = 0x32
    TRACE_READ = 0x33        # req: max_rows u16 -> mask u32, remaining u32, lost u32, rows (drivers.contract.trace_format)
    LIVE_CONFIGURE = 0x40    # req: mask u32 -> (empty)
    SAMPLE = 0x41            # -> live sample (see SAMPLE_HEADER)
    SYNC = 0x42              # req: n_steps u32 -> advance n_steps control periods, then live sample
    ERROR = 0x7F             # reply only: cmd u8, code u8, message (UTF-8)


class ErrorCode(enum.IntEnum):
    UNKNOWN_COMMAND = 1
    BAD_LENGTH = 2
    BAD_VALUE = 3
    NOT_ALLOWED = 4
    UNKNOWN_PARAMETER = 5
    VERSION = 6
    BUSY = 7                 # the line (or the rig) is held by another bench: connect later


# Live sample (SAMPLE and SYNC replies): step u64, statusword u16, error_code u16, mask u32,
# then one f64 per selected signal in drivers.contract.signals.SIGNAL_NAMES order.
SAMPLE_HEADER = struct.Struct("<QHHI")


def _crc8_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc << 1 ^ 0x07) & 0xFF if crc & 0x80 else crc << 1 & 0xFF
        table.append(crc)
    return tuple(table)


_CRC8 = _crc8_table()


def crc8(data: bytes) -> int:
    """CRC-8/SMBUS: poly 0x07, init 0x00, no reflection; check("123456789") = 0xF4."""
    crc = 0
    for byte in data:
        crc = _CRC8[crc ^ byte]
    return crc


def crc32(data: bytes) -> int:
    """CRC-32/IEEE (zlib); check("123456789") = 0xCBF43926."""
    return zlib.crc32(data) & 0xFFFFFFFF


@dataclass(frozen=True)
class Frame:
    seq: int
    cmd: int
    payload: bytes = b""


def encode_frame(seq: int, cmd: int, payload: bytes = b"") -> bytes:
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    head = struct.pack("<HBB", len(payload), seq & 0xFF, cmd & 0xFF)
    body = head + payload
    return SOF + head + bytes([crc8(head)]) + payload + struct.pack("<I", crc32(body))


class FrameDecoder:
    """Stream parser with resynchronisation: feed bytes, collect frames; bad frames are counted, skipped.

    On a header or payload CRC error only the first start byte is dropped and the search restarts, so a
    good frame that begins inside a corrupted one is still found.
    """

    def __init__(self, max_payload: int = MAX_PAYLOAD):
        self.max_payload = max_payload
        self.buffer = bytearray()
        self.crc_errors = 0
        self.discarded_bytes = 0

    def feed(self, data: bytes) -> list[Frame]:
        self.buffer += data
        frames = []
        while (frame := self._next()) is not None:
            frames.append(frame)
        return frames

    def resync(self) -> list[Frame]:
        """The line went quiet inside a frame: drop its first byte, count it as bad, search the rest again.

        Catches the rare corrupted header whose CRC-8 still matches and whose length would otherwise make the
        receiver wait for bytes that never come."""
        if not self.buffer:
            return []
        self.crc_errors += 1
        self._skip(1)
        return self.feed(b"")

    def bytes_wanted(self) -> int:
        """How many more bytes complete the next frame, as far as the buffer tells; never more than a frame
        still needs, so a blocking read of this many bytes cannot wait past the end of a good frame."""
        buf = self.buffer
        start = buf.find(SOF)
        if start < 0:
            return HEADER_SIZE - (1 if buf[-1:] == SOF[:1] else 0)
        have = len(buf) - start
        if have < HEADER_SIZE:
            return HEADER_SIZE - have
        head = bytes(buf[start + 2:start + 6])
        if crc8(head) != buf[start + 6]:
            return 1
        return max(1, HEADER_SIZE + (head[0] | head[1] << 8) + TRAILER_SIZE - have)

    def _skip(self, n: int) -> None:
        del self.buffer[:n]
        self.discarded_bytes += n

    def _next(self) -> Frame | None:
        buf = self.buffer
        while True:
            start = buf.find(SOF)
            if start < 0:
                keep = 1 if buf[-1:] == SOF[:1] else 0
                self._skip(len(buf) - keep)
                return None
            if start:
                self._skip(start)
            if len(buf) < HEADER_SIZE:
                return None
            head = bytes(buf[2:6])
            length = head[0] | head[1] << 8
            if crc8(head) != buf[6] or length > self.max_payload:
                self.crc_errors += 1
                self._skip(1)
                continue
            total = HEADER_SIZE + length + TRAILER_SIZE
            if len(buf) < total:
                return None
            payload = bytes(buf[HEADER_SIZE:HEADER_SIZE + length])
            (crc,) = struct.unpack_from("<I", buf, HEADER_SIZE + length)
            if crc != crc32(head + payload):
                self.crc_errors += 1
                self._skip(1)
                continue
            del buf[:total]
            return Frame(seq=head[2], cmd=head[3], payload=payload)


def pack_str8(text: str) -> bytes:
    raw = text.encode()[:255]
    return bytes([len(raw)]) + raw


def unpack_str8(data: bytes, offset: int) -> tuple[str, int]:
    n = data[offset]
    end = offset + 1 + n
    if end > len(data):
        raise ValueError("string runs past the end of the payload")
    return data[offset + 1:end].decode(), end


def error_payload(cmd: int, code: ErrorCode, message: str) -> bytes:
    return bytes([cmd & 0xFF, int(code)]) + message.encode()[:1000]


# CiA 402 / EMCY error codes the simulated drives raise, for readable status texts.
FAULT_TEXT: dict[int, str] = {
    0x2310: "overcurrent",
    0x3210: "DC-link overvoltage",
    0x3220: "DC-link undervoltage",
    0x4310: "drive overtemperature",
    0x7300: "sensor fault",
    0x8400: "speed control deviation",
    0x8611: "following error",
}


def fault_text(code: int) -> str:
    return FAULT_TEXT.get(code, f"error 0x{code:04X}")
