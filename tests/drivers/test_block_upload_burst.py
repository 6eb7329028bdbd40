"""The fast block-upload path: the node sends each sub-block as one burst (FastVirtualBus.send_frames), the
link takes a sub-block's segments at once (_accept_segments). Same frames on the wire as one send per
segment; a lost segment is acked short and the server repeats from there."""

from __future__ import annotations

import can
import numpy as np

import sim_backend.canopen.block_server as block_server
from drivers.canopen.sdo import accept_segments as _accept_segments, block_upload
from drivers.contract.trace_format import decode_rows, mask_for
from sim_backend.canopen.virtual_bus import FastVirtualBus
from sim_backend.rig import private_channel
from tests.canopen_helpers import Sniffer, rig

LIVE = ["speed_ref_mech_rad_s", "speed_est_mech_rad_s"]


def segment(seq: int, fill: int, last: bool = False) -> bytearray:
    return bytearray([seq | (0x80 if last else 0)] + [fill] * 7)


def test_accept_segments_stops_at_a_gap_and_at_the_last_segment():
    frames = [segment(1, 1), segment(2, 2), segment(4, 4), segment(5, 5)]
    assert _accept_segments(frames) == (2, False, bytes([1] * 7 + [2] * 7))
    frames = [segment(1, 1), segment(2, 2, last=True), segment(3, 3)]
    assert _accept_segments(frames) == (2, True, bytes([1] * 7 + [2] * 7))
    assert _accept_segments([segment(2, 2)]) == (0, False, b"")
    short = [segment(1, 1), bytearray([2, 9, 9])]        # a segment shorter than 8 bytes: taken as it is
    assert _accept_segments(short) == (2, False, bytes([1] * 7 + [9, 9]))


def test_send_frames_puts_the_same_frames_on_the_wire_as_send():
    channel = private_channel()
    sniffer = Sniffer(channel)
    bus = FastVirtualBus(channel=channel, receive_own_messages=False)
    try:
        payloads = [bytes([k]) * 8 for k in range(1, 6)]
        bus.send_frames([(0x581, p) for p in payloads])
        for p in payloads:
            bus.send(can.Message(arbitration_id=0x581, is_extended_id=False, data=p))
        got = sniffer.frames()
        assert [(m.arbitration_id, m.is_extended_id, m.dlc, bytes(m.data), m.is_rx) for m in got[:5]] == \
               [(m.arbitration_id, m.is_extended_id, m.dlc, bytes(m.data), m.is_rx) for m in got[5:]]
        assert [bytes(m.data) for m in got[:5]] == payloads
    finally:
        bus.shutdown()
        sniffer.close()


def test_send_frames_goes_through_an_overridden_send():
    sent = []

    class Counting(FastVirtualBus):
        def send(self, msg, timeout=None):
            sent.append(bytes(msg.data))
            super().send(msg, timeout)

    bus = Counting(channel=private_channel(), receive_own_messages=False)
    try:
        bus.send_frames([(0x581, b"\x01" * 8), (0x582, b"\x02" * 8)])
        assert sent == [b"\x01" * 8, b"\x02" * 8]
    finally:
        bus.shutdown()


def test_a_lost_segment_is_acked_short_and_served_again(monkeypatch):
    real = block_server.send_frames
    dropped = []

    def lose_the_40th_segment_once(network, frames):
        if not dropped and len(frames) > 40:
            dropped.append(frames[39])
            frames = frames[:39] + frames[40:]
        real(network, frames)

    monkeypatch.setattr(block_server, "send_frames", lose_the_40th_segment_once)
    with rig() as r:
        r.link.configure(LIVE, LIVE, 1)
        for _ in range(5):
            r.link.sync()
        r.sniffer.frames()
        data = block_upload(r.link.network, 1, 0x2101, 0, r.link.stall_timeout_s, r.link._send)
        acks = [bytes(m.data) for m in r.sniffer.frames() if m.arbitration_id == 0x601 and m.data[0] == 0xA2]
    assert dropped and acks[0][:2] == bytes([0xA2, 39])          # 39 in sequence, then the gap
    rows = decode_rows(data, mask_for(LIVE), 1e-4)
    assert len(rows["t_s"]) == 500 and np.allclose(np.diff(rows["t_s"]), 1e-4)
