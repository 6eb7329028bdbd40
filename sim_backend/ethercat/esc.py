"""The EtherCAT slave controller: its register and process memory, the datagram commands a master sends (with
working counter increments), SyncManagers (mailbox handshake, buffered process data), FMMUs for logical addressing,
the SII EEPROM interface (0x0500-0x050F) and the process-data watchdog registers. What the slave's firmware does (AL
state machine, CoE, the drive) sits behind the EscApplication protocol, as behind an ESC's PDI."""

from __future__ import annotations

import struct
import time
from typing import Protocol

from sim_backend.ethercat import frames as f

MEMORY = 0x2000
REG_TYPE, REG_STATION, REG_DL_STATUS = 0x0000, 0x0010, 0x0110
REG_AL_CONTROL, REG_AL_STATUS, REG_AL_CODE, REG_PDI_CONTROL = 0x0120, 0x0130, 0x0134, 0x0140
REG_WD_DIVIDER, REG_WD_PDI, REG_WD_PD, REG_WD_STATUS, REG_WD_COUNTER = 0x0400, 0x0410, 0x0420, 0x0440, 0x0442
REG_EEP_CONFIG, REG_EEP_CONTROL, REG_EEP_ADDRESS, REG_EEP_DATA = 0x0500, 0x0502, 0x0504, 0x0508
REG_FMMU, REG_SM = 0x0600, 0x0800
N_FMMU, N_SM = 8, 8
EEP_READ, EEP_R64 = 0x0100, 0x0040
SM_FULL = 0x08
# written by the ESC or the PDI only: a master's write leaves them alone
READ_ONLY = ((0x0000, 0x0010), (0x0110, 0x0120), (0x0130, 0x0140), (0x0440, 0x0442), (0x0508, 0x0510))


class EscApplication(Protocol):
    """The slave firmware behind the PDI."""

    def al_control(self, requested: int, ack: bool) -> None: ...
    def mailbox_received(self, data: bytes) -> None: ...
    def outputs_received(self) -> None: ...
    def sm_usable(self, n: int) -> bool: ...


