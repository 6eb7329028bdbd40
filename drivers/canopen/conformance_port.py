"""The conformance suite's port (drivers.conformance.port) over CANopen: SDO for object access, SYNC + the drive's
own TPDOs/RPDO for process data, the bench heartbeat consumed by the drive (0x1016) as liveness, EMCY, NMT.

Built from the link's helpers (bus, dispatch, sdo, pdo, profile) without the link itself: the suite must see the
drive's raw answers (abort codes, missing TPDOs, a boot-up or its absence), where the link turns them into errors.
"""

from __future__ import annotations

import struct
import threading
import time
from pathlib import Path
from typing import Any, Mapping

import can
import canopen
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from drivers.canopen import pdo as pdos
from drivers.canopen.bus import QuickVirtualBus, bus_kwargs, make_bus, open_bus
from drivers.canopen.config import CanopenDriveConfig
from drivers.canopen.dispatch import HandlingNetwork, frame_dispatch
from drivers.canopen.profile import ProfileConfig, resolve
from drivers.canopen.sdo import SdoAccess
from drivers.canopen.sync import SyncProducer
from drivers.conformance.port import CycleAnswer, ObjectAbort, PortError, ProcessDataPdo
from drivers.contract import objects as o
from drivers.contract.comm_loss import CommLossConfig
from drivers.contract.eds import load_od
from drivers.contract.errors import ContentError

NMT_RESET = {"node": 0x81, "communication": 0x82}
BOOT_WAIT_S = 10.0           # a drive still booting when the suite connects: how long it may take
MISSING_GRACE_S = 0.5        # lockstep: a TPDO not yet in is waited for this long (a loaded host), then noted missing and
                             # not waited for again until it comes back


