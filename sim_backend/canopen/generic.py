"""A third-party CiA 402 drive in the simulator: built from a vendor's EDS, standard objects only.

The vendor EDS gives the objects, their types and defaults, the identity and the default PDO mappings; the drive
spec (a rig's [simulator] section) gives what the EDS cannot: the units the simulated drive really uses (where its
EDS has a 0x60A9 the simulated drive reports the spec's unit there; where it has a 0x6091 the spec's gear ratio; which
shaft its velocity unit counts is the vendor's choice, `velocity_side`, and no object says it), the motor's rated
current and torque, and whether its PDO mappings are fixed. No drive clock, no trace recorder, no test hooks: the drivebench extension
objects are used only on a drive whose identity carries them, and a vendor's 0x2000.. objects mean what the vendor
says, which is nothing the simulator acts on.

Where the vendor EDS lacks the standard comm-loss objects (0x1016 consumer heartbeat, 0x6007 abort connection option,
0x605A quick stop option, 0x1029 error behaviour) or the communication cycle period 0x1006 (the simulator's time
per SYNC in lockstep), the simulated drive still has them, with CiA defaults: the bench configures them by SDO and
reads the device, not the EDS, so a real drive without them is refused (0x1016) or told nothing (0x1006) instead.
Objects whose EDS entry has no default get one (0, strings "sim"; a mapping's count: its non-zero entries), as a
device does.

Quirks real drives have, as options: `csv_only` (0x6502 = 0x100, 0x6060 = 3 aborted with 0x06090030),
`event_tpdos_only` (0x18xx sub 2 refuses 0-240; TPDOs go out on change and every event timer 0x18xx sub 5 of drive
time), `boot_delay_s` (no answer at all until the boot-up message 0x700 + id, data 00), `remote_drops_after_s`
(statusword bit 9 drops mid-run, the drive keeps its target and ignores the controlword; its comm-loss reaction still
acts), `local_control` (bit 9 = 0 from power-on), `mode_display_delay_s` (0x6061 late), `warning_emcy_after_s` (a
warning EMCY while enabled), `target_sdo_only_enabled` (0x60FF by SDO aborted 0x08000022 unless enabled),
`node_guarding` (0x100C/0x100D instead of 0x1016/0x1017), `comm_loss_delay_s` (a late comm-loss reaction),
`velocity_filter_s` (0x606C filtered: the reported speed lags the shaft), `bus_drop_at_s` / `bus_drop_s` (the bus
drops: no frame either way, the drive stays OPERATIONAL, no EMCY).
"""

from __future__ import annotations

from dataclasses import dataclass

from canopen import objectdictionary
from canopen.objectdictionary import ODRecord, ODVariable

from drivers.contract import extension
from drivers.contract import objects as o
from drivers.contract.units import decode_velocity_unit, MRAD_PER_S, parse_velocity_unit, VelocityScale
from sim_backend.canopen.drive_objects import DriveUnits


@dataclass(frozen=True)
class DriveSpec:
    velocity_unit: str | None = None          # e.g. "rpm", "inc/s"; None: the EDS's 0x60A9 default
    encoder_increments_per_rev: float | None = None
    gear_ratio: tuple[float, float] = (1.0, 1.0)   # 0x6091 (motor revs, driving shaft revs) where the EDS has it
    velocity_side: str | None = None          # which shaft the velocity unit counts: "motor" (motor rpm behind a
                                              # gear, as many drives do) or "shaft"; None: CiA default (units.py)
    rated_current_a: float | None = None
    rated_torque_nm: float | None = None
    fixed_pdo_mapping: bool = False
    comm_loss_objects: bool = True            # False: a drive that really lacks 0x1016/0x6007/0x1029 (tests)
    # vendor quirks (a [simulator] option each; docs/rig.md "Simulated quirks")
    comm_loss_reaction: bool = True           # False: 0x1016 watched (EMCY 0x8130, 0x1029 NMT change) but no 0x6007
                                              # and no CiA 402 reaction: the drive stays OPERATION ENABLED
    found_running_mech_rad_s: float | None = None   # enabled and turning at this speed when the bench connects
    tpdo_stops_after_s: float | None = None   # TPDO `tpdo_stops` (0: all) goes silent after this much drive time
    tpdo_stops: int = 0
    csv_only: bool = False                    # 0x6502 = 0x100: cyclic synchronous velocity, no profile velocity
    event_tpdos_only: bool = False            # TPDO transmission types 0-240 (SYNC) refused: 254/255 + event timer
    boot_delay_s: float = 0.0                 # silent this long after power-up, then the NMT boot-up message
    remote_drops_after_s: float | None = None # statusword bit 9 drops after this much OPERATION ENABLED drive time;
                                              # from then on controlword and target are ignored (local control)
    local_control: bool = False               # bit 9 = 0 from power-on: the controlword is ignored
    mode_display_delay_s: float = 0.0         # 0x6061 shows a new 0x6060 this long (wall time) after it is written
    warning_emcy_after_s: float | None = None # EMCY 0x4310 (temperature warning) + statusword bit 7 after this much
                                              # OPERATION ENABLED drive time; the drive stays enabled
    target_sdo_only_enabled: bool = False     # 0x60FF by SDO aborted 0x08000022 outside OPERATION ENABLED (RPDO ok)
    node_guarding: bool = False               # 0x100C/0x100D node guarding, no 0x1016/0x1017 heartbeat objects
    comm_loss_delay_s: float = 0.0            # its comm-loss reaction comes this much later than its consumer time
    velocity_filter_s: float = 0.0            # 0x606C first-order filtered with this time constant (drive time)
    bus_drop_at_s: float | None = None        # after this much OPERATIONAL drive time the bus drops (nothing heard or
    bus_drop_s: float = 0.2                   # sent) for bus_drop_s wall seconds; the drive stays OPERATIONAL


