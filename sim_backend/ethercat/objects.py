"""The CoE object dictionary of the simulated slave: the drive's EDS (the same objects as over CANopen, answered by
the same CiA 402 and extension handlers), plus the EtherCAT communication objects: 0x1C00 SyncManager types,
0x1C12/0x1C13 PDO assignment, 0x1C32/0x1C33 SyncManager parameters (cycle time). PDO mapping (0x1600/0x1A00) is
checked as a slave checks it: only in PRE-OP, only mappable objects of the stated size; a slave with a fixed mapping
refuses every write to it."""

from __future__ import annotations

import struct
from pathlib import Path

import canopen
from canopen import objectdictionary
from canopen.objectdictionary import ODRecord, ODVariable
from canopen.sdo import SdoAbortedError

from drivers.contract import objects as o
from drivers.contract.eds import load_od
from sim_backend.canopen import generic
from sim_backend.canopen.drive_objects import Cia402Objects, ExtensionObjects
from sim_backend.device import SimulatedDevice
from sim_backend.ethercat.coe import ABORT_LENGTH, ABORT_STATE, SdoAbort

SM_TYPES, RX_ASSIGN, TX_ASSIGN, SM_OUT_PARAM, SM_IN_PARAM = 0x1C00, 0x1C12, 0x1C13, 0x1C32, 0x1C33
ABORT_READ_ONLY, ABORT_NOT_MAPPABLE = 0x06010002, 0x06040041
MAPPING_OBJECTS = frozenset([RX_ASSIGN, TX_ASSIGN, *range(0x1600, 0x1800), *range(0x1A00, 0x1C00)])
DEFAULT_CYCLE_NS = 1_000_000
SIZES = {objectdictionary.BOOLEAN: 1, objectdictionary.INTEGER8: 1, objectdictionary.UNSIGNED8: 1,
         objectdictionary.INTEGER16: 2, objectdictionary.UNSIGNED16: 2, objectdictionary.INTEGER32: 4,
         objectdictionary.UNSIGNED32: 4, objectdictionary.REAL32: 4, objectdictionary.INTEGER64: 8,
         objectdictionary.UNSIGNED64: 8, objectdictionary.REAL64: 8}


def _var(name: str, index: int, sub: int, data_type: int, access: str, default) -> ODVariable:
    var = ODVariable(name, index, sub)
    var.data_type, var.access_type, var.default = data_type, access, default
    return var


def _array(name: str, index: int, data_type: int, values: list[int], access: str = "rw", capacity: int = 0) -> ODRecord:
    arr = ODRecord(name, index)
    arr.add_member(_var("Number of entries", index, 0, objectdictionary.UNSIGNED8, access, len(values)))
    for k, value in enumerate(values + [0] * (capacity - len(values)), 1):
        arr.add_member(_var(f"Entry {k}", index, k, data_type, access, value))
    return arr


def add_ethercat_objects(od: objectdictionary.ObjectDictionary, fixed_mapping: bool) -> None:
    access = "ro" if fixed_mapping else "rw"
    od.add_object(_array("Sync manager communication type", SM_TYPES, objectdictionary.UNSIGNED8, [1, 2, 3, 4], "ro"))
    od.add_object(_array("RxPDO assign", RX_ASSIGN, objectdictionary.UNSIGNED16, [0x1600], access, 4))
    od.add_object(_array("TxPDO assign", TX_ASSIGN, objectdictionary.UNSIGNED16, [0x1A00], access, 4))
    for index, name in ((SM_OUT_PARAM, "SM output parameter"), (SM_IN_PARAM, "SM input parameter")):
        rec = ODRecord(name, index)
        rec.add_member(_var("Number of entries", index, 0, objectdictionary.UNSIGNED8, "ro", 2))
        rec.add_member(_var("Synchronization type", index, 1, objectdictionary.UNSIGNED16, "rw", 0))  # free run
        rec.add_member(_var("Cycle time", index, 2, objectdictionary.UNSIGNED32, "rw", DEFAULT_CYCLE_NS))
        od.add_object(rec)
    if fixed_mapping:
        for index in [*range(0x1600, 0x1800), *range(0x1A00, 0x1C00)]:
            if index in od:
                for var in od[index].values():
                    var.access_type = "ro"


