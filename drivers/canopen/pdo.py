"""Live PDOs: which objects go into which TPDO within the bus budget, writing the mappings, and decoding what
arrives into drive-clock-stamped samples."""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Sequence

import canopen
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from drivers.api import LinkError, LiveSample
from drivers.canopen import objects as o
from drivers.canopen.bus import frame_bits
from drivers.canopen.sdo import abort_text

BUS_BUDGET_PCT = 80.0        # live PDOs + SYNC may use at most this much of the bus
STRUCT_CODES = {(o.UNSIGNED16, 16): "H", (o.INTEGER8, 8): "b", (o.UNSIGNED32, 32): "L", (o.INTEGER32, 32): "l",
                (o.UNSIGNED8, 8): "B", (o.INTEGER16, 16): "h", (o.REAL32, 32): "f"}


@dataclass(frozen=True)
class LivePlan:
    groups: list[list[tuple[str, str, float]]]      # per TPDO after TPDO1: (object name, signal, factor)
    encoding: str                                   # "real32" | "scaled"
    bus_load_pct: float


def plan_live(od: canopen.ObjectDictionary, live_signals: Sequence[str], tpdo1_bytes: int, bitrate: int,
              sync_period_s: float, eds_name: str) -> LivePlan:
    """REAL32 objects if they fit the bus budget at the SYNC rate, else the drive's scaled INTEGER16 objects
    (`scaled_<name>`)."""
    missing = [s for s in live_signals if s not in od]
    if missing:
        raise LinkError(f"{eds_name}: no object for live signal(s) {', '.join(missing)}")
    load = 0.0
    for encoding, per_pdo in (("real32", 2), ("scaled", 4)):
        names = [name if encoding == "real32" else o.SCALED_PREFIX + name for name in live_signals]
        if any(n not in od for n in names):
            continue
        entries = [(n, s, 1.0 if encoding == "real32" else float(od[n].factor)) for n, s in zip(names, live_signals)]
        groups = [entries[i:i + per_pdo] for i in range(0, len(entries), per_pdo)]
        sizes = [tpdo1_bytes] + [sum(len(od[n]) // 8 for n, _, _ in g) for g in groups]
        bits = frame_bits(0) + sum(frame_bits(n) for n in sizes)
        load = 100.0 * bits / (bitrate * sync_period_s)
        if load <= BUS_BUDGET_PCT and len(sizes) <= o.N_TPDO_MAX:
            return LivePlan(groups, encoding, load)
    raise LinkError(f"{len(live_signals)} live signals every {sync_period_s * 1e3:g} ms need "
                    f"{load:.0f}% of the {bitrate / 1e6:g} Mbit/s bus (budget {BUS_BUDGET_PCT:.0f}%, "
                    f"{o.N_TPDO_MAX} TPDOs)")


def write_mappings(node: canopen.RemoteNode, tpdo_maps: list[list[tuple[int, int]]],
                   rpdo1: Sequence[int]) -> None:
    """TPDO n+1 <- tpdo_maps[n] (SYNC every cycle), the remaining TPDOs of the EDS disabled; RPDO1 <- rpdo1
    (event-driven). The node must be PRE-OPERATIONAL."""
    od = node.object_dictionary
    try:
        for n in range(o.N_TPDO_MAX):
            if o.TPDO_COMM + n not in od:
                break
            pdo = node.tpdo[n + 1]
            pdo.read(from_od=True)
            pdo.clear()
            if n < len(tpdo_maps):
                for index, subindex in tpdo_maps[n]:
                    pdo.add_variable(index, subindex)
                pdo.cob_id = o.TPDO_COB[n] + node.id
                pdo.trans_type = 1
                pdo.enabled = True
            else:
                pdo.enabled = False
            pdo.save()
        rpdo = node.rpdo[1]
        rpdo.read(from_od=True)
        rpdo.clear()
        for index in rpdo1:
            rpdo.add_variable(index)
        rpdo.cob_id = o.RPDO_COB[0] + node.id
        rpdo.trans_type = 255
        rpdo.enabled = True
        rpdo.save()
    except SdoAbortedError as exc:
        raise LinkError(f"node {node.id}: PDO configuration rejected: SDO abort 0x{exc.code:08X} "
                        f"({abort_text(exc)})") from None
    except SdoCommunicationError as exc:
        raise LinkError(f"node {node.id}: PDO configuration: {exc}") from None


@dataclass
class _Tpdo:
    layout: struct.Struct
    names: list[str]
    factors: list[float]
    position: int                  # 0 = TPDO1 (statusword, mode, drive clock)


@dataclass
class TpdoDecoder:
    """Joins one SYNC's TPDOs into one LiveSample stamped with the drive clock (or, without one, SYNCs counted x
    period). Not thread-safe: the link calls it under its lock."""

    sync_period_s: float
    control_period_s: float | None
    tpdos: dict[int, _Tpdo] = field(default_factory=dict)
    last_cob: int = 0
    statusword: int = 0
    sync_count: int = 0
    _partial: dict[str, float] = field(default_factory=dict)
    _partial_t: float = 0.0
    _wraps: int = 0
    _last_step: int | None = None

    def add(self, cob: int, layout: str, names: list[str], factors: list[float], position: int) -> None:
        self.tpdos[cob] = _Tpdo(struct.Struct(layout), names, factors, position)

    def decode(self, cob: int, data: bytes) -> LiveSample | str | None:
        """A finished sample, None (more TPDOs of this SYNC to come), or an error text (wrong length)."""
        tpdo = self.tpdos[cob]
        if len(data) != tpdo.layout.size:
            return f"TPDO 0x{cob:03X} has {len(data)} bytes, its mapping needs {tpdo.layout.size}"
        values = tpdo.layout.unpack(data)
        if tpdo.position == 0:
            self._partial = {}
            fields = dict(zip(tpdo.names, values))
            self.statusword = fields["_statusword"]
            self.sync_count += 1
            step = fields.get("_step")
            if step is None:       # a drive without a clock object: count SYNCs
                self._partial_t = self.sync_count * self.sync_period_s
            else:
                if self._last_step is not None and step < self._last_step:
                    self._wraps += 1
                self._last_step = step
                self._partial_t = (step + (self._wraps << 32)) * self.control_period_s
        else:
            self._partial.update(zip(tpdo.names, (v * f for v, f in zip(values, tpdo.factors))))
        if cob == self.last_cob:
            return LiveSample(t_s=self._partial_t, values=dict(self._partial))
        return None
