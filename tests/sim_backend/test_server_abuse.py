"""The simulator's protocol servers under abuse, on real sockets: bounded buffers and queues, an accept loop that
survives running out of file descriptors, a frame parser that resynchronises in bounded time, one bench at a time on
a served rig with every session starting from a restarted drive — and a normal client still served afterwards.
(The long version with more iterations: benchmarks/abuse.py.)"""

from __future__ import annotations

import os
import resource
import socket
import struct
import time
from pathlib import Path

import can
import pytest

from drivers.contract.errors import LinkError
from drivers.api import LinkSettings
from drivers.contract.serial_frames import SOF, Cmd, crc8
from drivers.serial_link import SerialDriveLink
from sim_backend.device import SimulatedDevice
from sim_backend.rig import RigSpec, build
from sim_backend.serial_server import start_serial_tcp
from sim_backend.toy import ToyDrive
from tests.canopen_helpers import EDS


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def handshake(port: int, timeout: float = 5.0) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=timeout)
    expect(sock, b"< hi >")
    sock.sendall(b"< open can0 >")
    expect(sock, b"< ok >")
    sock.sendall(b"< rawmode >")
    expect(sock, b"< ok >")
    return sock


def expect(sock: socket.socket, marker: bytes) -> bytes:
    data = b""
    while marker not in data:
        chunk = sock.recv(4096)
        assert chunk, f"closed before {marker!r}; got {data!r}"
        data += chunk
    return data


def sdo_read_device_type(sock: socket.socket) -> bytes:
    """An SDO upload of 0x1000 over raw socketcand text; the server's answer frame (node 1)."""
    sock.sendall(b"< send 601 8 40 0 10 0 0 0 0 0 >")
    return expect(sock, b"< frame 581 ")


@pytest.fixture
def can_rig(request):
    return request.getfixturevalue("served")[0]


def test_socketcand_line_without_end_is_bounded_and_the_client_dropped(can_rig):
    before = rss_mb()
    for handshake_done in (False, True):
        sock = handshake(can_rig.port) if handshake_done else socket.create_connection(("127.0.0.1", can_rig.port))
        try:
            chunk = b"A" * 65536
            for _ in range(512):                         # 32 MiB without '>'
                sock.sendall(chunk)
        except OSError:
            pass                                         # dropped mid-stream: what we want
        sock.close()
    assert can_rig.stats["dropped_long_line"] == 2
    assert rss_mb() - before < 5.0
    with handshake(can_rig.port) as sock:                # a normal client afterwards
        assert b"< frame 581 " in sdo_read_device_type(sock)


@pytest.mark.slow
def test_socketcand_client_that_never_reads_is_dropped_and_the_bus_goes_on(can_rig):
    before = rss_mb()
    idle = handshake(can_rig.port)
    idle.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sender = can.Bus(interface="virtual", channel=can_rig.channel, receive_own_messages=False)
    deadline = time.monotonic() + 20
    while can_rig.stats["dropped_slow_client"] == 0 and time.monotonic() < deadline:
        for k in range(160):                             # ~16,000 frames/s: a full 1 Mbit/s bus
            sender.send(can.Message(arbitration_id=0x123, data=struct.pack("<Q", k), is_extended_id=False))
        time.sleep(0.01)
    sender.shutdown()
    idle.close()
    assert can_rig.stats["dropped_slow_client"] >= 1
    assert rss_mb() - before < 5.0
    with handshake(can_rig.port) as sock:
        assert b"< frame 581 " in sdo_read_device_type(sock)


@pytest.mark.slow
def test_socketcand_accept_survives_running_out_of_descriptors(can_rig):
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    hogs = []
    try:
        resource.setrlimit(resource.RLIMIT_NOFILE, (len(os.listdir("/proc/self/fd")) + 8, hard))
        try:
            while True:
                hogs.append(socket.socket())
        except OSError:
            pass
        hogs.pop().close()                               # one descriptor for the client; none for the server
        client = socket.socket()
        client.settimeout(0.5)
        try:
            client.connect(("127.0.0.1", can_rig.port))  # the kernel completes it; the server's accept() fails
        except OSError:
            pass
        time.sleep(0.5)
        client.close()
    finally:
        for h in hogs:
            h.close()
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
    assert can_rig.stats["accept_errors"] >= 1
    time.sleep(1.2)                                      # the backoff ends
    with handshake(can_rig.port) as sock:
        assert b"< frame 581 " in sdo_read_device_type(sock)


