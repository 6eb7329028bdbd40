"""The link's receive side above the bus: frames to canopen's subscribers in one call each (FrameDispatch), a
burst's runs to subscribers that take runs (RunReceiver), and the lockstep network that handles what a send brought
in the sending thread (HandlingNetwork)."""

from __future__ import annotations

import logging
import threading
from typing import Any, Callable

import can
import canopen


class RunReceiver:
    """A subscriber (network.subscribe) that also takes a run of frames in one call: `on_frame(can_id, data,
    timestamp)` per frame, `on_frames(frames, timestamp)` for consecutive frames (can_id, data) of one burst that
    all go to it alone (FrameDispatch.burst) — one SYNC's TPDOs, a block upload's sub-block."""

    def __init__(self, on_frame: Callable[[int, bytes, float], None],
                 on_frames: Callable[[list[tuple[int, bytes]], float], None]):
        self.on_frame, self.on_frames = on_frame, on_frames

    def __call__(self, can_id: int, data: bytes, timestamp: float) -> None:
        self.on_frame(can_id, data, timestamp)


def same_id_stretches(frames: list[tuple[int, bytes]]) -> list[tuple[int, int, int]]:
    """(can_id, start, end) of each stretch of consecutive frames with one CAN id."""
    out = []
    start, can_id = 0, frames[0][0] if frames else None
    for k, (cob, _) in enumerate(frames):
        if cob != can_id:
            out.append((can_id, start, k))
            start, can_id = k, cob
    if frames:
        out.append((can_id, start, len(frames)))
    return out


class FrameDispatch:
    """A canopen Network's receive listener in one call per frame: what canopen's MessageListener ->
    Network.notify -> NodeScanner do in three (the subscribers' callbacks in order, then the scanner; error and
    remote frames skipped; an exception logged, skipping the frame's remaining callbacks). ~70,000 frames a 20 s
    lockstep run. `burst` does the same for a burst's frames, consecutive frames that go to one RunReceiver alone
    in one call."""

    def __init__(self, network: Any):
        self.subscribers, self.scanner = network.subscribers, network.scanner
        self.log = logging.getLogger("canopen.network")

    def __call__(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame:
            return
        can_id = msg.arbitration_id
        try:
            callbacks = self.subscribers.get(can_id)
            if callbacks:
                data, timestamp = msg.data, msg.timestamp
                for callback in callbacks:
                    callback(can_id, data, timestamp)
            self.scanner.on_message_received(can_id)
        except Exception as exc:       # as canopen's listener: a callback's failure must not stop the receive thread
            self.log.error(str(exc))

    def burst(self, timestamp: float, frames: list[tuple[int, bytes]]) -> None:
        stretches = same_id_stretches(frames)
        k = 0
        while k < len(stretches):
            can_id, start, end = stretches[k]
            receiver = self._run_receiver(can_id)
            last = k
            while receiver is not None and last + 1 < len(stretches) and \
                    self._run_receiver(stretches[last + 1][0]) is receiver:
                last += 1
            try:
                if receiver is not None:
                    receiver.on_frames(frames[start:stretches[last][2]], timestamp)
                else:
                    for frame in frames[start:end]:
                        self._one(frame, timestamp)
                for can_id, _, _ in stretches[k:last + 1]:
                    self.scanner.on_message_received(can_id)     # notes the node ids heard: once per id is the same
            except Exception as exc:
                self.log.error(str(exc))
            k = last + 1

    def _run_receiver(self, can_id: int) -> RunReceiver | None:
        callbacks = self.subscribers.get(can_id)
        if callbacks and len(callbacks) == 1 and isinstance(callbacks[0], RunReceiver):
            return callbacks[0]
        return None

    def _one(self, frame: tuple[int, bytes], timestamp: float) -> None:
        can_id, data = frame
        for callback in self.subscribers.get(can_id) or ():
            callback(can_id, data, timestamp)


class HandlingNetwork(canopen.Network):
    """canopen's Network; with `after_send` set (a lockstep link on a QuickVirtualBus), each send_message is
    followed, in the sending thread, by after_send() — handling what the send brought (an inline receiver's
    answer) — and what the sending thread itself puts into the receive queue meanwhile does not wake the receive
    thread (BurstQueue.handled_by)."""

    after_send: Callable[[], None] | None = None

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        after_send = self.after_send
        if after_send is None or self.bus is None:        # (no bus: canopen's own error)
            super().send_message(can_id, data, remote)
            return
        arrivals = self.bus.queue
        arrivals.handled_by = threading.get_ident()
        try:
            super().send_message(can_id, data, remote)
        finally:
            arrivals.handled_by = None
        after_send()


def frame_dispatch(network: Any) -> FrameDispatch:
    return FrameDispatch(network)
