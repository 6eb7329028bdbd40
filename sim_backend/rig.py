"""One builder of a simulated rig: a simulated drive (and its load machine) behind the front ends a bench talks to.

    with build(RigSpec(motor=..., eds=..., modbus="tcp")) as rig:
        rig.device, rig.overrides          # the SimulatedDevice; endpoint overrides for the bench config

Front ends: CANopen on a private python-can `virtual` channel (optionally also served over socketcand), the serial
protocol over TCP or a pty, the load machine over Modbus TCP or Modbus RTU on a pty. With `wire_faults` the front
ends carry the fault wrappers (sim_backend.wire_faults). The device's own reaction to a silent master is the
standard one, configured by the bench (CANopen 0x1016/0x6007, the serial watchdog, the Modbus watchdog register).

`start` is the `[services]` starter the simulated bench configs name (`start = "sim_backend.rig:start"`): its rig
is described by rig_spec from [simulator] (drivers.contract.simulator.SimulatorConfig: motor, serial line, and for a
third-party drive `drive = "generic"` with its units and rated values), the bench's [drive]/[load] transports and
[bench] wire_faults. `sim serve` describes its rig with the same function.
"""

from __future__ import annotations

import contextlib
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

from drivers.contract.simulator import SimulatorConfig, SimulatorServeConfig, endpoint
from sim_backend.canopen.generic import DriveSpec
from sim_backend.device import SimulatedDevice
from sim_backend.drive_model import DriveModel

LOOPBACK = "127.0.0.1"


def private_channel() -> str:
    # ends in letters: log writers (python-can's BLF) read trailing digits of a channel name as its number
    return f"drivebench-{uuid.uuid4().hex[:12]}-vbus"


def make_model(motor: str | Path, seed: int) -> DriveModel:
    """The drive model of a motor config ('toy': sim_backend.toy.ToyDrive, protocol tests without physics)."""
    if str(motor) == "toy":
        from sim_backend.toy import ToyDrive
        return ToyDrive()
    from sim_backend.drive import make_drive
    make_drive(motor, seed).step(1)      # compile the kernels now, not inside the first SYNC
    return make_drive(motor, seed)


@dataclass(frozen=True)
class RigSpec:
    motor: str | Path                              # motor config file, or "toy"
    seed: int = 0
    eds: str | Path | None = None                  # the CANopen node's object dictionary; None: no CANopen front end
    node_id: int = 1
    socketcand: tuple[str, int] | None = None      # also serve the CAN channel over socketcand at (host, port)
    serial: str | None = None                      # "tcp" | "pty" | None
    serial_tcp: tuple[str, int] = (LOOPBACK, 0)
    modbus: str | None = None                      # "tcp" | "rtu-pty" | None
    modbus_tcp: tuple[str, int] = (LOOPBACK, 0)
    wire_faults: bool = False
    drive: DriveSpec | None = None                 # a third-party drive from a vendor EDS; None: drivebench's
    exclusive: bool = False                        # served: one bench at a time, each from a restarted drive
    load_map: str | Path | None = None             # the dynamometer's register map; None: drivebench-sim.toml
    instruments: Any = None                        # sim_backend.instruments.InstrumentSpec: a lab's instruments
    ethercat_eds: str | Path | None = None         # an EtherCAT CoE slave with this object dictionary (root)
    lab: Any = None                                # sim_backend.lab_rig.LabSpec: SCPI power analyser and scope
    instrument_names: tuple = ()                   # (kind, name) of the bench's [[instruments]]


@dataclass
class Rig:
    spec: RigSpec
    device: SimulatedDevice
    channel: str | None = None
    node: Any = None                               # SimCanopenNode
    endpoints: dict[str, str] = field(default_factory=dict)    # front end -> URL / channel / path, for people
    overrides: dict[str, dict] = field(default_factory=dict)   # bench config [drive]/[load] endpoint keys
    sessions: Any = None                           # BenchSessions of a served rig (spec.exclusive)
    servers: list[Any] = field(default_factory=list)           # the protocol servers (each has dead())

    def dead_endpoint(self) -> str | None:
        """The first front end that stopped serving by itself (why), or None while all serve."""
        for server in self.servers:
            why = server.dead()
            if why:
                return why
        return None