def serial_link(url: str) -> SerialDriveLink:
    return SerialDriveLink({"transport": "serial", "port": url, "timeout_s": 1.0, "sync_period_s": 0.001},
                           Path("."), LinkSettings())


def test_serial_flood_of_maximum_length_headers_does_not_stall_the_line():
    device = SimulatedDevice(ToyDrive())
    server = start_serial_tcp(device)
    try:
        head = struct.pack("<HBB", 65535, 0, Cmd.SYNC)
        bogus = SOF + head + bytes([crc8(head)])         # a valid header announcing 64 KiB
        with socket.create_connection(("127.0.0.1", server.port)) as sock:
            t0 = time.monotonic()
            sock.sendall(bogus * (1 << 17))              # 1.4 MB of them
            sock.sendall(bytes(4096))
            elapsed = time.monotonic() - t0
        assert elapsed < 5.0
        time.sleep(0.3)
        link = serial_link(server.url)
        t0 = time.monotonic()
        link.open()
        assert time.monotonic() - t0 < 2.0               # answered at once: the line did not stall
        link.close()
    finally:
        server.stop()
    assert server.error is None


def test_serial_second_client_is_refused_busy_and_the_first_keeps_the_line():
    device = SimulatedDevice(ToyDrive())
    server = start_serial_tcp(device)
    try:
        first = serial_link(server.url)
        first.open()
        second = serial_link(server.url)
        with pytest.raises(LinkError, match="BUSY"):
            second.open()
        first.enable_velocity_mode()                     # the first bench still has its line
        assert first.status().state == "OPERATION ENABLED"
        first.close()
        third = serial_link(server.url)                  # once it left, the next one gets in
        third.open()
        third.close()
    finally:
        server.stop()
    assert server.stats["refused_busy"] == 1 and server.error is None


@pytest.mark.slow
def test_served_rig_one_bench_at_a_time_across_transports_each_from_a_restarted_drive():
    spec = RigSpec(motor="toy", eds=EDS, socketcand=("127.0.0.1", 0), serial="tcp", exclusive=True)
    with build(spec) as rig:
        port = int(rig.endpoints["canopen"].split(":")[2].split("/")[0])
        can_bench = handshake(port)
        sdo_read_device_type(can_bench)                  # the CAN client sends: it is the rig's bench
        rig.device.write_named("fault_overcurrent", 1.0)  # what the last run left behind
        rig.device.target_speed_mech_rad_s = 20.0
        serial = serial_link(rig.endpoints["serial"])
        with pytest.raises(LinkError, match="BUSY.*one bench at a time|one bench at a time.*BUSY"):
            serial.open()
        second_can = handshake(port)
        second_can.sendall(b"< send 601 8 40 0 10 0 0 0 0 0 >")
        assert b"rig busy" in expect(second_can, b"one bench at a time >")
        second_can.close()
        can_bench.close()
        time.sleep(0.3)                                  # the server sees the first bench leave
        serial.open()                                    # admitted: the drive restarted for it
        assert not rig.device.faults.overcurrent and rig.device.target_speed_mech_rad_s == 0.0
        assert serial.status().state == "SWITCH ON DISABLED"
        serial.close()
        assert rig.sessions.admitted == 2 and rig.sessions.refused == 2


def _reset_storm(port: int, n: int) -> None:
    """n connections that reset at once (SO_LINGER 0: an RST, no FIN), like a port scan."""
    for _ in range(n):
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        try:
            s.connect(("127.0.0.1", port))
        except OSError:
            pass
        s.close()


