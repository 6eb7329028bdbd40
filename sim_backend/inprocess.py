"""The in-process simulator the bench starts through `[services] start = "sim_backend.inprocess:start"`.

A drive model from `[simulator] motor` behind a CANopen node on a private python-can `virtual` channel
(one per run, so parallel runs never hear each other) and the load machine on Modbus TCP at 127.0.0.1.
"""

from __future__ import annotations

import contextlib
import importlib
import uuid
from pathlib import Path
from typing import Iterator

from sim_backend.canopen_node import SimCanopenNode, start_node
from sim_backend.device import SimulatedDevice


def private_channel() -> str:
    # ends in letters: log writers (python-can's BLF) read trailing digits of a channel name as its number
    return f"drivebench-{uuid.uuid4().hex[:12]}-vbus"


def make_model(bench_cfg: dict, seed: int):
    motor = bench_cfg.get("simulator", {}).get("motor")
    if not motor:
        raise RuntimeError(f"{bench_cfg.get('_path', 'bench config')}: simulator.motor: missing")
    try:
        drive = importlib.import_module("sim_backend.drive")
    except ModuleNotFoundError as exc:
        raise RuntimeError(f"simulator: sim_backend.drive is not available ({exc})") from None
    drive.make_drive(motor, seed).step(1)      # compile the kernels now, not inside the first SYNC
    return drive.make_drive(motor, seed)


def _start_load_server(device: SimulatedDevice, host: str, port: int):
    try:
        modbus = importlib.import_module("sim_backend.modbus_server")
    except ModuleNotFoundError as exc:
        raise RuntimeError(f"simulator: the Modbus load-machine server is not available ({exc})") from None
    return modbus.start_modbus_tcp(device, host=host, port=port)


@contextlib.contextmanager
def start_device(device: SimulatedDevice, eds: str | Path, node_id: int = 1, load: bool = True,
                 channel: str | None = None) -> Iterator[tuple[dict, SimCanopenNode]]:
    """The node (and the Modbus server) in front of an existing SimulatedDevice; yields (overrides, node)."""
    channel = channel or private_channel()
    node = start_node(device, eds, node_id, interface="virtual", channel=channel)
    load_server = None
    try:
        overrides: dict = {"drive": {"channel": channel}}
        if load:
            load_server = _start_load_server(device, "127.0.0.1", 0)
            overrides["load"] = {"port": load_server.port}
        yield overrides, node
    finally:
        if load_server is not None:
            load_server.stop()
        node.stop()


@contextlib.contextmanager
def start(bench_cfg: dict, seed: int) -> Iterator[dict]:
    """Context manager: yields {"drive": {"channel": ...}, "load": {"port": ...}} for the bench config."""
    device = SimulatedDevice(make_model(bench_cfg, seed))
    drive = bench_cfg["drive"]
    with start_device(device, drive["eds"], int(drive.get("node_id", 1))) as (overrides, _node):
        # the link reads these from its [drive] section; the bench keeps them in [bench]
        bench = bench_cfg.get("bench", {})
        overrides["drive"].update({k: bench[k] for k in ("timing", "fault_reset") if k in bench})
        yield overrides
