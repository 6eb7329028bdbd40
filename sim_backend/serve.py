"""`drivebench sim serve --config FILE`: the simulator out of process, on the endpoints of [simulator.serve].

One drive model (from [simulator] motor) behind three front ends that share it:
  canopen   socketcand on [simulator.serve] canopen_socketcand (node [drive] node_id, EDS [drive] eds)
  serial    TCP on serial_tcp
  modbus    Modbus TCP on modbus_tcp (the load machine)
one_bench = true (default): one bench at a time over the drive's front ends, each finding the drive restarted
(sim_backend/sessions.py); false lets a second master in (a monitor in a test, diagnostics).
Prints one line per endpoint, runs until SIGINT/SIGTERM, then stops everything and returns 0.
"""

from __future__ import annotations

import signal
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING

from drivers.contract.checks import Problems, find_repo_root, read_toml, resolve_path
from drivers.contract.errors import InputError
from drivers.contract.simulator import SimulatorConfig

if TYPE_CHECKING:
    from sim_backend.rig import RigSpec


class EndpointDied(RuntimeError):
    """A protocol server stopped serving by itself."""


def _resolve(path: Path, value: str) -> Path:
    """The bench's own path rule (absolute, else from the repository root, else next to the config); a file that
    is not found comes back as named next to the config, for the error message."""
    found = resolve_path(str(value), find_repo_root(path), also=path.parent)
    return found if found is not None else path.parent / value


def load_serve_config(config_path: str | Path) -> "RigSpec":
    """The rig [simulator] and [simulator.serve] describe; InputError `file: field: reason` lines."""
    from sim_backend.rig import rig_spec

    path = Path(config_path)
    cfg = read_toml(path)
    problems = Problems(path)
    table = problems.table(cfg, "simulator", "")
    if table is not None and "serve" not in table:
        problems.add("simulator.serve", "missing table of endpoints")
    sim = SimulatorConfig.read(table, problems, root=find_repo_root(path), also=path.parent) if table else None
    drive, load = cfg.get("drive") or {}, cfg.get("load") or {}
    eds = _resolve(path, drive.get("eds", "config/od/drivebench-pmsm.eds"))
    if not eds.exists():
        problems.add("drive.eds", f"file not found: {drive.get('eds')!r}")
    load_map = _resolve(path, load["map"]) if load.get("map") else None
    if load_map is not None and not load_map.exists():
        problems.add("load.map", f"file not found: {load['map']!r}")
    problems.raise_if_any()
    try:
        return rig_spec(sim, seed=sim.seed, where=str(path), eds=eds, node_id=int(drive.get("node_id", 1)),
                        load_map=load_map, wire_faults=bool((cfg.get("bench") or {}).get("wire_faults", False)),
                        serve=sim.serve)
    except RuntimeError as exc:
        raise InputError(str(exc) if str(exc).startswith(str(path)) else f"{path}: simulator: {exc}") from None


def serve(spec: "RigSpec", stop: threading.Event, out=sys.stdout) -> None:
    from sim_backend.rig import build

    with build(spec) as rig:
        for name in ("canopen", "serial", "modbus"):
            if name in rig.endpoints:
                print(f"{name} {rig.endpoints[name]}", file=out, flush=True)
        print("ready (Ctrl-C to stop)", file=out, flush=True)
        # A signal may land on any thread; the handler only runs when the main thread wakes, so it must wake.
        while not stop.wait(0.2):
            why = rig.dead_endpoint()
            if why:                      # a dead endpoint is a dead process: the supervisor must see it
                raise EndpointDied(why)


def main(config_path: str | Path) -> int:
    try:
        cfg = load_serve_config(config_path)
    except InputError as exc:
        for line in exc.problems:
            print(f"error: {line}", file=sys.stderr)
        return 2
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        serve(cfg, stop)
    except EndpointDied as exc:
        print(f"error: {config_path}: endpoint stopped serving: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"error: {config_path}: simulator.serve: cannot open endpoint: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:
        print(f"error: {config_path}: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 2
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(prog="python -m sim_backend.serve")
    parser.add_argument("--config", required=True)
    sys.exit(main(parser.parse_args().config))