def test_serial_endpoint_survives_a_connect_storm_of_resets_and_a_real_client_still_works():
    device = SimulatedDevice(ToyDrive())
    server = start_serial_tcp(device)
    try:
        _reset_storm(server.port, 200)
        time.sleep(0.5)
        assert server.dead() is None and server.error is None
        link = serial_link(server.url)
        link.open()
        link.enable_velocity_mode()
        assert link.status().state == "OPERATION ENABLED"
        link.close()
    finally:
        server.stop()
    assert server.stats["sessions"] + server.stats["accept_errors"] >= 1


def test_serial_bench_reconnecting_right_after_closing_gets_the_line():
    # without pyserial's 0.3 s pause in close() (tests/conftest.py) the next bench connects within a millisecond
    device = SimulatedDevice(ToyDrive())
    server = start_serial_tcp(device)
    try:
        for _ in range(50):                              # close, and connect again within a millisecond
            link = serial_link(server.url)
            link.open()
            link.close()
    finally:
        server.stop()
    assert server.stats["refused_busy"] == 0 and server.error is None


def test_a_dead_serial_endpoint_is_reported_not_silent():
    """An error the endpoint cannot handle ends it loudly: dead() says why (sim serve polls it and exits 1)."""
    device = SimulatedDevice(ToyDrive())
    server = start_serial_tcp(device)
    try:
        def broken(backoff):
            raise RuntimeError("accept broke")
        server._accept = broken
        socket.create_connection(("127.0.0.1", server.port)).close()
        deadline = time.monotonic() + 5
        while server.dead() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert "accept broke" in (server.dead() or "")
    finally:
        server.stop()
    assert server.dead() is None                         # stopped on purpose: not dead


def test_second_socketcand_bench_reads_the_refusal_as_one_line_rig_busy(caplog, capfd):
    from drivers.canopen.link import CanopenDriveLink

    spec = RigSpec(motor="toy", eds=EDS, socketcand=("127.0.0.1", 0), exclusive=True)
    with build(spec) as rig:
        port = int(rig.endpoints["canopen"].split(":")[2].split("/")[0])
        first = handshake(port)
        sdo_read_device_type(first)                      # the first bench holds the rig
        link = CanopenDriveLink({"transport": "canopen", "interface": "socketcand", "channel": f"can0@127.0.0.1:{port}",
                                 "node_id": 1, "eds": str(EDS), "sdo_timeout_s": 0.5}, Path("."), LinkSettings())
        with caplog.at_level("WARNING"):
            with pytest.raises(LinkError) as refused:
                link.open()
            link.close()
        first.close()
    assert str(refused.value).startswith("rig busy: another bench")
    assert "\n" not in str(refused.value)
    assert not [r for r in caplog.records if r.name.startswith("can") and r.levelname in ("ERROR", "CRITICAL")
                and not r.name.startswith("canopen")]
    assert not [r for r in caplog.records if "Traceback" in r.getMessage()]
    assert "Traceback" not in capfd.readouterr().err


def test_serial_watchdog_counts_a_request_waiting_unread_as_the_masters_sign_but_not_a_closed_line():
    """A loaded host may not schedule the simulator for longer than the drive's comm-loss time: a request that arrived
    meanwhile is what a real drive's UART would have received. A bench that closed its line sends nothing."""
    import fcntl  # noqa: F401  (the server's FIONREAD check)
    from sim_backend.serial_server import _waiting

    a, b = socket.socketpair()
    try:
        assert not _waiting(b)
        a.sendall(b"\x55")
        time.sleep(0.05)
        assert _waiting(b)
        b.recv(1)
        a.close()
        time.sleep(0.05)
        assert not _waiting(b)                            # EOF is not a request
    finally:
        b.close()
    from sim_backend.comm_watchdog import Watchdog
    dog = Watchdog("drive")
    dog.arm(0.3)
    dog.touch()
    waiting = [True]
    dog.arrived = lambda: waiting[0]
    assert not dog.expired(time.monotonic() + 1.0)       # bytes waiting: not silent
    waiting[0] = False
    assert dog.expired(time.monotonic() + 2.0)           # nothing waiting: it trips
