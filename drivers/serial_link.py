"""DriveLink over the drivebench serial protocol (docs/serial-protocol.md), via pyserial.

The [drive] section: transport = "serial", port (or url: a device path, a pty path or any pyserial URL such
as socket://127.0.0.1:29537), baudrate, timeout_s, retries, sync_period_s. The bench's own timing ("lockstep" |
"realtime") and fault-reset policy ("once" | "never") come from [bench] as LinkSettings.
"""

from __future__ import annotations

import math
import struct
import threading
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import serial

from drivers.contract import cia402
from drivers.api import attempt_all, DriveIdentity, DriveLink, DriveStatus, LinkSettings, LiveSample
from drivers.contract.errors import LinkError
from drivers.contract.comm_loss import EXTERNAL_HINT, CommLossConfig
from drivers.contract import last_resort as lr
from drivers.contract.control_watch import ControlWatch, local_control_line
from drivers.contract.serial_frames import (
    PROTOCOL_MAJOR, PROTOCOL_MINOR, RESPONSE_FLAG, SAMPLE_HEADER, Cmd, ErrorCode, Frame, FrameDecoder,
    encode_frame, fault_text, unpack_str8,
)
from drivers.contract.signals import SIGNAL_NAMES, TIME_COLUMN
from drivers.serial_config import SerialDriveConfig
from drivers.contract.trace_format import decode_rows, mask_for, selected_names

TRIGGER_IMMEDIATE = 0
MAX_CATCH_UP_SYNCS = 100          # real time: more SYNCs than this behind and the link re-anchors its clock


