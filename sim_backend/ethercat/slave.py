"""The slave's firmware behind the ESC: the AL state machine with its status codes, the CoE mailbox, the process
data (RxPDO applied to the drive, one drive cycle per process-data frame, TxPDO packed after it) and the SM
watchdog: in OP, a master silent longer than 0x0420 x divider takes the slave to SAFE-OP with error 0x001B and the
drive reacts as its 0x6007 abort connection option says (SimulatedDevice's comm-loss reaction, then its own clock
runs on, as a real drive's does, until it has stopped)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from drivers.contract.cia402 import Command
from sim_backend.device import SimulatedDevice
from sim_backend.ethercat import sii
from sim_backend.ethercat.coe import CoeServer
from sim_backend.ethercat.esc import Esc
from sim_backend.ethercat.objects import (
    DEFAULT_CYCLE_NS, RX_ASSIGN, SM_OUT_PARAM, TX_ASSIGN, SdoAbort, SlaveObjects,
)

INIT, PREOP, BOOT, SAFEOP, OP = 0x01, 0x02, 0x03, 0x04, 0x08
# AL status codes (ETG.1000.6 Table 11)
AL_INVALID_STATE_CHANGE, AL_UNKNOWN_STATE, AL_BOOT_NOT_SUPPORTED = 0x0011, 0x0012, 0x0013
AL_INVALID_MAILBOX, AL_INVALID_OUTPUT, AL_INVALID_INPUT, AL_SM_WATCHDOG = 0x0016, 0x001D, 0x001E, 0x001B
AL_INVALID_SYNC_CYCLE = 0x0035


@dataclass(frozen=True)
class Quirks:
    """How this slave differs from the plain one, the way vendors' drives do."""

    refuse_safeop: int = 0          # an AL status code: the slave refuses PRE-OP -> SAFE-OP with it
    fixed_mapping: bool = False     # PDO assignment and mapping are read-only (the master reads them)
    serial: int = 1