class Esc:
    def __init__(self, sii: bytes, esc_type: int = 0x11, revision: int = 0x0002):
        self.mem = bytearray(MEMORY)
        self.sii = sii
        self.app: EscApplication | None = None
        struct.pack_into("<BBH", self.mem, REG_TYPE, esc_type, revision, 0x0001)
        struct.pack_into("<BBBB", self.mem, 0x0004, N_FMMU, N_SM, MEMORY // 1024 - 4, 0x0F)  # ports 0-1 MII
        struct.pack_into("<H", self.mem, 0x0008, 0x0000)          # features: no distributed clocks
        struct.pack_into("<H", self.mem, REG_DL_STATUS, 0x0211)   # PDI operational, link and comm on port 0
        struct.pack_into("<H", self.mem, REG_AL_STATUS, 0x0001)
        struct.pack_into("<H", self.mem, REG_PDI_CONTROL, 0x0005)
        struct.pack_into("<H", self.mem, REG_WD_DIVIDER, 0x09C2)  # 100 us watchdog units
        struct.pack_into("<HH", self.mem, REG_WD_PDI, 1000, 0)
        struct.pack_into("<H", self.mem, REG_WD_PD, 1000)         # 100 ms process-data watchdog
        struct.pack_into("<H", self.mem, REG_EEP_CONTROL, EEP_R64)
        self.outputs_written = False
        self.mailbox_in: bytes | None = None
        self.last_pd_write: float | None = None    # monotonic time of the last SM watchdog trigger
        self.frames = 0
        self.pd_cycle = False              # this frame read or wrote process data through an FMMU

    # -- registers ------------------------------------------------------------------------------------------------
    def u16(self, addr: int) -> int:
        return struct.unpack_from("<H", self.mem, addr)[0]

    def set_u16(self, addr: int, value: int) -> None:
        struct.pack_into("<H", self.mem, addr, value)

    @property
    def station(self) -> int:
        return self.u16(REG_STATION)

    def sm(self, n: int) -> tuple[int, int, int, bool]:
        """(start, length, control, enabled) of SyncManager n."""
        start, length, control, _status, activate = struct.unpack_from("<HHBBB", self.mem, REG_SM + 8 * n)
        return start, length, control, bool(activate & 1) and length > 0

    def set_sm_status(self, n: int, full: bool) -> None:
        addr = REG_SM + 8 * n + 5
        self.mem[addr] = (self.mem[addr] | SM_FULL) if full else (self.mem[addr] & ~SM_FULL)

    def watchdog_s(self) -> float:
        """The process-data watchdog time (0x0420 x (0x0400 + 2) x 40 ns); 0: off."""
        return self.u16(REG_WD_PD) * (self.u16(REG_WD_DIVIDER) + 2) * 40e-9

    def watchdog_expired(self) -> None:
        """The ESC's part of an expired SM watchdog: 0x0440 bit 0 cleared, 0x0442 counts."""
        self.set_u16(REG_WD_STATUS, 0)
        self.mem[REG_WD_COUNTER] = min(0xFF, self.mem[REG_WD_COUNTER] + 1)

    def set_al_status(self, state: int, code: int = 0, error: bool = False) -> None:
        self.set_u16(REG_AL_STATUS, state | (0x10 if error else 0))
        self.set_u16(REG_AL_CODE, code)

    def post_mailbox(self, data: bytes) -> None:
        """The firmware puts a mailbox message into SM1 (slave -> master) and marks it full."""
        start, length, _c, enabled = self.sm(1)
        if not enabled:
            return
        self.mem[start:start + length] = data[:length].ljust(length, b"\x00")
        self.set_sm_status(1, True)

    # -- physical access ------------------------------------------------------------------------------------------
    def read(self, addr: int, n: int) -> bytes:
        if addr + n > MEMORY:
            return bytes(n)
        data = bytes(self.mem[addr:addr + n])
        start, length, _c, enabled = self.sm(1)
        if enabled and addr <= start + length - 1 < addr + n and self.mem[REG_SM + 8 + 5] & SM_FULL:
            self.set_sm_status(1, False)     # the master read the mailbox's last byte: empty again
        return data

    def write(self, addr: int, data: bytes) -> None:
        end = addr + len(data)
        if end > MEMORY:
            return
        for k, byte in enumerate(data):
            a = addr + k
            if any(lo <= a < hi for lo, hi in READ_ONLY) or (REG_SM <= a < REG_SM + 8 * N_SM and (a - REG_SM) % 8 == 5):
                continue
            self.mem[a] = byte
        if addr <= REG_AL_CONTROL < end and self.app is not None:
            control = self.u16(REG_AL_CONTROL)
            self.app.al_control(control & 0x0F, bool(control & 0x10))
        if addr <= REG_EEP_CONTROL + 1 and REG_EEP_CONTROL < end:
            self._eeprom_command()
        self._sm_written(addr, end)

    def _eeprom_command(self) -> None:
        command = self.u16(REG_EEP_CONTROL) & 0x0700
        if command == EEP_READ:
            (word,) = struct.unpack_from("<I", self.mem, REG_EEP_ADDRESS)
            chunk = self.sii[2 * word:2 * word + 8]
            self.mem[REG_EEP_DATA:REG_EEP_DATA + 8] = chunk.ljust(8, b"\xff")
        # done at once: not busy, no error; write and reload are not offered (no write access)
        self.set_u16(REG_EEP_CONTROL, EEP_R64)

    def _sm_written(self, lo: int, hi: int) -> None:
        for n in range(N_SM):
            start, length, control, enabled = self.sm(n)
            if not enabled or not lo <= start + length - 1 < hi:
                continue
            if n == 0 and control & 0x0C == 0x04 and self.app is not None:
                self.app.mailbox_received(bytes(self.mem[start:start + length]))
            elif n == 2:
                self.outputs_written = True
                if control & 0x40:
                    self.last_pd_write = time.monotonic()
                    self.set_u16(REG_WD_STATUS, 1)

    # -- datagrams ------------------------------------------------------------------------------------------------
    def _fmmus(self):
        for k in range(N_FMMU):
            ls, ll, _sb, _eb, ps, _psb, kind, active = struct.unpack_from("<IHBBHBBB", self.mem, REG_FMMU + 16 * k)
            if active & 1 and ll:
                yield ls, ll, ps, kind

    def _sm_of(self, phys: int) -> int | None:
        for n in range(2, N_SM):
            start, length, _c, enabled = self.sm(n)
            if enabled and start <= phys < start + length:
                return n
        return None

    def _usable(self, phys: int) -> bool:
        n = self._sm_of(phys)
        return n is not None and (self.app is None or self.app.sm_usable(n))

    def logical(self, d: f.Datagram) -> None:
        lo, n = d.logical, len(d.data)
        did_read = did_write = False
        writes: list[tuple[int, bytes]] = []
        for ls, ll, ps, kind in self._fmmus():
            a, b = max(lo, ls), min(lo + n, ls + ll)
            if a >= b:
                continue
            phys = ps + a - ls
            if not self._usable(phys):
                continue
            self.pd_cycle = True
            if kind & 1 and d.cmd in (f.LRD, f.LRW):
                d.data[a - lo:b - lo] = self.read(phys, b - a)
                did_read = True
            if kind & 2 and d.cmd in (f.LWR, f.LRW):
                writes.append((phys, bytes(d.data[a - lo:b - lo])))
                did_write = True
        for phys, chunk in writes:
            self.write(phys, chunk)
        if d.cmd == f.LRW:
            d.wkc += (1 if did_read else 0) + (2 if did_write else 0)
        elif did_read or did_write:
            d.wkc += 1

    def datagram(self, d: f.Datagram) -> None:
        cmd, n = d.cmd, len(d.data)
        if cmd in (f.LRD, f.LWR, f.LRW):
            self.logical(d)
            return
        if cmd in (f.APRD, f.APWR, f.APRW, f.ARMW):
            addressed = d.adp == 0
            d.adp = (d.adp + 1) & 0xFFFF
        elif cmd in (f.FPRD, f.FPWR, f.FPRW, f.FRMW):
            addressed = d.adp == self.station
        elif cmd in (f.BRD, f.BWR, f.BRW):
            addressed = True
            d.adp = (d.adp + 1) & 0xFFFF
        else:
            return
        if cmd in (f.ARMW, f.FRMW):
            if addressed:
                d.data[:] = self.read(d.ado, n)
            else:
                self.write(d.ado, bytes(d.data))
            d.wkc += 1
            return
        if not addressed:
            return
        if cmd in (f.APRD, f.FPRD):
            d.data[:] = self.read(d.ado, n)
            d.wkc += 1
        elif cmd in (f.APWR, f.FPWR, f.BWR):
            self.write(d.ado, bytes(d.data))
            d.wkc += 1
        elif cmd == f.BRD:
            d.data[:] = bytes(x | y for x, y in zip(d.data, self.read(d.ado, n)))
            d.wkc += 1
        elif cmd in (f.APRW, f.FPRW, f.BRW):
            old = self.read(d.ado, n)
            self.write(d.ado, bytes(d.data))
            d.data[:] = old if cmd != f.BRW else bytes(x | y for x, y in zip(d.data, old))
            d.wkc += 3

    def frame(self, frame: bytes) -> bytes | None:
        """Process one frame as it passes the ESC; the frame as it goes back to the master (None: not EtherCAT)."""
        parsed = f.parse(frame)
        if parsed is None:
            return None
        head, datagrams = parsed
        self.frames += 1
        self.outputs_written = self.pd_cycle = False
        for d in datagrams:
            self.datagram(d)
        return f.reply(head, datagrams)
