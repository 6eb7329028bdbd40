"""What a lab engineer reads before the first run on a drive: `drivebench probe --bench CONFIG`, and a node scan.

Read-only: nothing is written to the drive (no PDO change, no NMT command, no state change). Every object is read
from the device itself by SDO; what the device does not have is reported as such.
"""

from __future__ import annotations

import struct
import time
from pathlib import Path
from typing import Any

import can
import canopen

from drivers.contract import cia402, extension
from drivers.contract.errors import LinkError
from drivers.contract import objects as o
from drivers.canopen.bus import bus_kwargs, open_bus
from drivers.canopen.profile import ProfileConfig, resolve
from drivers.contract.errors import ContentError
from drivers.canopen.sdo import SdoAccess
from drivers.contract.units import decode_velocity_unit

SCAN_TIMEOUT_S = 0.05


def _text(sdo: SdoAccess, index: int) -> str | None:
    try:
        return sdo.upload(index, 0).rstrip(b"\0").decode(errors="replace")
    except LinkError:
        return None


def _pdos(sdo: SdoAccess, od: canopen.ObjectDictionary, comm_base: int, map_base: int, limit: int) -> list[dict]:
    out = []
    for n in range(limit):
        cob = sdo.read_standard(comm_base + n, 1)
        if cob is None:
            break
        count = sdo.read_standard(map_base + n, 0) or 0
        objects = []
        for k in range(1, count + 1):
            index, sub, bits = o.unpack_mapping_entry(sdo.read_standard(map_base + n, k) or 0)
            try:
                obj = od[index]
                name = obj.name if sub == 0 or not hasattr(obj, "__getitem__") else obj[sub].name
            except KeyError:
                name = "?"
            objects.append(f"0x{index:04X}:{sub:02X} {name} ({bits} bit)")
        out.append({"number": n + 1, "cob_id": f"0x{cob & 0x7FF:03X}", "valid": not cob & o.COB_ID_INVALID,
                    "transmission_type": sdo.read_standard(comm_base + n, 2), "objects": objects})
    return out


def probe(section: dict, base_dir: Path) -> dict[str, Any]:
    """The drive's identity, profile, units, PDO mappings, heartbeat and comm-loss objects, and which drivebench
    features it carries; `profile` says what the bench would use, or what to fix in the bench config."""
    eds = Path(section["eds"]) if section.get("eds") else None
    if eds is not None and not eds.is_absolute():
        eds = base_dir / eds
    node_id = int(section["node_id"])
    network = canopen.Network()
    kwargs = bus_kwargs(section)
    try:
        open_bus(kwargs, lambda: network.connect(**kwargs))
    except (can.CanError, OSError, ValueError, TimeoutError, TypeError) as exc:
        raise LinkError(f"CAN interface {section.get('interface')!r} channel {section.get('channel')!r}: "
                        f"cannot open: {exc}") from None
    try:
        # no EDS yet (a lab's first step): every standard object is read from the device by its number anyway
        od = canopen.import_od(str(eds), node_id) if eds is not None else canopen.ObjectDictionary()
        node = network.add_node(node_id, od)
        node.sdo.RESPONSE_TIMEOUT = float(section.get("sdo_timeout_s", 0.5))
        sdo = SdoAccess(node, eds.name if eds is not None else "(no EDS)", node.sdo.RESPONSE_TIMEOUT)
        booting = (f"a drive still booting sends its NMT boot-up message (0x{o.HEARTBEAT + node_id:03X} data 00) "
                   f"when ready: probe again then, and write boot_timeout_s = 5 in [drive] so runs wait for it")
        try:
            vendor, product, revision, serial = (sdo.read_standard(o.IDENTITY, k) for k in (1, 2, 3, 4))
        except LinkError as exc:
            if "abort" in str(exc):
                raise
            raise LinkError(f"{exc}: the drive does not answer; {booting}; check node_id, bitrate and wiring") \
                from None
        if vendor is None:
            raise LinkError(f"node {node_id}: no identity object (0x1018) answered")
        device_type = sdo.read_standard(o.DEVICE_TYPE, 0) or 0
        modes = sdo.read_standard(o.SUPPORTED_DRIVE_MODES, 0)
        statusword = sdo.read_standard(o.STATUSWORD, 0)
        unit_code = sdo.read_standard(o.SI_UNIT_VELOCITY, 0)
        try:
            unit = decode_velocity_unit(unit_code).name if unit_code is not None else "not on this drive"
        except ContentError as exc:
            unit = f"0x{unit_code:08X}: {exc}"
        consumers = sdo.read_standard(o.CONSUMER_HEARTBEAT, 0)
        report: dict[str, Any] = {
            "node_id": node_id,
            "identity": {"vendor_id": f"0x{vendor:08X}", "product_code": f"0x{(product or 0):08X}",
                         "revision": f"0x{(revision or 0):08X}", "serial": serial,
                         "device_name": _text(sdo, o.DEVICE_NAME), "software_version": _text(sdo, o.SOFTWARE_VERSION)},
            "device_type": {"raw": f"0x{device_type:08X}", "profile": device_type & 0xFFFF,
                            "cia402": device_type & 0xFFFF == 402},
            "supported_modes": None if modes is None else [m.name.lower() for m in cia402.supported_modes(modes)],
            "state": None if statusword is None else cia402.state_name(statusword),
            "remote_bit9": None if statusword is None else bool(statusword & cia402.StatusBit.REMOTE),
            "units": {"velocity_0x60A9": unit,
                      "encoder_0x608F": _pair(sdo, o.POSITION_ENCODER_RESOLUTION,
                                              "{} increments per {} motor revolutions"),
                      "gear_0x6091": _pair(sdo, o.GEAR_RATIO, "{} motor : {} driving shaft revolutions"),
                      "rated_current_0x6075_mA": sdo.read_standard(o.MOTOR_RATED_CURRENT, 0),
                      "rated_torque_0x6076_mNm": sdo.read_standard(o.MOTOR_RATED_TORQUE, 0)},
            "tpdos": _pdos(sdo, od, o.TPDO_COMM, o.TPDO_MAP, o.N_TPDO_MAX),
            "rpdos": _pdos(sdo, od, o.RPDO_COMM, o.RPDO_MAP, o.N_RPDO_MAX),
            "heartbeat": {"producer_0x1017_ms": sdo.read_standard(o.PRODUCER_HEARTBEAT, 0),
                          "consumer_0x1016": None if consumers is None else
                          [f"0x{sdo.read_standard(o.CONSUMER_HEARTBEAT, k) or 0:08X}" for k in range(1, consumers + 1)],
                          "abort_connection_0x6007": sdo.read_standard(o.ABORT_CONNECTION_OPTION, 0, signed=True),
                          "quick_stop_0x605A": sdo.read_standard(o.QUICK_STOP_OPTION, 0, signed=True),
                          "error_behaviour_0x1029": sdo.read_standard(o.ERROR_BEHAVIOUR, 1)},
            "drivebench": {"extension": extension.carries_extension(vendor, product or 0),
                           "trace_recorder": extension.carries_extension(vendor, product or 0)
                           and sdo.read_standard(o.EXT_TRACE, o.TRACE_ROW_SIZE) is not None},
        }
        report["error_code_0x603F"] = sdo.read_standard(o.ERROR_CODE, 0)
        report["statusword"] = statusword
        report["supported_modes_0x6502"] = modes
        if consumers is None:
            report["heartbeat"]["warning"] = ("no consumer heartbeat (0x1016): this drive cannot stop itself when the "
                                              "bench dies; the bench refuses it unless comm_loss = \"external\"")
        try:
            profile = resolve(ProfileConfig.from_section(section), vendor, product or 0, sdo.read_standard, sdo.has)
            report["profile"] = profile.as_record()
        except ContentError as exc:
            report["profile"] = {"error": str(exc)}
        # last: a stray answer on another node's SDO channel must not meet one of the reads above
        bench_id = int(section.get("bench_node_id", o.HEARTBEAT_BENCH_NODE_ID))
        report["bench_node_id"] = {"id": bench_id,
                                   "answers_on_the_bus": bench_id == node_id or _answers(network, bench_id)}
        return report
    finally:
        network.disconnect()


