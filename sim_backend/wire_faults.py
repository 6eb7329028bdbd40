"""Wire faults: the simulated rig's front ends with frames dropped, delayed, corrupted or stopped, as a bad cable, a
flooded bus or a dead endpoint looks to the bench. Driven by the rig's FaultState (sim_backend.faults).

- `FaultyBus`: the simulator's end of python-can's virtual bus (a destroyed CAN frame is what the receiver sees as
  an error frame: the transmitter then repeats it), heartbeats stopped, error-frame floods, the node silent.
- `FaultyStreamProxy`: a TCP proxy in front of the serial server that drops, delays or bit-flips the drive's
  reply bytes, or cuts the line.
"""

from __future__ import annotations

import select
import socket
import threading
import time

import can

from drivers.contract.objects import HEARTBEAT
from sim_backend.canopen.virtual_bus import FastVirtualBus
from sim_backend.faults import FaultState

ERROR_FLOOD_PER_FRAME = 4        # error frames sent for every frame the drive sends while fault_bus_error is on


class FaultyBus(FastVirtualBus):
    """The simulator's end of the virtual bus, with the device's FaultState applied to every frame."""

    def __init__(self, faults: FaultState, node_id: int, **kwargs):
        super().__init__(**kwargs)
        self.faults = faults
        self.node_id = node_id

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        f = self.faults
        if f.drive_dead:
            f.frames["dead"] += 1
            return
        if f.heartbeat_stopped and msg.arbitration_id == HEARTBEAT + self.node_id:
            f.frames["heartbeat_suppressed"] += 1
            return
        if f.delay_s > 0:
            time.sleep(f.delay_s)
        if f.bus_error:
            for _ in range(ERROR_FLOOD_PER_FRAME):
                super().send(_error_frame(), timeout)
            f.frames["error_frames"] += ERROR_FLOOD_PER_FRAME
        fate = f.frame_fate()
        if fate == "drop":
            f.frames["dropped"] += 1
            return
        if fate == "corrupt":
            # on CAN a corrupted frame never arrives: receivers flag it with an error frame and the
            # transmitter repeats it (automatic retransmission)
            super().send(_error_frame(), timeout)
            f.frames["corrupted"] += 1
        f.frames["sent"] += 1
        super().send(msg, timeout)

    def _recv_internal(self, timeout):
        msg, filtered = super()._recv_internal(timeout)
        if msg is not None:
            if self.faults.drive_dead:
                return None, filtered
            self.faults.last_master_wall = time.monotonic()
        return msg, filtered


def _error_frame() -> can.Message:
    return can.Message(is_error_frame=True, arbitration_id=0x20000000 | 0x08, is_extended_id=True, dlc=8,
                       data=bytes(8), check=False)


class FaultyStreamProxy:
    """TCP proxy bench <-> serial server; the server's replies pass through the device's FaultState."""

    def __init__(self, faults: FaultState, target: tuple[str, int], host: str = "127.0.0.1"):
        self.faults = faults
        self.target = target
        self._listener = socket.create_server((host, 0))
        self.port = self._listener.getsockname()[1]
        self.url = f"socket://{host}:{self.port}"
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="faulty-serial-proxy", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self._listener], [], [], 0.1)
            if not ready:
                continue
            try:
                client, _ = self._listener.accept()
                upstream = socket.create_connection(self.target, timeout=5.0)
            except OSError:
                continue
            with client, upstream:
                self._pump(client, upstream)

    def _pump(self, client: socket.socket, upstream: socket.socket) -> None:
        f = self.faults
        while not self._stop.is_set():
            if f.drive_dead:
                return                                   # the line goes dead: both ends closed
            ready, _, _ = select.select([client, upstream], [], [], 0.1)
            for sock in ready:
                try:
                    data = sock.recv(65536)
                except OSError:
                    return
                if not data:
                    return
                if sock is client:
                    f.last_master_wall = time.monotonic()
                    upstream.sendall(data)
                    continue
                if f.drive_dead:
                    return
                if f.delay_s > 0:
                    time.sleep(f.delay_s)
                fate = f.frame_fate()
                if fate == "drop":
                    f.frames["dropped"] += 1
                    continue
                if fate == "corrupt":
                    data = bytearray(data)
                    bit = f.integers(8 * len(data))
                    data[bit // 8] ^= 1 << (bit % 8)
                    f.frames["corrupted"] += 1
                f.frames["sent"] += 1
                try:
                    client.sendall(bytes(data))
                except OSError:
                    return

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._listener.close()
