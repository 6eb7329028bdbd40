"""The fault model of one simulated rig: which faults are active, the seeded random source every drop/corrupt
decision draws from, and the log of what the device was told (typed events the tests and the fault campaign read).

Fault names are drivers.contract.parameters records of kind device fault or wire fault. Device faults act on the simulated
drive or load machine itself; wire faults need the front ends' wrappers (sim_backend.wire_faults), which a rig
carries when its bench declares `wire_faults = true`.
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Protocol, Union

import numpy as np

from drivers.contract.cia402 import Command
from drivers.contract.parameters import ParamKind, Parameter



class FaultTarget(Protocol):
    """What the fault models use of a simulated device (sim_backend.device.SimulatedDevice)."""

    lock: Any               # threading.RLock
    faults: "FaultState"
    time_s: float
    model: Any              # sim_backend.model.DriveModel
    load: Any               # the load machine's state (enabled, mode, value, fault)
    device: Any             # sim_backend.cia402 device state machine (power_enabled, state)

WATCH_PERIOD_S = 0.05
LOAD_FAULT_CODE = 0x7000         # the load machine's own fault code (its fault_code register)


@dataclass(frozen=True)
class ControlwordWritten:
    word: int

    @property
    def is_stop(self) -> bool:
        return self.word in (Command.QUICK_STOP, Command.DISABLE_VOLTAGE)

    def __str__(self) -> str:
        return f"controlword 0x{self.word:04X}"


@dataclass(frozen=True)
class LoadWritten:
    mode: int | None
    value: float | None
    enabled: bool | None

    @property
    def is_stop(self) -> bool:
        return self.enabled is False or self.value == 0.0

    def __str__(self) -> str:
        return f"load mode={self.mode} value={self.value} enabled={self.enabled}"


DeviceEvent = Union[ControlwordWritten, LoadWritten]


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
    kill_load: object = None                 # callable set by the rig: stops the Modbus server
    wrapped: bool = False                    # the rig's front ends carry the wire-fault wrappers
    injected: list[dict] = field(default_factory=list)       # {name, value, t_s, wall}
    events: collections.deque = field(default_factory=lambda: collections.deque(maxlen=512))  # (wall, DeviceEvent)
    counts: collections.Counter = field(default_factory=collections.Counter)   # str(event) -> how often
    frames: collections.Counter = field(default_factory=collections.Counter)   # sent / dropped / corrupted / ...
    first_stop_wall: float | None = None     # monotonic time of the first safe-stop command after a fault
    last_master_wall: float = field(default_factory=time.monotonic)   # last frame / byte from the bench
    drive_killed_wall: float | None = None
    load_killed_wall: float | None = None
    self_stops: list[str] = field(default_factory=list)   # what the device did on its own (comm-loss reaction)

    def __post_init__(self) -> None:
        self.rng = np.random.default_rng(self.seed)
        self._lock = threading.Lock()

    def clear_injections(self) -> None:
        """No fault acting (a new bench session); the wiring (kill_load, wrapped) and the logs stay."""
        with self._lock:
            self.drop_rate = self.corrupt_rate = self.delay_s = 0.0
            self.heartbeat_stopped = self.overcurrent = self.estimator_frozen = False
            self.drive_dead = self.load_dead = self.bus_error = False
            self.rng = np.random.default_rng(self.seed)

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

    def log(self, event: DeviceEvent) -> None:
        now = time.monotonic()
        self.events.append((now, event))
        self.counts[str(event)] += 1
        if event.is_stop and self.injected and self.first_stop_wall is None:
            self.first_stop_wall = now

    @property
    def detection_s(self) -> float | None:
        """Wall seconds from the first injected fault to the first safe-stop command the device received."""
        if self.first_stop_wall is None or not self.injected:
            return None
        return self.first_stop_wall - self.first_injection_wall

    def frame_fate(self) -> str:
        """'send', 'drop' or 'corrupt' for one outgoing frame (the random draws only happen at a non-zero rate)."""
        if self.drop_rate > 0 and self.draw() < self.drop_rate:
            return "drop"
        if self.corrupt_rate > 0 and self.draw() < self.corrupt_rate:
            return "corrupt"
        return "send"


def apply_fault(device: FaultTarget, param: Parameter, value: float) -> None:
    """A fault parameter written to the device (caller holds device.lock)."""
    f = device.faults
    name, on = param.name, bool(value)
    if param.kind is ParamKind.WIRE_FAULT and not f.wrapped:
        raise ValueError(f"{name}: this simulated rig has no frame-level fault wrappers (its bench config needs "
                         "[bench] wire_faults = true)")
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
        raise KeyError(f"no fault model for {name!r}")


def safe_state(device: FaultTarget) -> dict:
    """What the device says about its own safety at the end of a run."""
    with device.lock:
        return {"power_stage_on": bool(device.device.power_enabled), "state": device.device.state.name,
                "load_enabled": bool(device.load.enabled), "load_setpoint": float(device.load.value),
                "load_mode": int(device.load.mode)}


def is_safe(device: FaultTarget) -> bool:
    s = safe_state(device)
    return not s["power_stage_on"] and not s["load_enabled"]


def wait_safe(device: FaultTarget, timeout_s: float = 4.0) -> bool:
    """True once the device is in the safe state (polled; its own comm-loss reaction may still be about to act)."""
    deadline = time.monotonic() + timeout_s
    while not is_safe(device):
        if time.monotonic() > deadline:
            return False
        time.sleep(WATCH_PERIOD_S)
    return True
