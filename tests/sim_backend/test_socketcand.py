"""The socketcand server: python-can's client protocol byte for byte, bus semantics, and canopen's own
CiA 402 master (BaseNode402) driving the simulated node through it."""

from __future__ import annotations

import socket
import time

import can
import canopen
import pytest
from canopen.profiles.p402 import BaseNode402

from sim_backend.socketcand_server import format_frame, parse_send
from tests.canopen_helpers import EDS


def _recv_until(sock: socket.socket, marker: bytes, timeout: float = 5.0) -> bytes:
    sock.settimeout(timeout)
    data = b""
    while marker not in data:
        chunk = sock.recv(4096)
        assert chunk, "server closed the connection"
        data += chunk
    return data


def test_parse_and_format_match_python_can_client():
    from can.interfaces.socketcand.socketcand import (convert_ascii_message_to_can_message,
                                                      convert_can_message_to_ascii_message)
    msg = can.Message(arbitration_id=0x601, data=bytes.fromhex("4018100100000000"), is_extended_id=False)
    assert parse_send(convert_can_message_to_ascii_message(msg)).data == msg.data
    msg.timestamp = 12.5
    back = convert_ascii_message_to_can_message(format_frame(msg))
    assert (back.arbitration_id, bytes(back.data), back.is_extended_id) == (0x601, bytes(msg.data), False)
    empty = can.Message(arbitration_id=0x80, data=b"", is_extended_id=False, timestamp=1.0)
    assert convert_ascii_message_to_can_message(format_frame(empty)).dlc == 0
    assert parse_send("< send 080 0  >").dlc == 0
    with pytest.raises(ValueError):
        parse_send("< send 601 8 40 18 >")


def test_handshake_and_an_sdo_read_in_raw_ascii(served):
    server, *_ = served
    with socket.create_connection(("127.0.0.1", server.port), timeout=5) as sock:
        assert _recv_until(sock, b">") == b"< hi >"
        sock.sendall(b"< open can0 >")
        assert _recv_until(sock, b">") == b"< ok >"
        sock.sendall(b"< rawmode >")
        assert _recv_until(sock, b">") == b"< ok >"
        sock.sendall(b"< send 601 8 40 18 10 1 0 0 0 0 >")        # SDO read 0x1018:01 vendor-ID
        reply = _recv_until(sock, b"< frame 581 ")
        reply = _recv_until(sock, b">") if not reply.rstrip().endswith(b">") else reply
        frame = reply[reply.index(b"< frame 581 "):].split(b">")[0].decode()
        _, _, can_id, stamp, data = frame.split()[:5]
        assert float(stamp) > 0
        assert data == "431810010100DB00"                          # expedited, 4 bytes, 0x00DB0001


@pytest.mark.slow
def test_unknown_bus_name_is_refused(served):
    server, *_ = served
    with socket.create_connection(("127.0.0.1", server.port), timeout=5) as sock:
        _recv_until(sock, b">")
        sock.sendall(b"< open vcan9 >")
        assert _recv_until(sock, b">").startswith(b"< error")


def test_clients_hear_each_other_but_not_themselves(served):
    server, _node, _device, _channel = served
    a = can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=server.port)
    b = can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=server.port)
    try:
        a.send(can.Message(arbitration_id=0x123, data=b"\x01\x02", is_extended_id=False))
        got = None
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            got = b.recv(0.5)
            if got is not None and got.arbitration_id == 0x123:
                break
        assert got is not None and bytes(got.data) == b"\x01\x02"
        heard = []
        until = time.monotonic() + 0.5
        while time.monotonic() < until:
            if (msg := a.recv(0.1)) is not None:
                heard.append(msg.arbitration_id)
        assert 0x701 in heard and 0x123 not in heard               # the node's heartbeat, never its own frame
    finally:
        a.shutdown()
        b.shutdown()