def _answers(network: canopen.Network, node_id: int) -> bool:
    """Does a node answer an SDO read of 0x1000 at node_id (the bench's own heartbeat id would clash with it)?"""
    import threading

    answered = threading.Event()
    cob = o.SDO_TX + node_id
    network.subscribe(cob, lambda can_id, data, ts: answered.set())
    try:
        network.send_message(o.SDO_RX + node_id, struct.pack("<BHBL", 0x40, o.DEVICE_TYPE, 0, 0))
        return answered.wait(SCAN_TIMEOUT_S)
    finally:
        network.unsubscribe(cob)


def _pair(sdo: SdoAccess, index: int, text: str) -> str:
    a, b = sdo.read_standard(index, 1), sdo.read_standard(index, 2)
    return "not on this drive" if a is None or b is None else text.format(a, b)


def scan(section: dict, node_ids: range = range(1, 128), timeout_s: float = SCAN_TIMEOUT_S) -> list[dict]:
    """Nodes that answer an SDO read of 0x1000 (device type), with identity; read-only, ~timeout_s per node id."""
    try:
        bus = open_bus(bus_kwargs(section))
    except (can.CanError, OSError, ValueError, TimeoutError, TypeError) as exc:
        raise LinkError(f"CAN interface {section.get('interface')!r} channel {section.get('channel')!r}: "
                        f"cannot open: {exc}") from None
    found = []
    try:
        for node_id in node_ids:
            bus.send(can.Message(arbitration_id=o.SDO_RX + node_id, is_extended_id=False,
                                 data=struct.pack("<BHBL", 0x40, o.DEVICE_TYPE, 0, 0)))
            deadline = time.monotonic() + timeout_s
            while (left := deadline - time.monotonic()) > 0:
                msg = bus.recv(left)
                if msg is not None and msg.arbitration_id == o.SDO_TX + node_id and len(msg.data) == 8:
                    if msg.data[0] & 0xE0 == 0x40:
                        device_type = struct.unpack_from("<L", msg.data, 4)[0]
                        found.append({"node_id": node_id, "device_type": f"0x{device_type:08X}",
                                      "cia402": device_type & 0xFFFF == 402})
                    break
    finally:
        bus.shutdown()
    return found
