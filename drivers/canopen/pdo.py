"""Live PDOs of a real or simulated drive: the policy (remap when the drive allows it, else use the mapping read from
the device), writing mappings as CiA 301 prescribes, a snapshot of the drive's own PDO parameters restored at the
end, and the decoder that joins one SYNC's TPDOs into a sample.

A PDO is never left invalid by the bench: a mapping write the drive refuses restores that PDO from the snapshot
before the bench falls back to the device's own mapping.
"""

from __future__ import annotations

import logging
import math
import struct
import time
from dataclasses import dataclass, field
from typing import Callable, Iterable, Sequence

from canopen import objectdictionary

from drivers.contract.errors import LinkError
from drivers.api import LiveSample
from drivers.contract import objects as o
from drivers.canopen.bus import frame_bits
from drivers.canopen.sdo import SdoAccess

log = logging.getLogger(__name__)

BUS_BUDGET_PCT = 80.0        # live PDOs + SYNC may use at most this much of the bus
POLICIES = ("auto", "remap", "device")
STRUCT_CODES = {(o.BOOLEAN, 8): "B", (o.UNSIGNED8, 8): "B", (o.INTEGER8, 8): "b", (o.UNSIGNED16, 16): "H",
                (o.INTEGER16, 16): "h", (o.UNSIGNED32, 32): "L", (o.INTEGER32, 32): "l", (o.REAL32, 32): "f"}
COMM_SUBS = (1, 2, 3, 5)     # COB-ID, transmission type, inhibit time, event timer
SYNC_EVERY_CYCLE = 1
EVENT_DRIVEN = 255
SYNC_TYPES = range(0, 241)   # CiA 301 transmission types answering SYNC (0 acyclic, 1-240 every n-th SYNC)


@dataclass(frozen=True)
class Entry:
    """One mapped object: what it is to the bench (role: "_statusword", "_mode", "_step", a signal name, or ""
    for an object the bench does not read) and how to scale it."""

    index: int
    subindex: int
    bits: int
    code: str                   # struct code; "" = skipped bytes
    role: str = ""
    factor: float = 1.0

    @property
    def mapping(self) -> int:
        return o.mapping_entry(self.index, self.subindex, self.bits)


@dataclass
class Tpdo:
    number: int                 # 1-based
    cob: int
    entries: list[Entry]
    trans_type: int = SYNC_EVERY_CYCLE
    event_timer_ms: int = 0

    @property
    def event_driven(self) -> bool:
        return self.trans_type not in SYNC_TYPES

    @property
    def layout(self) -> struct.Struct:
        return struct.Struct("<" + "".join(e.code or f"{e.bits // 8}x" for e in self.entries))

    @property
    def size(self) -> int:
        return sum(e.bits for e in self.entries) // 8


@dataclass
class Rpdo:
    number: int
    cob: int
    entries: list[Entry]

    def pack(self, values: dict[int, int]) -> bytes:
        """values: object index -> raw value (controlword, target velocity, mode); unmapped objects as 0."""
        return struct.pack("<" + "".join(e.code for e in self.entries), *(values.get(e.index, 0) for e in self.entries))


@dataclass
class PdoPlan:
    policy: str                             # "remap" | "device"
    tpdos: list[Tpdo]
    rpdo: Rpdo | None                       # None: target velocity by SDO
    bus_load_pct: float
    dropped: list[str] = field(default_factory=list)     # wanted signals no TPDO carries
    encoding: str = "native"

    def as_record(self) -> dict:
        return {"policy": self.policy, "bus_load_pct": round(self.bus_load_pct, 2), "encoding": self.encoding,
                "tpdos": [{"number": t.number, "cob_id": f"0x{t.cob:03X}", "transmission_type": t.trans_type,
                           **({"event_timer_ms": t.event_timer_ms} if t.event_driven else {}),
                           "objects": [f"0x{e.index:04X}:{e.subindex:02X}" + (f" {e.role}" if e.role else "")
                                       for e in t.entries]} for t in self.tpdos],
                "rpdo": None if self.rpdo is None else {"number": self.rpdo.number, "cob_id": f"0x{self.rpdo.cob:03X}",
                                                         "objects": [f"0x{e.index:04X}" for e in self.rpdo.entries]},
                "not_carried": list(self.dropped)}