class Slave:
    def __init__(self, device: SimulatedDevice, eds: str | Path, quirks: Quirks = Quirks(), drive=None):
        """`drive`: sim_backend.canopen.generic.DriveSpec of a third-party drive; None: drivebench's."""
        self.device = device
        self.quirks = quirks
        fixed = quirks.fixed_mapping or bool(drive is not None and drive.fixed_pdo_mapping)
        self.objects = SlaveObjects(device, eds, fixed, drive)
        ident = self.objects.od[0x1018]
        name = str(self.objects.od[0x1008].default) if 0x1008 in self.objects.od else "CiA 402 servo drive"
        self.identity = sii.SiiIdentity(ident[1].default or 0, ident[2].default or 0, ident[3].default or 0,
                                        quirks.serial, name)
        self.esc = Esc(sii.build_sii(self.identity, self._bytes(RX_ASSIGN), self._bytes(TX_ASSIGN)))
        self.esc.app = self
        self.coe = CoeServer(self.objects.get, self.objects.set, self.esc.post_mailbox, sii.MBX_SIZE)
        self.state = INIT
        self.cycles = 0
        self.events: list[tuple[str, float, str]] = []     # (what, ms after the master's last frame, drive state)
        self._last_frame: float | None = None
        self._powered = False
        self.rx: list[tuple[int, int, int]] = []
        self.tx: list[tuple[int, int, int]] = []
        device.on_master_lost.append(self._watchdog_expired)
        device.arm_watchdogs()

    def _bytes(self, assign: int) -> int:
        return sum(bits for _i, _s, bits in self.objects.mapping(assign)) // 8

    # -- AL state machine -----------------------------------------------------------------------------------------
    def al_control(self, requested: int, ack: bool) -> None:
        status = self.esc.u16(0x0130)
        error = bool(status & 0x10) and not ack
        if requested == self.state:
            self.esc.set_al_status(self.state, self.esc.u16(0x0134) if error else 0, error)
            return
        code = self._transition(requested)
        if code:
            self.esc.set_al_status(self.state, code, True)
        else:
            self.esc.set_al_status(self.state)

    def _transition(self, requested: int) -> int:
        current = self.state
        if requested == INIT:
            self._leave_op()
            self.state = INIT
            self.objects.preop = True
            return 0
        if requested == BOOT:
            return AL_BOOT_NOT_SUPPORTED
        if requested == PREOP:
            if not self._mailbox_ok():
                return AL_INVALID_MAILBOX
            self._leave_op()
            self.state, self.objects.preop = PREOP, True
            return 0
        if requested == SAFEOP:
            if current == OP:
                self._leave_op()
                self.state = SAFEOP
                return 0
            if current != PREOP:
                return AL_INVALID_STATE_CHANGE
            if self.quirks.refuse_safeop:
                return self.quirks.refuse_safeop
            code = self._process_data_ok()
            if code:
                return code
            self.state, self.objects.preop = SAFEOP, False
            return 0
        if requested == OP:
            if current != SAFEOP:
                return AL_INVALID_STATE_CHANGE
            self.state = OP
            _s, _l, control, _e = self.esc.sm(2)
            self.device.master_watchdog.arm(self.esc.watchdog_s() if control & 0x40 else 0.0)
            return 0
        return AL_UNKNOWN_STATE

    def _leave_op(self) -> None:
        """Out of OP on the master's request: the outputs are no longer valid, so the power stage goes off."""
        if self.state == OP:
            self.device.master_watchdog.arm(0.0)
            with self.device.lock:
                if self.device.device.power_enabled:
                    self.device.write_controlword(Command.DISABLE_VOLTAGE)

    def _mailbox_ok(self) -> bool:
        return (self.esc.sm(0)[0::3] == (sii.MBX_OUT_ADDR, True) and self.esc.sm(0)[1] == sii.MBX_SIZE
                and self.esc.sm(1)[0::3] == (sii.MBX_IN_ADDR, True) and self.esc.sm(1)[1] == sii.MBX_SIZE)

    def _process_data_ok(self) -> int:
        """The SyncManagers the master set for process data against the PDOs assigned: the AL status code if not."""
        try:
            rx, tx = self.objects.mapping(RX_ASSIGN), self.objects.mapping(TX_ASSIGN)
            for index, sub, bits in rx + tx:
                if index:
                    self.objects.check_entry(index << 16 | sub << 8 | bits, rx=(index, sub, bits) in rx)
        except SdoAbort:
            return AL_INVALID_OUTPUT
        for n, entries, code, address in ((2, rx, AL_INVALID_OUTPUT, sii.PD_OUT_ADDR),
                                          (3, tx, AL_INVALID_INPUT, sii.PD_IN_ADDR)):
            start, length, _c, enabled = self.esc.sm(n)
            size = sum(bits for _i, _s, bits in entries) // 8
            if size and (not enabled or start != address or length != size):
                return code
        cycle = self.objects.raw(SM_OUT_PARAM, 2)
        if cycle and round(cycle * 1e-9 / self.device.model.control_period_s) < 1:
            return AL_INVALID_SYNC_CYCLE
        self.rx, self.tx = rx, tx
        return 0

    def sm_usable(self, n: int) -> bool:
        """Outputs count in OP only; inputs from SAFE-OP (the firmware deactivates SMs it does not serve)."""
        return self.state == OP if n == 2 else self.state in (SAFEOP, OP)

    # -- mailbox and process data ---------------------------------------------------------------------------------
    def mailbox_received(self, data: bytes) -> None:
        self.coe.received(data)

    def outputs_received(self) -> None:
        """The RxPDO into the drive's objects (OP only: SM2 is not served below it)."""
        start = sii.PD_OUT_ADDR
        mem = self.esc.mem
        for index, sub, bits in self.rx:
            n = bits // 8
            if index:
                try:
                    self.objects.node.set_data(index, sub, bytes(mem[start:start + n]))
                except Exception:        # a value the drive refuses is dropped, as a drive drops it
                    pass
            start += n
        self.device.master_watchdog.touch()

    def cycle(self) -> None:
        """One process-data cycle: the drive advances by the SM cycle time (0x1C32:02), then the TxPDO is packed."""
        cycle_ns = self.objects.raw(SM_OUT_PARAM, 2) or DEFAULT_CYCLE_NS
        steps = max(1, round(cycle_ns * 1e-9 / self.device.model.control_period_s))
        self.device.advance(steps)
        self.cycles += 1
        start = sii.PD_IN_ADDR
        for index, sub, bits in self.tx:
            n = bits // 8
            data = self.objects.node.get_data(index, sub) if index else bytes(n)
            self.esc.mem[start:start + n] = data[:n].ljust(n, b"\x00")
            start += n

    def frame(self, frame: bytes) -> bytes | None:
        """One frame through the ESC, then the firmware's work for it (as the PDI does after the frame passed)."""
        with self.device.lock:
            reply = self.esc.frame(frame)
            if reply is None:
                return None
            if self.esc.outputs_written and self.state == OP:
                self.outputs_received()
                self._last_frame = time.monotonic()
            if self.esc.pd_cycle and self.state in (SAFEOP, OP):
                self.cycle()
            return reply

    def _since_last_frame_ms(self) -> float:
        return -1.0 if self._last_frame is None else round((time.monotonic() - self._last_frame) * 1e3, 1)

    def watch_power(self) -> None:
        """Note when the power stage goes off after having been on (the SIGKILL test reads these events)."""
        powered = self.device.device.power_enabled
        if self._powered and not powered:
            self.events.append(("power_off", self._since_last_frame_ms(), self.device.device.state.name))
        self._powered = powered

    def _watchdog_expired(self) -> None:
        """Called by the device's watchdog after its 0x6007 reaction: the ESC's and the AL's part."""
        self.events.append(("sm_watchdog", self._since_last_frame_ms(), self.device.device.state.name))
        if self.state == OP:
            self.esc.watchdog_expired()
            self.state = SAFEOP
            self.esc.set_al_status(SAFEOP, AL_SM_WATCHDOG, True)

