"""Serial drive link against the simulated drive over TCP and a pty: round trips, determinism, bad bytes."""

import socket
import struct
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.contract.errors import LinkError
from drivers.contract.serial_frames import RESPONSE_FLAG, Cmd, ErrorCode, FrameDecoder, encode_frame
from drivers.api import LinkSettings
from drivers.contract.cia402 import state_name as state_from_statusword
from drivers.serial_link import SerialDriveLink
from drivers.contract.signals import SIGNAL_NAMES
from sim_backend.device import SimulatedDevice
from sim_backend.serial_server import SerialProtocolHandler, start_serial_pty, start_serial_tcp
from sim_backend.toy import ToyDrive

LIVE = ["speed_ref_mech_rad_s", "speed_est_mech_rad_s", "i_sy_a", "torque_load_nm"]
TRACE = ["speed_est_mech_rad_s", "i_sy_a"]


def make_link(url: str, **extra) -> SerialDriveLink:
    settings = LinkSettings(**{k: extra.pop(k) for k in ("timing", "fault_reset") if k in extra})
    section = {"transport": "serial", "port": url, "timeout_s": 2.0, "sync_period_s": 0.001} | extra
    return SerialDriveLink(section, Path("."), settings)


@pytest.fixture(params=["tcp", "pty"])
def served(request):
    device = SimulatedDevice(ToyDrive())
    server = start_serial_tcp(device) if request.param == "tcp" else start_serial_pty(device)
    url = server.url if request.param == "tcp" else server.path
    yield device, server, url
    server.stop()
    assert server.error is None


def test_round_trip_enable_speed_sync_trace(served):
    device, server, url = served
    link = make_link(url)
    ident = link.open()
    assert ident.device_name == "drivebench simulated PMSM drive" and ident.has_trace_recorder   # as over CANopen
    assert link.control_period_s == pytest.approx(1e-4) and link.sync_steps == 10
    assert "flux_est_scale" in link.parameters and "plant_rs" in link.parameters
    link.configure(LIVE, TRACE, 2)
    assert link.status().state == "SWITCH ON DISABLED"
    link.enable_velocity_mode()
    assert link.status().state == "OPERATION ENABLED"
    link.set_speed_ref(80.0)
    samples = [s for _ in range(300) for s in link.sync()]
    assert [s.t_s for s in samples[:3]] == pytest.approx([0.001, 0.002, 0.003])
    assert samples[-1].t_s == pytest.approx(0.3)
    assert set(samples[-1].values) == set(LIVE)
    speed = samples[-1].values["speed_est_mech_rad_s"]
    assert 80.0 * (1 - np.exp(-0.3 / 0.05)) * 0.98 < speed < 80.0     # the toy's 50 ms lag
    assert speed == device.latest[SIGNAL_NAMES.index("speed_est_mech_rad_s")]
    trace = link.fetch_trace()
    assert set(trace) == {"t_s", *TRACE}
    assert len(trace["t_s"]) == 3000 // 2 and trace["t_s"][0] == pytest.approx(0.0002)
    assert np.all(np.diff(trace["t_s"]) > 0)
    assert trace["speed_est_mech_rad_s"][-1] == pytest.approx(speed, rel=1e-6)   # float32 rows
    assert len(link.fetch_trace()["t_s"]) == 0
    link.write_parameter("flux_est_scale", 0.5)
    link.write_parameter_index(link.parameters.index("plant_rs"), 1.5)
    assert device.model.hooks["flux_est_scale"] == 0.5 and device.model.plant_factors["plant_rs"] == 1.5
    sample = link.sample()
    assert sample.t_s == pytest.approx(0.3)                              # SAMPLE does not advance
    link.quick_stop()                  # brakes to standstill on the quick-stop ramp, then off by itself (0x605A = 2)
    assert link.report["stop"]["standstill"] and abs(device.model.load_feedback()[0]) <= 0.5
    assert link.status().state == "SWITCH ON DISABLED" and not device.device.power_enabled
    link.disable()
    assert link.status().state == "SWITCH ON DISABLED" and not device.device.power_enabled
    link.enable_velocity_mode()
    link.quick_stop()
    link.enable_velocity_mode()                                  # from quick stop, as a next run finds it
    assert link.status().state == "OPERATION ENABLED"
    link.disable()
    link.close()
    assert link.stats["crc_errors"] == link.stats["retries"] == link.stats["seq_errors"] == 0
    assert server.stats["crc_errors"] == 0


def test_parameter_and_value_errors_are_clear(served):
    _, _, url = served
    link = make_link(url)
    link.open()
    with pytest.raises(LinkError, match=r"PARAM_WRITE_NAME rejected: unknown parameter 'no_such_hook'"):
        link.write_parameter("no_such_hook", 1.0)
    with pytest.raises(LinkError, match=r"parameter index 999 out of range"):
        link.write_parameter_index(999, 1.0)
    with pytest.raises(LinkError, match=r"not finite"):
        link.set_speed_ref(float("nan"))
    link.close()