def is_drivebench(od: objectdictionary.ObjectDictionary) -> bool:
    if o.IDENTITY not in od:
        return False
    identity = od[o.IDENTITY]
    return extension.carries_extension(identity[1].default or 0, identity[2].default or 0)


def _var(name: str, index: int, subindex: int, data_type: int, access: str, default: int) -> ODVariable:
    var = ODVariable(name, index, subindex)
    var.data_type, var.access_type, var.default = data_type, access, default
    return var


def add_missing_standard_objects(od: objectdictionary.ObjectDictionary, comm_loss: bool = True,
                                 abort_option: bool = True) -> list[str]:
    """The comm-loss objects a CiA 402 drive has even where its EDS omits them; returns what was added. A drive
    without a CiA 402 comm-loss reaction (`abort_option` False) has no 0x6007, whatever its EDS says."""
    added = []
    if not abort_option and o.ABORT_CONNECTION_OPTION in od:
        del od[o.ABORT_CONNECTION_OPTION]
    comm_loss_reaction = comm_loss and abort_option
    records = ((o.CONSUMER_HEARTBEAT, "Consumer heartbeat time", "Consumer heartbeat time 1", o.UNSIGNED32),
               (o.ERROR_BEHAVIOUR, "Error behaviour", "Communication error", o.UNSIGNED8))
    for index, name, entry, data_type in records if comm_loss else ():
        if index not in od:
            record = ODRecord(name, index)
            record.add_member(_var("Number of entries", index, 0, o.UNSIGNED8, "const", 1))
            record.add_member(_var(entry, index, 1, data_type, "rw", 0))
            od.add_object(record)
            added.append(f"0x{index:04X}")
    for index, name, data_type, default in ((o.ABORT_CONNECTION_OPTION, "Abort connection option code", o.INTEGER16, 1),
                                            (o.QUICK_STOP_OPTION, "Quick stop option code", o.INTEGER16, 2),
                                            (o.COMM_CYCLE_PERIOD, "Communication cycle period", o.UNSIGNED32, 1000)):
        if index not in od and (comm_loss_reaction or index != o.ABORT_CONNECTION_OPTION):
            od.add_object(_var(name, index, 0, data_type, "rw", default))
            added.append(f"0x{index:04X}")
    return added


def fill_defaults(od: objectdictionary.ObjectDictionary) -> None:
    """Every readable number gets a value: 0, or for a PDO mapping's count the number of non-zero entries."""
    for obj in od.values():
        members = [obj] if isinstance(obj, ODVariable) else list(obj.values())
        count_unknown = not isinstance(obj, ODVariable) and 0 in obj and obj[0].default is None
        for var in members:
            if var.default is None and var.data_type in objectdictionary.NUMBER_TYPES:
                var.default = 0
            elif var.default is None and var.data_type == objectdictionary.VISIBLE_STRING:
                var.default = "sim"
        if count_unknown and (o.RPDO_MAP <= obj.index < o.TPDO_COMM or o.TPDO_MAP <= obj.index < o.TPDO_MAP + 0x200):
            entries = [obj[k].default for k in sorted(obj.subindices) if k > 0]
            obj[0].default = next((k for k, e in enumerate(entries) if not e), len(entries))


def units(od: objectdictionary.ObjectDictionary, spec: DriveSpec) -> DriveUnits:
    """What the simulated drive uses: the spec where it says, else the EDS defaults (drivebench's EDS: mrad/s)."""
    if spec.velocity_unit is not None:
        unit = parse_velocity_unit(spec.velocity_unit)
    elif o.SI_UNIT_VELOCITY in od and od[o.SI_UNIT_VELOCITY].default:
        unit = decode_velocity_unit(int(od[o.SI_UNIT_VELOCITY].default))
    elif is_drivebench(od):
        unit = MRAD_PER_S
    else:
        raise ValueError("the simulated drive's velocity unit: its EDS has no 0x60A9, give [simulator] velocity_unit")
    increments = spec.encoder_increments_per_rev
    if increments is None and o.POSITION_ENCODER_RESOLUTION in od:
        res = od[o.POSITION_ENCODER_RESOLUTION]
        if res[1].default and res[2].default:
            increments = res[1].default / res[2].default
    if unit.needs_encoder and not increments:
        raise ValueError(f"the simulated drive's unit {unit.name} needs [simulator] encoder_increments_per_rev")
    return DriveUnits(VelocityScale(unit, increments, *spec.gear_ratio, side=spec.velocity_side), spec.rated_current_a,
                      spec.rated_torque_nm)
