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

from drivers.contract.checks import find_repo_root, resolve_path
from drivers.contract.errors import ContentError, InputError
from drivers.contract.toml_file import read_toml_file

if TYPE_CHECKING:
    from sim_backend.rig import RigSpec


class EndpointDied(RuntimeError):
    """A protocol server stopped serving by itself."""


def _endpoint(path: Path, serve: dict, key: str) -> tuple[str, int] | None:
    value = serve.get(key)
    if value is None:
        return None
    host, sep, port = str(value).rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise InputError(f"{path}: simulator.serve.{key}: expected 'host:port', got {value!r}")
    if not _loopback(host):
        raise InputError(f"{path}: simulator.serve.{key}: {host} is not a loopback address: the simulator serves "
                         f"127.0.0.1 only (no authentication: anyone who reaches the port drives the rig)")
    return host, int(port)


def _loopback(host: str) -> bool:
    import ipaddress

    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _resolve(path: Path, value: str) -> Path:
    """The bench's own path rule (absolute, else from the repository root, else next to the config); a file that
    is not found comes back as named next to the config, for the error message."""

    found = resolve_path(str(value), find_repo_root(path), also=path.parent)
    return found if found is not None else path.parent / value


def load_serve_config(config_path: str | Path) -> dict:
    path = Path(config_path)
    try:
        cfg, _ = read_toml_file(path)
    except ContentError as exc:
        raise InputError(f"{path}: (file): {exc}") from None
    sim = cfg.get("simulator")
    if not isinstance(sim, dict) or not sim.get("motor"):
        raise InputError(f"{path}: simulator.motor: missing (sim serve needs a motor model)")
    serve = sim.get("serve")
    if not isinstance(serve, dict):
        raise InputError(f"{path}: simulator.serve: missing table of endpoints")
    drive = cfg.get("drive", {})
    toy = sim["motor"] == "toy"        # sim_backend.toy.ToyDrive: protocol tests without physics
    out = {
        "motor": "toy" if toy else _resolve(path, sim["motor"]),
        "seed": int(sim.get("seed", 0)),
        "eds": _resolve(path, drive.get("eds", "config/od/drivebench-pmsm.eds")),
        "node_id": int(drive.get("node_id", 1)),
        "socketcand": _endpoint(path, serve, "canopen_socketcand"),
        "serial": _endpoint(path, serve, "serial_tcp"),
        "modbus": _endpoint(path, serve, "modbus_tcp"),
        "wire_faults": bool((cfg.get("bench") or {}).get("wire_faults", False)),
        "drive": _drive_spec(path, sim),
        "one_bench": serve.get("one_bench", True),
        "load_map": _resolve(path, (cfg.get("load") or {})["map"]) if (cfg.get("load") or {}).get("map") else None,
        "instruments": _instrument_spec(path, sim),
    }
    if not isinstance(out["one_bench"], bool):
        raise InputError(f"{path}: simulator.serve.one_bench: must be true or false, got {out['one_bench']!r}")
    if not toy and not out["motor"].exists():
        raise InputError(f"{path}: simulator.motor: file not found: {sim['motor']!r}")
    if out["load_map"] is not None and not out["load_map"].exists():
        raise InputError(f"{path}: load.map: file not found: {cfg['load']['map']!r}")
    if not out["eds"].exists():
        raise InputError(f"{path}: drive.eds: file not found: {drive.get('eds')!r}")
    return out


def _drive_spec(path: Path, simulator: dict):
    from sim_backend.rig import drive_spec
    try:
        return drive_spec(simulator)
    except (RuntimeError, TypeError) as exc:
        raise InputError(f"{path}: simulator.drive: {exc}") from None


def _instrument_spec(path: Path, simulator: dict):
    """[simulator.instruments]: the dynamometer's encoder and torque transducer of an instruments rig, or None."""
    if simulator.get("instruments") is None:
        return None
    from sim_backend.instruments import InstrumentSpec
    try:
        return InstrumentSpec.from_table(simulator["instruments"], f"{path}: simulator.instruments")
    except RuntimeError as exc:
        raise InputError(str(exc)) from None


def rig_spec(cfg: dict) -> "RigSpec":
    from sim_backend.rig import RigSpec
    return RigSpec(motor=cfg["motor"], seed=cfg["seed"], drive=cfg["drive"], eds=cfg["eds"] if cfg["socketcand"] else None,
                   node_id=cfg["node_id"], socketcand=cfg["socketcand"],
                   serial="tcp" if cfg["serial"] else None, serial_tcp=cfg["serial"] or ("127.0.0.1", 0),
                   modbus="tcp" if cfg["modbus"] else None, modbus_tcp=cfg["modbus"] or ("127.0.0.1", 0),
                   wire_faults=cfg["wire_faults"], exclusive=cfg["one_bench"],
                   load_map=cfg.get("load_map"), instruments=cfg.get("instruments"))


def serve(cfg: dict, stop: threading.Event, out=sys.stdout) -> None:
    from sim_backend.rig import build

    with build(rig_spec(cfg)) as rig:
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
        print(f"error: {exc}", file=sys.stderr)
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