def test_fault_shows_in_status_and_is_reset_at_enable(served):
    device, _, url = served
    link = make_link(url)
    link.open()
    link.enable_velocity_mode()
    device.model.raise_fault(0x2310)
    link.sync()
    status = link.status()
    assert status.fault and status.state == "FAULT" and status.emcy == [(0x2310, "overcurrent")]
    assert link.status().emcy == []                    # EMCY codes are reported once
    link.close()                                       # one client holds the line at a time
    strict = make_link(url, fault_reset="never")
    strict.open()
    with pytest.raises(LinkError, match=r"drive is in FAULT \(overcurrent\) and the fault-reset policy is 'never'"):
        strict.enable_velocity_mode()
    strict.close()
    link = make_link(url)
    link.open()
    link.enable_velocity_mode()                        # fault_reset = "once": rising edge of bit 7, then enable
    assert link.status().state == "OPERATION ENABLED" and device.model.fault_code() == 0
    link.close()


def test_statusword_decoding():
    assert state_from_statusword(0x0250) == "SWITCH ON DISABLED"
    assert state_from_statusword(0x0231) == "READY TO SWITCH ON"
    assert state_from_statusword(0x0637) == "OPERATION ENABLED"
    assert state_from_statusword(0x0207) == "QUICK STOP ACTIVE"
    assert state_from_statusword(0x0208) == "FAULT"


def script(run_sync, set_ref, write_param):
    out = []
    set_ref(50.0)
    out += [run_sync() for _ in range(150)]
    write_param("flux_est_scale", 0.7)
    set_ref(-20.0)
    out += [run_sync() for _ in range(150)]
    return np.array(out)


def test_serial_telemetry_identical_to_in_process():
    """The same command sequence over the wire and straight into the device gives the same bits."""
    direct = SimulatedDevice(ToyDrive())
    for word in (0x06, 0x07, 0x0F):
        direct.write_controlword(word)

    def direct_sync():
        direct.advance(10)
        return direct.latest.copy()

    def direct_ref(v):
        direct.target_speed_mech_rad_s = v

    expected = script(direct_sync, direct_ref, direct.write_named)

    device = SimulatedDevice(ToyDrive())
    with start_serial_tcp(device) as server:
        link = make_link(server.url)
        link.open()
        link.configure(SIGNAL_NAMES, ["speed_est_mech_rad_s"], 1)
        link.enable_velocity_mode()
        def serial_sync():
            values = link.sync()[0].values
            return [values[n] for n in SIGNAL_NAMES]

        got = script(serial_sync, link.set_speed_ref, link.write_parameter)
        link.close()
    assert got.shape == expected.shape == (300, len(SIGNAL_NAMES))
    assert np.array_equal(got, expected)
    assert np.any(got[:, SIGNAL_NAMES.index("speed_est_mech_rad_s")] < 0)


def test_realtime_mode_paces_drive_time_to_wall_clock():
    device = SimulatedDevice(ToyDrive())
    with start_serial_tcp(device) as server:
        link = make_link(server.url, timing="realtime", sync_period_s=0.01)
        link.open()
        start = time.monotonic()
        samples = []
        while time.monotonic() - start < 0.3:
            before = time.monotonic() - start
            samples += link.sync()
            after = time.monotonic() - start
        link.close()
    t_drive = samples[-1].t_s
    assert np.all(np.diff([s.t_s for s in samples]) == pytest.approx(0.01))
    # every SYNC due when the last call began was sent, none before its time
    assert before - 0.05 < t_drive <= after + 0.01 + 1e-9


# --- bad bytes -------------------------------------------------------------------------------------------------

class ManglingProxy:
    """TCP proxy between link and server; `to_client`/`to_server` callables may rewrite each chunk."""

    def __init__(self, target_port: int):
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.target_port = target_port
        self.to_client = lambda data: data
        self.to_server = lambda data: data
        self.threads = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self):
        try:
            client, _ = self.listener.accept()
        except OSError:
            return
        upstream = socket.create_connection(("127.0.0.1", self.target_port))
        for src, dst, attr in ((client, upstream, "to_server"), (upstream, client, "to_client")):
            t = threading.Thread(target=self._pump, args=(src, dst, attr), daemon=True)
            t.start()
            self.threads.append(t)
        self.socks = (client, upstream)

    def _pump(self, src, dst, attr):
        while True:
            try:
                data = src.recv(65536)
            except OSError:
                return
            if not data:
                dst.close()
                return
            data = getattr(self, attr)(data)
            if data:
                try:
                    dst.sendall(data)
                except OSError:
                    return

    def close(self):
        self.listener.close()
        for s in getattr(self, "socks", ()):
            try:
                s.shutdown(socket.SHUT_RDWR)    # wakes the pump threads blocked in recv
            except OSError:
                pass
            s.close()