def entry_for(od: objectdictionary.ObjectDictionary, index: int, subindex: int = 0, role: str = "",
              factor: float = 1.0) -> Entry:
    obj = od[index]
    var = obj if isinstance(obj, objectdictionary.ODVariable) else obj[subindex]
    bits = len(var)
    return Entry(index, subindex, bits, STRUCT_CODES.get((var.data_type, bits), ""), role, factor)


def load_pct(sizes: Sequence[int], bitrate: int, sync_period_s: float) -> float:
    bits = frame_bits(0) + sum(frame_bits(n) for n in sizes)
    return 100.0 * bits / (bitrate * sync_period_s)


def pack_groups(head: list[Entry], entries: list[Entry], n_tpdo: int, bitrate: int,
                sync_period_s: float) -> tuple[list[list[Entry]], list[Entry], float]:
    """TPDO contents: the head in TPDO1, then the entries in order, first fit into 8-byte frames, within the bus
    budget and the drive's number of TPDOs. Returns (groups, entries that did not fit, bus load %)."""
    groups = [list(head)]
    dropped: list[Entry] = []
    for entry in entries:
        target = next((g for g in groups[1:] if sum(e.bits for e in g) + entry.bits <= 64), None)
        if target is None:
            trial = groups + [[entry]]
            if len(trial) > n_tpdo or load_pct([sum(e.bits for e in g) // 8 for g in trial], bitrate,
                                               sync_period_s) > BUS_BUDGET_PCT:
                dropped.append(entry)
                continue
            groups.append([entry])
        else:
            target.append(entry)
    return groups, dropped, load_pct([sum(e.bits for e in g) // 8 for g in groups], bitrate, sync_period_s)


# -- snapshot / restore ---------------------------------------------------------------------------------------------

@dataclass
class PdoSnapshot:
    """The drive's own PDO parameters as read by SDO before the bench changed anything (raw bytes per sub)."""

    values: dict[tuple[int, int], bytes] = field(default_factory=dict)
    touched: dict[int, bool] = field(default_factory=dict)   # comm index the bench wrote -> its mapping too

    @classmethod
    def read(cls, sdo: SdoAccess) -> "PdoSnapshot":
        snap = cls()
        for comm_base, map_base, count in ((o.RPDO_COMM, o.RPDO_MAP, o.N_RPDO_MAX), (o.TPDO_COMM, o.TPDO_MAP,
                                                                                      o.N_TPDO_MAX)):
            for n in range(count):
                if not sdo.has(comm_base + n):
                    break
                for sub in COMM_SUBS:
                    if sdo.has(comm_base + n, sub):
                        snap.values[(comm_base + n, sub)] = sdo.upload(comm_base + n, sub)
                if sdo.has(map_base + n):
                    n_mapped = sdo.upload(map_base + n, 0)
                    snap.values[(map_base + n, 0)] = n_mapped
                    for sub in range(1, n_mapped[0] + 1):
                        snap.values[(map_base + n, sub)] = sdo.upload(map_base + n, sub)
        return snap

    def raw(self, index: int, sub: int) -> int:
        return int.from_bytes(self.values[(index, sub)], "little")

    def mapping(self, map_index: int) -> list[tuple[int, int, int]]:
        n = self.values[(map_index, 0)][0] if (map_index, 0) in self.values else 0
        return [o.unpack_mapping_entry(self.raw(map_index, k)) for k in range(1, n + 1)]

    def restore_one(self, sdo: SdoAccess, comm: int) -> None:
        """Invalidate, mapping back (where the bench changed it), communication parameters back, COB-ID (and its
        validity) back."""
        mapping = comm + (o.RPDO_MAP - o.RPDO_COMM)
        cob = self.values[(comm, 1)]
        sdo.download(comm, 1, (int.from_bytes(cob, "little") | o.COB_ID_INVALID).to_bytes(4, "little"))
        if self.touched.get(comm) and (mapping, 0) in self.values:
            sdo.download(mapping, 0, b"\0")
            for sub in range(1, self.values[(mapping, 0)][0] + 1):
                sdo.download(mapping, sub, self.values[(mapping, sub)])
            sdo.download(mapping, 0, self.values[(mapping, 0)])
        for sub in COMM_SUBS[1:]:
            if (comm, sub) in self.values:
                sdo.download(comm, sub, self.values[(comm, sub)])
        sdo.download(comm, 1, cob)

    def restore(self, sdo: SdoAccess) -> list[str]:
        """Every PDO the bench wrote, back as it was; the failures, as text (every PDO is tried)."""
        errors = []
        for comm in sorted(self.touched):
            try:
                self.restore_one(sdo, comm)
            except LinkError as exc:
                errors.append(str(exc))
        self.touched.clear()
        return errors

    def touch(self, comm: int, mapping: bool = False) -> None:
        self.touched[comm] = self.touched.get(comm, False) or mapping


# -- writing ------------------------------------------------------------------------------------------------------

def write_pdo(sdo: SdoAccess, snap: PdoSnapshot, comm: int, cob: int, trans_type: int,
              entries: list[Entry] | None, event_timer_ms: int = 0) -> None:
    """CiA 301 order: COB-ID invalid, (mapping count 0, entries, count), transmission type (and event timer), COB-ID
    valid. On a refusal the PDO is restored from the snapshot before the LinkError goes up."""
    mapping = comm + (o.RPDO_MAP - o.RPDO_COMM)
    snap.touch(comm)
    try:
        sdo.download(comm, 1, (cob | o.COB_ID_INVALID).to_bytes(4, "little"))
        if entries is not None:
            sdo.download(mapping, 0, b"\0")
            snap.touch(comm, mapping=True)
            for k, entry in enumerate(entries, start=1):
                sdo.download(mapping, k, entry.mapping.to_bytes(4, "little"))
            sdo.download(mapping, 0, bytes([len(entries)]))
        sdo.download(comm, 2, bytes([trans_type]))
        if event_timer_ms:
            sdo.download(comm, 5, event_timer_ms.to_bytes(2, "little"))
        sdo.download(comm, 1, cob.to_bytes(4, "little"))
    except LinkError:
        try:
            snap.restore_one(sdo, comm)
            snap.touched.pop(comm, None)
        except LinkError as exc:
            log.error("PDO 0x%04X: restoring after a refused write failed: %s", comm, exc)
        raise


def disable_pdo(sdo: SdoAccess, snap: PdoSnapshot, comm: int) -> None:
    cob = snap.raw(comm, 1)
    if not cob & o.COB_ID_INVALID:
        snap.touch(comm)
        sdo.download(comm, 1, (cob | o.COB_ID_INVALID).to_bytes(4, "little"))


def count_pdos(sdo: SdoAccess, comm_base: int, limit: int) -> int:
    return next((n for n in range(limit) if not sdo.has(comm_base + n)), limit)


def event_timer_for(sync_period_s: float) -> int:
    """An event-driven TPDO's event timer (0x18xx sub 5, ms): the SYNC period, rounded up, at least 1 ms."""
    return max(1, min(0xFFFF, math.ceil(sync_period_s * 1000 - 1e-9)))


def write_tpdo(sdo: SdoAccess, snap: PdoSnapshot, comm: int, cob: int, entries: list[Entry] | None,
               sync_period_s: float) -> tuple[int, int]:
    """A TPDO sent on every SYNC (type 1); where the drive refuses SYNC transmission (an abort on 0x18xx sub 2),
    event-driven (type 255) with the event timer at the SYNC period. Returns (transmission type, event timer ms)."""
    try:
        write_pdo(sdo, snap, comm, cob, SYNC_EVERY_CYCLE, entries)
        return SYNC_EVERY_CYCLE, 0
    except LinkError as exc:
        if f"0x{comm:04X}:02" not in str(exc) or "aborted" not in str(exc):
            raise
        log.info("TPDO 0x%04X: SYNC transmission refused (%s); event-driven instead", comm, exc)
    timer = event_timer_for(sync_period_s)
    try:
        write_pdo(sdo, snap, comm, cob, EVENT_DRIVEN, entries, timer)
    except LinkError as exc:
        raise LinkError(f"{exc}: 0x{comm:04X} (TPDO communication parameter) refuses transmission type 1 (every SYNC) "
                        f"and 255 (event-driven, event timer {timer} ms at 0x{comm:04X}:05); the bench cannot "
                        f"receive this TPDO: map the signals into another TPDO, or write pdo = \"device\" in [drive] "
                        f"to use the drive's own mapping") from None
    return EVENT_DRIVEN, timer


def apply_remap(sdo: SdoAccess, snap: PdoSnapshot, node_id: int, groups: list[list[Entry]],
                rpdo_entries: list[Entry], sync_period_s: float = 0.001) -> tuple[list[Tpdo], Rpdo]:
    """Our mapping in TPDO 1..n (SYNC every cycle, else event-driven), the drive's other TPDOs off,
    RPDO1 <- rpdo_entries."""
    tpdos = []
    for n, group in enumerate(groups):
        cob = o.TPDO_COB[n] + node_id
        trans_type, timer = write_tpdo(sdo, snap, o.TPDO_COMM + n, cob, group, sync_period_s)
        tpdos.append(Tpdo(n + 1, cob, group, trans_type, timer))
    for n in range(len(groups), count_pdos(sdo, o.TPDO_COMM, o.N_TPDO_MAX)):
        disable_pdo(sdo, snap, o.TPDO_COMM + n)
    cob = o.RPDO_COB[0] + node_id
    write_pdo(sdo, snap, o.RPDO_COMM, cob, EVENT_DRIVEN, rpdo_entries)
    return tpdos, Rpdo(1, cob, rpdo_entries)


def apply_device_mapping(sdo: SdoAccess, snap: PdoSnapshot, od: objectdictionary.ObjectDictionary,
                         roles: dict[tuple[int, int], tuple[str, float]],
                         sync_period_s: float = 0.001) -> tuple[list[Tpdo], Rpdo | None]:
    """Use the TPDOs whose mapping (read from the device) carries something the bench reads: made valid and sent on
    every SYNC (only their communication parameters are written). The RPDO that carries the target velocity, made
    valid and event-driven; None when there is none (target by SDO)."""
    tpdos: list[Tpdo] = []
    for n in range(count_pdos(sdo, o.TPDO_COMM, o.N_TPDO_MAX)):
        mapped = snap.mapping(o.TPDO_MAP + n)
        if not any((i, s) in roles for i, s, _ in mapped):
            continue
        entries = [_device_entry(od, i, s, bits, roles) for i, s, bits in mapped]
        cob = snap.raw(o.TPDO_COMM + n, 1) & 0x7FF
        trans_type, timer = write_tpdo(sdo, snap, o.TPDO_COMM + n, cob, None, sync_period_s)
        tpdos.append(Tpdo(n + 1, cob, entries, trans_type, timer))
    rpdo = None
    for n in range(count_pdos(sdo, o.RPDO_COMM, o.N_RPDO_MAX)):
        mapped = snap.mapping(o.RPDO_MAP + n)
        if any(i == o.TARGET_VELOCITY for i, _, _ in mapped):
            entries = [_device_entry(od, i, s, bits, {}) for i, s, bits in mapped]
            if all(e.code for e in entries):
                cob = snap.raw(o.RPDO_COMM + n, 1) & 0x7FF
                write_pdo(sdo, snap, o.RPDO_COMM + n, cob, EVENT_DRIVEN, None)
                rpdo = Rpdo(n + 1, cob, entries)
                break
    return tpdos, rpdo


def _device_entry(od, index: int, subindex: int, bits: int, roles: dict) -> Entry:
    role, factor = roles.get((index, subindex), ("", 1.0))
    try:
        known = entry_for(od, index, subindex, role, factor)
        if known.bits == bits:
            return known
    except KeyError:
        pass
    return Entry(index, subindex, bits, "", "", 1.0)      # an object the bench does not read: skipped bytes


# -- decoding -----------------------------------------------------------------------------------------------------

@dataclass
class TpdoDecoder:
    """Joins one SYNC's TPDOs into one LiveSample. Time: the drive clock when a TPDO carries it; else, in lockstep,
    SYNCs counted x period (exact: the drive advances one period per SYNC); in real time `placer(stamp, received)`
    of the first TPDO (drivers.canopen.sync: the SYNC it answers, or for event-driven TPDOs the receive time on the
    bench clock). Not thread-safe: the link calls it under its lock."""

    sync_period_s: float
    control_period_s: float | None
    placer: Callable[[float | None, float], float] | None = None
    tpdos: dict[int, Tpdo] = field(default_factory=dict)
    statusword: int = 0
    sync_count: int = 0
    incomplete: int = 0                     # samples emitted with a TPDO missing (real time)
    _partial: dict[str, float] = field(default_factory=dict)
    _seen: set[int] = field(default_factory=set)
    _partial_t: float = 0.0
    _wraps: int = 0
    _last_step: int | None = None
    # cob -> (the Tpdo, its layout, (role, factor) of each value it carries): built once, not at every frame
    _plans: dict[int, tuple[Tpdo, struct.Struct, list[tuple[str, float]]]] = field(default_factory=dict)

    def add(self, tpdo: Tpdo) -> None:
        self.tpdos[tpdo.cob] = tpdo

    @property
    def has_clock(self) -> bool:
        return any(e.role == "_step" for t in self.tpdos.values() for e in t.entries)

    def decode(self, cob: int, data: bytes, timestamp: float = 0.0) -> list[LiveSample] | str:
        """Finished samples (usually none or one), or an error text (wrong length)."""
        tpdo = self.tpdos[cob]
        plan = self._plans.get(cob)
        if plan is None or plan[0] is not tpdo:
            plan = self._plans[cob] = (tpdo, tpdo.layout, [(e.role, e.factor) for e in tpdo.entries if e.code])
        _, layout, carried = plan
        if len(data) != layout.size:
            return f"TPDO 0x{cob:03X} has {len(data)} bytes, its mapping needs {layout.size}"
        out: list[LiveSample] = []
        if cob in self._seen:                        # a new SYNC before the last one completed: a TPDO was lost
            self.incomplete += 1
            out.append(self._emit())
        if not self._seen:
            self._start(timestamp)
        self._seen.add(cob)
        for (role, factor), value in zip(carried, layout.unpack(data)):
            if role == "_statusword":
                self.statusword = value
            elif role == "_step":
                if self._last_step is not None and value < self._last_step:
                    self._wraps += 1
                self._last_step = value
                self._partial_t = (value + (self._wraps << 32)) * self.control_period_s
            elif role and not role.startswith("_"):
                self._partial[role] = value * factor
        if len(self._seen) == len(self.tpdos):
            out.append(self._emit())
        return out

    def _start(self, timestamp: float) -> None:
        self.sync_count += 1
        if self.placer is not None:
            self._partial_t = self.placer(timestamp, time.time())
        else:
            self._partial_t = self.sync_count * self.sync_period_s

    def _emit(self) -> LiveSample:
        sample = LiveSample(t_s=self._partial_t, values=dict(self._partial))
        self._partial, self._seen = {}, set()
        return sample


def roles_for(sources: Iterable, head: dict[int, str]) -> dict[tuple[int, int], tuple[str, float]]:
    roles = {(index, 0): (role, 1.0) for index, role in head.items()}
    roles.update({(s.index, s.subindex): (s.signal, s.factor) for s in sources})
    return roles


def nan_row(names: Sequence[str]) -> dict[str, float]:
    return {n: math.nan for n in names}
