"""The simulated drive's and load machine's own reaction to a lost master: what a drive does on its own when the
bench goes silent (CiA 402 0x6007 "abort connection" = disable voltage) and what a dynamometer's Modbus watchdog
does: power stage off / load disabled at zero torque once nothing came from the bench for COMM_LOSS_S, or
COMM_LOSS_S after their endpoint died."""

from __future__ import annotations

import contextlib
import threading
import time
from typing import TYPE_CHECKING, Iterator

from drivers.cia402 import Command, State
from sim_backend.faults import WATCH_PERIOD_S

if TYPE_CHECKING:
    from sim_backend.device import SimulatedDevice

COMM_LOSS_S = 2.0


def watch(device: "SimulatedDevice", done: threading.Event, linger_s: float = 2 * COMM_LOSS_S) -> None:
    """Keeps watching for linger_s after the bench has gone (`done`), as a drive's firmware would."""
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
                device.device.write_controlword(Command.DISABLE_VOLTAGE, fault_active=False)
                device.model.set_enabled(device.device.power_enabled)
                f.self_stops.append(f"drive: master silent for {now - f.last_master_wall:.2f} s, disable voltage")
            if (f.load_killed_wall is not None and now - f.load_killed_wall > COMM_LOSS_S
                    and device.load.enabled):
                device.load.enabled = False
                device.load.value = 0.0
                device.model.set_load(device.load.mode, 0.0, False)
                f.self_stops.append("load machine: Modbus endpoint dead, torque off and disabled")
        time.sleep(WATCH_PERIOD_S)


@contextlib.contextmanager
def watching(device: "SimulatedDevice") -> Iterator[None]:
    done = threading.Event()
    device.faults.last_master_wall = time.monotonic()
    thread = threading.Thread(target=watch, args=(device, done), name="comm-loss-watchdog", daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
