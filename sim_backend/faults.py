"""Fault injection on the simulator's side: what a broken drive, a bad cable or a dead process looks like.

The names are `sim_backend.hooks.FAULT_INJECTIONS`; a scenario writes them like any injection (simulator only,
refused on a bench with plant_injections = false), a test or benchmark may also set a FaultState directly.

- `FaultState`: the active faults of one simulated device, one seeded numpy Generator for every random
  decision (drop / corrupt), and the log of the commands the device received (what tests and the fault
  campaign check: quick stop, disable, load zero torque, and when the first of them arrived).
- `FaultyBus`: the simulator's end of python-can's virtual bus with frames dropped, delayed or destroyed
  (a destroyed CAN frame is what the receiver sees as an error frame: the transmitter then repeats it),
  heartbeats stopped, error-frame floods, or the whole node silent.
- `FaultyStreamProxy`: a TCP proxy in front of the serial server that drops, delays or bit-flips the drive's
  reply bytes, or cuts the line.
- `start_canopen` / `start_serial`: [services] starters like `sim_backend.inprocess:start` and
  `sim_backend.serial_server:start_inprocess`, with the wrappers in place. `RIGS` keeps the last started
  devices so a test in the same process can look at the simulated device after the run.
"""

from __future__ import annotations

import collections
import contextlib
import select
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Iterator

import can
import numpy as np

if TYPE_CHECKING:
    from sim_backend.device import SimulatedDevice

EMCY_OVERCURRENT = 0x2310
LOAD_FAULT_CODE = 0x7000
ERROR_FLOOD_PER_FRAME = 4        # error frames sent for every frame the drive sends while fault_bus_error is on
CW_QUICK_STOP, CW_DISABLE_VOLTAGE = 0x0002, 0x0000
COMM_LOSS_S = 2.0                # the drive's / load machine's own reaction to a lost master (CiA 402 0x6007 style)
WATCHDOG_PERIOD_S = 0.05


@dataclass
class FaultState:
    seed: int = 0
    drop_rate: float = 0.0
    corrupt_rate: float = 0.0
    delay_s: float = 0.0
    heartbeat_stopped: bool = False
    overcurrent: bool = False
    estimator_frozen: bool = False
    drive_dead: bool = False
    load_dead: bool = False
    bus_error: bool = False
    kill_load: object = None                 # callable set by the starter: stops the Modbus server
    wrapped: bool = False                    # a faults starter put the frame / stream wrappers in place
    injected: list[dict] = field(default_factory=list)       # {name, value, t_s, wall}
    commands: collections.deque = field(default_factory=lambda: collections.deque(maxlen=512))
    counts: collections.Counter = field(default_factory=collections.Counter)
    frames: collections.Counter = field(default_factory=collections.Counter)   # sent / dropped / corrupted / ...
    first_stop_wall: float | None = None     # monotonic time of the first safe-stop command after a fault
    last_master_wall: float = field(default_factory=time.monotonic)   # last frame / byte from the bench
    drive_killed_wall: float | None = None
    load_killed_wall: float | None = None
    self_stops: list[str] = field(default_factory=list)   # what the device's own comm-loss watchdog did

    def __post_init__(self) -> None:
        self.rng = np.random.default_rng(self.seed)
        self._lock = threading.Lock()

    def reseed(self, seed: int) -> None:
        with self._lock:
            self.seed = seed
            self.rng = np.random.default_rng(seed)

    def draw(self) -> float:
        with self._lock:
            return float(self.rng.random())

    def integers(self, high: int) -> int:
        with self._lock:
            return int(self.rng.integers(high))

    @property
    def first_injection_wall(self) -> float | None:
        return self.injected[0]["wall"] if self.injected else None

    def log_command(self, what: str) -> None:
        now = time.monotonic()
        self.commands.append((now, what))
        self.counts[what] += 1
        is_stop = what in (f"controlword 0x{CW_QUICK_STOP:04X}", f"controlword 0x{CW_DISABLE_VOLTAGE:04X}") or (
            what.startswith("load ") and ("enabled=False" in what or "value=0.0" in what))
        if is_stop and self.injected and self.first_stop_wall is None:
            self.first_stop_wall = now

    @property
    def detection_s(self) -> float | None:
        """Wall seconds from the first injected fault to the first safe-stop command the device received."""
        if self.first_stop_wall is None or not self.injected:
            return None
        return self.first_stop_wall - self.first_injection_wall

    # -- per frame -----------------------------------------------------------------------------------
    def frame_fate(self) -> str:
        """'send', 'drop' or 'corrupt' for one outgoing frame (the random draws only happen at a non-zero rate)."""
        if self.drop_rate > 0 and self.draw() < self.drop_rate:
            return "drop"
        if self.corrupt_rate > 0 and self.draw() < self.corrupt_rate:
            return "corrupt"
        return "send"