class SlaveObjects:
    """get/set for the CoE server and the process data, over canopen's LocalNode object store."""

    def __init__(self, device: SimulatedDevice, eds: str | Path, fixed_mapping: bool = False,
                 drive: generic.DriveSpec | None = None):
        """`drive`: a third-party drive's spec (units, rated values, comm-loss objects) as the CANopen node takes it."""
        spec = drive or generic.DriveSpec()
        od = load_od(eds, 1)
        generic.add_missing_standard_objects(od, spec.comm_loss_objects, spec.comm_loss_reaction)
        device.cia402_comm_loss_reaction = spec.comm_loss_reaction
        generic.fill_defaults(od)
        add_ethercat_objects(od, fixed_mapping)
        self.od = od
        self.fixed_mapping = fixed_mapping
        self.node = canopen.LocalNode(1, od)
        self.cia402 = Cia402Objects(device, lambda: None, generic.units(od, spec))
        self.handlers = [self.cia402]
        if generic.is_drivebench(od):
            self.handlers.append(ExtensionObjects(device, od))
        self.node.add_read_callback(self._on_read)
        self.node.add_write_callback(self._on_write)
        self.preop = True                     # mapping writes allowed (the AL state is PRE-OP)
        for index in (o.QUICK_STOP_OPTION, o.ABORT_CONNECTION_OPTION):
            if index in od and od[index].default is not None:
                self.cia402.write(index, 0, od[index], int(od[index].default))

    def _on_read(self, index, subindex, od):
        for handler in self.handlers:
            value = handler.read(index, subindex, od)
            if value is not None:
                return value
        return None

    def _on_write(self, index, subindex, od, data):
        value = od.decode_raw(data) if od.data_type != objectdictionary.DOMAIN else bytes(data)
        for handler in self.handlers:
            if handler.write(index, subindex, od, value):
                return

    def variable(self, index: int, sub: int) -> ODVariable:
        try:
            obj = self.od[index]
        except KeyError:
            raise SdoAbort(o.ABORT_NOT_IN_OD) from None
        if isinstance(obj, ODVariable):
            return obj
        if sub not in obj.subindices:
            raise SdoAbort(0x06090011)
        return obj[sub]

    def get(self, index: int, sub: int) -> bytes:
        self.variable(index, sub)
        try:
            return self.node.get_data(index, sub, check_readable=True)
        except SdoAbortedError as exc:
            raise SdoAbort(exc.code) from None

    def set(self, index: int, sub: int, data: bytes) -> None:
        var = self.variable(index, sub)
        if var.access_type in ("ro", "const"):
            raise SdoAbort(ABORT_READ_ONLY)
        size = SIZES.get(var.data_type)
        if size is not None and len(data) != size:
            raise SdoAbort(ABORT_LENGTH)
        if index in MAPPING_OBJECTS:
            if not self.preop:
                raise SdoAbort(ABORT_STATE)
            if sub > 0 and (0x1600 <= index < 0x1800 or 0x1A00 <= index < 0x1C00):
                self.check_entry(struct.unpack("<I", data)[0], rx=index < 0x1A00)
        try:
            self.node.set_data(index, sub, data, check_writable=True)
        except SdoAbortedError as exc:
            raise SdoAbort(exc.code) from None

    def check_entry(self, entry: int, rx: bool) -> None:
        index, sub, bits = entry >> 16, entry >> 8 & 0xFF, entry & 0xFF
        if index == 0 or (index < 0x1000 and sub == 0):
            return                             # padding / data type gap
        var = self.variable(index, sub)
        if not var.pdo_mappable or SIZES.get(var.data_type, 0) * 8 != bits:
            raise SdoAbort(ABORT_NOT_MAPPABLE)
        if rx and var.access_type in ("ro", "const"):
            raise SdoAbort(ABORT_NOT_MAPPABLE)

    def raw(self, index: int, sub: int) -> int:
        var = self.variable(index, sub)
        return var.decode_raw(self.node.get_data(index, sub))

    def mapping(self, assign: int) -> list[tuple[int, int, int]]:
        """(index, sub, bits) of every entry of the PDOs assigned in 0x1C12 / 0x1C13."""
        entries = []
        for k in range(1, self.raw(assign, 0) + 1):
            pdo = self.raw(assign, k)
            for n in range(1, self.raw(pdo, 0) + 1):
                entry = self.raw(pdo, n)
                entries.append((entry >> 16, entry >> 8 & 0xFF, entry & 0xFF))
        return entries