def corrupt_first(n: int):
    """A mangler that flips one bit in the last byte of the first n chunks."""
    left = [n]

    def mangle(data: bytes) -> bytes:
        if left[0] > 0:
            left[0] -= 1
            return data[:-1] + bytes([data[-1] ^ 0x10])
        return data
    return mangle


@pytest.fixture
def proxied():
    device = SimulatedDevice(ToyDrive())
    server = start_serial_tcp(device)
    proxy = ManglingProxy(server.port)
    yield device, server, proxy
    proxy.close()
    server.stop()


def test_corrupted_reply_is_retried_and_sync_executes_once(proxied):
    device, server, proxy = proxied
    link = make_link(f"socket://127.0.0.1:{proxy.port}", timeout_s=5.0)
    link.open()
    link.enable_velocity_mode()
    proxy.to_client = corrupt_first(2)
    start = time.monotonic()
    sample = link.sync()[0]
    assert time.monotonic() - start < 4.0          # resent at once on the CRC error, not after the timeout
    assert link.stats["crc_errors"] == 2 and link.stats["retries"] == 2
    assert sample.t_s == pytest.approx(0.001) and device.step_count == 10    # retried SYNC advanced once
    assert link.sync()[0].t_s == pytest.approx(0.002)
    link.close()


def test_corrupted_request_is_dropped_by_the_drive_then_retried(proxied):
    device, server, proxy = proxied
    link = make_link(f"socket://127.0.0.1:{proxy.port}", timeout_s=0.3)
    link.open()
    proxy.to_server = corrupt_first(1)
    assert link.sync()[0].t_s == pytest.approx(0.001)
    assert server.stats["crc_errors"] == 1 and link.stats["timeouts"] == 1 and link.stats["retries"] == 1
    link.close()


def test_persistent_corruption_gives_a_clear_link_error(proxied):
    _, _, proxy = proxied
    link = make_link(f"socket://127.0.0.1:{proxy.port}", timeout_s=1.0, retries=2)
    link.open()
    proxy.to_client = corrupt_first(10**9)
    with pytest.raises(LinkError, match=r"no valid reply to SYNC \(seq \d+\) after 3 attempts: CRC error, "
                                        r"CRC error, CRC error"):
        link.sync()
    assert link.stats["crc_errors"] == 3
    link.close()


class FakeDrive:
    """A TCP 'drive' whose replies a test scripts: reply(frame) -> bytes to send (may be empty)."""

    def __init__(self, reply):
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.url = f"socket://127.0.0.1:{self.listener.getsockname()[1]}"
        self.reply = reply
        self.received = []
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self):
        try:
            conn, _ = self.listener.accept()
        except OSError:
            return
        self.conn = conn
        dec = FrameDecoder()
        while True:
            try:
                data = conn.recv(4096)
            except OSError:
                return
            if not data:
                return
            for frame in dec.feed(data):
                self.received.append(frame)
                out = self.reply(frame)
                if out:
                    conn.sendall(out)

    def close(self):
        self.listener.close()
        if hasattr(self, "conn"):
            try:
                self.conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            self.conn.close()


def test_wrong_sequence_numbers_are_dropped_then_link_error():
    fake = FakeDrive(lambda f: encode_frame(f.seq + 1, f.cmd | RESPONSE_FLAG, b""))
    link = make_link(fake.url, timeout_s=0.2, retries=1)
    with pytest.raises(LinkError, match=r"no valid reply to HELLO \(seq 1\) after 2 attempts: timeout"):
        link.open()
    assert link.stats["seq_errors"] == 2 and link.stats["timeouts"] == 2
    link.close()
    fake.close()


def test_stale_reply_before_the_right_one_is_skipped():
    device = SimulatedDevice(ToyDrive())
    handler = SerialProtocolHandler(device)

    def reply(frame):
        stale = encode_frame(frame.seq - 1, frame.cmd | RESPONSE_FLAG, b"old")
        return stale + handler.handle(frame)

    fake = FakeDrive(reply)
    link = make_link(fake.url)
    link.open()
    assert link.sync()[0].t_s == pytest.approx(0.001)
    assert link.stats["seq_errors"] == 4 and link.stats["retries"] == 0    # HELLO, IDENTITY, PARAM_LIST, SYNC
    link.close()
    fake.close()


