"""The simulated node's heartbeat producer (0x1017)."""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Protocol

from drivers.contract import objects as o



class HeartbeatNode(Protocol):
    """What the heartbeat producer and consumer use of a simulated node (sim_backend.canopen.node.SimCanopenNode)."""

    node_id: int
    node: Any               # canopen.LocalNode (its nmt state)
    network: Any            # canopen.Network
    device: Any             # sim_backend.device.SimulatedDevice (master watchdog, lock)

log = logging.getLogger(__name__)


class HeartbeatProducer:
    """Heartbeat (0x700 + id, NMT state) every producer heartbeat time (0x1017).

    Sent from the SYNC handler when due, and from a thread when SYNCs are rare: a sleeping thread alone
    (python-can's cyclic task) can starve for seconds behind a busy 1 kHz receive thread in one process.
    """

    def __init__(self, node: HeartbeatNode):
        self._node = node
        self._period_s = 0.0
        self._last = 0.0
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=f"heartbeat-{node.node_id}", daemon=True)
        self._thread.start()

    def set_period_ms(self, period_ms: int) -> None:
        with self._lock:
            self._period_s = period_ms / 1000.0
            self._last = 0.0
        self.maybe_send()             # the first heartbeat right away, then every period
        self._wake.set()

    def maybe_send(self) -> None:
        with self._lock:
            now = time.monotonic()
            if self._period_s <= 0 or now - self._last < self._period_s or self._closed:
                return
            if getattr(self._node, "muted", None) is not None and self._node.muted():
                return
            self._last = now
        nmt = self._node.node.nmt
        try:
            self._node.network.send_message(o.HEARTBEAT + self._node.node_id, [nmt._state])
        except Exception as exc:     # bus closed while stopping
            log.debug("heartbeat: %s", exc)

    def _run(self) -> None:
        while not self._closed:
            with self._lock:
                period, last = self._period_s, self._last
            timeout = None if period <= 0 else max(0.0, last + period - time.monotonic())
            self._wake.wait(timeout)
            self._wake.clear()
            if not self._closed:
                self.maybe_send()

    def close(self) -> None:
        self._closed = True
        self._wake.set()
        self._thread.join(timeout=1.0)


class HeartbeatConsumer:
    """0x1016: the drive watches its master's heartbeat. Each non-zero entry (node id << 16 | time ms) is watched;
    the device's master watchdog is armed with the shortest time and touched by every heartbeat of a watched node.
    On expiry the device applies 0x6007; with 0x1029 sub 1 = 0 the node also goes pre-operational."""

    def __init__(self, node: HeartbeatNode):
        self._node = node
        self._subscribed: set[int] = set()

    def configure(self, entries: list[int]) -> None:
        network, device = self._node.network, self._node.device
        for cob in self._subscribed:
            network.unsubscribe(cob, self._on_heartbeat)
        self._subscribed = set()
        watched = [(e >> 16 & 0x7F, e & 0xFFFF) for e in entries if e & 0xFFFF and e >> 16 & 0x7F]
        with device.lock:
            device.master_watchdog.arm(min((ms for _, ms in watched), default=0) / 1000.0)
        for node_id, _ in watched:
            cob = o.HEARTBEAT + node_id
            network.subscribe(cob, self._on_heartbeat)
            self._subscribed.add(cob)
        if watched:
            device.arm_watchdogs()

    def _on_heartbeat(self, can_id, data, timestamp):
        self._node.device.master_watchdog.touch()
