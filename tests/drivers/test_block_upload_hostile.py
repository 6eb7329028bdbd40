"""The block-upload client under a hostile bus: every way a transfer can go wrong ends it in bounded time with a
LinkError, on the wire (issue: one SDO abort frame during a trace upload left `drivebench run` spinning forever with
the drive enabled). A scripted server on python-can's virtual bus answers the client frame by frame."""

from __future__ import annotations

import struct
import threading
import time

import can
import canopen
import pytest

from drivers.contract.errors import LinkError
from drivers.contract import objects as o
from drivers.canopen.sdo import block_upload
MAX_STALLED_SUBBLOCKS = 3
from sim_backend.rig import private_channel

NODE = 5
INDEX = 0x2101
SIZE = 7 * 300          # three sub-blocks' worth: the transfer is mid-way when the server misbehaves


class ScriptedServer:
    """Answers the initiate correctly and sends the first sub-block; then `behaviour` decides every answer."""

    def __init__(self, channel: str, behaviour: str):
        self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.behaviour = behaviour
        self.received: list[bytes] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def send(self, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=o.SDO_TX + NODE, data=data.ljust(8, b"\0"), is_extended_id=False))

    def sub_block(self, first_fill: int) -> None:
        for seq in range(1, o.MAX_BLOCK_SIZE + 1):
            self.send(bytes([seq]) + bytes([first_fill]) * 7)

    def _serve(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.02)
            if msg is None or msg.arbitration_id != o.SDO_RX + NODE:
                continue
            data = bytes(msg.data)
            self.received.append(data)
            cmd = data[0]
            if cmd & 0xE3 == o.BLOCK_UPLOAD_INITIATE:
                self.send(struct.pack("<BHBL", o.BLOCK_RESPONSE_INITIATE | o.BLOCK_CRC_SUPPORTED
                                      | o.BLOCK_SIZE_INDICATED, INDEX, 0, SIZE))
            elif cmd == o.BLOCK_UPLOAD_START:
                self.sub_block(1)
            elif cmd == o.BLOCK_UPLOAD_ACK:
                if self.behaviour == "abort":        # what the server says after another client aborted it
                    self.send(struct.pack("<BHBL", o.SDO_ABORT, INDEX, 0, 0x05040001))
                elif self.behaviour == "garbage":    # frames that are no valid segment, answered to every ack
                    for _ in range(3):
                        self.send(bytes([0x05]) + b"\xEE" * 7)
                    self.send(bytes([0x85]) + b"\xEE" * 7)
                elif self.behaviour == "silent":
                    pass

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.bus.shutdown()


@pytest.fixture
def bus_pair():
    channel = private_channel()
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel, receive_own_messages=False)
    servers: list[ScriptedServer] = []

    def start(behaviour: str) -> ScriptedServer:
        servers.append(ScriptedServer(channel, behaviour))
        return servers[-1]

    yield network, start
    for server in servers:
        server.close()
    network.disconnect()


def upload(network, timeout_s: float = 1.0, cancel: threading.Event | None = None) -> bytes:
    return block_upload(network, NODE, INDEX, 0, timeout_s,
                        lambda cob, data: network.send_message(cob, data), cancel)


def failed_upload(bus_pair, behaviour: str, error: str, within_s: float, timeout_s: float = 1.0):
    """Start a server that misbehaves so, upload; the upload must fail with `error` within `within_s`."""
    network, start = bus_pair
    server = start(behaviour)
    t0 = time.monotonic()
    with pytest.raises(LinkError, match=error):
        upload(network, timeout_s=timeout_s)
    assert time.monotonic() - t0 < within_s
    return server


def test_an_abort_frame_after_the_first_sub_block_ends_the_transfer(bus_pair):
    server = failed_upload(bus_pair, "abort", "aborted with 0x05040001", 0.5)
    acks = [f for f in server.received if f[0] == o.BLOCK_UPLOAD_ACK]
    assert len(acks) == 1 and acks[0][1] == o.MAX_BLOCK_SIZE       # the first sub-block was taken whole


def test_sub_blocks_without_a_valid_segment_end_the_transfer(bus_pair):
    server = failed_upload(bus_pair, "garbage", "without a valid segment", 1.0)
    time.sleep(0.1)                                     # the server's thread takes the abort
    acks = [f for f in server.received if f[0] == o.BLOCK_UPLOAD_ACK]
    assert len(acks) == MAX_STALLED_SUBBLOCKS           # the first ack plus the ones for garbage, then an abort
    aborts = [f for f in server.received if f[0] == o.SDO_ABORT]
    assert aborts and struct.unpack_from("<L", aborts[-1], 4)[0] == o.ABORT_SEQUENCE


@pytest.mark.slow
def test_a_silent_server_ends_the_transfer_at_the_timeout(bus_pair):
    t0 = time.monotonic()
    failed_upload(bus_pair, "silent", "stopped arriving", 1.0, timeout_s=0.3)
    assert time.monotonic() - t0 > 0.25


def test_cancel_from_another_thread_ends_the_transfer_at_once(bus_pair):
    network, start = bus_pair
    server = start("silent")
    cancel = threading.Event()
    threading.Timer(0.2, cancel.set).start()
    t0 = time.monotonic()
    with pytest.raises(LinkError, match="cancelled"):
        upload(network, timeout_s=30.0, cancel=cancel)
    assert time.monotonic() - t0 < 1.0
    time.sleep(0.05)
    assert server.received[-1][0] == o.SDO_ABORT        # the server is told the transfer is over
