"""The simulated drive as a CANopen CiA 402 node, built from the same EDS the bench loads.

canopen's LocalNode gives the object dictionary, the SDO server and NMT. What it lacks is added here: TPDOs sent on
SYNC (packed from the live object values, so PDO and SDO always agree; sim_backend.canopen.pdo), RPDOs applied to
the drive, EMCY on faults, SDO block upload (block_server), the heartbeat (heartbeat) and lockstep time — each SYNC
advances the drive by the communication cycle period (0x1006) before its TPDOs go out. What the objects mean is in
drive_objects.

Everything runs on the node network's receive thread, or, for a frame whose sender offers it while the node is idle,
in the sender's thread (virtual_bus.InlineReceiveQueue: one at a time, in order, as the receive thread would);
SimulatedDevice's lock guards the drive against the other protocol servers.
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from pathlib import Path

import can
import canopen
from canopen import objectdictionary
from canopen.sdo import SdoAbortedError

from drivers.contract import objects as o
from drivers.contract.cia402 import State
from drivers.contract.eds import load_od
from sim_backend.canopen.block_server import DriveLocalNode
from sim_backend.canopen import generic
from sim_backend.canopen.drive_objects import Cia402Objects, ExtensionObjects, error_register_for
from sim_backend.canopen.heartbeat import HeartbeatConsumer, HeartbeatProducer
from sim_backend.canopen.pdo import PDO_PARAMETERS, PdoEngine
from sim_backend.canopen.virtual_bus import FastVirtualBus, send_frames
from sim_backend.device import SimulatedDevice

log = logging.getLogger(__name__)

NMT_START_BOOT_UP, NMT_ENTER_PRE_OPERATIONAL = 0x81, 0x80     # NmtSlave.send_command: reset node, pre-operational
CSV_ONLY_MODES = 1 << 8             # 0x6502 of a drive with cyclic synchronous velocity only (many servo drives)


class SimCanopenNode:
    """One simulated drive on a CAN bus. `stop()` takes it off the bus."""

    def __init__(self, device: SimulatedDevice, eds_path: str | Path, node_id: int, bus: can.BusABC,
                 drive: generic.DriveSpec | None = None):
        """`drive`: a third-party drive's spec (units, rated values, fixed mappings); None for drivebench's drives,
        whose EDS says everything."""
        self.device = device
        self.node_id = node_id
        self.network = canopen.Network(bus)
        self.network.NOTIFIER_CYCLE = 0.02      # stop() returns within 20 ms (the notifier thread polls)
        od = load_od(eds_path, node_id)
        spec = drive or generic.DriveSpec()
        self.spec = spec
        self.added_objects = generic.add_missing_standard_objects(od, spec.comm_loss_objects, spec.comm_loss_reaction)
        device.cia402_comm_loss_reaction = spec.comm_loss_reaction
        device.remote_drops_after_s = spec.remote_drops_after_s
        device.local_control = spec.local_control
        device.device.remote = not spec.local_control
        device.warning_emcy_after_s = spec.warning_emcy_after_s
        device.comm_loss_delay_s = spec.comm_loss_delay_s
        device.velocity_filter_s = spec.velocity_filter_s
        if spec.node_guarding:              # node guarding instead of heartbeat: no 0x1016, no 0x1017 (after boot)
            if o.CONSUMER_HEARTBEAT in od:
                del od[o.CONSUMER_HEARTBEAT]
            for index, name, data_type in ((0x100C, "Guard time", o.UNSIGNED16), (0x100D, "Life time factor",
                                                                                    o.UNSIGNED8)):
                if index not in od:
                    od.add_object(generic._var(name, index, 0, data_type, "rw", 0))
        self._tpdo_stop = (None if spec.tpdo_stops_after_s is None else
                           (spec.tpdo_stops_after_s, spec.tpdo_stops))   # after this much operational drive time
        self._operational_since: float | None = None
        self._drop_until = 0.0                # the bus-drop quirk: muted until then (monotonic)
        generic.fill_defaults(od)
        self.od = od
        self.node = DriveLocalNode(node_id, od)
        self.cia402 = Cia402Objects(device, self._emcy_reset_if_cleared, generic.units(od, spec),
                                    supported_modes=CSV_ONLY_MODES if spec.csv_only else _eds_modes(od))
        if generic.is_drivebench(od):
            self.extension: ExtensionObjects | None = ExtensionObjects(device, od)
            self._handlers = (self.cia402, self.extension)
        else:
            self.extension = None
            self._handlers = (self.cia402,)
        if spec.event_tpdos_only:           # the drive's own TPDOs are event-driven too
            for n in range(o.N_TPDO_MAX):
                if o.TPDO_COMM + n in od and 2 in od[o.TPDO_COMM + n].subindices:
                    var = od[o.TPDO_COMM + n][2]
                    var.default = var.value = 255
        self.cia402.mode_display_delay_s = spec.mode_display_delay_s
        self.cia402.target_sdo_only_enabled = spec.target_sdo_only_enabled
        self.pdos = PdoEngine(od, self._raw, self.node.get_data, self.node.set_data, self._fast_getter,
                              fixed_mapping=spec.fixed_pdo_mapping, event_only=spec.event_tpdos_only)
        self.cia402.from_rpdo = lambda: self.pdos.applying
        self.node.add_read_callback(self._on_read)
        self.node.add_write_callback(self._on_write)
        if self.extension is not None:
            self.node.sdo.on_upload_complete = self.extension.upload_complete
        self.node.after_write = self._after_write
        self._sync_count = 0
        self._was_fault = False
        self.rpdo_length_errors = 0
        self.steps_per_sync = self._read_steps_per_sync()
        self._rebuild_pdos()
        self.network.connect()
        self.network.notifier.add_listener(_ErrorLogger())
        if type(bus) is FastVirtualBus:       # not a bus with its own receive semantics (wire_faults.FaultyBus)
            bus.handle_inline(self._handle_inline)
        self.heartbeat = HeartbeatProducer(self)
        self.consumer = HeartbeatConsumer(self)
        device.on_master_lost.append(self._on_master_lost)
        for index in (o.QUICK_STOP_OPTION, o.ABORT_CONNECTION_OPTION):      # the device starts from the EDS defaults
            if index in od and od[index].default is not None:
                self.cia402.write(index, 0, od[index], int(od[index].default))
        nmt = self.node.nmt                   # canopen's NmtSlave keeps the NMT state; we send its heartbeat
        nmt.start_heartbeat = self.heartbeat.set_period_ms
        nmt.stop_heartbeat = lambda: self.heartbeat.set_period_ms(0)
        nmt.update_heartbeat = lambda: None   # the producer reads the state when it sends
        nmt.on_command = self._on_nmt_command
        self._boot_timer: threading.Timer | None = None
        if spec.boot_delay_s > 0:             # still booting: not on the bus (no SDO, no SYNC) until the boot-up
            self._boot_timer = threading.Timer(spec.boot_delay_s, self._boot)
            self._boot_timer.daemon = True
            self._boot_timer.start()
        else:
            self._boot()

    def _boot(self) -> None:
        """On the bus: SDO server, NMT and SYNC answered; boot-up message, then PRE-OPERATIONAL with heartbeat."""
        self.network.add_node(self.node)
        self.network.subscribe(o.SYNC, self._on_sync)
        self.node.nmt.send_command(NMT_START_BOOT_UP)
        self.node.nmt.send_command(NMT_ENTER_PRE_OPERATIONAL)
        if self.spec.node_guarding and o.PRODUCER_HEARTBEAT in self.od:   # canopen's NMT read it at the boot
            del self.od[o.PRODUCER_HEARTBEAT]

    def _on_nmt_command(self, can_id, data, timestamp) -> None:
        """NMT as a drive does it: stop / reset communication / reset node while powered apply 0x6007 (CiA 402); a
        reset restores the communication objects (0x1000-0x1FFF; reset node: every object) to their power-on values
        and ends with the boot-up message, then PRE-OPERATIONAL. canopen's NmtSlave only changes the state."""
        if len(data) < 2 or data[1] not in (self.node_id, 0):
            return
        command = data[0]
        if command in (0x02, 0x81, 0x82):
            self.device.connection_aborted({0x02: "NMT stop", 0x81: "NMT reset node",
                                            0x82: "NMT reset communication"}[command])
        if command not in (0x81, 0x82):
            type(self.node.nmt).on_command(self.node.nmt, can_id, data, timestamp)
            return
        if command == 0x81:
            self.device.write_controlword(0)            # the application restarts: power stage off
            self.node.data_store.clear()
            for index in (o.QUICK_STOP_OPTION, o.ABORT_CONNECTION_OPTION):
                if index in self.od and self.od[index].default is not None:
                    self.cia402.write(index, 0, self.od[index], int(self.od[index].default))
        else:
            for index in [i for i in self.node.data_store if 0x1000 <= i < 0x2000]:
                del self.node.data_store[index]
        self.consumer.configure([])
        self.steps_per_sync = self._read_steps_per_sync()
        self._rebuild_pdos()
        self.node.nmt.send_command(NMT_START_BOOT_UP)
        self.node.nmt.send_command(NMT_ENTER_PRE_OPERATIONAL)

    def _handle_inline(self, msg: can.Message) -> None:
        """A frame handled in its sender's thread (InlineReceiveQueue): what the receive thread's notifier does."""
        try:
            for listener in self.network.notifier.listeners:
                listener(msg)
        except Exception as exc:          # as on the receive thread: logged, never raised into the sender
            log.error("CANopen node receive thread: %s", exc)

    @property
    def nmt_state(self) -> int:
        return self.node.nmt._state

    # -- drive clock ---------------------------------------------------------------------------------
    def _read_steps_per_sync(self) -> int:
        period_us = self._raw(o.COMM_CYCLE_PERIOD, 0)
        return max(1, round(period_us * 1e-6 / self.device.model.control_period_s))

    def _raw(self, index: int, subindex: int) -> int:
        obj = self.od[index]
        if not isinstance(obj, objectdictionary.ODVariable):
            obj = obj[subindex]
        return obj.decode_raw(self.node.get_data(index, subindex))

    # -- object access -------------------------------------------------------------------------------
    def _on_read(self, index, subindex, od):
        for handler in self._handlers:
            value = handler.read(index, subindex, od)
            if value is not None:
                return value
        return None

    def _on_write(self, index, subindex, od, data):
        value = od.decode_raw(data) if od.data_type != objectdictionary.DOMAIN else bytes(data)
        if any(handler.write(index, subindex, od, value) for handler in self._handlers):
            return
        if index == o.COMM_CYCLE_PERIOD:
            steps = value * 1e-6 / self.device.model.control_period_s
            own = value in (od.default, od.value)          # a drive takes its own power-on value back
            if (value == 0 or abs(steps - round(steps)) > 1e-6) and not own:
                raise SdoAbortedError(o.ABORT_INVALID_VALUE)
        elif index in PDO_PARAMETERS:
            self.pdos.check_write(index, subindex, value)
            self.pdos.dirty = True

    def _after_write(self, index: int, subindex: int) -> None:
        if index == o.CONSUMER_HEARTBEAT and subindex > 0:
            self.consumer.configure([self._raw(index, k) for k in range(1, self._raw(index, 0) + 1)])
        if index == o.COMM_CYCLE_PERIOD:
            self.steps_per_sync = self._read_steps_per_sync()
        # a write that cannot change the PDOs leaves them dirty: the next SYNC rebuilds them (~1 ms each, ~90 writes
        # when the bench maps its PDOs)
        if self.pdos.dirty and index in PDO_PARAMETERS and self.pdos.changes_pdos(index, subindex):
            self._rebuild_pdos()

    def _fast_getter(self, index: int, subindex: int):
        for handler in self._handlers:
            fast = handler.fast_getter(index, subindex)
            if fast is not None:
                return fast
        return None

    # -- PDOs ----------------------------------------------------------------------------------------
    def _rebuild_pdos(self) -> None:
        old, new = self.pdos.rebuild()
        for cob in old:
            self.network.unsubscribe(cob, self._on_rpdo)
        for cob in new:
            self.network.subscribe(cob, self._on_rpdo)

    def _on_rpdo(self, can_id, data, timestamp):
        if self.nmt_state != o.NMT_OPERATIONAL or self.muted():
            return
        pdo = self.pdos.rpdos.get(can_id)
        if pdo is None:
            return
        if len(data) < pdo.length:
            self.rpdo_length_errors += 1
            self._send_emcy(o.EMCY_PDO_LENGTH, error_register_for(o.EMCY_PDO_LENGTH))
            return
        self.pdos.receive(pdo, bytes(data))

    def muted(self) -> bool:
        """The bus-drop quirk: nothing heard, nothing sent (the drive's own state untouched)."""
        drop = self.spec.bus_drop_at_s
        if (drop is not None and self._drop_until == 0.0 and self._operational_since is not None
                and self.device.time_s - self._operational_since >= drop):
            self._drop_until = time.monotonic() + self.spec.bus_drop_s
        return time.monotonic() < self._drop_until

    def _on_sync(self, can_id, data, timestamp):
        if self.muted():
            return
        self.heartbeat.maybe_send()
        if self.pdos.dirty:
            self._rebuild_pdos()
        self.pdos.apply_pending()
        self.device.advance(self.steps_per_sync)
        for code in self.device.take_emcy():
            self._send_emcy(code, error_register_for(code))
            self._was_fault = True
        self._sync_count += 1
        if self.nmt_state != o.NMT_OPERATIONAL:
            self._operational_since = None
            return
        frames = self.pdos.tpdo_frames(self._sync_count, self.device.time_s)
        if self._operational_since is None:
            self._operational_since = self.device.time_s
        if self._tpdo_stop is not None:
            if self.device.time_s - self._operational_since > self._tpdo_stop[0]:
                frames = self._without_stopped_tpdo(frames)
        if frames:
            send_frames(self.network, frames)     # one burst: the bench's receive thread wakes once per SYNC

    def _without_stopped_tpdo(self, frames: list[tuple[int, bytes]]) -> list[tuple[int, bytes]]:
        """The quirk of a drive whose TPDO goes silent (a firmware bug, a PDO inhibit gone wrong)."""
        number = self._tpdo_stop[1]
        if number == 0:
            return []
        silent = {pdo.cob_id for k, pdo in enumerate(self.pdos.tpdos, 1) if k == number}
        return [f for f in frames if f[0] not in silent]

    # -- EMCY / heartbeat ----------------------------------------------------------------------------
    def _send_emcy(self, code: int, register: int) -> None:
        stamp = struct.pack("<L", self.device.step_count & 0xFFFFFFFF)   # manufacturer field: drive clock
        self.node.emcy.send(code, register, stamp)

    def _emcy_reset_if_cleared(self) -> None:
        if self._was_fault and self.device.device.state is not State.FAULT:
            self._was_fault = False
            self.node.emcy.reset(0, bytes(5))

    def _on_master_lost(self) -> None:
        """0x1029 sub 1 (communication error): 0 -> pre-operational, 2 -> stopped, 1 -> no change."""
        try:
            for code in self.device.take_emcy():   # at once, as a drive does: not with the next SYNC
                self._send_emcy(code, error_register_for(code))
                self._was_fault = True
        except Exception as exc:                   # bus closed while stopping
            log.debug("EMCY on master lost: %s", exc)
        behaviour = self._raw(o.ERROR_BEHAVIOUR, 1) if o.ERROR_BEHAVIOUR in self.od else 1
        if behaviour in (0, 2):
            self.node.nmt.state = "PRE-OPERATIONAL" if behaviour == 0 else "STOPPED"

    def stop_heartbeat(self) -> None:
        """What a crashed node looks like to the bench: no more heartbeats, no more answers."""
        self.node.nmt.stop_heartbeat()

    def stop(self) -> None:
        if self._boot_timer is not None:
            self._boot_timer.cancel()
        self.heartbeat.close()
        self.network.disconnect()


def _eds_modes(od: objectdictionary.ObjectDictionary) -> int | None:
    """0x6502 as the EDS gives it: the modes 0x6060 accepts (None: no 0x6502, every mode accepted)."""
    if o.SUPPORTED_DRIVE_MODES in od and od[o.SUPPORTED_DRIVE_MODES].default:
        return int(od[o.SUPPORTED_DRIVE_MODES].default)
    return None


class _ErrorLogger(can.Listener):
    def on_message_received(self, msg):
        pass

    def on_error(self, exc):
        log.error("CANopen node receive thread: %s", exc)


def start_node(device: SimulatedDevice, eds_path: str | Path, node_id: int, **bus_kwargs) -> SimCanopenNode:
    """Put a simulated drive on a python-can bus (e.g. interface="virtual", channel=...)."""
    bus_kwargs.setdefault("receive_own_messages", False)
    if bus_kwargs.get("interface") == "virtual":
        bus_kwargs.pop("interface")
        bus = FastVirtualBus(**bus_kwargs)
    else:
        bus = can.Bus(**bus_kwargs)
    return SimCanopenNode(device, eds_path, node_id, bus)