class SerialDriveLink(DriveLink):
    def __init__(self, config: SerialDriveConfig | Mapping[str, Any], base_dir: Path, settings: LinkSettings):
        cfg = SerialDriveConfig.from_mapping(config)
        if not isinstance(cfg.port, str) or not cfg.port:
            raise ValueError("[drive] port: required for transport 'serial' (a device path or pyserial URL)")
        self.url = cfg.port
        self.baudrate = int(cfg.baudrate)
        self.timeout_s = float(cfg.timeout_s)
        self.retries = int(cfg.retries)
        self.sync_period_s = float(cfg.sync_period_s)
        self.timing = settings.timing
        self.fault_reset_policy = settings.fault_reset
        self._quick_stop_state: cia402.State | None = None     # set by begin_quick_stop, taken by quick_stop
        self.standstill_mech_rad_s = float(cfg.standstill_mech_rad_s)
        self.stop_timeout_s = float(cfg.stop_timeout_s)
        self.report: dict = {}                 # what the link read and set, for the record
        self.comm_loss = CommLossConfig.from_section(cfg)
        self._watchdog_armed = False
        self.control = ControlWatch(tuple(cfg.enable_bits or ()))    # statusword bit 9 and [drive] enable_bits
        self._reference_speed = None
        if self.timeout_s <= 0 or self.retries < 0 or self.sync_period_s <= 0:
            raise ValueError("[drive] timeout_s and sync_period_s must be > 0 and retries >= 0")
        self.base_dir = base_dir
        self.stats = {"crc_errors": 0, "seq_errors": 0, "timeouts": 0, "retries": 0, "requests": 0,
                      "realtime_overruns": 0}
        self.control_period_s = 0.0
        self.sync_steps = 1
        self.parameters: tuple[str, ...] = ()
        self.identity: DriveIdentity | None = None
        self.live_mask = (1 << len(SIGNAL_NAMES)) - 1
        self.trace_lost_rows = 0
        self._port: serial.SerialBase | None = None
        self._decoder = FrameDecoder()
        self._seq = 0
        self._rt_anchor: float | None = None
        self._rt_sent = 0
        self._names_cache: dict[int, list[str]] = {}
        self._line = threading.RLock()
        self._emcy_codes: list[int] = []      # read with any STATUS, handed over by status()
        self.where = f"serial drive {self.url}"

    # --- transport -------------------------------------------------------------------------------------------

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFF
        return self._seq

    def _read_reply(self, seq: int, deadline: float) -> tuple[Frame | None, bool]:
        """Wait for the reply with this seq. Returns (frame or None on timeout, saw a CRC error)."""
        port = self._port
        crc_seen = False
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                # quiet inside a frame: maybe a corrupted length; look for our reply past its first byte
                before = self._decoder.crc_errors
                frames = self._decoder.resync()
                self.stats["crc_errors"] += self._decoder.crc_errors - before
                for frame in frames:
                    if frame.seq == seq and frame.cmd & RESPONSE_FLAG:
                        return frame, True
                return None, crc_seen
            port.timeout = left
            try:
                data = port.read(self._decoder.bytes_wanted())
            except (serial.SerialException, OSError) as exc:
                raise LinkError(f"serial drive {self.url}: {exc}") from None
            before = self._decoder.crc_errors
            frames = self._decoder.feed(data)
            if self._decoder.crc_errors != before:
                self.stats["crc_errors"] += self._decoder.crc_errors - before
                crc_seen = True
            for frame in frames:
                if frame.seq == seq and frame.cmd & RESPONSE_FLAG:
                    return frame, crc_seen
                self.stats["seq_errors"] += 1       # a stale or foreign reply: not ours, drop it
            if crc_seen and not self._decoder.buffer:
                return None, True                   # our reply was mangled: ask again now, not at the timeout

    def _transact(self, cmd: Cmd, payload: bytes = b"") -> bytes:
        """One request and its reply; one at a time (the bench's command and telemetry threads share the line)."""
        with self._line:
            return self._transact_locked(cmd, payload)

    def _transact_locked(self, cmd: Cmd, payload: bytes) -> bytes:
        if self._port is None:
            raise LinkError(f"serial drive {self.url}: link not open")
        seq = self._next_seq()
        frame = encode_frame(seq, cmd, payload)
        self.stats["requests"] += 1
        problems: list[str] = []
        for attempt in range(self.retries + 1):
            if attempt:
                self.stats["retries"] += 1
            try:
                self._port.write(frame)
            except (serial.SerialException, OSError) as exc:
                raise LinkError(f"serial drive {self.url}: write failed: {exc}") from None
            reply, crc_seen = self._read_reply(seq, time.monotonic() + self.timeout_s)
            if reply is None:
                if crc_seen:
                    problems.append("CRC error")
                else:
                    self.stats["timeouts"] += 1
                    problems.append(f"timeout {self.timeout_s:g} s")
                continue
            if reply.cmd == Cmd.ERROR | RESPONSE_FLAG:
                raise LinkError(f"serial drive {self.url}: {cmd.name} rejected: {self._error_text(reply.payload)}")
            if reply.cmd != cmd | RESPONSE_FLAG:
                raise LinkError(f"serial drive {self.url}: {cmd.name} (seq {seq}) answered by command "
                                f"0x{reply.cmd:02X}")
            return reply.payload
        raise LinkError(f"serial drive {self.url}: no valid reply to {cmd.name} (seq {seq}) after "
                        f"{self.retries + 1} attempts: {', '.join(problems)}")

    @staticmethod
    def _error_text(payload: bytes) -> str:
        if len(payload) < 2:
            return "error reply without a code"
        try:
            code = ErrorCode(payload[1]).name
        except ValueError:
            code = f"code {payload[1]}"
        return f"{payload[2:].decode(errors='replace')} ({code})"

    # --- DriveLink --------------------------------------------------------------------------------------------

    def open(self) -> DriveIdentity:
        self.close()
        self._decoder = FrameDecoder()
        try:
            self._port = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=self.timeout_s,
                                               write_timeout=max(self.timeout_s, 1.0))
        except (serial.SerialException, OSError, ValueError) as exc:
            raise LinkError(f"serial drive {self.url}: cannot open: {exc}") from None
        self._port.reset_input_buffer()
        hello = self._transact(Cmd.HELLO, bytes([PROTOCOL_MAJOR, PROTOCOL_MINOR]))
        major, minor, _max_payload, period, n_signals = struct.unpack("<BBHdB", hello[:13])
        if major != PROTOCOL_MAJOR:
            raise LinkError(f"serial drive {self.url}: drive speaks protocol {major}.{minor}, "
                            f"this bench {PROTOCOL_MAJOR}.{PROTOCOL_MINOR}")
        if n_signals != len(SIGNAL_NAMES):
            raise LinkError(f"serial drive {self.url}: drive has {n_signals} signals, catalogue has "
                            f"{len(SIGNAL_NAMES)}")
        self.control_period_s = period
        self.sync_steps = max(1, round(self.sync_period_s / period))
        ident = self._transact(Cmd.IDENTITY)
        vendor, product, revision, serial_no, flags = struct.unpack_from("<IIIIB", ident)
        name, offset = unpack_str8(ident, 17)
        firmware, _ = unpack_str8(ident, offset)
        self.identity = DriveIdentity(vendor, product, revision, serial_no, name, firmware, bool(flags & 1))
        plist = self._transact(Cmd.PARAM_LIST)
        names, offset = [], 1
        for _ in range(plist[0]):
            n, offset = unpack_str8(plist, offset)
            names.append(n)
        self.parameters = tuple(names)
        return self.identity

    def _arm_watchdog(self) -> None:
        """The drive's own reaction to a silent bench (serial WATCHDOG, protocol 1.1: CiA 402 0x6007 codes)."""
        cfg = self.comm_loss
        if cfg.mode == "external":
            self.report["comm_loss"] = {"mode": "external", "external_stop": cfg.external_stop,
                                        "note": "the rig stops the drive by other means: unverified comm-loss reaction"}
            return
        self._transact(Cmd.WATCHDOG, struct.pack("<Hh", cfg.consumer_time_ms, cfg.abort_option))
        self._watchdog_armed = True
        self.report["comm_loss"] = {"mode": "watchdog", "timeout_ms": cfg.consumer_time_ms,
                                    "reaction": f"{cfg.abort_option} (0x6007 code)"}

    def configure(self, live_signals: Sequence[str], trace_signals: Sequence[str], trace_decimation: int) -> None:
        try:
            live_mask = mask_for(tuple(live_signals))
            trace_mask = mask_for(tuple(trace_signals))
        except ValueError as exc:
            raise LinkError(f"serial drive {self.url}: {exc}") from None
        self._arm_watchdog()
        self._transact(Cmd.LIVE_CONFIGURE, struct.pack("<I", live_mask))
        self.live_mask = live_mask
        if self.identity and self.identity.has_trace_recorder and trace_mask:
            self._transact(Cmd.TRACE_CONFIGURE, struct.pack("<IHB", trace_mask, trace_decimation, TRIGGER_IMMEDIATE))
            self._transact(Cmd.TRACE_START)

    def drill(self, before_withhold=None) -> dict:
        """The bench-death drill on the serial line: enabled at zero velocity, the bench sends nothing for the watchdog
        time plus a margin (any request feeds the drive's WATCHDOG), then reads the status once: the drive must have
        left OPERATION ENABLED. Then the power stage off (a fault the drill caused reset) and the run goes on."""
        cfg = self.comm_loss
        if cfg.mode == "external":
            return {"what": "drive", "result": "unverified", "mode": "external", "external_stop": cfg.external_stop,
                    "note": "not drilled: the bench config states the rig's own stop chain; nothing proves it"}
        self.enable_velocity_mode()
        if before_withhold is not None:
            before_withhold()
        report = {"what": "drive", "mode": "watchdog", "consumer_ms": cfg.consumer_time_ms, "margin_ms": cfg.margin_ms}
        with self._line:                     # nothing reaches the drive while it is left alone
            withheld = time.monotonic()
            time.sleep((cfg.consumer_time_ms + cfg.margin_ms) / 1000.0)
            silent_ms = (time.monotonic() - withheld) * 1e3
        word = self.read_statusword()
        state = cia402.decode(word)
        report.update(silent_ms=round(silent_ms, 1), state_after=cia402.state_name(word))
        if state in cia402.FAULT_STATES:
            cia402.fault_reset(self, self._step_timeout_s, self.where)
        elif state in cia402.POWERED_STATES:
            self.disable()
        self._emcy_codes.clear()
        if state is not cia402.State.OPERATION_ENABLED:
            report.update(result="passed", left_operation_enabled_ms=round(silent_ms, 1),
                          note="one status read after the silence (any request feeds the watchdog): a bound")
            return report
        report["result"] = "failed"
        report["refusal"] = (f"{self.where}: comm-loss drill failed: the drive stayed OPERATION ENABLED {silent_ms:.0f} "
                             f"ms after the bench's last request (watchdog {cfg.consumer_time_ms} ms + margin "
                             f"{cfg.margin_ms} ms); where the rig stops it by other means write [drive] "
                             f"{EXTERNAL_HINT}")
        return report

    def keepalive(self) -> None:
        """Any request feeds the drive's WATCHDOG: a status read (its EMCY codes kept for status())."""
        self._read_status()

    def write_controlword(self, word: int) -> int:
        """cia402 port: the drive answers a controlword with its statusword."""
        (status,) = struct.unpack("<H", self._transact(Cmd.CONTROLWORD, struct.pack("<H", word)))
        return status

    def _read_status(self) -> tuple[int, int]:
        p = self._transact(Cmd.STATUS)
        statusword, error_code, _mode, _step, n = struct.unpack_from("<HHbQB", p)
        self._emcy_codes.extend(struct.unpack_from(f"<{n}H", p, 14))
        return statusword, error_code

    def read_statusword(self) -> int:
        return self._read_status()[0]

    @property
    def _step_timeout_s(self) -> float:
        return max(1.0, 4 * self.timeout_s)

    def set_reference_speed(self, speed) -> None:
        self._reference_speed = speed

    def enable_velocity_mode(self) -> None:
        word = self.read_statusword()
        if not word & cia402.StatusBit.REMOTE:
            raise LinkError(f"{self.where}: {local_control_line(word)}")
        cia402.enable_operation(self, fault_reset_policy=self.fault_reset_policy, timeout_s=self._step_timeout_s,
                                where=self.where, select_mode=lambda: self._transact(
                                    Cmd.MODE, struct.pack("<b", cia402.Mode.PROFILE_VELOCITY)),
                                fault_detail=lambda: fault_text(self._read_status()[1]))

    def set_speed_ref(self, speed_mech_rad_s: float) -> None:
        self._transact(Cmd.TARGET_VELOCITY, struct.pack("<d", speed_mech_rad_s))

    def write_parameter(self, name: str, value: float) -> None:
        self._transact(Cmd.PARAM_WRITE_NAME, struct.pack("<d", value) + name.encode())

    def write_parameter_index(self, index: int, value: float) -> None:
        self._transact(Cmd.PARAM_WRITE_INDEX, struct.pack("<Hd", index, value))

    def _decode_sample(self, p: bytes) -> LiveSample:
        step, status, _error, mask = SAMPLE_HEADER.unpack_from(p)
        self.control.feed(status)
        names = self._names_cache.get(mask)
        if names is None:
            names = self._names_cache[mask] = selected_names(mask)
        values = np.frombuffer(p, dtype="<f8", count=len(names), offset=SAMPLE_HEADER.size)
        return LiveSample(step * self.control_period_s, dict(zip(names, values.tolist())))

    def sample(self) -> LiveSample:
        """The drive's latest sample, without advancing its clock."""
        return self._decode_sample(self._transact(Cmd.SAMPLE))

    def _sync_once(self) -> LiveSample:
        return self._decode_sample(self._transact(Cmd.SYNC, struct.pack("<I", self.sync_steps)))

    def sync(self) -> list[LiveSample]:
        if self.timing == "lockstep":
            return [self._sync_once()]
        # Real time: SYNCs paced by the wall clock; drive time = n_syncs * sync period tracks it.
        period = self.sync_steps * self.control_period_s
        now = time.monotonic()
        if self._rt_anchor is None:
            self._rt_anchor, self._rt_sent = now, 0
        due = int((now - self._rt_anchor) / period) + 1 - self._rt_sent
        if due <= 0:
            time.sleep(self._rt_anchor + self._rt_sent * period - now)
            due = 1
        if due > MAX_CATCH_UP_SYNCS:
            self.stats["realtime_overruns"] += 1
            self._rt_anchor = now - (self._rt_sent + MAX_CATCH_UP_SYNCS - 1) * period
            due = MAX_CATCH_UP_SYNCS
        samples = [self._sync_once() for _ in range(due)]
        self._rt_sent += due
        return samples

    def fetch_trace(self) -> dict[str, np.ndarray] | None:
        if not (self.identity and self.identity.has_trace_recorder):
            return None
        chunks: list[dict[str, np.ndarray]] = []
        mask = 0
        for _ in range(100_000):
            p = self._transact(Cmd.TRACE_READ, struct.pack("<H", 0xFFFF))
            mask, remaining, lost = struct.unpack_from("<III", p)
            self.trace_lost_rows = lost
            if len(p) > 12:
                try:
                    chunks.append(decode_rows(p[12:], mask, self.control_period_s))
                except ValueError as exc:
                    raise LinkError(f"serial drive {self.url}: trace upload: {exc}") from None
            if remaining == 0:
                break
        if not chunks:
            return {TIME_COLUMN: np.zeros(0), **{n: np.zeros(0) for n in selected_names(mask)}}
        return {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}

    def status(self) -> DriveStatus:
        statusword, _error_code = self._read_status()
        self.control.feed(statusword)
        codes, self._emcy_codes = self._emcy_codes, []
        return DriveStatus(state=cia402.state_name(statusword), fault=cia402.decode(statusword) in cia402.FAULT_STATES,
                           heartbeat_ok=True, emcy=[(c, fault_text(c)) for c in codes],
                           warning=bool(statusword & cia402.StatusBit.WARNING), control_lost=self.control.lost)

    def begin_quick_stop(self) -> None:
        """The quick-stop command alone, state confirmed: the safe stop's first step, before the load machine is
        touched; quick_stop() then waits for standstill."""
        self.control.refuse(self.where, "quick stop")
        self._quick_stop_state = cia402.quick_stop(self, self._step_timeout_s, self.where)

    def quick_stop(self) -> None:
        """Quick stop (unless begin_quick_stop gave it), then wait (bounded) until the shaft is below the standstill
        threshold."""
        state, self._quick_stop_state = self._quick_stop_state, None
        self.control.refuse(self.where, "quick stop")
        if state is None:
            state = cia402.quick_stop(self, self._step_timeout_s, self.where)
        if state is cia402.State.FAULT:
            return
        latest: list[LiveSample] = []

        def advance() -> None:
            if self.timing == "lockstep":
                latest[:] = [self._sync_once()]
            else:
                time.sleep(max(self.sync_period_s, 0.01))
                latest[:] = [self.sample()]

        def speed() -> float | None:
            return latest[-1].values.get("speed_est_mech_rad_s") if latest else None

        advances = math.ceil(self.stop_timeout_s / self.sync_period_s) if self.timing == "lockstep" else None
        self.report["stop"] = cia402.wait_standstill(advance, speed, self.standstill_mech_rad_s, self.stop_timeout_s,
                                                     advances)

    def disable(self) -> None:
        # disable voltage: power stage off from every state (shutdown 0x06 is refused in QUICK STOP ACTIVE)
        self.control.refuse(self.where, "disable voltage")
        attempt_all(lambda: self.set_speed_ref(0.0),
                    lambda: cia402.disable_voltage(self, self._step_timeout_s, self.where))

    def close(self) -> None:
        if self._port is not None:
            if self._watchdog_armed and not self._secured():
                self._watchdog_armed = False     # left armed in the drive: the bench goes silent, the drive reacts
            if self._watchdog_armed:             # a normal end: the bench leaves, the drive need not react
                try:
                    self._transact(Cmd.WATCHDOG, struct.pack("<Hh", 0, self.comm_loss.abort_option))
                    self._watchdog_armed = False
                except LinkError:
                    pass
            self._port.close()
            self._port = None

    @property
    def last_resort_bound_s(self) -> float:
        return (self.comm_loss.consumer_time_ms + self.comm_loss.margin_ms) / 1000.0 + self.stop_timeout_s + lr.MARGIN_S

    def secure(self) -> str | None:
        if not self._watchdog_armed:
            return None
        secured = self._secured()
        if not secured:
            self._watchdog_armed = False   # left armed in the drive
        return self.report["last_resort"]["line"] if "last_resort" in self.report else None

    def _secured(self) -> bool:
        """Disabled: the WATCHDOG may be switched off. Else the last resort, silent for the watchdog's time (any
        request feeds it), the reference sensor watched (drivers.contract.last_resort.request_fed_last_resort)."""
        if self.report.get("last_resort") is None:
            quiet_s = (self.comm_loss.consumer_time_ms + self.comm_loss.margin_ms) / 1000.0
            result = lr.request_fed_last_resort(lambda: self._read_status()[0], self._reference_speed,
                                                self.standstill_mech_rad_s, quiet_s, self.stop_timeout_s)
            if result is None:
                return True
            self.report["last_resort"] = result
            lr.announce(f"{self.where}: {result['line']}")
        return self.report["last_resort"].get("outcome") == "stopped itself"