class CanopenConformancePort:
    def __init__(self, section: Mapping[str, Any], base_dir: Path, timing: str = "lockstep"):
        self.cfg = CanopenDriveConfig.from_mapping(section)
        self.section = dict(section)
        eds = Path(self.cfg.eds)
        self.eds_path = eds if eds.is_absolute() else Path(base_dir) / eds
        self.node_id = int(self.cfg.node_id)
        self.where = f"node {self.node_id}"
        self.period_s = float(section.get("sync_period_s", 0.01))
        self.timing = timing
        self.comm_loss = CommLossConfig.from_section(self.cfg)
        self.network: HandlingNetwork | None = None
        self.node: canopen.RemoteNode | None = None
        self.sdo: SdoAccess | None = None
        self.profile = None
        self._has: dict[tuple[int, int], bool] = {}
        self._lock = threading.Condition()
        self._frames: dict[int, bytes] = {}
        self._counts: dict[int, int] = {}
        self._tpdos: list[pdos.Tpdo] = []
        self._rpdo: pdos.Rpdo | None = None
        self._snapshot: pdos.PdoSnapshot | None = None
        self._controlword, self._target, self._mode_value = 0, 0, 0
        self._emcy: list[tuple[int, int]] = []
        self._nmt: tuple[int | None, float] = (None, 0.0)
        self._boot_up = threading.Event()
        self._heartbeat_task = None
        self._consumer_restore: list[tuple[int, int, int]] = []
        self._silent: set[int] = set()
        self.bus_off_reason = ""
        self._sync: SyncProducer | None = None       # real time: SYNC (and the command RPDO) from a thread
        self._send_command = True
        self._sync_errors: list[str] = []

    # -- connection ------------------------------------------------------------------------------------------
    def open(self) -> dict[str, Any]:
        kwargs = bus_kwargs(self.section)
        self.bus_off_reason = (f"python-can interface {kwargs['interface']!r} has no way to force the bench's "
                               f"controller into bus-off" if kwargs["interface"] in ("virtual", "socketcand") else
                               "bus-off needs a fault on the wire (a shorted CAN_H/CAN_L or a disturber node)")
        self.network = network = HandlingNetwork()
        network.NOTIFIER_CYCLE = 0.02

        def connect() -> None:
            bus = make_bus(kwargs)
            if isinstance(bus, QuickVirtualBus) and self.timing == "lockstep":
                bus.inline_delivery = True
                dispatch_ = frame_dispatch(network)
                network.after_send = lambda: bus.handle_arrived(network.notifier.listeners, dispatch_.burst)
            network.bus = bus
            network.listeners = [frame_dispatch(network)]
            return network.connect(**kwargs)
        try:
            open_bus(kwargs, connect)
        except (can.CanError, OSError, ValueError, TimeoutError, TypeError) as exc:
            raise PortError(f"CAN interface {kwargs['interface']!r}: cannot open: {exc}") from None
        od = load_od(self.eds_path, self.node_id)
        self.node = network.add_node(self.node_id, od)
        self.node.sdo.RESPONSE_TIMEOUT = float(self.cfg.sdo_timeout_s)
        self.node.sdo.MAX_RETRIES = 1
        self.sdo = SdoAccess(self.node, self.eds_path.name, float(self.cfg.sdo_timeout_s))
        network.subscribe(o.HEARTBEAT + self.node_id, self._on_heartbeat)
        network.subscribe(o.EMCY + self.node_id, self._on_emcy)
        started = time.monotonic()
        answered = None
        while answered is None:
            try:
                identity = [self._upload_int(o.IDENTITY, k) for k in (1, 2, 3, 4)]
                answered = time.monotonic() - started
            except PortError:
                if time.monotonic() - started > BOOT_WAIT_S:
                    raise PortError(f"{self.where}: no answer to SDO and no boot-up within {BOOT_WAIT_S:g} s")
                self._boot_up.wait(0.05)
        boot = {"answered_after_s": round(answered, 3), "boot_up_seen": self._boot_up.is_set(),
                "boot_up_after_s": getattr(self, "_boot_up_at", None) and round(self._boot_up_at - started, 3)}
        vendor, product = identity[0], identity[1]
        try:
            self.profile = resolve(ProfileConfig.from_section(self.cfg), vendor, product, self.sdo.read_standard,
                                   self.sdo.has)
        except ContentError as exc:
            raise PortError(f"{self.where}: drive profile: {exc}") from None
        text = {}
        for key, index in (("device_name", o.DEVICE_NAME), ("software_version", o.SOFTWARE_VERSION)):
            try:
                text[key] = self.read_bytes(index).rstrip(b"\0").decode(errors="replace")
            except (ObjectAbort, PortError):
                text[key] = ""
        return {"identity": {"vendor_id": f"0x{vendor:08X}", "product_code": f"0x{product:08X}",
                             "revision": f"0x{identity[2]:08X}", "serial": identity[3], **text},
                "profile": self.profile.as_record(), "boot": boot}

    def _upload_int(self, index: int, sub: int) -> int:
        return int.from_bytes(self.read_bytes(index, sub), "little")

    def close(self) -> None:
        self._stop_sync()
        if self._heartbeat_task is not None:
            self._heartbeat_task.stop()
            self._heartbeat_task = None
        if self.network is not None:
            try:
                self.network.disconnect()
            except Exception:          # closing must not mask the suite's own result
                pass
            self.network = None

    # -- object access ---------------------------------------------------------------------------------------
    def _transfer(self, verb: str, index: int, sub: int, call):
        try:
            with self.sdo.lock:
                return call()
        except SdoAbortedError as exc:
            raise ObjectAbort(index, sub, exc.code, f"{self.where}: SDO {verb}") from None
        except SdoCommunicationError as exc:
            raise PortError(f"{self.where}: SDO {verb} of 0x{index:04X}:{sub:02X}: {exc}") from None

    def has(self, index: int, subindex: int = 0) -> bool:
        key = (index, subindex)
        if key not in self._has:
            try:
                self.read_bytes(index, subindex)
                self._has[key] = True
            except ObjectAbort:
                self._has[key] = False
        return self._has[key]

    def read_bytes(self, index: int, subindex: int = 0) -> bytes:
        return self._transfer("read", index, subindex, lambda: self.node.sdo.upload(index, subindex))

    def read(self, index: int, subindex: int = 0, signed: bool = False) -> int:
        return int.from_bytes(self.read_bytes(index, subindex), "little", signed=signed)

    def write_bytes(self, index: int, subindex: int, data: bytes) -> None:
        self._transfer("write", index, subindex, lambda: self.node.sdo.download(index, subindex, data))

    def write(self, index: int, subindex: int, value: int, size: int, signed: bool = False) -> None:
        if index == o.CONTROLWORD:
            self._controlword = value
        elif index == o.TARGET_VELOCITY:
            self._target = value
        elif index == o.MODES_OF_OPERATION:
            self._mode_value = value
        self.write_bytes(index, subindex, value.to_bytes(size, "little", signed=signed))

    # -- units -----------------------------------------------------------------------------------------------
    def to_drive_velocity(self, speed_mech_rad_s: float) -> int:
        return self.profile.velocity.to_drive(speed_mech_rad_s)

    def from_drive_velocity(self, value: int) -> float:
        return value * self.profile.velocity.rad_s_per_unit

    # -- process data ----------------------------------------------------------------------------------------
    def start_process_data(self) -> list[ProcessDataPdo]:
        self.node.nmt.state = "PRE-OPERATIONAL"
        self.sdo.write_standard(o.COMM_CYCLE_PERIOD, 0, round(self.period_s * 1e6), 4)
        if self._snapshot is None:
            self._snapshot = pdos.PdoSnapshot.read(self.sdo)
        roles = {(o.STATUSWORD, 0): ("_statusword", 1.0), (o.VELOCITY_ACTUAL, 0): ("_velocity", 1.0)}
        tpdos, self._rpdo = pdos.apply_device_mapping(self.sdo, self._snapshot, self.node.object_dictionary, roles,
                                                      self.period_s)
        self._tpdos = tpdos
        for tpdo in tpdos:
            self.network.subscribe(tpdo.cob, self._on_tpdo)
        self.node.nmt.state = "OPERATIONAL"
        if self.timing != "lockstep":
            self._start_sync()
        return [ProcessDataPdo(t.number, tuple((e.index, e.subindex, e.bits) for e in t.entries),
                               not t.event_driven, t.event_timer_ms) for t in tpdos]

    def has_command_frame(self) -> bool:
        return self._rpdo is not None

    def set_command(self, controlword: int | None = None, target: int | None = None) -> None:
        if controlword is not None:
            self.write(o.CONTROLWORD, 0, controlword, 2)
        if target is not None:             # by SDO too: the object holds it now, whatever cycles follow
            self.write(o.TARGET_VELOCITY, 0, target, 4, signed=True)

    def cycle(self, sync: bool = True, command: bool = True) -> CycleAnswer:
        if self.timing != "lockstep":
            return self._realtime_cycle(sync, command)
        with self._lock:
            self._frames, self._counts = {}, {}
        if command and self._rpdo is not None:
            frame = self._rpdo.pack({o.CONTROLWORD: self._controlword, o.TARGET_VELOCITY: self._target,
                                     o.MODES_OF_OPERATION: self._mode()})
            self.network.send_message(self._rpdo.cob, frame)
        if not sync:
            return CycleAnswer()
        self.network.send_message(o.SYNC, b"")
        expected = {t.cob for t in self._tpdos if not t.event_driven} - self._silent
        deadline = time.monotonic() + MISSING_GRACE_S
        with self._lock:
            while not expected <= set(self._frames) and time.monotonic() < deadline:
                self._lock.wait(max(0.0, deadline - time.monotonic()))
            frames = dict(self._frames)
        self._silent |= expected - set(frames)          # not waited for again until it comes back
        self._silent -= set(frames)
        with self._lock:
            counts = dict(self._counts)
        return self._decode(frames, 1, counts)

    def _realtime_cycle(self, sync: bool, command: bool) -> CycleAnswer:
        """Real time: SYNC comes from the producer thread on its own schedule; a cycle is one period of it and
        what arrived meanwhile. No SYNC: the producer stops until the next cycle that wants one; no command: the
        thread leaves the RPDO out."""
        self._send_command = command
        if not sync:
            self._stop_sync()
            time.sleep(self.period_s)
            return CycleAnswer()
        if self._sync is None:
            self._start_sync()
        with self._lock:
            self._frames, self._counts = {}, {}
            before = self._sync.count
        time.sleep(self.period_s)
        with self._lock:
            frames, counts = dict(self._frames), dict(self._counts)
        if self._sync_errors:
            raise PortError(f"{self.where}: {self._sync_errors[-1]}")
        return self._decode(frames, self._sync.count - before, counts)

    def _start_sync(self) -> None:
        self._sync = SyncProducer(self._send_sync, self.period_s, self._sync_errors.append)
        self._sync.start()

    def _stop_sync(self) -> None:
        if self._sync is not None:
            self._sync.stop()
            self._sync = None

    def _send_sync(self, data: bytes) -> None:
        """The SYNC thread's frames: the command RPDO (where one carries the target), then SYNC; nothing else waits
        in front of them."""
        rpdo = self._rpdo
        frame = None
        if rpdo is not None and self._send_command:
            frame = rpdo.pack({o.CONTROLWORD: self._controlword, o.TARGET_VELOCITY: self._target,
                               o.MODES_OF_OPERATION: self._mode_value})
        with self.network.send_lock:
            if frame is not None:
                self.network.bus.send(can.Message(arbitration_id=rpdo.cob, data=frame, is_extended_id=False))
            self.network.bus.send(can.Message(arbitration_id=o.SYNC, data=data, is_extended_id=False))

    def _decode(self, frames: dict[int, bytes], syncs: int, counts: dict[int, int]) -> CycleAnswer:
        answer = CycleAnswer(syncs=syncs, counts={t.number: counts.get(t.cob, 0) for t in self._tpdos})
        for tpdo in self._tpdos:
            data = frames.get(tpdo.cob)
            if data is None:
                continue
            answer.frames[tpdo.number] = bytes(data)
            if len(data) >= tpdo.size:
                for entry, value in zip(tpdo.entries, self._unpack(tpdo, data)):
                    if entry.role == "_statusword":
                        answer.statusword = value
                    elif entry.role == "_velocity":
                        answer.velocity_raw = value
        return answer

    @staticmethod
    def _unpack(tpdo: pdos.Tpdo, data: bytes) -> list:
        values = iter(tpdo.layout.unpack_from(data))
        return [next(values) if e.code else None for e in tpdo.entries]

    def _mode(self) -> int:
        return self._mode_value

    def pdo_mapping(self, number: int) -> list[tuple[int, int, int]]:
        count = self.read(o.TPDO_MAP + number - 1, 0)
        return [o.unpack_mapping_entry(self.read(o.TPDO_MAP + number - 1, k)) for k in range(1, count + 1)]

    def remap(self, number: int, objects: list[tuple[int, int, int]]) -> None:
        """CiA 301 7.5.2.36 order: COB-ID invalid, count 0, entries, count n, COB-ID valid (transmission type kept)."""
        comm, mapping = o.TPDO_COMM + number - 1, o.TPDO_MAP + number - 1
        self._snapshot.touch(comm, mapping=True)
        cob = self.read(comm, 1)
        self.node.nmt.state = "PRE-OPERATIONAL"
        try:
            self.write(comm, 1, cob | o.COB_ID_INVALID, 4)
            self.write(mapping, 0, 0, 1)
            for k, (index, sub, bits) in enumerate(objects, start=1):
                self.write(mapping, k, o.mapping_entry(index, sub, bits), 4)
            self.write(mapping, 0, len(objects), 1)
            self.write(comm, 1, cob & ~o.COB_ID_INVALID, 4)
        finally:
            self.node.nmt.state = "OPERATIONAL"

    def restore_process_data(self) -> list[str]:
        self._stop_sync()
        if self._snapshot is None:
            return []
        self.node.nmt.state = "PRE-OPERATIONAL"
        errors = self._snapshot.restore(self.sdo)
        for tpdo in self._tpdos:
            self.network.unsubscribe(tpdo.cob, self._on_tpdo)
        self._tpdos, self._rpdo = [], None
        return errors

    def process_data_snapshot(self) -> dict[tuple[int, int], bytes]:
        return {} if self._snapshot is None else dict(self._snapshot.values)

    # -- liveness and EMCY -----------------------------------------------------------------------------------
    def arm_liveness(self, timeout_ms: int) -> dict[str, Any]:
        bench = self.comm_loss.bench_node_id
        n = self.read(o.CONSUMER_HEARTBEAT, 0)
        entries = {k: self.read(o.CONSUMER_HEARTBEAT, k) for k in range(1, n + 1)}
        sub = next((k for k, v in entries.items() if (v >> 16) & 0xFF == bench), None) or next(
            (k for k, v in entries.items() if v & 0xFFFF == 0 or (v >> 16) & 0xFF == 0), 1)
        self._consumer_restore.append((o.CONSUMER_HEARTBEAT, sub, entries.get(sub, 0)))
        self.write(o.CONSUMER_HEARTBEAT, sub, bench << 16 | timeout_ms, 4)
        self.withhold_liveness()        # its first frame now: a consumer starts watching at the first heartbeat
        self.resume_liveness()
        return {"consumer_heartbeat_0x1016": f"sub {sub} = 0x{bench << 16 | timeout_ms:08X}",
                "bench_heartbeat": f"0x{o.HEARTBEAT + bench:03X} every {self.comm_loss.producer_period_s * 1e3:g} ms"}

    def withhold_liveness(self) -> None:
        if self._heartbeat_task is not None:
            self._heartbeat_task.stop()
            self._heartbeat_task = None

    def resume_liveness(self) -> None:
        if self._heartbeat_task is None:
            self._heartbeat_task = self.network.send_periodic(o.HEARTBEAT + self.comm_loss.bench_node_id,
                                                              [o.NMT_OPERATIONAL], self.comm_loss.producer_period_s)

    def disarm_liveness(self) -> list[str]:
        errors = []
        for index, sub, value in reversed(self._consumer_restore):
            try:
                self.write(index, sub, value, 4)
            except (ObjectAbort, PortError) as exc:
                errors.append(str(exc))
        self._consumer_restore.clear()
        self.withhold_liveness()
        return errors

    def take_emcy(self) -> list[tuple[int, int]]:
        with self._lock:
            out, self._emcy = self._emcy, []
            return out

    def drive_liveness(self) -> tuple[int | None, float]:
        with self._lock:
            return self._nmt

    # -- network management ----------------------------------------------------------------------------------
    def network_reset(self, what: str, timeout_s: float) -> float | None:
        self._boot_up.clear()
        sent = time.monotonic()
        self.network.send_message(o.NMT, bytes([NMT_RESET[what], self.node_id]))
        if not self._boot_up.wait(timeout_s):
            return None
        return self._boot_up_at - sent

    def network_operational(self) -> None:
        self.node.nmt.state = "OPERATIONAL"

    def network_stop(self) -> None:
        self.node.nmt.state = "STOPPED"

    def bus_off_recovery(self) -> str | None:
        return None

    # -- receive side ----------------------------------------------------------------------------------------
    def _on_heartbeat(self, can_id, data, timestamp) -> None:
        state = data[0] & 0x7F if data else None
        with self._lock:
            self._nmt = (state, time.monotonic())
        if state == 0:
            self._boot_up_at = time.monotonic()
            self._boot_up.set()

    def _on_emcy(self, can_id, data, timestamp) -> None:
        if len(data) >= 3:
            code, register = struct.unpack_from("<HB", data)
            with self._lock:
                self._emcy.append((code, register))

    def _on_tpdo(self, can_id, data, timestamp) -> None:
        with self._lock:
            self._frames[can_id] = bytes(data)
            self._counts[can_id] = self._counts.get(can_id, 0) + 1
            self._lock.notify_all()


def open_port(section: Mapping[str, Any], base_dir: Path, timing: str) -> CanopenConformancePort:
    """Entry point `drivebench.conformance_ports` canopen."""
    return CanopenConformancePort(section, base_dir, timing)
