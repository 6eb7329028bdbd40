"""The simulated drive's serial protocol (docs/serial-protocol.md) on a SimulatedDevice: request frames executed,
reply frames built, a retried request answered again without executing twice. No transport: the servers of
sim_backend/serial_server.py feed it the frames of their line."""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

import numpy as np

from drivers.contract.serial_frames import (
    MAX_PAYLOAD, PROTOCOL_MAJOR, PROTOCOL_MINOR, RESPONSE_FLAG, SAMPLE_HEADER, Cmd, ErrorCode, Frame,
    encode_frame, error_payload, pack_str8,
)
from drivers.contract.signals import SIGNAL_NAMES
from drivers.contract import extension, parameters
from drivers.contract.cia402 import FAULT_RESET_BIT, State
from sim_backend.device import SimulatedDevice
from sim_backend.trace import TRIGGER_IMMEDIATE, TRIGGER_ON_ENABLE

MAX_SYNC_STEPS = 1_000_000
ALL_SIGNALS = (1 << len(SIGNAL_NAMES)) - 1


class CommandError(Exception):
    def __init__(self, code: ErrorCode, message: str):
        super().__init__(message)
        self.code = code


def _expect_len(payload: bytes, n: int, cmd: Cmd) -> None:
    if len(payload) != n:
        raise CommandError(ErrorCode.BAD_LENGTH, f"{cmd.name} takes {n} payload bytes, got {len(payload)}")


def _mask_index(mask: int) -> np.ndarray:
    return np.array([i for i in range(len(SIGNAL_NAMES)) if mask >> i & 1], dtype=np.intp)