def test_silent_drive_times_out_with_clear_error():
    fake = FakeDrive(lambda f: b"")
    link = make_link(fake.url, timeout_s=0.2, retries=2)
    start = time.monotonic()
    with pytest.raises(LinkError, match=r"HELLO \(seq 1\) after 3 attempts: timeout 0.2 s, timeout 0.2 s, timeout"):
        link.open()
    assert time.monotonic() - start < 5.0
    assert len(fake.received) == 3 and {f.seq for f in fake.received} == {1}     # retries keep the SEQ
    link.close()
    fake.close()


def test_unknown_command_gets_an_error_reply_on_the_wire():
    device = SimulatedDevice(ToyDrive())
    with start_serial_tcp(device) as server:
        with socket.create_connection(("127.0.0.1", server.port), timeout=5) as sock:
            sock.sendall(encode_frame(7, 0x55, b"\x01\x02"))
            dec = FrameDecoder()
            frames = []
            while not frames:
                frames = dec.feed(sock.recv(4096))
    (frame,) = frames
    assert frame.seq == 7 and frame.cmd == Cmd.ERROR | RESPONSE_FLAG
    assert frame.payload[:2] == bytes([0x55, ErrorCode.UNKNOWN_COMMAND])
    assert frame.payload[2:] == b"unknown command 0x55"


def test_bad_length_and_version_errors():
    handler = SerialProtocolHandler(SimulatedDevice(ToyDrive()))
    dec = FrameDecoder()
    (short,) = dec.feed(handler.handle(next(iter(FrameDecoder().feed(encode_frame(1, Cmd.SYNC, b"\x01"))))))
    assert short.payload[1] == ErrorCode.BAD_LENGTH
    (version,) = dec.feed(handler.handle(next(iter(FrameDecoder().feed(encode_frame(2, Cmd.HELLO, b"\x02\x00"))))))
    assert version.payload[1] == ErrorCode.VERSION and b"protocol 2.0 unsupported" in version.payload


def test_protocol_error_reply_reaches_the_link_as_link_error():
    device = SimulatedDevice(ToyDrive())
    with start_serial_tcp(device) as server:
        link = make_link(server.url)
        link.open()
        with pytest.raises(LinkError, match=r"SYNC rejected: SYNC of 0 steps outside 1..1000000 \(BAD_VALUE\)"):
            link._transact(Cmd.SYNC, struct.pack("<I", 0))
        link.close()


def test_unopenable_port_is_a_link_error():
    link = make_link("/dev/does-not-exist-drivebench")
    with pytest.raises(LinkError, match="cannot open"):
        link.open()


def test_missing_port_is_a_config_error():
    with pytest.raises(ValueError, match=r"\[drive\] port: required"):
        SerialDriveLink({"transport": "serial"}, Path("."), LinkSettings())


def bogus_header(length: int = 60000) -> bytes:
    """A corrupted header that still passes its CRC-8: it announces a payload that never comes."""
    from drivers.contract.serial_frames import crc8
    head = struct.pack("<HBB", length, 0x33, 0xC2)
    return b"\xa5\x5a" + head + bytes([crc8(head)])


def test_drive_resyncs_past_a_header_announcing_a_payload_that_never_comes():
    device = SimulatedDevice(ToyDrive())
    with start_serial_tcp(device) as server:
        with socket.create_connection(("127.0.0.1", server.port), timeout=10) as sock:
            sock.sendall(bogus_header() + encode_frame(9, Cmd.SAMPLE))
            dec = FrameDecoder()
            frames = []
            while not frames:
                frames = dec.feed(sock.recv(4096))
    assert frames[0].seq == 9 and frames[0].cmd == Cmd.SAMPLE | RESPONSE_FLAG
    assert server.stats["crc_errors"] >= 1


def test_link_resyncs_past_a_header_announcing_a_payload_that_never_comes(proxied):
    device, _, proxy = proxied
    link = make_link(f"socket://127.0.0.1:{proxy.port}", timeout_s=0.5)
    link.open()
    sent = [False]

    def prepend_bogus(data: bytes) -> bytes:
        if not sent[0]:
            sent[0] = True
            return bogus_header() + data
        return data

    proxy.to_client = prepend_bogus
    assert link.sync()[0].t_s == pytest.approx(0.001)
    assert link.stats["crc_errors"] >= 1 and link.stats["retries"] == 0    # found in the buffer, not resent
    assert device.step_count == 10
    link.close()


def test_a_simulator_exception_is_answered_not_silent():
    class Broken(ToyDrive):
        def step(self, n):
            raise FloatingPointError("plant diverged")

    with start_serial_tcp(SimulatedDevice(Broken())) as server:
        link = make_link(server.url)
        link.open()
        with pytest.raises(LinkError, match=r"SYNC rejected: drive failure: FloatingPointError: plant diverged"):
            link.sync()
        assert link.status().state == "SWITCH ON DISABLED"       # the drive still answers
        link.close()
        assert server.error is None
