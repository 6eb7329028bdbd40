"""DriveLink over CANopen CiA 402 (python-can + canopen): any python-can interface, any 402 drive.

What the bench gets from a drive:
- identity (0x1018), device name (0x1008), software version (0x100A) and its drive profile (drivers.canopen.profile):
  which objects give which signals in which units, read from the drive's factor group at connect time;
- the 402 state machine (drivers.contract.cia402) stepped by SDO — confirmed, and usable whatever state the drive's PDOs are
  in; the target velocity streamed by an RPDO when one carries it (else by SDO), in the drive's velocity unit;
- live samples from TPDOs sent on SYNC (drivers.canopen.pdo: our mapping where the drive allows it, else the one read
  from the device; the drive's own PDO parameters restored at the end);
- heartbeat consumer (0x700+id) and EMCY (0x80+id); the bench's own heartbeat and the drive's reaction to losing it
  (drivers.canopen.comm_loss_guard) armed before anything moves;
- on a drive carrying drivebench's extension, its drive clock and the trace recorder uploaded by SDO block transfer.

Timing: "lockstep" sends one SYNC per sync() and waits for that SYNC's TPDOs; "realtime" produces SYNC on the wall
clock (drivers.canopen.sync) and sync() returns what arrived since the last call. Samples are stamped with the drive's
own clock where the drive has one; otherwise with the SYNC they answer x period (lockstep: counted; real time:
drivers.canopen.sync.SyncTimeline, so a late frame is jitter and a missing answer a gap), and event-driven TPDOs (a
drive refusing SYNC transmission) with their receive time on the bench clock, their jitter stated in the record.

Velocity mode: profile velocity (3) where 0x6502 has it, else cyclic synchronous velocity (9: the target goes out
by RPDO with every SYNC); `velocity_mode` in [drive] chooses. `boot_timeout_s`: how long a drive that does not answer
yet may take to send its NMT boot-up message.
"""

from __future__ import annotations

import collections
import logging
import math
import struct
import threading
import time
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import can
import canopen
import numpy as np
from canopen import objectdictionary
from canopen.emcy import EmcyError
from canopen.sdo import SdoAbortedError

from drivers.contract import cia402
from drivers.api import DriveIdentity, DriveLink, DriveStatus, LinkSettings, LiveSample
from drivers.contract.errors import LinkError
from drivers.contract import objects as o
from drivers.canopen import pdo as pdos
from drivers.canopen.config import CanopenDriveConfig
from drivers.canopen.bus import BusErrorCounter, QuickVirtualBus, SocketcandRefusal, bus_kwargs, make_bus, open_bus
from drivers.canopen.comm_loss_guard import CommLossGuard
from drivers.canopen import closing, mode_select
from drivers.canopen.bus_drop import BusDropWatch
from drivers.contract.control_watch import ControlWatch
from drivers.canopen import drill as drills
from drivers.contract.comm_loss import CommLossConfig
from drivers.canopen.profile import DriveProfile, ProfileConfig, resolve
from drivers.contract.errors import ContentError
from drivers.contract.eds import load_od
from drivers.canopen.dispatch import FrameDispatch, HandlingNetwork, RunReceiver, frame_dispatch
from drivers.canopen.sdo import SdoAccess, block_upload
from drivers.canopen.sync import NativeSync, ReceiveClock, SyncProducer, SyncTimeline, has_native_cyclic
from drivers.contract.signals import SIGNAL_NAMES, TIME_COLUMN
from drivers.contract.trace_format import decode_rows, mask_for

log = logging.getLogger(__name__)

MIN_STALL_TIMEOUT_S = 2.0
MAX_UPLOADS_PER_FETCH = 64     # bounds one fetch_trace() whatever the node reports as available; the rest comes next time
REALTIME_BATCH_S = 0.01      # real time: sync() hands over samples in batches of at most this period
HEAD = {o.STATUSWORD: "_statusword", o.MODES_DISPLAY: "_mode"}
SYNC_COUNTER_OVERFLOW = 0x1019      # CiA 301 synchronous counter overflow value (0: SYNC without a counter)
SYNC_COUNTER_MAX = 240
VELOCITY_MODES = {"auto": None, "pv": cia402.Mode.PROFILE_VELOCITY, "csv": cia402.Mode.CYCLIC_SYNC_VELOCITY}


