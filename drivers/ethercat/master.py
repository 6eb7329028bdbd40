"""The EtherCAT master for one CoE slave, through pysoem (SOEM): open on a named interface, bus scan, identity from
the SII, INIT -> PRE-OP -> SAFE-OP -> OP with AL status codes named on failure, CoE SDO, PDO assignment and mapping
written in PRE-OP (or a fixed mapping read), and process data exchanged either by the caller (lockstep) or by a
cyclic thread in free run whose working counter is checked every cycle."""

from __future__ import annotations

import os
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import pysoem

from drivers.contract.errors import LinkError

RX_ASSIGN, TX_ASSIGN, SM_OUT_PARAM = 0x1C12, 0x1C13, 0x1C32
STATE_NAMES = {pysoem.INIT_STATE: "INIT", pysoem.PREOP_STATE: "PRE-OP", pysoem.BOOT_STATE: "BOOT",
               pysoem.SAFEOP_STATE: "SAFE-OP", pysoem.OP_STATE: "OP", 0: "NONE"}
FIXES = {0x0016: "the slave wants other mailbox SyncManagers: check its ESI/SII",
         0x001D: "the output PDO mapping or SM2 does not fit the slave: check [drive] PDOs against its ESI",
         0x001E: "the input PDO mapping or SM3 does not fit the slave: check [drive] PDOs against its ESI",
         0x001B: "the SM watchdog expired: the bench stopped exchanging process data",
         0x0035: "the slave refuses this cycle time: set [drive] cycle_s to one it supports",
         0x0011: "the slave refused the state sequence: power-cycle it and retry"}
MIN_PD_SLEEP_S = 0.0002


def state_name(state: int) -> str:
    base = STATE_NAMES.get(state & 0x0F, f"0x{state & 0x0F:X}")
    return base + (" + ERROR" if state & pysoem.STATE_ERROR else "")


def al_text(code: int) -> str:
    return f"AL status code 0x{code:04X} ({pysoem.al_status_code_to_string(code)})"


@dataclass
class CycleStats:
    """What the cyclic thread saw: periods between frames sent, working counters lost."""

    periods_s: list[float] = field(default_factory=list)
    cycles: int = 0
    lost_wkc: int = 0
    late: int = 0

    def p99_s(self) -> float | None:
        if not self.periods_s:
            return None
        ordered = sorted(self.periods_s)
        return ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))]