NEEDS_WRAPPERS = ("fault_drop_frames_rate", "fault_corrupt_frames_rate", "fault_delay_frames_s",
                  "fault_stop_heartbeat", "fault_kill_endpoint", "fault_bus_error")


def apply_fault(device: "SimulatedDevice", name: str, value: float) -> None:
    """A fault injection written to the device (caller holds device.lock)."""
    f = device.faults
    on = bool(value)
    if name in NEEDS_WRAPPERS and not f.wrapped:
        raise ValueError(f"{name}: this simulator has no frame-level fault wrappers; use [services] start = "
                         "'sim_backend.faults:start_canopen' or 'sim_backend.faults:start_serial'")
    f.injected.append({"name": name, "value": float(value), "t_s": device.time_s, "wall": time.monotonic()})
    if name == "fault_drop_frames_rate":
        f.drop_rate = float(value)
    elif name == "fault_corrupt_frames_rate":
        f.corrupt_rate = float(value)
    elif name == "fault_delay_frames_s":
        f.delay_s = float(value)
    elif name == "fault_stop_heartbeat":
        f.heartbeat_stopped = on
    elif name == "fault_overcurrent":
        f.overcurrent = on          # the device's fault detection latches FAULT + EMCY at the next step
    elif name == "fault_freeze_estimator":
        f.estimator_frozen = on
        for hook in ("freeze_speed_est", "freeze_flux_est"):
            device.model.set_hook(hook, 1.0 if on else 0.0)
    elif name == "fault_kill_endpoint":
        which = int(value)
        if which & 1:
            f.drive_dead = True
            f.drive_killed_wall = time.monotonic()
        if which & 2:
            f.load_dead = True
            f.load_killed_wall = time.monotonic()
            if callable(f.kill_load):   # not on this thread: the Modbus server's loop may wait for device.lock
                threading.Thread(target=f.kill_load, name="kill-load-endpoint", daemon=True).start()
    elif name == "fault_bus_error":
        f.bus_error = on
    elif name == "fault_load_machine":
        if on:
            device.load.fault = LOAD_FAULT_CODE
            device.load.enabled = False
            device.model.set_load(device.load.mode, device.load.value, False)
    else:
        raise KeyError(f"unknown fault injection {name!r}")


# -- CAN ---------------------------------------------------------------------------------------------------

def _faulty_bus_class():
    from sim_backend.canopen_node import FastVirtualBus

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
            if f.heartbeat_stopped and msg.arbitration_id == 0x700 + self.node_id:
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

    return FaultyBus


def _error_frame() -> can.Message:
    return can.Message(is_error_frame=True, arbitration_id=0x20000000 | 0x08, is_extended_id=True, dlc=8,
                       data=bytes(8), check=False)


# -- serial ------------------------------------------------------------------------------------------------

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


# -- the device's own reaction to a lost master -------------------------------------------------------------

def comm_loss_watchdog(device: "SimulatedDevice", done: threading.Event, linger_s: float = 2 * COMM_LOSS_S) -> None:
    """What a drive and a dynamometer do on their own when their master goes silent (CiA 402 0x6007 "abort
    connection" = disable voltage; a dyno's Modbus watchdog): power stage off / load disabled at zero torque
    once nothing came from the bench for COMM_LOSS_S, or COMM_LOSS_S after their endpoint died. Keeps watching
    for linger_s after the bench has gone (`done`), as a drive's firmware would."""
    from sim_backend.cia402 import State

    f = device.faults
    done_at: float | None = None
    while True:
        now = time.monotonic()
        if done.is_set():
            done_at = done_at or now
            if now - done_at > linger_s:
                return
        with device.lock:
            silent = now - f.last_master_wall > COMM_LOSS_S or (
                f.drive_killed_wall is not None and now - f.drive_killed_wall > COMM_LOSS_S)
            if silent and device.device.power_enabled and device.device.state is not State.FAULT:
                device.device.write_controlword(CW_DISABLE_VOLTAGE, fault_active=False)
                device.model.set_enabled(device.device.power_enabled)
                f.self_stops.append(f"drive: master silent for {now - f.last_master_wall:.2f} s, disable voltage")
            if (f.load_killed_wall is not None and now - f.load_killed_wall > COMM_LOSS_S
                    and device.load.enabled):
                device.load.enabled = False
                device.load.value = 0.0
                device.model.set_load(device.load.mode, 0.0, False)
                f.self_stops.append("load machine: Modbus endpoint dead, torque off and disabled")
        time.sleep(WATCHDOG_PERIOD_S)