@pytest.mark.slow
def test_canopen_base_node_402_drives_the_simulated_node_over_socketcand(served):
    server, _node, device, _channel = served
    network = canopen.Network()
    network.NOTIFIER_CYCLE = 0.1
    network.connect(interface="socketcand", channel="can0", host="127.0.0.1", port=server.port)
    try:
        drive = BaseNode402(1, str(EDS))
        network.add_node(drive)
        drive.sdo.RESPONSE_TIMEOUT = 2.0
        drive.nmt.state = "PRE-OPERATIONAL"
        drive.setup_402_state_machine()                 # reads the PDO configuration over SDO
        drive.TIMEOUT_CHECK_TPDO = drive.TIMEOUT_SWITCH_STATE_SINGLE = 2.0
        drive.TIMEOUT_SWITCH_STATE_FINAL = drive.TIMEOUT_SWITCH_OP_MODE = 5.0
        network.sync.start(0.01)                        # BaseNode402 needs SYNC running for its TPDOs
        drive.nmt.state = "OPERATIONAL"
        drive.op_mode = "PROFILED VELOCITY"
        assert drive.op_mode == "PROFILED VELOCITY"
        drive.state = "OPERATION ENABLED"
        assert drive.state == "OPERATION ENABLED"
        assert device.device.power_enabled
        drive.rpdo[1]["Target velocity"].raw = 20_000   # 20 rad/s in mrad/s
        drive.rpdo[1].transmit()
        deadline = time.monotonic() + 10
        while drive.sdo["Velocity actual value"].raw < 19_000:
            assert time.monotonic() < deadline, "drive did not reach the target velocity"
            time.sleep(0.05)
        drive.state = "SWITCH ON DISABLED"
        assert not device.device.power_enabled
        network.sync.stop()
    finally:
        network.disconnect()


def test_the_link_s_socketcand_connection_has_nagle_off_by_default(served):
    """python-can's client leaves Nagle on unless tcp_tune: SYNCs and commands then leave in bursts. The link's
    connection has TCP_NODELAY set; `[drive.can] tcp_tune = false` leaves python-can's default."""
    from drivers.api import LinkSettings
    from drivers.canopen.link import CanopenDriveLink

    server, *_ = served
    nodelay = {}
    for name, can_options in (("default", {}), ("told not to", {"tcp_tune": False})):
        link = CanopenDriveLink(dict(transport="canopen", interface="socketcand", channel=f"can0@127.0.0.1:{server.port}",
                                     node_id=1, eds=str(EDS), sdo_timeout_s=2.0, heartbeat_timeout_s=5.0,
                                     can=can_options), EDS.parent, LinkSettings())
        try:
            link.open()
            sock = link.network.bus._SocketCanDaemonBus__socket      # python-can keeps it private
            nodelay[name] = sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY)
        finally:
            link.close()
    assert nodelay["default"] and not nodelay["told not to"]


def test_a_handshake_reply_sharing_a_segment_with_the_first_frame_is_accepted_and_the_frame_kept():
    """python-can's client compared each whole read with `< ok >`; a served drive's heartbeat in the same TCP segment
    (`< ok >< frame 701 ... >`) made it refuse a healthy rig (seen under load in the Ray campaign test)."""
    import socket
    import threading

    from drivers.canopen.bus import make_bus

    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    port = server.getsockname()[1]

    def serve() -> None:
        conn, _ = server.accept()
        with conn:
            conn.sendall(b"< hi >")
            conn.recv(256)                                   # < open can0 >
            conn.sendall(b"< ok >")
            conn.recv(256)                                   # < rawmode >
            conn.sendall(b"< ok >< frame 701 1.5 7F >")      # one segment
            conn.recv(256)                                   # until the bus closes

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    bus = make_bus({"interface": "socketcand", "channel": "can0", "host": "127.0.0.1", "port": port,
                    "tcp_tune": True})
    try:
        msg = bus.recv(timeout=2.0)      # delivered from what came with the handshake: no new data arrives
        assert msg is not None and msg.arbitration_id == 0x701 and bytes(msg.data) == b"\x7f"
    finally:
        bus.shutdown()
        server.close()