def rig_model(spec: RigSpec) -> DriveModel:
    """The rig's drive model, seen through its instruments where the spec has them."""
    model = make_model(spec.motor, spec.seed)
    if spec.lab is not None:
        from sim_backend.terminals import TappedModel
        model = TappedModel(model)
    if spec.instruments is None:
        return model
    # only an instruments rig imports it: its scipy.signal import took 0.5-1.9 s of the first run on every rig
    from sim_backend.instruments import InstrumentedModel
    return InstrumentedModel(model, spec.instruments, spec.seed)


@contextlib.contextmanager
def build(spec: RigSpec, device: SimulatedDevice | None = None) -> Iterator[Rig]:
    """Start the rig's front ends (in this process); stop them all on exit, whatever happened."""
    if device is None:
        device = SimulatedDevice(rig_model(spec))
    device.faults.reseed(spec.seed)
    device.faults.wrapped = spec.wire_faults
    rig = Rig(spec, device)
    if spec.exclusive:
        from sim_backend.sessions import BenchSessions

        def restart() -> None:
            device.restart(rig_model(spec))
            _found_running(device, spec.drive)
        rig.sessions = BenchSessions(restart)
    with contextlib.ExitStack() as stack:
        stack.callback(device.stop_watchdogs)
        if spec.eds is not None:
            _canopen(stack, rig)
        if spec.serial is not None:
            _serial(stack, rig)
        if spec.modbus is not None:
            _modbus(stack, rig)
        if spec.ethercat_eds is not None:
            _ethercat(stack, rig)
        if spec.lab is not None:
            _lab(stack, rig)
        _found_running(device, spec.drive)
        yield rig


SPIN_UP_MAX_S = 5.0


def _found_running(device: SimulatedDevice, drive: DriveSpec | None) -> None:
    """The quirk of a drive somebody left running: enabled in profile velocity and turning at the stated speed when
    the bench connects (the drive's time ran until the shaft got there)."""
    speed = drive.found_running_mech_rad_s if drive is not None else None
    if not speed:
        return
    from drivers.contract.signals import SIGNAL_NAMES

    with device.lock:
        for word in (0x06, 0x07, 0x0F):
            device.write_controlword(word)
        device.target_speed_mech_rad_s = float(speed)
        chunk = max(1, round(0.1 / device.model.control_period_s))
        column = SIGNAL_NAMES.index("speed_true_mech_rad_s")
        for _ in range(round(SPIN_UP_MAX_S / 0.1)):
            device.advance(chunk)
            if abs(device.latest[column] - speed) <= 0.02 * abs(speed):
                break


def _stopper(handle) -> Callable[[], None]:
    def stop() -> None:
        try:
            handle.stop()
        except Exception:
            pass
    return stop


def _canopen(stack: contextlib.ExitStack, rig: Rig) -> None:
    from sim_backend.canopen.node import SimCanopenNode
    from sim_backend.canopen.virtual_bus import FastVirtualBus

    spec = rig.spec
    rig.channel = private_channel()
    if spec.wire_faults:
        from sim_backend.wire_faults import FaultyBus
        bus = FaultyBus(rig.device.faults, spec.node_id, channel=rig.channel, receive_own_messages=False)
    else:
        bus = FastVirtualBus(channel=rig.channel, receive_own_messages=False)
    rig.node = SimCanopenNode(rig.device, spec.eds, spec.node_id, bus, spec.drive)
    stack.callback(rig.node.stop)
    rig.overrides.setdefault("drive", {})["channel"] = rig.channel
    rig.endpoints["canopen"] = f"virtual:{rig.channel} node={spec.node_id}"
    if spec.socketcand is not None:
        from sim_backend.socketcand_server import SocketcandServer
        server = SocketcandServer(rig.channel, *spec.socketcand, sessions=rig.sessions)
        stack.callback(server.stop)
        rig.servers.append(server)
        rig.endpoints["canopen"] = f"{server.url} node={spec.node_id}"