@contextlib.contextmanager
def _watchdog(device: "SimulatedDevice") -> Iterator[None]:
    done = threading.Event()
    device.faults.last_master_wall = time.monotonic()
    thread = threading.Thread(target=comm_loss_watchdog, args=(device, done), name="comm-loss-watchdog",
                              daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()


def wait_safe(device: "SimulatedDevice", timeout_s: float = COMM_LOSS_S + 2.0) -> bool:
    """True once the device is in the safe state (polled; the watchdog may still be about to act)."""
    deadline = time.monotonic() + timeout_s
    while not is_safe(device):
        if time.monotonic() > deadline:
            return False
        time.sleep(WATCHDOG_PERIOD_S)
    return True


# -- [services] starters -----------------------------------------------------------------------------------

RIGS: list["SimulatedDevice"] = []     # devices started in this process, newest last (tests, fault campaign)


def _new_device(bench_cfg: dict, seed: int) -> "SimulatedDevice":
    from sim_backend.device import SimulatedDevice
    from sim_backend.inprocess import make_model

    if bench_cfg.get("simulator", {}).get("motor") == "toy":
        from sim_backend.toy import ToyDrive
        device = SimulatedDevice(ToyDrive())
    else:
        device = SimulatedDevice(make_model(bench_cfg, seed))
    device.faults.reseed(seed)
    device.faults.wrapped = True
    RIGS.append(device)
    del RIGS[:-8]
    return device


def _stopper(handle) -> callable:
    def stop() -> None:
        try:
            handle.stop()
        except Exception:
            pass
    return stop


@contextlib.contextmanager
def start_canopen(bench_cfg: dict, seed: int) -> Iterator[dict]:
    """Like sim_backend.inprocess:start (CANopen on a private virtual channel + Modbus TCP), with faults."""
    from sim_backend.canopen_node import SimCanopenNode
    from sim_backend.inprocess import private_channel
    from sim_backend.modbus_server import start_modbus_tcp

    device = _new_device(bench_cfg, seed)
    drive = bench_cfg["drive"]
    node_id = int(drive.get("node_id", 1))
    channel = private_channel()
    bus = _faulty_bus_class()(device.faults, node_id, channel=channel, receive_own_messages=False)
    node = SimCanopenNode(device, drive["eds"], node_id, bus)
    try:
        load_server = start_modbus_tcp(device, "127.0.0.1", 0)
        device.faults.kill_load = _stopper(load_server)
        try:
            bench = bench_cfg.get("bench", {})
            overrides = {"drive": {"channel": channel, **{k: bench[k] for k in ("timing", "fault_reset")
                                                          if k in bench}},
                         "load": {"port": load_server.port}}
            with _watchdog(device):
                yield overrides
        finally:
            _stopper(load_server)()
    finally:
        node.stop()


@contextlib.contextmanager
def start_serial(bench_cfg: dict, seed: int) -> Iterator[dict]:
    """Like sim_backend.serial_server:start_inprocess (serial over TCP + Modbus TCP), with faults."""
    from sim_backend.modbus_server import start_modbus_tcp
    from sim_backend.serial_server import start_serial_tcp

    device = _new_device(bench_cfg, seed)
    drive_server = start_serial_tcp(device)
    proxy = FaultyStreamProxy(device.faults, ("127.0.0.1", drive_server.port))
    try:
        load_server = start_modbus_tcp(device)
        device.faults.kill_load = _stopper(load_server)
        try:
            bench = bench_cfg.get("bench", {})
            with _watchdog(device):
                yield {"drive": {"port": proxy.url, **{k: bench[k] for k in ("timing", "fault_reset") if k in bench}},
                       "load": {"host": "127.0.0.1", "port": load_server.port}}
        finally:
            _stopper(load_server)()
    finally:
        proxy.stop()
        drive_server.stop()


def safe_state(device: "SimulatedDevice") -> dict:
    """What the device says about its own safety at the end of a run."""
    with device.lock:
        return {"power_stage_on": bool(device.device.power_enabled), "state": device.device.state.name,
                "load_enabled": bool(device.load.enabled), "load_setpoint": float(device.load.value),
                "load_mode": int(device.load.mode)}


def is_safe(device: "SimulatedDevice") -> bool:
    s = safe_state(device)
    return not s["power_stage_on"] and not s["load_enabled"]