class EthercatMaster:
    """One slave at `position` (1-based) on `interface`. `where` prefixes every error."""

    def __init__(self, interface: str, position: int = 1, sdo_timeout_s: float = 1.0, state_timeout_s: float = 3.0):
        self.interface = interface
        self.position = position
        self.where = f"EtherCAT {interface} slave {position}"
        self.sdo_timeout_us = int(sdo_timeout_s * 1e6)
        self.state_timeout_us = int(state_timeout_s * 1e6)
        self.master = pysoem.Master()
        self.master.always_release_gil = True      # SOEM's waits must not stop this process's other threads
        self.master.sdo_read_timeout = self.master.sdo_write_timeout = self.sdo_timeout_us
        self.slave = None
        self.expected_wkc = 0
        self.outputs = b""
        self.inputs = b""
        self.stats = CycleStats()
        self._pd_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.receive_timeout_us = 2000             # a frame later than this counts as lost
        self.on_inputs: Callable[[bytes, int], None] | None = None   # cyclic thread: (inputs, wkc) each cycle
        self.opened = False
        self.last_exchange: float | None = None

    @staticmethod
    def lenient_frames() -> None:
        """SOEM's frame and mailbox timeouts (process-wide) stretched for a simulated slave on a loaded host: a frame
        answered after SOEM's 2 ms is taken as lost and its register access fails. A rig keeps SOEM's defaults."""
        pysoem.settings.timeouts.ret = 20_000
        pysoem.settings.timeouts.tx_mailbox = 200_000

    # -- bus -----------------------------------------------------------------------------------------------------
    def open(self) -> None:
        if os.path.isdir("/sys/class/net") and self.interface not in os.listdir("/sys/class/net"):
            raise LinkError(f"{self.where}: no network interface {self.interface!r} on this host "
                            f"(have: {', '.join(sorted(os.listdir('/sys/class/net')))}); set [drive] interface")
        try:
            self.master.open(self.interface)
        except ConnectionError:
            raise LinkError(f"{self.where}: cannot open {self.interface!r} for raw EtherCAT frames: run as root or "
                            f"give the interpreter CAP_NET_RAW (docs/ethercat.md)") from None
        self.opened = True
        found = self.master.config_init()
        if found <= 0:
            raise LinkError(f"{self.where}: no EtherCAT slave answers on {self.interface}: check the cable, the "
                            f"drive's power and that [drive] interface is the port the drive is on")
        if self.position > found:
            raise LinkError(f"{self.where}: only {found} slave(s) on the bus; set [drive] slave to 1..{found}")
        self.slave = self.master.slaves[self.position - 1]
        self.require(pysoem.PREOP_STATE, "INIT -> PRE-OP")

    def scan(self) -> list[tuple[int, int, int, str]]:
        return [(s.man, s.id, s.rev, s.name) for s in self.master.slaves]

    def al_status_code(self) -> int:
        return struct.unpack("<H", self.slave._fprd(0x0134, 2))[0]

    def require(self, state: int, what: str) -> None:
        """Wait for the slave to reach `state`; else LinkError naming the state it is in and its AL status code."""
        reached = self.slave.state_check(state, self.state_timeout_us)
        if reached == state:
            return
        self.master.read_state()
        code = self.slave.al_status
        detail = f"{al_text(code)}; {FIXES.get(code, 'see the drive manual for this code')}" if code else "no AL code"
        raise LinkError(f"{self.where}: {what} refused: slave stays in {state_name(self.slave.state)}: {detail}")

    def request(self, state: int) -> None:
        self.slave.state = state
        self.slave.write_state()

    # -- CoE ------------------------------------------------------------------------------------------------------
    def _retry(self, call):
        """A mailbox exchange whose frame went missing (WkcError) is tried again, twice: reads are idempotent and
        a download writes the same value again."""
        for attempt in range(3):
            try:
                return call()
            except pysoem.WkcError:
                if attempt == 2:
                    raise
                time.sleep(0.01)

    def sdo_read(self, index: int, sub: int, size: int = 0) -> bytes:
        try:
            return self._retry(lambda: self.slave.sdo_read(index, sub, size))
        except pysoem.SdoError as exc:
            raise LinkError(f"{self.where}: SDO read 0x{index:04X}:{sub:02X} aborted 0x{exc.abort_code:08X} "
                            f"({exc.desc})") from None
        except (pysoem.WkcError, pysoem.MailboxError, pysoem.PacketError) as exc:
            raise LinkError(f"{self.where}: SDO read 0x{index:04X}:{sub:02X}: {type(exc).__name__} {exc}") from None

    def sdo_write(self, index: int, sub: int, data: bytes) -> None:
        try:
            self._retry(lambda: self.slave.sdo_write(index, sub, data))
        except pysoem.SdoError as exc:
            raise LinkError(f"{self.where}: SDO write 0x{index:04X}:{sub:02X} aborted 0x{exc.abort_code:08X} "
                            f"({exc.desc})") from None
        except (pysoem.WkcError, pysoem.MailboxError, pysoem.PacketError) as exc:
            raise LinkError(f"{self.where}: SDO write 0x{index:04X}:{sub:02X}: {type(exc).__name__} {exc}") from None

    def read_u(self, index: int, sub: int, fmt: str) -> int | float:
        data = self.sdo_read(index, sub)
        return struct.unpack(fmt, data[:struct.calcsize(fmt)].ljust(struct.calcsize(fmt), b"\0"))[0]

    def assign(self, rx: dict[int, list[int]], tx: dict[int, list[int]]) -> bool:
        """PDO assignment and mapping written in PRE-OP (CiA 402 over EtherCAT: 0x1C12/0x1C13, 0x16xx/0x1Axx).
        False: the slave's mapping is fixed (it refuses the first write as read-only): the caller reads it."""
        try:
            self.sdo_write(RX_ASSIGN, 0, b"\0")
        except LinkError as exc:
            if "0x06010002" in str(exc):
                return False
            raise
        self.sdo_write(TX_ASSIGN, 0, b"\0")
        for assign_index, pdos in ((RX_ASSIGN, rx), (TX_ASSIGN, tx)):
            for k, (pdo, entries) in enumerate(pdos.items(), 1):
                self.sdo_write(pdo, 0, b"\0")
                for n, entry in enumerate(entries, 1):
                    try:
                        self.sdo_write(pdo, n, struct.pack("<I", entry))
                    except LinkError as exc:
                        raise LinkError(f"{exc}: the slave rejects 0x{entry >> 16:04X}:{entry >> 8 & 0xFF:02X} "
                                        f"({entry & 0xFF} bits) in PDO 0x{pdo:04X}; map only objects its ESI marks "
                                        f"PdoMapping, or leave the mapping to the drive") from None
                self.sdo_write(pdo, 0, bytes([len(entries)]))
                self.sdo_write(assign_index, k, struct.pack("<H", pdo))
            self.sdo_write(assign_index, 0, bytes([len(pdos)]))
        return True

    def read_mapping(self, assign: int) -> list[tuple[int, int, int]]:
        entries = []
        for k in range(1, int(self.read_u(assign, 0, "<B")) + 1):
            pdo = int(self.read_u(assign, k, "<H"))
            for n in range(1, int(self.read_u(pdo, 0, "<B")) + 1):
                raw = int(self.read_u(pdo, n, "<I"))
                entries.append((raw >> 16, raw >> 8 & 0xFF, raw & 0xFF))
        return entries

    # -- process data ----------------------------------------------------------------------------------------------
    def start_operation(self, cycle_s: float, watchdog_ms: float, exchange: Callable[[], object] | None = None) -> None:
        """PRE-OP -> SAFE-OP -> OP: cycle time into 0x1C32:02, the SM watchdog time, the IO map, the states."""
        try:
            self.sdo_write(SM_OUT_PARAM, 2, struct.pack("<I", round(cycle_s * 1e9)))
        except LinkError:
            pass                                   # a slave without 0x1C32 runs free on its own cycle
        if watchdog_ms > 0:
            self.slave.set_watchdog("processdata", watchdog_ms)
        try:
            self.master.config_map()
        except pysoem.ConfigMapError as exc:
            raise LinkError(f"{self.where}: mapping the process data failed: {exc.error_list}") from None
        self.require(pysoem.SAFEOP_STATE, "PRE-OP -> SAFE-OP")
        self.expected_wkc = self.master.expected_wkc
        self.outputs = bytes(len(self.slave.output))
        self.go_op(exchange)

    def go_op(self, exchange: Callable[[], object] | None = None) -> None:
        """SAFE-OP -> OP, exchanging process data meanwhile (a slave wants valid outputs first); `exchange`: the
        caller's own cycle (lockstep: each cycle is drive time the caller keeps)."""
        self.request(pysoem.OP_STATE)
        deadline = time.monotonic() + self.state_timeout_us * 1e-6
        while time.monotonic() < deadline:
            (exchange or self.exchange)()
            if self.slave.state_check(pysoem.OP_STATE, 1000) == pysoem.OP_STATE:
                return
        self.require(pysoem.OP_STATE, "SAFE-OP -> OP")

    def exchange(self) -> tuple[bytes, int]:
        """One process-data cycle: outputs out, inputs in; the working counter it came back with."""
        with self._pd_lock:
            self.slave.output = self.outputs
            self.master.send_processdata()
            wkc = self.master.receive_processdata(self.receive_timeout_us)
            self.inputs = self.slave.input
            self.last_exchange = time.monotonic()
        return self.inputs, wkc

    def start_cyclic(self, cycle_s: float) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._cyclic, args=(cycle_s,), name="ethercat-pd", daemon=True)
        self._thread.start()

    def stop_cyclic(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    @property
    def cyclic(self) -> bool:
        return self._thread is not None

    def _cyclic(self, cycle_s: float) -> None:
        """Free run at cycle_s on an absolute schedule (SCHED_FIFO where permitted, as a master's cycle runs)."""
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(50))
        except (PermissionError, OSError, AttributeError):
            pass
        stats = self.stats
        next_t = time.perf_counter()
        last = None
        while not self._stop.is_set():
            now = time.perf_counter()
            if last is not None:
                stats.periods_s.append(now - last)
                if len(stats.periods_s) > 600_000:
                    del stats.periods_s[:100_000]
            last = now
            inputs, wkc = self.exchange()
            stats.cycles += 1
            if wkc != self.expected_wkc:
                stats.lost_wkc += 1
            if self.on_inputs is not None:
                self.on_inputs(inputs, wkc)
            next_t += cycle_s
            delay = next_t - time.perf_counter()
            if delay < -cycle_s:                  # far behind: re-anchor instead of bursting
                stats.late += 1
                next_t = time.perf_counter()
            elif delay > MIN_PD_SLEEP_S:
                time.sleep(delay - MIN_PD_SLEEP_S)
                while time.perf_counter() < next_t:
                    pass

    def close(self, to_init: bool = True) -> None:
        self.stop_cyclic()
        if self.opened:
            if to_init and self.slave is not None:
                try:
                    self.request(pysoem.INIT_STATE)
                except Exception:
                    pass
            self.master.close()
            self.opened = False