class CanopenDriveLink(DriveLink):
    def __init__(self, config: CanopenDriveConfig | Mapping[str, Any], base_dir: Path, settings: LinkSettings):
        cfg = self.section = CanopenDriveConfig.from_mapping(config)
        eds = Path(cfg.eds)
        self.eds_path = eds if eds.is_absolute() else Path(base_dir) / eds
        self.node_id = int(cfg.node_id)
        self.sync_period_s = float(cfg.sync_period_s)
        self.heartbeat_timeout_s = float(cfg.heartbeat_timeout_s)
        self.sdo_timeout_s = float(cfg.sdo_timeout_s)
        self.pdo_policy = cfg.pdo
        self.standstill_mech_rad_s = float(cfg.standstill_mech_rad_s)
        self.stop_timeout_s = float(cfg.stop_timeout_s)
        self.boot_timeout_s = float(cfg.boot_timeout_s)
        self.velocity_mode_choice = str(cfg.velocity_mode)
        self.mode = cia402.Mode.PROFILE_VELOCITY      # what enable_velocity_mode() selected
        self.profile_config = ProfileConfig.from_section(cfg)
        self.comm_loss_config = CommLossConfig.from_section(cfg)
        self.timing = settings.timing
        self.fault_reset_policy = settings.fault_reset
        # Waits the drive's SDO timeout does not cover: a lockstep SYNC's TPDOs and the frames inside a running
        # block transfer. Generous, because a simulator on a loaded host can stall for a few hundred ms.
        self.stall_timeout_s = max(MIN_STALL_TIMEOUT_S, self.sdo_timeout_s, 10 * self.sync_period_s)
        self.where = f"node {self.node_id}"
        self.network: canopen.Network | None = None
        self.node: canopen.RemoteNode | None = None
        self.sdo: SdoAccess | None = None
        self.identity: DriveIdentity | None = None
        self.profile: DriveProfile | None = None
        self.plan: pdos.PdoPlan | None = None
        self.control_period_s: float | None = None
        self.report: dict[str, Any] = {}             # what was read and set, for the record
        self._snapshot: pdos.PdoSnapshot | None = None
        self._guard: CommLossGuard | None = None
        self._producer_restore: int | None = None     # 0x1017 as the drive had it (drivers.canopen.closing)
        self.control = ControlWatch(tuple(cfg.enable_bits or ()))    # statusword bit 9 and [drive] enable_bits
        self.bus_drop = BusDropWatch(self.sync_period_s)
        self._lock = threading.Condition()
        self._cancel = threading.Event()
        self._last_heartbeat = 0.0
        self._heartbeat_state: int | None = None
        self._booted = threading.Event()
        self._emcy: list[tuple[int, str]] = []
        self._errors: list[str] = []
        self._samples: collections.deque[LiveSample] = collections.deque()
        self._latest: LiveSample | None = None
        self._completed = 0           # SYNC cycles whose TPDOs all arrived
        self._decoder = pdos.TpdoDecoder(self.sync_period_s, None)
        self._controlword = 0
        self._target = 0              # in the drive's velocity unit
        self._quick_stop_state: cia402.State | None = None     # set by begin_quick_stop, taken by quick_stop
        self._trace_mask = 0
        self._sync: SyncProducer | NativeSync | None = None
        self._placer: SyncTimeline | ReceiveClock | None = None
        self._sync_counter_restore: int | None = None
        self._rpdo_frame: bytes | None = None     # CSV: what goes out before every SYNC
        self.time_base = "sync count"             # "drive clock" | "sync count" | "sync answered" | "receive time"
        self.commands: collections.deque[dict] = collections.deque(maxlen=10_000)   # realtime: with their SYNC
        self.frames_sent = 0
        self.live_bus_load_pct = 0.0
        self.live_encoding = "native"
        self._rx_lag_s = 0.0
        self._last_return = 0.0
        self.bus_errors = BusErrorCounter()
        self._reference_speed: Callable[[], float | None] | None = None
        self._refusal: SocketcandRefusal | None = None
        self._dispatch: FrameDispatch | None = None
        self._tpdo_receiver = RunReceiver(self._on_tpdo, self._on_tpdos)

    # -- connection ----------------------------------------------------------------------------------
    def open(self) -> DriveIdentity:
        kwargs = bus_kwargs(self.section)
        try:
            self.network = HandlingNetwork()
            self.network.NOTIFIER_CYCLE = 0.02  # close() returns within 20 ms (the notifier thread polls)
            open_bus(kwargs, lambda: self._connect(kwargs))
        except (can.CanError, OSError, ValueError, TimeoutError, TypeError) as exc:
            raise LinkError(f"CAN interface {self.section.get('interface')!r} channel "
                            f"{self.section.get('channel')!r}: cannot open: {exc}") from None
        try:
            od = load_od(self.eds_path, self.node_id)
        except Exception as exc:
            raise LinkError(f"{self.eds_path}: cannot load the object dictionary: {exc}") from None
        self.network.notifier.add_listener(self.bus_errors.on_message_received)   # without Listener.__call__
        self.node = self.network.add_node(self.node_id, od)
        self.node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout_s
        self.node.sdo.MAX_RETRIES = 1
        self.sdo = sdo = SdoAccess(self.node, self.eds_path.name, self.sdo_timeout_s)
        self._last_heartbeat = time.monotonic()
        self.network.subscribe(o.HEARTBEAT + self.node_id, self._on_heartbeat)
        self.network.subscribe(o.EMCY + self.node_id, self._on_emcy)

        try:
            vendor, product, revision, serial = self._read_identity_after_boot(kwargs["interface"])
        except LinkError:
            if self._refusal is not None and self._refusal.refused.wait(SocketcandRefusal.WAIT_S):
                raise LinkError(f"{self._refusal.reason} ({self.section.get('interface')} "
                                f"{kwargs.get('host')}:{kwargs.get('port')})") from None
            raise
        name, version = (self._optional_text(index) for index in (o.DEVICE_NAME, o.SOFTWARE_VERSION))
        try:
            self.profile = resolve(self.profile_config, vendor, product, sdo.read_standard, sdo.has)
        except ContentError as exc:
            raise LinkError(f"{self.where}: drive profile: {exc}") from None
        has_trace = False
        if self.profile.extension:
            self.control_period_s = sdo.read(o.EXT_CONTROL_PERIOD_NS) * 1e-9
            try:
                self.node.sdo.upload(o.EXT_TRACE, o.TRACE_ROW_SIZE)
                has_trace = sdo.has(o.EXT_TRACE_DATA)
            except SdoAbortedError:
                has_trace = False
        # heartbeat producer at a quarter of our timeout
        closing.set_producer_heartbeat(self, max(10, min(1000, int(self.heartbeat_timeout_s * 1000 / 4))))
        self.identity = DriveIdentity(vendor_id=vendor, product_code=product, revision=revision, serial=serial,
                                      device_name=name, firmware_version=version,
                                      has_trace_recorder=has_trace)
        self.report["profile"] = self.profile.as_record()
        return self.identity

    def _connect(self, kwargs: dict) -> canopen.Network:
        """The bus first, a socketcand refusal watched on it before the network's receive thread starts (a refusal
        that arrives first would otherwise be parsed as a frame and kill that thread)."""
        bus = make_bus(kwargs)
        if isinstance(bus, QuickVirtualBus) and self.timing == "lockstep":   # nothing else runs while the bench waits
            bus.inline_delivery = True      # an in-process node answers in the sending thread, which handles the answer
            self.network.after_send = lambda: bus.handle_arrived(self.network.notifier.listeners, self._on_burst)
        self._refusal = SocketcandRefusal(bus) if kwargs["interface"] == "socketcand" else None
        self.network.bus = bus
        self._dispatch = frame_dispatch(self.network)
        self.network.listeners = [self._dispatch]
        return self.network.connect(**kwargs)

    def _on_burst(self, timestamp: float, frames: list[tuple[int, bytes]]) -> None:
        """A burst of frames handled at once (QuickVirtualBus.handle_arrived): what the notifier's listeners do."""
        self._dispatch.burst(timestamp, frames)
        self.bus_errors.count_good(len(frames))

    def _read_identity_after_boot(self, interface: str) -> tuple[int, int, int, int]:
        """0x1018 (identity), the first SDO. A drive that does not answer may still be booting: with `boot_timeout_s`
        the bench waits (that long from open()) for its NMT boot-up message (0x700 + id, data 0x00) or any heartbeat,
        then asks again."""
        deadline = time.monotonic() + self.boot_timeout_s
        waited_from = time.monotonic()
        while True:
            try:
                return tuple(self.sdo.read(o.IDENTITY, k) for k in (1, 2, 3, 4))
            except LinkError as exc:
                if "aborted" in str(exc):
                    raise
                if time.monotonic() >= deadline:
                    hint = (f"no NMT boot-up (0x{o.HEARTBEAT + self.node_id:03X} data 00) within boot_timeout_s = "
                            f"{self.boot_timeout_s:g} s" if self.boot_timeout_s > 0 else
                            "a drive still booting sends its NMT boot-up message (0x700 + node id, data 00) when "
                            "ready: write boot_timeout_s = 5 in [drive] to wait for it")
                    served = (" (a served simulator admits one bench at a time: is another bench connected?)"
                              if interface == "socketcand" else "")
                    raise LinkError(f"{exc}: the drive does not answer; {hint}; check node_id, bitrate and wiring"
                                    f"{served}") from None
                if self._booted.wait(max(0.0, deadline - time.monotonic())):   # set also during the failed read
                    self._booted.clear()
                    self.report["boot_up_after_s"] = round(time.monotonic() - waited_from, 3)

    def _optional_text(self, index: int) -> str:
        """Device name / software version: informative; a drive that does not answer them still runs."""
        if not self.sdo.has(index):
            return ""
        try:
            return str(self.sdo.read(index))
        except LinkError as exc:
            log.info("node %d: %s", self.node_id, exc)
            return ""

    def interrupt(self) -> None:
        """From another thread: end a trace upload in progress at once (the bench is abandoning a stuck run loop
        and its safe stop needs the node's SDO channel). Uploads stay refused from then on."""
        self._cancel.set()

    def close(self) -> None:
        """The drive's own settings back (comm-loss objects first, then PDOs), then off the bus — only once the drive
        is disabled; else the last resort (drivers.canopen.closing): 0x1016 left armed, the heartbeat withheld."""
        self._stop_sync_producer()
        if self.network is None:
            return
        errors: list[str] = []
        if self.sdo is not None:
            try:
                if closing.secured(self):
                    errors += closing.restore(self)
            except Exception as exc:       # closing must not mask the run's own error
                errors.append(str(exc))
        for error in errors:
            log.warning("node %d: restoring the drive's settings: %s", self.node_id, error)
        try:
            self.network.disconnect()
        except Exception as exc:
            log.warning("closing CAN network: %s", exc)
        self.network = None

    def sdo_upload(self, index: int, subindex: int = 0) -> bytes:
        """Raw SDO read of any index, with or without an EDS entry (LinkError names the index)."""
        return self.sdo.upload(index, subindex)

    # -- configuration -------------------------------------------------------------------------------
    @property
    def has_drive_clock(self) -> bool:
        return self.control_period_s is not None

    def measured_signals(self) -> frozenset[str]:
        """The signals that arrive live (what the PDO plan carries)."""
        if self.plan is None:
            return frozenset()
        return frozenset(e.role for t in self.plan.tpdos for e in t.entries if e.role and not e.role.startswith("_"))

    def _wanted(self, live_signals: Sequence[str]) -> tuple[list[pdos.Entry], str]:
        """The objects to carry live, most wanted first, and their encoding."""
        od = self.node.object_dictionary
        if self.profile.extension:
            for encoding in ("real32", "scaled"):
                names = [s if encoding == "real32" else o.SCALED_PREFIX + s for s in live_signals]
                if all(n in od for n in names):
                    entries = [pdos.entry_for(od, od[n].index, od[n].subindex, s,
                                              1.0 if encoding == "real32" else float(od[n].factor))
                               for n, s in zip(names, live_signals)]
                    if self._fits(entries) or encoding == "scaled":
                        return entries, encoding
            missing = [s for s in live_signals if s not in od]
            raise LinkError(f"{self.eds_path.name}: no object for live signal(s) {', '.join(missing)}")
        sources = sorted(self.profile.sources, key=lambda s: (s.signal not in live_signals,
                                                              list(SIGNAL_NAMES).index(s.signal)))
        return [pdos.entry_for(od, s.index, s.subindex, s.signal, s.factor) for s in sources], "native"

    def _head(self) -> list[pdos.Entry]:
        od = self.node.object_dictionary
        head = [pdos.entry_for(od, o.STATUSWORD, 0, "_statusword")]
        if self.sdo.has(o.MODES_DISPLAY):
            head.append(pdos.entry_for(od, o.MODES_DISPLAY, 0, "_mode"))
        if self.has_drive_clock:
            head.append(pdos.entry_for(od, o.EXT_STEP_COUNT, 0, "_step"))
        return head

    def _fits(self, entries: list[pdos.Entry]) -> bool:
        n_tpdo = pdos.count_pdos(self.sdo, o.TPDO_COMM, o.N_TPDO_MAX)
        _, dropped, load = pdos.pack_groups(self._head(), entries, n_tpdo, self._bitrate, self.sync_period_s)
        return not dropped

    @property
    def _bitrate(self) -> int:
        return self.section.get("bitrate") or 1_000_000

    def configure(self, live_signals: Sequence[str], trace_signals: Sequence[str], trace_decimation: int) -> None:
        self._stop_sync_producer()
        self.node.nmt.state = "PRE-OPERATIONAL"
        cycle_us = round(self.sync_period_s * 1e6)    # by the device, not the EDS: an EDS may omit what a drive has
        self.report["comm_cycle_period_0x1006"] = (f"{cycle_us} us" if self.sdo.write_standard(
            o.COMM_CYCLE_PERIOD, 0, cycle_us, 4) else "not on this drive")
        if self._snapshot is None:
            self._snapshot = pdos.PdoSnapshot.read(self.sdo)
        self.plan = self._plan_pdos(live_signals)
        self.live_encoding, self.live_bus_load_pct = self.plan.encoding, self.plan.bus_load_pct
        self.report["pdo"] = self.plan.as_record()
        our_cobs = {t.cob for t in self.plan.tpdos} | {c + self.node_id for c in o.TPDO_COB}
        for cob in our_cobs & set(self.network.subscribers):   # our decoder replaces canopen's PdoMap
            self.network.unsubscribe(cob)
        event_driven = any(t.event_driven for t in self.plan.tpdos)
        if self.has_drive_clock:
            self.time_base = "drive clock"
        elif self.timing != "realtime":
            self.time_base = "sync count"
        else:
            self.time_base = "receive time" if event_driven else "sync answered"
        decoder = pdos.TpdoDecoder(self.sync_period_s, self.control_period_s,
                                   placer=self._place if self.time_base in ("sync answered", "receive time") else None)
        for tpdo in self.plan.tpdos:
            decoder.add(tpdo)
        with self._lock:
            self._decoder = decoder
        for cob in decoder.tpdos:
            self.network.subscribe(cob, self._tpdo_receiver)

        if self._guard is None:
            self._guard = CommLossGuard(self.comm_loss_config, self.sdo, self.network)
            self.report["comm_loss"] = self._guard.arm()

        if self.identity and self.identity.has_trace_recorder:
            self._trace_mask = mask_for(list(trace_signals)) if trace_signals else 0
            if self._trace_mask:
                for sub, value in ((o.TRACE_CONTROL, o.TRACE_STOP), (o.TRACE_MASK, self._trace_mask),
                                   (o.TRACE_DECIMATION, int(trace_decimation)), (o.TRACE_TRIGGER, 0),
                                   (o.TRACE_CONTROL, o.TRACE_CLEAR), (o.TRACE_CONTROL, o.TRACE_START)):
                    self.sdo.write(o.EXT_TRACE, sub, value)
        self.read_statusword()
        if self.profile is not None:      # known before the SYNC producer starts: CSV needs ours (RPDO before SYNC)
            self.mode = self._velocity_mode()
        self._configure_sync_counter()
        self.node.nmt.state = "OPERATIONAL"
        if self.timing == "realtime":
            self._start_sync_producer()

    def _configure_sync_counter(self) -> None:
        """CiA 301 SYNC counter where the drive has 0x1019 (real time only: in lockstep each SYNC is answered before
        the next). 0x1019 may only change while 0x1006 is 0 (CiA 301), so 0x1006 goes to 0 and back around it."""
        if self.timing != "realtime" or not self.sdo.has(SYNC_COUNTER_OVERFLOW) or self._sync_counter_restore is not None:
            self.report.setdefault("sync_counter", "not on this drive" if self.timing == "realtime" else "lockstep")
            return
        try:
            old = self.sdo.read_standard(SYNC_COUNTER_OVERFLOW, 0)
            self.sdo.write_standard(o.COMM_CYCLE_PERIOD, 0, 0, 4)
            self.sdo.write_standard(SYNC_COUNTER_OVERFLOW, 0, SYNC_COUNTER_MAX, 1)
            self._sync_counter_restore = old or 0
            self.report["sync_counter"] = f"1..{SYNC_COUNTER_MAX} (0x1019)"
        except LinkError as exc:
            self.report["sync_counter"] = f"refused: {exc}"
        finally:
            self.sdo.write_standard(o.COMM_CYCLE_PERIOD, 0, round(self.sync_period_s * 1e6), 4)

    def _plan_pdos(self, live_signals: Sequence[str]) -> pdos.PdoPlan:
        if self.pdo_policy not in pdos.POLICIES:
            raise LinkError(f"{self.where}: pdo policy {self.pdo_policy!r} is not one of {', '.join(pdos.POLICIES)}")
        od = self.node.object_dictionary
        wanted, encoding = self._wanted(live_signals)
        n_tpdo = pdos.count_pdos(self.sdo, o.TPDO_COMM, o.N_TPDO_MAX)
        if self.pdo_policy in ("auto", "remap"):
            groups, dropped, load = pdos.pack_groups(self._head(), wanted, n_tpdo, self._bitrate, self.sync_period_s)
            if self.profile.extension and dropped:
                raise LinkError(f"{len(wanted)} live signals every {self.sync_period_s * 1e3:g} ms need more than "
                                f"{pdos.BUS_BUDGET_PCT:.0f}% of the {self._bitrate / 1e6:g} Mbit/s bus (budget "
                                f"{pdos.BUS_BUDGET_PCT:.0f}%, {n_tpdo} TPDOs)")
            rpdo = [pdos.entry_for(od, i) for i in (o.CONTROLWORD, o.TARGET_VELOCITY, o.MODES_OF_OPERATION)
                    if self.sdo.has(i)]
            try:
                tpdos, rpdo_layout = pdos.apply_remap(self.sdo, self._snapshot, self.node_id, groups, rpdo,
                                                      self.sync_period_s)
                return pdos.PdoPlan("remap", tpdos, rpdo_layout, load, [e.role for e in dropped], encoding)
            except LinkError as exc:
                if self.pdo_policy == "remap":
                    raise LinkError(f"{self.where}: the drive refused our PDO mapping: {exc}") from None
                log.info("node %d: fixed PDO mapping (%s); using the device's own", self.node_id, exc)
                self.report["pdo_remap_refused"] = str(exc)
        head = {o.STATUSWORD: "_statusword", o.MODES_DISPLAY: "_mode"}
        if self.has_drive_clock:
            head[o.EXT_STEP_COUNT] = "_step"
        roles = {(e.index, e.subindex): (e.role, e.factor) for e in wanted}
        roles.update({(i, 0): (r, 1.0) for i, r in head.items()})
        tpdos, rpdo_layout = pdos.apply_device_mapping(self.sdo, self._snapshot, od, roles, self.sync_period_s)
        carried = {e.role for t in tpdos for e in t.entries}
        if "_statusword" not in carried and not tpdos:
            raise LinkError(f"{self.where}: no TPDO of the drive's fixed mapping (0x1A00-0x1A07, TPDO mapping "
                            f"parameters) carries anything the bench reads (0x6041 statusword, 0x606C velocity "
                            f"actual, ...): map them with the vendor's tool, or name the objects its TPDOs carry in "
                            f"[drive.signals], e.g. speed_est_mech_rad_s = \"0x606C\"")
        load = pdos.load_pct([t.size for t in tpdos], self._bitrate, self.sync_period_s)
        return pdos.PdoPlan("device", tpdos, rpdo_layout, load,
                            [e.role for e in wanted if e.role not in carried], encoding)

    # -- receive side (CAN notifier thread) ----------------------------------------------------------
    def _add_error(self, message: str) -> None:
        with self._lock:
            self._errors.append(message)
            self._lock.notify_all()

    def _on_heartbeat(self, can_id, data, timestamp):
        with self._lock:
            self._last_heartbeat = time.monotonic()
            self._heartbeat_state = data[0] & 0x7F if data else None
            self.bus_drop.heartbeat_at = timestamp
        self._booted.set()                    # boot-up (state 0) or a heartbeat: the node is up

    def _on_emcy(self, can_id, data, timestamp):
        if len(data) < 3:
            self._errors.append(f"EMCY 0x{can_id:03X} with {len(data)} bytes")
            return
        code, register = struct.unpack_from("<HB", data)
        text = EmcyError(code, register, bytes(data[3:]), timestamp).get_desc() or "unknown"
        log.info("node %d EMCY 0x%04X (%s), error register 0x%02X", self.node_id, code, text, register)
        with self._lock:
            self._emcy.append((code, f"{text}; error register 0x{register:02X}"))
            self.bus_drop.emcy()

    def _on_tpdo(self, can_id, data, timestamp):
        self._on_tpdos([(can_id, data)], timestamp)

    def _on_tpdos(self, frames: list[tuple[int, bytes]], timestamp: float) -> None:
        """TPDOs received at `timestamp` (one frame from the notifier, or a SYNC's burst at once), decoded in order
        under one hold of the lock; waiters woken once."""
        now = time.time()
        if abs(now - timestamp) < 3600.0:       # interfaces stamping with the epoch clock: receive backlog
            self._rx_lag_s = now - timestamp
        with self._lock:
            if self.timing == "realtime":
                self.bus_drop.tpdo(timestamp, self._heartbeat_state, getattr(self._placer, "unanswered", None))
            woken = False
            for can_id, data in frames:
                result = self._decoder.decode(can_id, data, timestamp)
                if isinstance(result, str):
                    self._errors.append(result)
                    woken = True
                elif result:
                    self.control.feed(self._decoder.statusword)
                    self._samples.extend(result)
                    self._latest = result[-1]
                    self._completed += len(result)
                    woken = True
            if woken:
                self._lock.notify_all()

    # -- SYNC ----------------------------------------------------------------------------------------
    @property
    def heartbeat_state(self) -> tuple[int | None, float]:
        """The NMT state the drive's last heartbeat carried, and when it came (monotonic)."""
        with self._lock:
            return self._heartbeat_state, self._last_heartbeat

    def take_emcy(self) -> list[tuple[int, str]]:
        with self._lock:
            emcy, self._emcy = self._emcy, []
            return emcy

    def drop_pending(self) -> list[str]:
        """Forget the samples and link complaints of a drill (the drive in pre-operational sends no TPDOs); returns
        the complaints, for the drill's record."""
        with self._lock:
            errors, self._errors = self._errors, []
            self._samples.clear()
            self.bus_drop.reset()
            return errors

    def drill(self, before_withhold: Callable[[], None] | None = None) -> dict[str, Any]:
        """The bench-death drill (drivers.canopen.drill): the drive's reaction to the bench's silence, proved."""
        result = drills.drill(self, before_withhold)
        self.report["drill"] = result
        return result

    last_resort_bound_s = property(closing.last_resort_bound_s)

    def secure(self) -> str | None:
        secured = closing.secured(self)
        return None if secured and "last_resort" not in self.report else self.report["last_resort"]["line"]

    def set_reference_speed(self, speed: Callable[[], float | None]) -> None:
        """The rig's reference sensor (mech rad/s), so a drive found running is judged at rest by the shaft too."""
        self._reference_speed = speed

    def _check_health(self) -> None:
        bus_problem = self.bus_errors.problem(self.network.bus if self.network is not None else None)
        if bus_problem:
            raise LinkError(f"{self.where}: {bus_problem}")
        if self._errors:
            errors, self._errors = self._errors, []
            raise LinkError(f"{self.where}: " + "; ".join(errors))
        if not self._heartbeat_ok():
            lag = self._rx_lag_s
            behind = (f"; frames reach the link {lag:.1f} s after they were sent (this process is not keeping up)"
                      if lag > 0.5 * self.heartbeat_timeout_s else "")
            raise LinkError(f"{self.where}: no heartbeat for more than {self.heartbeat_timeout_s} s{behind}")

    def _heartbeat_ok(self) -> bool:
        return time.monotonic() - self._last_heartbeat <= self.heartbeat_timeout_s

    def sync(self) -> list[LiveSample]:
        """Lockstep: one SYNC, its sample. Real time: the samples since the last call, in batches at most
        every REALTIME_BATCH_S, waiting (up to 20 SYNC periods, at most 1 s) for at least one."""
        with self._lock:
            self._check_health()
            if self.timing == "realtime":
                # Pace the caller: return a batch at most every REALTIME_BATCH_S (and not before one sample is
                # in), so a bench loop costs per batch, not per SYNC, and leaves the CPU to the CAN threads.
                now = time.monotonic()
                # a SYNC period of REALTIME_BATCH_S or more: every sample at once (commands follow it within the
                # period); faster SYNCs: batches of REALTIME_BATCH_S
                not_before = self._last_return + (REALTIME_BATCH_S if self.sync_period_s < REALTIME_BATCH_S else 0.0)
                deadline = now + min(1.0, max(0.05, 20 * self.sync_period_s))
                while not self._errors:
                    now = time.monotonic()
                    if (self._samples and now >= not_before) or now >= deadline:
                        break
                    self._lock.wait(max(0.0, (not_before if self._samples else deadline) - now))
                self._last_return = time.monotonic()
                self._check_health()
                samples = list(self._samples)
                self._samples.clear()
                return samples
            target = self._completed + 1
        if self._rpdo_frame is not None:             # CSV: a target with every SYNC
            self._send(self.plan.rpdo.cob, self._rpdo_frame)
        self._send(o.SYNC, b"")
        deadline = time.monotonic() + self.stall_timeout_s
        with self._lock:
            while self._completed < target:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self._errors:
                    break
                self._lock.wait(remaining)
            if self._completed < target:
                self._check_health()
                raise LinkError(f"{self.where}: no TPDOs for SYNC within {self.stall_timeout_s:g} s")
            self._check_health()
            samples = list(self._samples)
            self._samples.clear()
            return samples

    def _send(self, cob: int, data: bytes) -> None:
        try:
            self.network.send_message(cob, data)
            self.frames_sent += 1
        except (can.CanError, OSError) as exc:
            raise LinkError(f"CAN send of 0x{cob:03X} failed: {exc}") from None

    def _start_sync_producer(self) -> None:
        bus = self.network.bus
        counter = SYNC_COUNTER_MAX if self._sync_counter_restore is not None else 0
        if has_native_cyclic(bus) and not counter and self.mode is not cia402.Mode.CYCLIC_SYNC_VELOCITY:
            self._sync = NativeSync(bus, self.sync_period_s)
        else:
            self._sync = SyncProducer(self._send_sync, self.sync_period_s, self._add_error, counter_overflow=counter)
        if self.time_base == "sync answered":
            self._placer = SyncTimeline(self.sync_period_s, self._sync.sent_before, self._sync.epoch_of)
        elif self.time_base == "receive time":
            self._placer = ReceiveClock(self.sync_period_s, lambda: self._sync.epoch_of(1) if self._sync else None)
        self._sync.start()
        self.report["sync"] = {"period_s": self.sync_period_s,
                               "producer": "interface (native cyclic)" if self._sync.native else "bench thread"}

    def _send_sync(self, data: bytes) -> None:
        """The SYNC thread's one frame (and in CSV the target's RPDO just before it): python-can's send under the
        network's send lock, held for that frame only; no SDO, heartbeat or journal work waits in front of it."""
        rpdo = self._rpdo_frame
        with self.network.send_lock:
            if rpdo is not None:
                self.network.bus.send(can.Message(arbitration_id=self.plan.rpdo.cob, data=rpdo, is_extended_id=False))
            self.network.bus.send(can.Message(arbitration_id=o.SYNC, data=data, is_extended_id=False))

    def _place(self, stamp: float | None, received: float) -> float:
        """Decoder callback (under the link's lock): a real-time answer's time on the bench's SYNC clock."""
        placer = self._placer
        if isinstance(placer, SyncTimeline):
            return placer.place(stamp, received) * self.sync_period_s
        if isinstance(placer, ReceiveClock):
            return placer.place(stamp, received)
        return self._decoder.sync_count * self.sync_period_s

    def now_s(self) -> float | None:
        """Real time without a drive clock: the drive's time now on the samples' time axis (SYNC n at n periods) —
        the SYNC sent as long before now as the latest answer came after its SYNC (a drive answers at once: the last
        SYNC sent; a simulator falling behind under load: the SYNC it is working on), so a reading taken now (the
        rig's reference sensor) is paired with the samples of its time, not with older ones that arrive late.
        None where the samples' own stamps are the clock."""
        if self._sync is None or self.time_base not in ("sync answered", "receive time"):
            return None
        if self.time_base == "receive time":
            origin = self._sync.epoch_of(1)
            return None if origin is None else time.time() - origin + self.sync_period_s
        lag = self._placer.last_lag if isinstance(self._placer, SyncTimeline) else None
        if lag is None:
            return self._sync.count * self.sync_period_s
        seq, _ = self._sync.sent_before(time.time() - max(0.0, lag))
        return max(seq, self._placer.last) * self.sync_period_s

    def sync_report(self) -> dict:
        """The SYNC statistics at the bench and how samples were placed in time, for the record."""
        out: dict[str, Any] = {"period_ms": round(self.sync_period_s * 1e3, 6), "timing": self.timing,
                               "time_base": self.time_base}
        if self._sync is not None:
            out.update(self._sync.report())
            out["producer"] = "interface (native cyclic)" if self._sync.native else "bench thread"
            out["counter"] = self._sync.counter_overflow or None
        if self._placer is not None:
            out.update(self._placer.report())
        with self._lock:
            out["incomplete_answers"] = self._decoder.incomplete
        return out

    def _stop_sync_producer(self) -> None:
        if self._sync is not None:
            self._sync.stop()
            self.report["sync"] = self.sync_report()
            self._sync = None

    @property
    def sync_producer(self) -> SyncProducer | NativeSync | None:
        return self._sync

    # -- 402 state machine (drivers.contract.cia402; controlword by SDO: confirmed, whatever the PDOs do) -----
    def _send_rpdo(self) -> None:
        rpdo = self.plan.rpdo if self.plan is not None else None
        if rpdo is None:
            self.sdo.write_standard(o.TARGET_VELOCITY, 0, self._target, 4, signed=True)
            return
        frame = self._pack_rpdo()
        if self._rpdo_frame is not None and isinstance(self._sync, SyncProducer):
            return                               # CSV in real time: the SYNC thread sends it before every SYNC
        self._send(rpdo.cob, frame)

    def _pack_rpdo(self) -> bytes:
        """The RPDO as it is now; in CSV also what goes out before every SYNC (`_rpdo_frame`)."""
        frame = self.plan.rpdo.pack({o.CONTROLWORD: self._controlword, o.TARGET_VELOCITY: self._target,
                                     o.MODES_OF_OPERATION: self.mode})
        if self.mode is cia402.Mode.CYCLIC_SYNC_VELOCITY:
            self._rpdo_frame = frame
        return frame

    def write_controlword(self, word: int) -> None:
        self._controlword = word
        if self._rpdo_frame is not None:         # CSV: the cyclic RPDO carries the new word before the SDO lands
            self._pack_rpdo()
        self.sdo.write(o.CONTROLWORD, 0, word)

    def read_statusword(self) -> int:
        word = self.sdo.read(o.STATUSWORD)
        self.control.feed(word)
        with self._lock:
            self._decoder.statusword = word
        return word

    @property
    def _step_timeout_s(self) -> float:
        return max(self.sdo_timeout_s, 0.5)

    def fault_reset(self) -> None:
        cia402.fault_reset(self, self._step_timeout_s, self.where)

    def enable_velocity_mode(self) -> None:
        self._check_health()
        if self.profile is None:
            raise LinkError(f"{self.where}: the drive's velocity unit is not known: not enabling")

        def fault_detail() -> str:
            code = self.sdo.read_standard(o.ERROR_CODE, 0)
            return "no error code" if code is None else f"error code 0x{code:04X}"

        mode_select.check_remote(self)
        self._wait_for_rest()
        cia402.enable_operation(self, fault_reset_policy=self.fault_reset_policy, timeout_s=self._step_timeout_s,
                                where=self.where, select_mode=lambda: mode_select.select_mode(self),
                                fault_detail=fault_detail, bring_to_rest=self._bring_to_rest)
        mode_select.after_enable(self)
        if self.timing == "realtime":
            # the run's time starts here: what arrived while the bench configured and enabled the drive (SYNC runs
            # from configure() on, 0.1-0.5 s of SDO round trips under load) would put the scenario's t = 0 back by
            # that much, and its first command would jump into the profile (a 0.5 s ramp taken as a step at 0.4 s)
            with self._lock:
                self._samples.clear()
                self.bus_drop.reset()
                if isinstance(self._placer, SyncTimeline):
                    self._placer.rebase()

    def _velocity_mode(self) -> cia402.Mode:
        """Profile velocity where the drive has it, else cyclic synchronous velocity (0x6502 bits 2 and 8), unless
        [drive] velocity_mode says; a drive with neither is refused with what to write."""
        if self.velocity_mode_choice not in VELOCITY_MODES:
            raise LinkError(f"{self.where}: velocity_mode {self.velocity_mode_choice!r} is not one of "
                            f"{', '.join(VELOCITY_MODES)}")
        chosen = VELOCITY_MODES[self.velocity_mode_choice]
        bits = self.sdo.read_standard(o.SUPPORTED_DRIVE_MODES, 0) if self.sdo.has(o.SUPPORTED_DRIVE_MODES) else None
        self.report["supported_modes_0x6502"] = None if bits is None else f"0x{bits:08X}"
        if chosen is not None or bits is None:
            return chosen or cia402.Mode.PROFILE_VELOCITY
        have = cia402.supported_modes(bits)
        for mode in (cia402.Mode.PROFILE_VELOCITY, cia402.Mode.CYCLIC_SYNC_VELOCITY):
            if mode in have:
                return mode
        raise LinkError(f"{self.where}: 0x6502 (supported drive modes) = 0x{bits:08X}: neither profile velocity (3, "
                        f"bit 2) nor cyclic synchronous velocity (9, bit 8); the bench commands a velocity. If the "
                        f"drive has one that 0x6502 does not report, write velocity_mode = \"pv\" or "
                        f"velocity_mode = \"csv\" in [drive]")

    def _rest_speed(self) -> float | None:
        """|speed| for 'at rest': the larger of the drive's report and the reference sensor's (either may be None)."""
        speeds = [self._speed_now()]
        if self._reference_speed is not None:
            reference = self._reference_speed()
            speeds.append(None if reference is None else abs(reference))
        known = [s for s in speeds if s is not None and math.isfinite(s)]
        return max(known) if known else None

    def _bring_to_rest(self) -> None:
        """A drive found powered (left running by someone): quick stop, then wait (bounded) until both the drive and
        the reference sensor say standstill; else nothing is enabled."""
        before = self._rest_speed()
        cia402.quick_stop(self, self._step_timeout_s, self.where)
        self._await_rest("found running", before)

    def _wait_for_rest(self) -> None:
        """A shaft still turning with the power stage off (coasting, or turned by the load) is waited for too."""
        if cia402.decode(self.read_statusword()) in cia402.POWERED_STATES:
            return                         # enable_operation brings it to rest (_bring_to_rest)
        speed = self._rest_speed()
        if speed is not None and speed > self.standstill_mech_rad_s:
            self._await_rest("found turning with its power stage off", speed)

    def _await_rest(self, what: str, before: float | None) -> None:
        advance = self.sync if self.timing == "lockstep" else (lambda: time.sleep(max(self.sync_period_s, 0.01)))
        rest = cia402.wait_standstill(advance, self._rest_speed, self.standstill_mech_rad_s, self.stop_timeout_s,
                                      self._stop_advances())
        self.report["found_running"] = {"what": what, "speed_mech_rad_s": before, **rest}
        if not rest["standstill"]:
            speed = rest["speed_at_disable_mech_rad_s"]
            raise LinkError(f"{self.where}: drive {what} at {before if before is not None else float('nan'):.1f} "
                            f"rad/s did not come to standstill within {self.stop_timeout_s:g} s (now "
                            f"{'unknown' if speed is None else f'{speed:.1f}'} rad/s): not enabling onto a turning "
                            f"shaft")

    def set_speed_ref(self, speed_mech_rad_s: float) -> None:
        if not math.isfinite(speed_mech_rad_s):
            raise LinkError(f"speed reference {speed_mech_rad_s} rad/s is not finite")
        value = self.profile.velocity.to_drive(speed_mech_rad_s)
        if not -2**31 <= value < 2**31:
            raise LinkError(f"speed reference {speed_mech_rad_s} rad/s is {value} {self.profile.velocity.unit.name}, "
                            "outside INTEGER32")
        self._target = value
        self._send_rpdo()
        if self.timing == "realtime" and self._sync is not None:
            self.commands.append({"sync": self._sync.count, "wall_ns": time.perf_counter_ns(),
                                  "speed_mech_rad_s": speed_mech_rad_s, "drive_value": value})

    def _speed_now(self) -> float | None:
        """|shaft speed| as the drive reports it (live sample in lockstep, else SDO), for the standstill wait."""
        source = self.profile.source("speed_est_mech_rad_s") if self.profile else None
        latest = self._latest
        if latest is not None and "speed_est_mech_rad_s" in latest.values and self.timing == "lockstep":
            return abs(latest.values["speed_est_mech_rad_s"])
        if source is not None:
            raw = self.sdo.read_standard(source.index, source.subindex, signed=True)
            return None if raw is None else abs(raw * source.factor)
        if self.profile is not None and self.profile.extension:
            var = self.node.object_dictionary["speed_est_mech_rad_s"]
            return abs(float(self.sdo.read(var.index, var.subindex)))
        return None

    def begin_quick_stop(self) -> None:
        """The quick-stop command alone (controlword 0x0002 by SDO, the state confirmed on the statusword): the
        safe stop's first step, before the load machine is touched; quick_stop() then waits for standstill."""
        self.control.refuse(self.where, "quick stop")
        self._quick_stop_state = cia402.quick_stop(self, self._step_timeout_s, self.where)

    def quick_stop(self) -> None:
        """Quick stop (unless begin_quick_stop gave it), then wait (bounded) until the shaft is below the standstill
        threshold."""
        state, self._quick_stop_state = self._quick_stop_state, None
        self.control.refuse(self.where, "quick stop")
        if state is None:
            state = cia402.quick_stop(self, self._step_timeout_s, self.where)
        if state is cia402.State.FAULT:
            return
        advance = self.sync if self.timing == "lockstep" else (lambda: time.sleep(max(self.sync_period_s, 0.01)))
        self.report["stop"] = cia402.wait_standstill(advance, self._speed_now, self.standstill_mech_rad_s,
                                                     self.stop_timeout_s, self._stop_advances(), self._stopped_itself)

    def _stopped_itself(self) -> bool:
        """The drive ended its quick stop on its own (its statusword, live in lockstep, else by SDO)."""
        word = self._decoder.statusword if self.timing == "lockstep" else self.read_statusword()
        return cia402.decode(word) is cia402.State.SWITCH_ON_DISABLED

    def _stop_advances(self) -> int | None:
        return math.ceil(self.stop_timeout_s / self.sync_period_s) if self.timing == "lockstep" else None

    def disable(self) -> None:
        self.control.refuse(self.where, "disable voltage")
        self._target = 0
        if self._rpdo_frame is not None:
            self._pack_rpdo()
        try:
            cia402.disable_voltage(self, self._step_timeout_s, self.where)
        finally:
            if self._sync is not None:       # the SYNC statistics are the run's, not of the bench writing its files
                self._sync.freeze()

    def status(self) -> DriveStatus:
        with self._lock:
            emcy, self._emcy = self._emcy, []
            word = self._decoder.statusword
            state = cia402.decode(word)
            return DriveStatus(state=cia402.state_name(word), fault=state in cia402.FAULT_STATES,
                               heartbeat_ok=self._heartbeat_ok(), emcy=emcy, control_lost=self.control.lost,
                               bus_drop=self.bus_drop.lost,
                               warning=bool(word & cia402.StatusBit.WARNING))

    # -- parameters ----------------------------------------------------------------------------------
    def write_parameter(self, name: str, value: float) -> None:
        od = self.node.object_dictionary
        if name not in od:
            raise LinkError(f"{self.eds_path.name}: the drive has no parameter named {name!r}")
        var = od[name]
        if not isinstance(var, objectdictionary.ODVariable) or var.index not in o.MANUFACTURER_RANGE:
            raise LinkError(f"{name!r} is not a manufacturer object (0x2000-0x5FFF) of {self.eds_path.name}")
        if not var.writable:
            raise LinkError(f"{name!r} (0x{var.index:04X}) is read-only")
        raw = float(value) if var.data_type in objectdictionary.FLOAT_TYPES else int(round(value))
        self.sdo.write(var.index, var.subindex, raw)

    # -- trace recorder ------------------------------------------------------------------------------
    def fetch_trace(self) -> dict[str, np.ndarray] | None:
        if not self.identity or not self.identity.has_trace_recorder:
            return None
        if not self._trace_mask:
            return {TIME_COLUMN: np.zeros(0)}
        pieces = []
        available = self.sdo.read(o.EXT_TRACE, o.TRACE_ROWS_AVAILABLE)
        for _ in range(MAX_UPLOADS_PER_FETCH):
            if available <= 0:
                break
            with self.sdo.lock:                  # the block upload takes over the node's SDO channel
                data = block_upload(self.network, self.node_id, o.EXT_TRACE_DATA, 0, self.stall_timeout_s,
                                    self._send, self._cancel)
            if not data:
                break
            pieces.append(data)
            available = self.sdo.read(o.EXT_TRACE, o.TRACE_ROWS_AVAILABLE) if self.timing == "lockstep" else 0
        try:
            columns = decode_rows(b"".join(pieces), self._trace_mask, self.control_period_s)
        except ValueError as exc:
            raise LinkError(f"{self.where}: trace upload: {exc}") from None
        lost = self.sdo.read(o.EXT_TRACE, o.TRACE_LOST_ROWS)
        if lost:
            log.warning("node %d: trace recorder overwrote %d rows before they were uploaded", self.node_id, lost)
        return columns