@dataclass
class SerialProtocolHandler:
    """Executes request frames on a SimulatedDevice and builds reply frames."""

    device: SimulatedDevice
    serial_number: int = 1
    live_mask: int = ALL_SIGNALS
    requests: int = 0
    replays: int = 0
    _last_request: tuple[int, int, bytes] | None = None
    _last_reply: bytes = b""
    _params: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        self._live_index = _mask_index(self.live_mask)
        self._params = parameters.names_for(getattr(self.device.model, "kind", "pmsm"))

    def handle(self, frame: Frame) -> bytes:
        self.device.master_watchdog.touch()          # any valid frame is a sign of the master (WATCHDOG)
        key = (frame.seq, frame.cmd, frame.payload)
        if key == self._last_request and frame.cmd != Cmd.HELLO:
            self.replays += 1            # a retry: answer again without executing twice (SYNC!)
            return self._last_reply
        self.requests += 1
        try:
            cmd = Cmd(frame.cmd)
        except ValueError:
            cmd = None
        try:
            if cmd is None or cmd is Cmd.ERROR:
                raise CommandError(ErrorCode.UNKNOWN_COMMAND, f"unknown command 0x{frame.cmd:02X}")
            reply = encode_frame(frame.seq, frame.cmd | RESPONSE_FLAG, self._execute(cmd, frame.payload))
        except CommandError as exc:
            reply = encode_frame(frame.seq, Cmd.ERROR | RESPONSE_FLAG, error_payload(frame.cmd, exc.code, str(exc)))
        except Exception as exc:        # a simulator failure must reach the bench as an answer, not as silence
            reply = encode_frame(frame.seq, Cmd.ERROR | RESPONSE_FLAG, error_payload(
                frame.cmd, ErrorCode.NOT_ALLOWED, f"drive failure: {type(exc).__name__}: {exc}"))
        self._last_request, self._last_reply = key, reply
        return reply

    def _sample(self) -> bytes:
        dev = self.device
        with dev.lock:
            head = SAMPLE_HEADER.pack(dev.step_count, dev.device.statusword, dev.device.error_code, self.live_mask)
            return head + np.asarray(dev.latest, dtype="<f8")[self._live_index].tobytes()

    def _execute(self, cmd: Cmd, p: bytes) -> bytes:
        dev = self.device
        if cmd is Cmd.SYNC:                 # first: the hot path in lockstep
            _expect_len(p, 4, cmd)
            (n_steps,) = struct.unpack("<I", p)
            if not 1 <= n_steps <= MAX_SYNC_STEPS:
                raise CommandError(ErrorCode.BAD_VALUE, f"SYNC of {n_steps} steps outside 1..{MAX_SYNC_STEPS}")
            with dev.lock:
                dev.advance(n_steps)
                return self._sample()
        if cmd is Cmd.HELLO:
            _expect_len(p, 2, cmd)
            if p[0] != PROTOCOL_MAJOR:
                raise CommandError(ErrorCode.VERSION, f"protocol {p[0]}.{p[1]} unsupported, drive speaks "
                                                      f"{PROTOCOL_MAJOR}.{PROTOCOL_MINOR}")
            return struct.pack("<BBHdB", PROTOCOL_MAJOR, PROTOCOL_MINOR, MAX_PAYLOAD,
                               dev.model.control_period_s, len(SIGNAL_NAMES))
        if cmd is Cmd.IDENTITY:
            _expect_len(p, 0, cmd)
            kind = getattr(dev.model, "kind", "pmsm")
            return (struct.pack("<IIIIB", extension.VENDOR_ID, extension.PRODUCT_CODES.get(kind, 0),
                                extension.REVISION, self.serial_number, 1)
                    + pack_str8(extension.device_name(kind)) + pack_str8(extension.FIRMWARE_VERSION))
        if cmd is Cmd.CONTROLWORD:
            _expect_len(p, 2, cmd)
            (word,) = struct.unpack("<H", p)
            with dev.lock:
                if word & FAULT_RESET_BIT and dev.device.state is State.FAULT:
                    dev.reset_fault()
                dev.write_controlword(word)
                return struct.pack("<H", dev.device.statusword)
        if cmd is Cmd.STATUS:
            _expect_len(p, 0, cmd)
            with dev.lock:
                codes = dev.take_emcy()[:255]
                return (struct.pack("<HHbQB", dev.device.statusword, dev.device.error_code, dev.mode_of_operation,
                                    dev.step_count, len(codes)) + struct.pack(f"<{len(codes)}H", *codes))
        if cmd is Cmd.MODE:
            _expect_len(p, 1, cmd)
            with dev.lock:
                (dev.mode_of_operation,) = struct.unpack("<b", p)
                return struct.pack("<b", dev.mode_of_operation)
        if cmd is Cmd.TARGET_VELOCITY:
            _expect_len(p, 8, cmd)
            (speed,) = struct.unpack("<d", p)
            if not math.isfinite(speed):
                raise CommandError(ErrorCode.BAD_VALUE, f"target velocity {speed} is not finite")
            dev.set_target(speed)
            return b""
        if cmd is Cmd.WATCHDOG:
            _expect_len(p, 4, cmd)
            timeout_ms, reaction = struct.unpack("<Hh", p)
            if reaction not in (0, 1, 2, 3):
                raise CommandError(ErrorCode.BAD_VALUE, f"watchdog reaction {reaction} is not 0..3 (0x6007 codes)")
            with dev.lock:
                dev.abort_connection_option = reaction
                dev.master_watchdog.arm(timeout_ms / 1000.0)
                dev.master_watchdog.touch()
            if timeout_ms:
                dev.arm_watchdogs()
            return b""
        if cmd is Cmd.PARAM_LIST:
            _expect_len(p, 0, cmd)
            return bytes([len(self._params)]) + b"".join(pack_str8(n) for n in self._params)
        if cmd in (Cmd.PARAM_WRITE_INDEX, Cmd.PARAM_WRITE_NAME):
            if cmd is Cmd.PARAM_WRITE_INDEX:
                _expect_len(p, 10, cmd)
                index, value = struct.unpack("<Hd", p)
                if index >= len(self._params):
                    raise CommandError(ErrorCode.UNKNOWN_PARAMETER, f"parameter index {index} out of range "
                                                                    f"(0..{len(self._params) - 1})")
                name = self._params[index]
            else:
                if len(p) < 9:
                    raise CommandError(ErrorCode.BAD_LENGTH, "PARAM_WRITE_NAME needs a value and a name")
                (value,) = struct.unpack_from("<d", p)
                name = p[8:].decode(errors="replace")
            if name not in self._params:
                raise CommandError(ErrorCode.UNKNOWN_PARAMETER, f"unknown parameter '{name}'")
            if not math.isfinite(value):
                raise CommandError(ErrorCode.BAD_VALUE, f"value {value} for '{name}' is not finite")
            try:
                dev.write_named(name, value)
            except (KeyError, ValueError) as exc:
                raise CommandError(ErrorCode.BAD_VALUE, f"'{name}' = {value} rejected: {exc}") from None
            return b""
        if cmd is Cmd.TRACE_CONFIGURE:
            _expect_len(p, 7, cmd)
            mask, decimation, trigger = struct.unpack("<IHB", p)
            if trigger not in (TRIGGER_IMMEDIATE, TRIGGER_ON_ENABLE):
                raise CommandError(ErrorCode.BAD_VALUE, f"unknown trace trigger {trigger}")
            with dev.lock:
                try:
                    dev.trace.configure(mask, decimation, trigger)
                except ValueError as exc:
                    raise CommandError(ErrorCode.BAD_VALUE, str(exc)) from None
            return b""
        if cmd in (Cmd.TRACE_START, Cmd.TRACE_STOP):
            _expect_len(p, 0, cmd)
            with dev.lock:
                dev.trace.start() if cmd is Cmd.TRACE_START else dev.trace.stop()
            return b""
        if cmd is Cmd.TRACE_READ:
            _expect_len(p, 2, cmd)
            (max_rows,) = struct.unpack("<H", p)
            with dev.lock:
                fit = (MAX_PAYLOAD - 12) // dev.trace.row_size
                data = dev.trace.read(min(max_rows, fit))
                return struct.pack("<III", dev.trace.mask, dev.trace.rows_available, dev.trace.lost_rows) + data
        if cmd is Cmd.LIVE_CONFIGURE:
            _expect_len(p, 4, cmd)
            (mask,) = struct.unpack("<I", p)
            if mask >> len(SIGNAL_NAMES):
                raise CommandError(ErrorCode.BAD_VALUE, f"live mask 0x{mask:X} selects unknown signals")
            self.live_mask = mask
            self._live_index = _mask_index(mask)
            return b""
        if cmd is Cmd.SAMPLE:
            _expect_len(p, 0, cmd)
            return self._sample()
        raise CommandError(ErrorCode.UNKNOWN_COMMAND, f"command {cmd.name} not handled")
