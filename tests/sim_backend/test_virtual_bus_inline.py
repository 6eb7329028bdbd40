"""The in-process lockstep path of the virtual bus: a frame handled in its sender's thread when the node is idle
(InlineReceiveQueue), the answer handled by the sender (QuickVirtualBus.handle_arrived), bursts passed as one item
(BurstQueue) and dispatched as runs (FrameDispatch.burst) — the same frames in the same order as the threaded path."""

from __future__ import annotations

import threading
import time

import can
import canopen

from drivers.canopen.bus import BusErrorCounter, QuickVirtualBus
from drivers.canopen.dispatch import FrameDispatch, RunReceiver, same_id_stretches
from sim_backend.canopen.virtual_bus import FastVirtualBus, InlineReceiveQueue
from sim_backend.rig import private_channel


def frame(cob: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=cob, is_extended_id=False, data=data)


def wait_until(condition, timeout_s: float = 2.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.005)
    return condition()


def test_an_idle_node_handles_a_frame_in_the_senders_thread_and_a_busy_one_keeps_the_order():
    channel = private_channel()
    node = FastVirtualBus(channel=channel, receive_own_messages=False)
    link = QuickVirtualBus(channel=channel, receive_own_messages=False)
    link.inline_delivery = True
    handled: list[tuple[bytes, str]] = []
    release = threading.Event()

    def handler(msg: can.Message) -> None:
        handled.append((bytes(msg.data), threading.current_thread().name))
        if msg.data[0] == 2:             # the node's receive thread is busy with this one
            release.wait(2.0)

    node.handle_inline(handler)
    notifier = can.Notifier(node, [handler], timeout=0.02)
    try:
        link.send(frame(0x601, b"\x01"))
        assert handled == [(b"\x01", threading.current_thread().name)]        # at once, in this thread
        other = QuickVirtualBus(channel=channel, receive_own_messages=False)  # a sender that does not offer it
        other.send(frame(0x601, b"\x02"))
        assert wait_until(lambda: len(handled) == 2)
        link.send(frame(0x601, b"\x03"))          # the node is busy: queued, handled after 2 by its thread
        assert len(handled) == 2
        release.set()
        assert wait_until(lambda: len(handled) == 3)
        assert [d for d, _ in handled] == [b"\x01", b"\x02", b"\x03"]
        assert handled[2][1] != threading.current_thread().name
        other.shutdown()
    finally:
        release.set()
        notifier.stop()
        node.shutdown()
        link.shutdown()


def test_a_burst_reaches_a_link_as_one_item_and_comes_out_frame_by_frame_as_sent():
    channel = private_channel()
    node = FastVirtualBus(channel=channel, receive_own_messages=False)
    link = QuickVirtualBus(channel=channel, receive_own_messages=False)
    plain = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    frames = [(0x181, b"\x01\x02"), (0x281, b"\x03" * 8), (0x281, b"\x04" * 8), (0x381, b"")]
    try:
        node.send_frames(frames)
        assert link.queue.qsize() == 1                            # one item, not four Messages
        got = [link.recv(0.5) for _ in frames]
        seen = [plain.recv(0.5) for _ in frames]
        for msgs in (got, seen):
            assert [(m.arbitration_id, bytes(m.data), m.dlc, m.is_extended_id) for m in msgs] == \
                   [(cob, data, len(data), False) for cob, data in frames]
        assert link.recv(0.05) is None and plain.recv(0.05) is None
    finally:
        for bus in (node, link, plain):
            bus.shutdown()


def test_handle_arrived_does_what_the_listeners_would_in_order():
    channel = private_channel()
    node = FastVirtualBus(channel=channel, receive_own_messages=False)
    link = QuickVirtualBus(channel=channel, receive_own_messages=False)
    got: list[tuple[str, int, bytes]] = []
    try:
        node.send(frame(0x701, b"\x05"))
        node.send_frames([(0x181, b"\x01"), (0x181, b"\x02")])
        node.send(frame(0x081, b"\x10"))
        link.handle_arrived([lambda m: got.append(("frame", m.arbitration_id, bytes(m.data)))],
                            lambda t, frames: got.extend(("burst", cob, bytes(d)) for cob, d in frames))
        assert got == [("frame", 0x701, b"\x05"), ("burst", 0x181, b"\x01"), ("burst", 0x181, b"\x02"),
                       ("frame", 0x081, b"\x10")]
        assert link.queue.qsize() == 0 and link.recv(0.05) is None
    finally:
        node.shutdown()
        link.shutdown()


def test_burst_dispatch_gives_run_receivers_runs_and_other_subscribers_frames():
    network = canopen.Network()
    per_frame: list[tuple[int, bytes]] = []
    runs: list[list[tuple[int, bytes]]] = []
    singles: list[tuple[int, bytes]] = []
    tpdos = RunReceiver(lambda c, d, t: per_frame.append((c, d)), lambda frames, t: runs.append(list(frames)))
    for cob in (0x181, 0x281):
        network.subscribe(cob, tpdos)
    network.subscribe(0x701, lambda c, d, t: singles.append((c, d)))
    frames = [(0x181, b"a"), (0x281, b"b"), (0x701, b"c"), (0x281, b"d"), (0x281, b"e"), (0x999, b"f")]
    FrameDispatch(network).burst(0.0, frames)
    assert runs == [[(0x181, b"a"), (0x281, b"b")], [(0x281, b"d"), (0x281, b"e")]]
    assert singles == [(0x701, b"c")] and per_frame == []
    assert same_id_stretches(frames) == [(0x181, 0, 1), (0x281, 1, 2), (0x701, 2, 3), (0x281, 3, 5), (0x999, 5, 6)]


def test_a_run_of_good_frames_counts_down_the_error_counter_like_frame_by_frame():
    one, run = BusErrorCounter(), BusErrorCounter()
    for counter in (one, run):
        counter.counter = 20
    for _ in range(7):
        one.on_message_received(frame(0x181, b""))
    run.count_good(7)
    assert one.counter == run.counter == 13
    run.count_good(50)
    assert run.counter == 0


def test_the_inline_queue_is_a_queue_for_everyone_else():
    queue = InlineReceiveQueue(lambda msg: None)
    queue.put(frame(0x601, b"\x01"))
    queue.put_inline(frame(0x601, b"\x02"))                   # something is queued ahead: queued behind it
    assert [bytes(queue.get_nowait().data) for _ in range(2)] == [b"\x01", b"\x02"]
