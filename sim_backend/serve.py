"""`drivebench sim serve --config FILE`: the simulator out of process, on the endpoints of [simulator.serve].

One drive model (from [simulator] motor) behind three front ends that share it:
  canopen   socketcand on [simulator.serve] canopen_socketcand (node [drive] node_id, EDS [drive] eds)
  serial    TCP on serial_tcp
  modbus    Modbus TCP on modbus_tcp (the load machine)
Prints one line per endpoint, runs until SIGINT/SIGTERM, then stops everything and returns 0.
"""

from __future__ import annotations

import signal
import sys
import threading
import tomllib
from pathlib import Path



class ServeError(Exception):
    """Bad config: one line naming file, field and reason."""


def _endpoint(path: Path, serve: dict, key: str) -> tuple[str, int] | None:
    value = serve.get(key)
    if value is None:
        return None
    host, sep, port = str(value).rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ServeError(f"{path}: simulator.serve.{key}: expected 'host:port', got {value!r}")
    return host, int(port)


def _resolve(path: Path, value: str) -> Path:
    p = Path(value)
    if p.is_absolute():
        return p
    for base in (path.parent, *path.parents):
        if (base / "pyproject.toml").exists() and (base / p).exists():
            return base / p
    return path.parent / p


def load_serve_config(config_path: str | Path) -> dict:
    path = Path(config_path)
    try:
        with path.open("rb") as f:
            cfg = tomllib.load(f)
    except FileNotFoundError:
        raise ServeError(f"{path}: (file): not found") from None
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ServeError(f"{path}: (file): cannot read as TOML: {exc}") from None
    sim = cfg.get("simulator")
    if not isinstance(sim, dict) or not sim.get("motor"):
        raise ServeError(f"{path}: simulator.motor: missing (sim serve needs a motor model)")
    serve = sim.get("serve")
    if not isinstance(serve, dict):
        raise ServeError(f"{path}: simulator.serve: missing table of endpoints")
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
    }
    if not toy and not out["motor"].exists():
        raise ServeError(f"{path}: simulator.motor: file not found: {sim['motor']!r}")
    if not out["eds"].exists():
        raise ServeError(f"{path}: drive.eds: file not found: {drive.get('eds')!r}")
    return out


def serve(cfg: dict, stop: threading.Event, out=sys.stdout) -> None:
    from sim_backend.canopen_node import start_node
    from sim_backend.device import SimulatedDevice
    from sim_backend.inprocess import private_channel
    from sim_backend.socketcand_server import SocketcandServer

    if cfg["motor"] == "toy":
        from sim_backend.toy import ToyDrive
        device = SimulatedDevice(ToyDrive())
    else:
        from sim_backend.drive import make_drive
        make_drive(cfg["motor"], cfg["seed"]).step(1)     # compile the kernels before the first SYNC
        device = SimulatedDevice(make_drive(cfg["motor"], cfg["seed"]))
    stoppers = []
    try:
        if cfg["socketcand"]:
            channel = private_channel()
            node = start_node(device, cfg["eds"], cfg["node_id"], interface="virtual", channel=channel)
            stoppers.append(node.stop)
            server = SocketcandServer(channel, *cfg["socketcand"])
            stoppers.append(server.stop)
            print(f"canopen {server.url} node={cfg['node_id']}", file=out, flush=True)
        if cfg["serial"]:
            from sim_backend.serial_server import start_serial_tcp
            handle = start_serial_tcp(device, *cfg["serial"])
            stoppers.append(handle.stop)
            print(f"serial socket://{cfg['serial'][0]}:{handle.port}", file=out, flush=True)
        if cfg["modbus"]:
            from sim_backend.modbus_server import start_modbus_tcp
            handle = start_modbus_tcp(device, *cfg["modbus"])
            stoppers.append(handle.stop)
            print(f"modbus tcp://{cfg['modbus'][0]}:{handle.port} unit=1", file=out, flush=True)
        print("ready (Ctrl-C to stop)", file=out, flush=True)
        stop.wait()
    finally:
        for stopper in reversed(stoppers):
            try:
                stopper()
            except Exception as exc:      # keep stopping the others
                print(f"warning: stopping: {exc}", file=sys.stderr)


def main(config_path: str | Path) -> int:
    try:
        cfg = load_serve_config(config_path)
    except ServeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        serve(cfg, stop)
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
