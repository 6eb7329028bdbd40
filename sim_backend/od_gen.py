"""Generates the drivebench object dictionaries (EDS, CiA 306) that the bench and the simulator both load.

    python -m sim_backend.od_gen            # rewrites config/od/drivebench-{pmsm,spim}.eds

Layout (see docs/canopen.md):
  0x1000-0x1A07  CiA 301 communication objects (identity, heartbeat, SYNC, EMCY, 4 RPDOs, 8 TPDOs)
  0x6040-0x6502  CiA 402 objects; velocities are INTEGER32 in mrad/s, mechanical
  0x2000-0x2002  drive clock (step counter), control period, drive kind
  0x2010-0x201F  live telemetry, REAL32, one object per drivers.contract.signals.SIGNAL_NAMES entry (PDO mappable)
  0x2030-0x203F  the same as scaled INTEGER16 (EDS Factor), for when REAL32 does not fit the bus budget
  0x2100/0x2101  trace recorder: configuration record and DOMAIN data (SDO block upload)
  0x2200+/0x2300+/0x2400+/0x2480+  test hooks / firmware parameters / plant injections / fault injections, REAL32 rw
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path

from drivers.contract import extension, parameters
from drivers.contract import objects as o
from drivers.contract.objects import (
    DOMAIN, INTEGER8, INTEGER16, INTEGER32, REAL32, UNSIGNED8, UNSIGNED16, UNSIGNED32, VISIBLE_STRING, signal_index,
)
from drivers.contract.parameters import ParamKind
from drivers.contract.signals import SIGNALS

SCALE_BY_UNIT = {"rad/s": 0.05, "rad": 1e-4, "Wb": 1e-4, "A": 0.01, "V": 0.1, "N*m": 0.01}
N_RPDO, N_TPDO = o.N_RPDO_MAX, o.N_TPDO_MAX
# one object block per parameter kind (drivers.contract.parameters), in catalogue order
PARAMETER_BLOCKS = ((o.EXT_HOOK_BASE, (ParamKind.TEST_HOOK,)), (o.EXT_FIRMWARE_BASE, (ParamKind.FIRMWARE,)),
                    (o.EXT_PLANT_BASE, (ParamKind.PLANT,)),
                    (o.EXT_FAULT_BASE, (ParamKind.WIRE_FAULT, ParamKind.DEVICE_FAULT)))


@dataclass
class Var:
    name: str
    data_type: int
    access: str
    default: str | None = None
    pdo: bool = False
    description: str = ""
    factor: float | None = None


@dataclass
class Obj:
    index: int
    name: str
    var: Var | None = None                                  # VAR object
    subs: dict[int, Var] = field(default_factory=dict)      # RECORD object
    description: str = ""


def _u32(value: int) -> str:
    return f"0x{value:08X}"


def _mapping_parameter(index: int, pdo: str, entries: list[int]) -> Obj:
    """A PDO mapping parameter record: the mapped entries, the remaining of 8 slots zero."""
    subs = {0: Var("Number of mapped objects", UNSIGNED8, "rw", str(len(entries)))}
    for k in range(8):
        subs[k + 1] = Var(f"Mapped object {k + 1}", UNSIGNED32, "rw", _u32(entries[k] if k < len(entries) else 0))
    return Obj(index, f"{pdo} mapping parameter", subs=subs)


def _pdo_objects() -> list[Obj]:
    objs = []
    rpdo_maps = {0: [0x60400010, 0x60FF0020, 0x60600008]}
    tpdo_maps = {0: [0x60410010, 0x60610008, (o.EXT_STEP_COUNT << 16) | 0x20],
                 1: [(signal_index(0) << 16) | 0x20, (signal_index(1) << 16) | 0x20]}
    for n in range(N_RPDO):
        cob = f"$NODEID+0x{o.RPDO_COB[n]:X}" if n in rpdo_maps else _u32(o.COB_ID_INVALID | o.RPDO_COB[n])
        objs.append(Obj(0x1400 + n, f"RPDO {n + 1} communication parameter", subs={
            0: Var("Highest sub-index supported", UNSIGNED8, "const", "0x02"),
            1: Var(f"COB-ID used by RPDO {n + 1}", UNSIGNED32, "rw", cob),
            2: Var("Transmission type", UNSIGNED8, "rw", "0xFF")}))
    objs += [_mapping_parameter(0x1600 + n, f"RPDO {n + 1}", rpdo_maps.get(n, [])) for n in range(N_RPDO)]
    for n in range(N_TPDO):
        enabled = n in tpdo_maps
        cob = f"$NODEID+0x{o.TPDO_COB[n]:X}" if enabled and n < 4 else (
            _u32(o.COB_ID_INVALID | o.TPDO_COB[n]) if n < 4
            else _u32(o.COB_ID_INVALID | o.COB_ID_NO_RTR | (o.TPDO_COB[n] + 1)))
        objs.append(Obj(0x1800 + n, f"TPDO {n + 1} communication parameter", subs={
            0: Var("Highest sub-index supported", UNSIGNED8, "const", "0x06"),
            1: Var(f"COB-ID used by TPDO {n + 1}", UNSIGNED32, "rw", cob),
            2: Var("Transmission type", UNSIGNED8, "rw", "0x01"),
            3: Var("Inhibit time", UNSIGNED16, "rw", "0"),
            5: Var("Event timer", UNSIGNED16, "rw", "0"),
            6: Var("SYNC start value", UNSIGNED8, "rw", "0")}))
    objs += [_mapping_parameter(0x1A00 + n, f"TPDO {n + 1}", tpdo_maps.get(n, [])) for n in range(N_TPDO)]
    return objs


def objects(kind: str) -> list[Obj]:
    objs = [
        Obj(0x1000, "Device type", Var("Device type", UNSIGNED32, "ro", "0x00020192",
                                       description="CiA 402 drive")),
        Obj(0x1001, "Error register", Var("Error register", UNSIGNED8, "ro", "0", pdo=True)),
        Obj(0x1005, "COB-ID SYNC", Var("COB-ID SYNC", UNSIGNED32, "rw", "0x00000080")),
        Obj(0x1006, "Communication cycle period", Var(
            "Communication cycle period", UNSIGNED32, "rw", "1000",
            description="SYNC period in us; the simulator advances this much drive time per SYNC")),
        Obj(0x1008, "Manufacturer device name", Var("Manufacturer device name", VISIBLE_STRING, "const",
                                                     extension.device_name(kind))),
        Obj(0x1009, "Manufacturer hardware version", Var("Manufacturer hardware version", VISIBLE_STRING,
                                                         "const", "sim")),
        Obj(0x100A, "Manufacturer software version", Var("Manufacturer software version", VISIBLE_STRING,
                                                         "const", extension.FIRMWARE_VERSION)),
        Obj(0x1014, "COB-ID EMCY", Var("COB-ID EMCY", UNSIGNED32, "ro", "$NODEID+0x80")),
        Obj(0x1016, "Consumer heartbeat time", subs={
            0: Var("Highest sub-index supported", UNSIGNED8, "const", "0x01"),
            1: Var("Consumer heartbeat time 1", UNSIGNED32, "rw", "0x00000000",
                   description="node id << 16 | time in ms; 0 = not monitored")}),
        Obj(0x1017, "Producer heartbeat time", Var("Producer heartbeat time", UNSIGNED16, "rw", "100",
                                                   description="ms")),
        Obj(0x1018, "Identity object", subs={
            0: Var("Highest sub-index supported", UNSIGNED8, "const", "0x04"),
            1: Var("Vendor-ID", UNSIGNED32, "ro", _u32(extension.VENDOR_ID)),
            2: Var("Product code", UNSIGNED32, "ro", _u32(extension.PRODUCT_CODES[kind])),
            3: Var("Revision number", UNSIGNED32, "ro", _u32(extension.REVISION)),
            4: Var("Serial number", UNSIGNED32, "ro", "0x00000001")}),
        Obj(0x1029, "Error behaviour", subs={
            0: Var("Highest sub-index supported", UNSIGNED8, "const", "0x01"),
            1: Var("Communication error", UNSIGNED8, "rw", "0x00",
                   description="0 pre-operational, 1 no change, 2 stopped")}),
        Obj(0x1200, "SDO server parameter", subs={
            0: Var("Highest sub-index supported", UNSIGNED8, "const", "0x02"),
            1: Var("COB-ID client to server", UNSIGNED32, "ro", "$NODEID+0x600"),
            2: Var("COB-ID server to client", UNSIGNED32, "ro", "$NODEID+0x580")}),
    ]
    objs += _pdo_objects()
    objs += [
        Obj(o.EXT_STEP_COUNT, "drive_step_count", Var(
            "drive_step_count", UNSIGNED32, "ro", "0", pdo=True,
            description="drive clock: control periods since power-up")),
        Obj(o.EXT_CONTROL_PERIOD_NS, "control_period_ns", Var("control_period_ns", UNSIGNED32, "ro", "100000")),
        Obj(o.EXT_DRIVE_KIND, "drive_kind", Var("drive_kind", VISIBLE_STRING, "const", kind)),
    ]
    for i, sig in enumerate(SIGNALS):
        objs.append(Obj(signal_index(i), sig.name, Var(sig.name, REAL32, "ro", "0", pdo=True,
                                                       description=f"{sig.description} [{sig.unit}]")))
    for i, sig in enumerate(SIGNALS):
        factor = SCALE_BY_UNIT[sig.unit]
        objs.append(Obj(o.EXT_SCALED_BASE + i, o.SCALED_PREFIX + sig.name, Var(
            o.SCALED_PREFIX + sig.name, INTEGER16, "ro", "0", pdo=True, factor=factor,
            description=f"{sig.name} / {factor:g}, saturated to INTEGER16 [{sig.unit}]")))
    trace_subs = {0: Var("Highest sub-index supported", UNSIGNED8, "const", f"0x{len(o.TRACE_SUBS):02X}")}
    defaults = {1: _u32((1 << len(SIGNALS)) - 1), 2: "1", 3: "0", 4: "0", 5: "0", 6: "0", 7: "0",
                8: "200000", 9: "100000"}
    for sub, (name, dtype, access) in o.TRACE_SUBS.items():
        trace_subs[sub] = Var(name, dtype, access, defaults[sub])
    objs.append(Obj(o.EXT_TRACE, "trace_recorder", subs=trace_subs,
                    description="mask: bit i = drivers.contract.signals.SIGNAL_NAMES[i]"))
    objs.append(Obj(o.EXT_TRACE_DATA, "trace_data", Var(
        "trace_data", DOMAIN, "ro",
        description="oldest recorded rows (drivers.contract.trace_format), removed once the upload completes")))
    for base, kinds in PARAMETER_BLOCKS:
        for i, name in enumerate(parameters.names_for(kind, *kinds)):
            objs.append(Obj(base + i, name, Var(name, REAL32, "rw", "0")))
    objs += [
        Obj(0x6007, "Abort connection option code", Var(
            "Abort connection option code", INTEGER16, "rw", "3",
            description="reaction to a lost heartbeat: 0 none, 1 fault, 2 disable voltage, 3 quick stop")),
        Obj(0x603F, "Error code", Var("Error code", UNSIGNED16, "ro", "0", pdo=True)),
        Obj(0x6040, "Controlword", Var("Controlword", UNSIGNED16, "rw", "0", pdo=True)),
        Obj(0x6041, "Statusword", Var("Statusword", UNSIGNED16, "ro", "0", pdo=True)),
        Obj(0x605A, "Quick stop option code", Var(
            "Quick stop option code", INTEGER16, "rw", "2",
            description="2: stop on the quick-stop ramp (current limit), then switch on disabled")),
        Obj(0x6060, "Modes of operation", Var("Modes of operation", INTEGER8, "rw", "3", pdo=True)),
        Obj(0x6061, "Modes of operation display", Var("Modes of operation display", INTEGER8, "ro", "3",
                                                      pdo=True)),
        Obj(0x606C, "Velocity actual value", Var("Velocity actual value", INTEGER32, "ro", "0", pdo=True,
                                                 description="estimated speed, mrad/s mechanical")),
        Obj(0x60FF, "Target velocity", Var("Target velocity", INTEGER32, "rw", "0", pdo=True,
                                           description="mrad/s mechanical")),
        Obj(0x60A9, "SI unit velocity", Var("SI unit velocity", UNSIGNED32, "ro", "0xFD100300",
                                            description="mrad/s: exponent -3, radian, per second")),
        Obj(0x6502, "Supported drive modes", Var("Supported drive modes", UNSIGNED32, "ro", "0x00000004",
                                                 description="profile velocity only")),
    ]
    return sorted(objs, key=lambda o: o.index)


def _var_lines(section: str, var: Var) -> list[str]:
    lines = [f"[{section}]", f"ParameterName={var.name}", "ObjectType=0x7", f"DataType=0x{var.data_type:04X}",
             f"AccessType={var.access}"]
    if var.default is not None:
        lines.append(f"DefaultValue={var.default}")
    lines.append(f"PDOMapping={1 if var.pdo else 0}")
    if var.description:
        lines.append(f"Description={var.description}")
    if var.factor is not None:
        lines.append(f"Factor={var.factor:g}")
    return lines + [""]


def render(kind: str) -> str:
    objs = objects(kind)
    mandatory = [o for o in objs if o.index in (0x1000, 0x1001, 0x1018)]
    manufacturer = [o for o in objs if 0x2000 <= o.index < 0x6000]
    optional = [o for o in objs if o not in mandatory and o not in manufacturer]
    out = [
        "[FileInfo]", f"FileName=drivebench-{kind}.eds", "FileVersion=1", "FileRevision=0", "EDSVersion=4.0",
        f"Description=drivebench simulated {kind.upper()} drive, CiA 402 profile velocity; generated by "
        "sim_backend/od_gen.py, do not edit", "CreatedBy=drivebench", "",
        "[DeviceInfo]", "VendorName=drivebench", f"VendorNumber={_u32(extension.VENDOR_ID)}",
        f"ProductName=drivebench-{kind}", f"ProductNumber={_u32(extension.PRODUCT_CODES[kind])}",
        f"RevisionNumber={_u32(extension.REVISION)}", "OrderCode=sim",
        *[f"BaudRate_{r}={1 if r in (125, 250, 500, 1000) else 0}" for r in (10, 20, 50, 125, 250, 500, 800, 1000)],
        "SimpleBootUpMaster=0", "SimpleBootUpSlave=1", "Granularity=8", "DynamicChannelsSupported=0",
        "GroupMessaging=0", f"NrOfRXPDO={N_RPDO}", f"NrOfTXPDO={N_TPDO}", "LSS_Supported=0", "",
        "[DummyUsage]", *[f"Dummy000{i}=0" for i in range(1, 8)], "",
        "[Comments]", "Lines=2", "Line1=Velocities (0x606C, 0x60FF) are INTEGER32 in mrad/s, mechanical.",
        "Line2=Manufacturer objects carry drivebench signal, hook and parameter names as ParameterName.", "",
    ]
    for title, group in (("MandatoryObjects", mandatory), ("OptionalObjects", optional),
                         ("ManufacturerObjects", manufacturer)):
        out += [f"[{title}]", f"SupportedObjects={len(group)}"]
        out += [f"{k + 1}=0x{entry.index:04X}" for k, entry in enumerate(group)] + [""]
        for entry in group:
            if entry.var is not None:
                lines = _var_lines(f"{entry.index:04X}", entry.var)
                if entry.description and not entry.var.description:
                    lines.insert(-1, f"Description={entry.description}")
                out += lines
            else:
                out += [f"[{entry.index:04X}]", f"ParameterName={entry.name}", "ObjectType=0x9",
                        f"SubNumber=0x{len(entry.subs):X}"]
                if entry.description:
                    out.append(f"Description={entry.description}")
                out.append("")
                for sub, var in entry.subs.items():
                    out += _var_lines(f"{entry.index:04X}sub{sub:X}", var)
    return "\n".join(out)


def write_all(od_dir: Path) -> list[Path]:
    paths = []
    for kind in ("pmsm", "spim"):
        path = od_dir / f"drivebench-{kind}.eds"
        path.write_text(render(kind))
        paths.append(path)
    return paths


def main(argv: list[str] | None = None) -> int:
    od_dir = Path(argv[0]) if argv else Path(__file__).resolve().parent.parent / "config" / "od"
    for path in write_all(od_dir):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