def _serial(stack: contextlib.ExitStack, rig: Rig) -> None:
    from sim_backend.serial_server import start_serial_pty, start_serial_tcp

    spec = rig.spec
    server = (start_serial_pty(rig.device) if spec.serial == "pty"
              else start_serial_tcp(rig.device, *spec.serial_tcp, sessions=rig.sessions))
    stack.callback(server.stop)
    rig.servers.append(server)
    port = server.serial_port
    if spec.wire_faults and spec.serial == "tcp":
        from sim_backend.wire_faults import FaultyStreamProxy
        proxy = FaultyStreamProxy(rig.device.faults, (LOOPBACK, server.port))
        stack.callback(proxy.stop)
        port = proxy.url
    rig.overrides.setdefault("drive", {})["port"] = port
    rig.endpoints["serial"] = port


def _ethercat(stack: contextlib.ExitStack, rig: Rig) -> None:
    from sim_backend.ethercat.front import EthercatFront
    from sim_backend.ethercat.slave import Slave

    front = EthercatFront(Slave(rig.device, rig.spec.ethercat_eds, drive=rig.spec.drive))
    stack.callback(front.stop)
    rig.servers.append(front)
    rig.overrides.setdefault("drive", {})["interface"] = front.master_iface
    rig.endpoints["ethercat"] = f"{front.master_iface} (slave in netns {front.namespace})"


def _modbus(stack: contextlib.ExitStack, rig: Rig) -> None:
    from sim_backend.modbus_server import start_modbus_rtu_pty, start_modbus_tcp

    spec = rig.spec
    regs = None
    if spec.load_map is not None:
        from drivers.contract.load_map import read_load_map
        regs = read_load_map(spec.load_map)
    if spec.modbus == "rtu-pty":
        server = start_modbus_rtu_pty(rig.device, regs=regs)
        rig.overrides.setdefault("load", {})["port"] = server.path
        rig.endpoints["modbus"] = f"rtu:{server.path} unit=1"
    else:
        server = start_modbus_tcp(rig.device, *spec.modbus_tcp, regs=regs)
        rig.overrides.setdefault("load", {}).update(host=spec.modbus_tcp[0], port=server.port)
        rig.endpoints["modbus"] = f"tcp://{spec.modbus_tcp[0]}:{server.port} unit=1"
    stop = _stopper(server)
    rig.servers.append(server)
    rig.device.faults.kill_load = stop
    stack.callback(stop)


def _lab(stack: contextlib.ExitStack, rig: Rig) -> None:
    from sim_backend.lab_rig import start_lab

    names: dict[str, list[str]] = {}
    for kind, name in rig.spec.instrument_names:
        names.setdefault(kind, []).append(name)
    servers, resources = start_lab(stack, rig.device.model, rig.spec.lab, rig.spec.seed, names)
    rig.servers.extend(servers)
    rig.overrides["instruments"] = resources
    rig.endpoints.update({f"scpi:{name}": resource for name, resource in resources.items()})


