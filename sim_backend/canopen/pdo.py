"""The simulated node's PDO engine: mappings read from the node's own object dictionary (so what the bench writes by
SDO is what goes out), mapping writes checked as a drive checks them, TPDOs packed on SYNC, RPDOs applied."""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass
from typing import Callable

from canopen import objectdictionary
from canopen.sdo import SdoAbortedError

from drivers.contract import objects as o

log = logging.getLogger(__name__)

PDO_PARAMETERS = range(o.RPDO_COMM, o.TPDO_MAP + 0x200)


@dataclass
class Pdo:
    cob_id: int
    trans_type: int
    entries: list[tuple[int, int, int]]     # (index, subindex, bits)
    last: bytes = b""
    packer: tuple | None = None             # (struct, getters) when every mapped object has a fast getter
    event_timer_ms: int = 0                 # TPDO 254/255: sent at least this often (0x18xx sub 5), 0 = on change only
    last_sent_s: float | None = None        # drive time of the last event-driven send

    @property
    def length(self) -> int:
        return sum(bits for _, _, bits in self.entries) // 8


def is_mapping_parameter(index: int) -> bool:
    return o.RPDO_MAP <= index < o.TPDO_COMM or o.TPDO_MAP <= index < o.TPDO_MAP + 0x200


class PdoEngine:
    """raw(index, sub) reads the node's object dictionary; get_data/set_data go through its callbacks;
    fast_getters(index) may give a (struct code, getter) pair that packs a mapped object without a lookup."""

    def __init__(self, od: objectdictionary.ObjectDictionary, raw: Callable[[int, int], int],
                 get_data: Callable[[int, int], bytes], set_data: Callable[[int, int, bytes], None],
                 fast_getter: Callable[[int, int], tuple[str, Callable[[], object]] | None],
                 fixed_mapping: bool = False, event_only: bool = False):
        self.od = od
        self.fixed_mapping = fixed_mapping      # a drive whose mappings cannot be changed (only COB-ID, type)
        self.event_only = event_only            # a drive whose TPDOs refuse SYNC transmission types (0-240)
        self._raw = raw
        self._get = get_data
        self._set = set_data
        self._fast_getter = fast_getter
        self.tpdos: list[Pdo] = []
        self.rpdos: dict[int, Pdo] = {}
        self.pending: list[tuple[Pdo, bytes]] = []
        self.dirty = True

    def check_write(self, index: int, subindex: int, value: int) -> None:
        """SDO abort for a mapping a drive would refuse: too long, an object that cannot be mapped."""
        if self.event_only and o.TPDO_COMM <= index < o.TPDO_MAP and subindex == 2 and value <= 240:
            raise SdoAbortedError(o.ABORT_INVALID_VALUE)
        if not is_mapping_parameter(index):
            return
        if self.fixed_mapping:
            raise SdoAbortedError(o.ABORT_READ_ONLY)
        tx = index >= o.TPDO_MAP
        if subindex == 0:
            if value > 8:
                raise SdoAbortedError(o.ABORT_PDO_TOO_LONG)
            bits = sum(self._raw(index, k) & 0xFF for k in range(1, value + 1))
            if bits > 64:
                raise SdoAbortedError(o.ABORT_PDO_TOO_LONG)
            return
        if value == 0:
            return
        m_index, m_sub, bits = o.unpack_mapping_entry(value)
        try:
            obj = self.od[m_index]
            if not isinstance(obj, objectdictionary.ODVariable):
                obj = obj[m_sub]
        except KeyError:
            raise SdoAbortedError(o.ABORT_CANNOT_MAP) from None
        if not obj.pdo_mappable or bits != len(obj) or (tx and not obj.readable) or (not tx and not obj.writable):
            raise SdoAbortedError(o.ABORT_CANNOT_MAP)

    def changes_pdos(self, index: int, subindex: int) -> bool:
        """Whether a write just made to this PDO parameter can change what rebuild() reads: not a mapping entry past
        the mapping's count, nor anything but the COB-ID of a PDO whose COB-ID says invalid (rebuild() skips it).
        A remap (COB-ID invalid, count 0, entries, count, type, COB-ID valid) changes them at two of its writes."""
        comm = index - 0x200 if is_mapping_parameter(index) else index
        if comm == index and subindex == 1:
            return True
        try:
            if self._raw(comm, 1) & o.COB_ID_INVALID:
                return False
            return not (comm != index and subindex > self._raw(index, 0))
        except (KeyError, SdoAbortedError):
            return True

    def _read(self, comm: int, mapping: int) -> Pdo:
        entries = [o.unpack_mapping_entry(self._raw(mapping, k)) for k in range(1, self._raw(mapping, 0) + 1)]
        timer = self._raw(comm, 5) if comm >= o.TPDO_COMM and 5 in getattr(self.od[comm], "subindices", {}) else 0
        return Pdo(cob_id=self._raw(comm, 1), trans_type=self._raw(comm, 2), entries=entries, event_timer_ms=timer)

    def rebuild(self) -> tuple[list[int], list[int]]:
        """Re-read every PDO; returns (RPDO COB-IDs no longer used, RPDO COB-IDs now used)."""
        old = list(self.rpdos)
        self.tpdos = list(self._valid(o.TPDO_COMM, o.TPDO_MAP, o.N_TPDO_MAX))
        for pdo in self.tpdos:
            pdo.packer = self._packer(pdo)
        self.rpdos = {pdo.cob_id: pdo for pdo in self._valid(o.RPDO_COMM, o.RPDO_MAP, o.N_RPDO_MAX)}
        self.dirty = False
        return old, list(self.rpdos)

    def _valid(self, comm_base: int, map_base: int, n_max: int):
        """The valid PDOs with a mapping, in number order, up to the first one the dictionary lacks."""
        for n in range(n_max):
            if comm_base + n not in self.od:
                return
            pdo = self._read(comm_base + n, map_base + n)
            if not pdo.cob_id & o.COB_ID_INVALID and pdo.entries:
                pdo.cob_id &= 0x7FF
                yield pdo

    def receive(self, pdo: Pdo, data: bytes) -> None:
        """An RPDO of the right length: synchronous ones wait for the next SYNC, the others act now."""
        if pdo.trans_type <= 240:
            self.pending.append((pdo, data))
        else:
            self.apply(pdo, data)

    def apply_pending(self) -> None:
        pending, self.pending = self.pending, []
        for pdo, payload in pending:
            self.apply(pdo, payload)

    applying = False               # an RPDO's objects are being written (a drive may treat them unlike SDO writes)

    def apply(self, pdo: Pdo, data: bytes) -> None:
        offset = 0
        self.applying = True
        try:
            for index, subindex, bits in pdo.entries:
                n = bits // 8
                try:
                    self._set(index, subindex, data[offset:offset + n])
                except SdoAbortedError as exc:
                    log.warning("RPDO 0x%X: object 0x%04X:%02X rejected (0x%08X)", pdo.cob_id, index, subindex,
                                exc.code)
                offset += n
        finally:
            self.applying = False

    def pack(self, pdo: Pdo) -> bytes:
        if pdo.packer is not None:
            layout, getters = pdo.packer
            return layout.pack(*[get() for get in getters])
        return b"".join(bytes(self._get(i, s)) for i, s, _ in pdo.entries)

    def _packer(self, pdo: Pdo) -> tuple | None:
        """Per-SYNC packing without the generic object lookup, for the objects TPDOs usually carry."""
        fmt, getters = "<", []
        for index, subindex, _ in pdo.entries:
            fast = self._fast_getter(index, subindex)
            if fast is None:
                return None
            fmt += fast[0]
            getters.append(fast[1])
        return struct.Struct(fmt), getters

    def tpdo_frames(self, sync_count: int, drive_time_s: float | None = None) -> list[tuple[int, bytes]]:
        """The TPDOs due at this SYNC: cyclic ones every n-th SYNC, acyclic/event ones when their data changed, and
        event ones with an event timer also when it ran out (drive time: the drive advances on SYNC)."""
        frames = []
        for pdo in self.tpdos:
            t = pdo.trans_type
            if 1 <= t <= 240:
                if sync_count % t == 0:
                    frames.append((pdo.cob_id, self.pack(pdo)))
            else:                       # 0 (acyclic synchronous), 254/255 (event): on change, or the timer ran out
                payload = self.pack(pdo)
                timer_due = (t >= 254 and pdo.event_timer_ms and drive_time_s is not None and
                             (pdo.last_sent_s is None
                              or drive_time_s - pdo.last_sent_s >= pdo.event_timer_ms * 1e-3 - 1e-9))
                if payload != pdo.last or timer_due:
                    pdo.last = payload
                    pdo.last_sent_s = drive_time_s
                    frames.append((pdo.cob_id, payload))
        return frames