def rig_spec(sim: SimulatorConfig, *, seed: int, where: str, transport: str | None = None,
             eds: str | Path | None = None, node_id: int = 1, load_transport: str | None = None, load_map: str | Path | None = None,
             wire_faults: bool = False, serve: SimulatorServeConfig | None = None,
             instrument_names: tuple = ()) -> RigSpec:
    """The one place a rig is described from a bench config's [simulator] (with the [drive], [load] and [bench] keys
    the rig needs): in process (the [services] starter, front ends by the bench's transports) or served
    (`sim serve`, front ends on [simulator.serve]'s endpoints)."""
    common = dict(motor=sim.motor, seed=seed, drive=drive_spec(sim), node_id=node_id, wire_faults=wire_faults,
                  load_map=load_map, instruments=_instruments(sim, where), lab=_lab_spec(sim, where),
                  instrument_names=tuple(instrument_names))
    if serve is None:
        return RigSpec(**common, eds=eds if transport == "canopen" else None,
                       serial=sim.serial_line if transport == "serial" else None,
                       modbus={"modbus-tcp": "tcp", "modbus-rtu": "rtu-pty"}.get(load_transport or ""),
                       ethercat_eds=eds if transport == "ethercat" else None)
    socketcand, serial_tcp, modbus_tcp = (endpoint(serve.canopen_socketcand), endpoint(serve.serial_tcp),
                                          endpoint(serve.modbus_tcp))
    return RigSpec(**common, eds=eds if socketcand else None, socketcand=socketcand,
                   serial="tcp" if serial_tcp else None, serial_tcp=serial_tcp or (LOOPBACK, 0),
                   modbus="tcp" if modbus_tcp else None, modbus_tcp=modbus_tcp or (LOOPBACK, 0),
                   exclusive=serve.one_bench)


def spec_for_bench(bench_cfg: dict, seed: int) -> RigSpec:
    """The in-process rig a simulated bench config describes (the plain tables a [services] starter receives)."""
    where = bench_cfg.get("_path", "bench config")
    if not (bench_cfg.get("simulator") or {}).get("motor"):
        raise RuntimeError(f"{where}: simulator.motor: missing (a simulated bench needs a motor model)")
    sim = SimulatorConfig.from_mapping(bench_cfg["simulator"])
    drive, load = bench_cfg.get("drive") or {}, bench_cfg.get("load") or {}
    return rig_spec(sim, seed=seed, where=where, transport=drive.get("transport"), eds=drive.get("eds"),
                    node_id=int(drive.get("node_id") or 1), load_transport=load.get("transport"),
                    load_map=load.get("map") if load.get("transport") else None,
                    wire_faults=bool((bench_cfg.get("bench") or {}).get("wire_faults", False)),
                    instrument_names=tuple((i["kind"], i["name"]) for i in bench_cfg.get("instruments") or ()))


def _instruments(sim: SimulatorConfig, where: str):
    """[simulator.instruments], checked (RuntimeError `file: field: reason`), or None."""
    if sim.instruments is None:
        return None
    from sim_backend.instruments import InstrumentSpec
    return InstrumentSpec.from_table(sim.instruments, f"{where}: simulator.instruments")


def _lab_spec(sim: SimulatorConfig, where: str):
    """[simulator.lab_instruments], checked, or None."""
    if sim.lab_instruments is None:
        return None
    from sim_backend.lab_rig import LabSpec
    return LabSpec.from_table(sim.lab_instruments, f"{where}: simulator.lab_instruments")


def drive_spec(sim: SimulatorConfig) -> DriveSpec | None:
    """[simulator] drive = "generic": a third-party CiA 402 drive from the bench's EDS, with its stated options."""
    if sim.drive == "drivebench":
        return None
    if sim.drive != "generic":
        raise RuntimeError(f"simulator.drive: {sim.drive!r} is not 'drivebench' or 'generic'")
    return DriveSpec(**sim.generic())


@contextlib.contextmanager
def start(bench_cfg: dict, seed: int) -> Iterator[dict]:
    """[services] starter: yields the endpoint overrides for the bench config."""
    spec = spec_for_bench(bench_cfg, seed)
    if spec.ethercat_eds is not None:     # its own process: pysoem holds the GIL while SOEM waits for frames
        from sim_backend.ethercat.rig_child import serve_out_of_process
        with serve_out_of_process(bench_cfg, seed) as overrides:
            yield overrides
        return
    with build(spec) as rig:
        yield rig.overrides


def warm_up(bench_cfg: dict) -> None:
    """[services] warm-up (entry-point group drivebench.warm_ups): what a process that forks many runs of this bench
    pays once, before it forks — the bench's drive model built and stepped (its compiled kernels loaded). Opens no
    endpoint and touches no other state."""
    rig_model(spec_for_bench(bench_cfg, 0))
