"""Modbus load machines by data: map files, wire bytes for two different maps, round trips over TCP and RTU (pty)
against the simulated machine, exceptions, timeouts, and the machine's communication watchdog."""

import os
import select
import socket
import struct
import threading
import time
import tty
from pathlib import Path

import pytest

from drivers.contract.errors import LinkError
from drivers.contract.load_map import LoadMode
from drivers.contract.errors import ContentError
from drivers.contract.load_map import read_load_map
from drivers.modbus_load import ModbusLoadLink
from sim_backend.device import SimulatedDevice
from sim_backend.modbus_server import MAP_FILE, TORQUE_LIMIT_NM, start_modbus_rtu_pty, start_modbus_tcp
from sim_backend.toy import ToyDrive

ROOT = Path(__file__).resolve().parents[2]
SIM_MAP = "config/load-machines/drivebench-sim.toml"
DYNO_MAP = "config/load-machines/example-torque-only-dyno.toml"


def crc16_modbus_reference(data: bytes) -> int:
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def test_crc16_reference_check_value():
    assert crc16_modbus_reference(b"123456789") == 0x4B37


def test_the_simulated_machine_serves_the_map_file_the_bench_reads():
    assert MAP_FILE == ROOT / SIM_MAP
    m = read_load_map(MAP_FILE)
    assert (m["setpoint"].address, m["speed"].address, m["watchdog"].address, m["version"].extra["expect"]) == (2, 16, 5, 2)
    assert [mode.name for mode in m.modes] == ["TORQUE", "VISCOUS", "BRAKE"]


def test_word_orders_and_types():
    m = read_load_map(ROOT / SIM_MAP)
    assert m["setpoint"].encode(2.5, "big") == [0x4020, 0x0000]          # float32, high word first ("ABCD")
    assert m["setpoint"].encode(-1.0, "big") == [0xBF80, 0x0000]
    dyno = read_load_map(ROOT / DYNO_MAP)
    assert dyno["speed"].encode(0x12345678, "little") == [0x5678, 0x1234]   # int32, low word first ("CDAB")
    assert dyno["speed"].decode([0x5678, 0x1234], "little") == 0x12345678
    assert dyno["speed"].decode(dyno["speed"].encode(-5, "little"), "little") == -5
    assert dyno.modes == (LoadMode.TORQUE,) and dyno.speed_factor == pytest.approx(0.1 * 3.141592653589793 / 30)


@pytest.mark.parametrize("text, field, reason", [
    ("[registers.enable]\naddress = 0\ntype = \"uint16\"\n", "registers.setpoint", "missing"),
    ("[registers.speed]\naddress = 1\ntype = \"float64\"\n", "registers.speed.type", "must be one of"),
    ("[registers.speed]\naddress = 70000\ntype = \"uint16\"\n", "registers.speed.address", "0..65535"),
    ("[registers.speed]\naddress = 1\ntype = \"uint16\"\nunit = \"furlong/s\"\n", "registers.speed.unit", "rad/s"),
    ("[registers.warp]\naddress = 1\ntype = \"uint16\"\n", "registers.warp", "unknown role"),
    ("[registers.setpoint]\naddress = 0\ntype = \"float32\"\n[registers.enable]\naddress = 1\ntype = \"uint16\"\n",
     "registers.enable", "overlaps registers.setpoint"),
    ("[machine]\nword_order = \"middle\"\n", "machine.word_order", "'big' or 'little'"),
])
def test_map_file_problems_name_the_field(tmp_path, text, field, reason):
    path = tmp_path / "m.toml"
    path.write_text(text)
    with pytest.raises(ContentError) as err:
        read_load_map(path)
    assert any(f == field and reason in r for f, r in err.value.problems), err.value.problems


# --- exact bytes on the wire against scripted fake machines -----------------------------------------------------

def answer(pdu: bytes, value: int = 1) -> bytes:
    """What a minimal, well-behaved Modbus machine answers (every holding register reads `value`)."""
    fc = pdu[0]
    if fc in (3, 4):
        (count,) = struct.unpack(">H", pdu[3:5])
        return bytes([fc, 2 * count]) + struct.pack(">H", value) * count
    if fc == 6:
        return pdu[:5]
    if fc == 16:
        return pdu[:5]
    return bytes([fc | 0x80, 1])


class FakeTcpMachine:
    def __init__(self, silent: bool = False, value: int = 1):
        self.value = value
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.silent = silent
        self.requests: list[bytes] = []
        threading.Thread(target=self._run, daemon=True).start()

    def _recv(self, conn, n):
        data = b""
        while len(data) < n:
            chunk = conn.recv(n - len(data))
            if not chunk:
                raise OSError("closed")
            data += chunk
        return data

    def _run(self):
        try:
            conn, _ = self.listener.accept()
            with conn:
                while True:
                    head = self._recv(conn, 7)
                    (length,) = struct.unpack(">H", head[4:6])
                    pdu = self._recv(conn, length - 1)
                    self.requests.append(head + pdu)
                    if not self.silent:
                        reply = answer(pdu, self.value)
                        conn.sendall(head[:4] + struct.pack(">H", len(reply) + 1) + head[6:7] + reply)
        except OSError:
            return

    def close(self):
        self.listener.close()


def _bench_requests(fake) -> list[bytes]:
    """What the bench sent, without the watchdog keep-alive's status reads (their timing is the thread's)."""
    status_read = bytes.fromhex("0000 0006")
    return [r for r in fake.requests if not (r[2:6] == status_read and r[7:] in (bytes.fromhex("03 0014 0001"),))]


def test_setpoint_write_exact_modbus_tcp_adu():
    fake = FakeTcpMachine(value=2)
    link = ModbusLoadLink({"transport": "modbus-tcp", "host": "127.0.0.1", "port": fake.port, "unit_id": 7,
                           "timeout_s": 2.0, "map": SIM_MAP}, ROOT)
    link.open()
    link.set_load(LoadMode.TORQUE, 2.5)
    link.enable(True)
    link.close()
    fake.close()
    read_version, read_identity, arm, setpoint, enable, disarm = _bench_requests(fake)
    assert read_version[2:] == bytes.fromhex("0000 0006 07 03 0020 0001")
    assert read_identity[2:] == bytes.fromhex("0000 0006 07 03 0028 0010")
    assert arm[2:] == bytes.fromhex("0000 0006 07 06 0005 03E8")             # watchdog 1000 ms
    # MBAP: transaction id (any), protocol 0, length 13, unit 7; PDU: FC16 at 1, 3 registers, 6 bytes:
    # mode 0 (TORQUE), setpoint 2.5 as float32 0x40200000, high word first: one request, never half a change.
    assert setpoint[2:] == bytes.fromhex("0000 000D 07 10 0001 0003 06 0000 4020 0000")
    assert enable[2:] == bytes.fromhex("0000 0006 07 06 0000 0001")
    assert disarm[2:] == bytes.fromhex("0000 0006 07 06 0005 0000")          # a normal end disarms it
    ids = [struct.unpack(">H", r[:2])[0] for r in fake.requests]
    assert len(set(ids)) == len(ids)


def test_a_third_party_map_puts_other_bytes_on_the_wire():
    """The same link and the same calls, another machine: torque-only, integer registers in engineering units,
    feedback in input registers (FC4), 32-bit values low word first."""
    fake = FakeTcpMachine(value=0x0102)
    link = ModbusLoadLink({"transport": "modbus-tcp", "host": "127.0.0.1", "port": fake.port, "unit_id": 9,
                           "timeout_s": 2.0, "map": DYNO_MAP}, ROOT)
    assert link.open() == "example torque-only dynamometer"
    link.set_load(LoadMode.TORQUE, 2.5)
    with pytest.raises(LinkError, match="has no viscous mode"):
        link.set_load(LoadMode.VISCOUS, 0.1)
    link.enable(True)
    fb = link.feedback()
    link.close()
    fake.close()
    arm, setpoint, enable, feedback, disarm = [r for r in fake.requests if r[7] != 4 or r[8:10] != b"\x00\xcb"]
    assert arm[2:] == bytes.fromhex("0000 0006 09 06 006E 01F4")              # watchdog 500 ms at 110
    assert setpoint[2:] == bytes.fromhex("0000 0006 09 06 0065 00FA")         # 2.5 N*m / 0.01 = 250 at 101
    assert enable[2:] == bytes.fromhex("0000 0006 09 06 0064 0001")
    assert feedback[2:] == bytes.fromhex("0000 0006 09 04 00C8 0004")         # FC4, 200..203 in one request
    assert disarm[2:] == bytes.fromhex("0000 0006 09 06 006E 0000")
    # every register reads 0x0102: speed int32 (low word first) 0x01020102 x 0.1 rpm, torque 258 x 0.01 N*m,
    # status 0x0102: bit 0 clear (not enabled), bit 3 clear (no fault)
    assert fb.speed_mech_rad_s == pytest.approx(0x01020102 * 0.1 * 3.141592653589793 / 30)
    assert fb.torque_nm == pytest.approx(2.58) and not fb.enabled and not fb.fault


class FakeRtuMachine:
    """Answers on the master side of a pty; the link opens the slave like a serial port."""

    def __init__(self, silent: bool = False, value: int = 1):
        self.value = value
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.silent = silent
        self.requests: list[bytes] = []
        self._stop = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _read(self, n):
        data = b""
        while len(data) < n:
            ready, _, _ = select.select([self.master], [], [], 0.1)
            if self._stop:
                raise OSError("stopped")
            if ready:
                data += os.read(self.master, n - len(data))
        return data

    def _run(self):
        try:
            while True:
                head = self._read(7)
                rest = self._read(1) if head[1] in (3, 6) else self._read(head[6] + 2)   # FC3/6: 8-byte frames; FC16: byte count in head[6]
                adu = head + rest
                self.requests.append(adu)
                if not self.silent:
                    body = adu[:1] + answer(adu[1:-2], self.value)
                    os.write(self.master, body + struct.pack("<H", crc16_modbus_reference(body)))
        except OSError:
            return

    def close(self):
        self._stop = True
        self._thread.join(10)             # it polls every 0.1 s; close the fds only once it is gone
        for fd in (self.master, self.slave):
            os.close(fd)


def test_setpoint_write_exact_modbus_rtu_frame():
    fake = FakeRtuMachine(value=2)
    link = ModbusLoadLink({"transport": "modbus-rtu", "port": fake.path, "baudrate": 115200, "unit_id": 3,
                           "timeout_s": 2.0, "map": SIM_MAP}, ROOT)
    link.open()
    link.set_load(LoadMode.BRAKE, 2.5)
    link.close()
    fake.close()
    setpoint = [r for r in fake.requests if r[1] == 0x10][-1]
    body = bytes.fromhex("03 10 0001 0003 06 0002 4020 0000")
    assert setpoint == body + struct.pack("<H", crc16_modbus_reference(body))


def test_other_register_map_version_is_refused():
    fake = FakeTcpMachine(value=1)
    link = ModbusLoadLink({"transport": "modbus-tcp", "host": "127.0.0.1", "port": fake.port, "timeout_s": 2.0,
                           "map": SIM_MAP}, ROOT)
    with pytest.raises(LinkError, match="register map version 1, the map file drivebench-sim.toml describes version 2"):
        link.open()
    assert link._client is None
    fake.close()


def test_modbus_tcp_timeout_is_a_clear_link_error():
    fake = FakeTcpMachine(silent=True)
    link = ModbusLoadLink({"transport": "modbus-tcp", "host": "127.0.0.1", "port": fake.port, "timeout_s": 0.2,
                           "retries": 1, "map": SIM_MAP}, ROOT)
    start = time.monotonic()
    with pytest.raises(LinkError, match=r"read_holding_registers of register 32 \(version\): no valid reply "
                                        r"within 0.2 s x 2"):
        link.open()
    assert time.monotonic() - start < 10.0
    link.close()
    fake.close()


def test_modbus_rtu_timeout_is_a_clear_link_error():
    fake = FakeRtuMachine(silent=True)
    link = ModbusLoadLink({"transport": "modbus-rtu", "port": fake.path, "baudrate": 115200, "timeout_s": 0.2,
                           "retries": 0, "map": SIM_MAP}, ROOT)
    with pytest.raises(LinkError, match=r"modbus-rtu .*register 32 \(version\): no valid reply"):
        link.open()
    link.close()
    fake.close()


def test_unreachable_machine_is_a_link_error():
    with socket.create_server(("127.0.0.1", 0)) as s:
        port = s.getsockname()[1]
    link = ModbusLoadLink({"transport": "modbus-tcp", "host": "127.0.0.1", "port": port, "timeout_s": 0.5,
                           "map": SIM_MAP}, ROOT)
    with pytest.raises(LinkError, match="cannot connect"):
        link.open()


# --- against the simulated load machine ----------------------------------------------------------------------

@pytest.fixture(params=["tcp", "rtu"])
def machine(request):
    device = SimulatedDevice(ToyDrive())
    if request.param == "tcp":
        server = start_modbus_tcp(device)
        section = {"transport": "modbus-tcp", "host": "127.0.0.1", "port": server.port}
    else:
        server = start_modbus_rtu_pty(device)
        section = {"transport": "modbus-rtu", "port": server.path, "baudrate": 115200}
    link = ModbusLoadLink(section | {"timeout_s": 2.0, "map": SIM_MAP}, ROOT)
    yield device, server, link
    link.close()
    server.stop()


def run_drive(device, speed, steps):
    for word in (0x06, 0x07, 0x0F):
        device.write_controlword(word)
    device.target_speed_mech_rad_s = speed
    device.advance(steps)


def test_round_trip_load_torque_and_feedback(machine):
    device, _, link = machine
    assert link.open() == "drivebench-sim load machine"
    link.set_load(LoadMode.TORQUE, 2.5)
    link.enable(True)
    assert (device.load.mode, device.load.value, device.load.enabled) == (0, 2.5, True)
    run_drive(device, 50.0, 500)
    fb = link.feedback()
    speed, torque = device.model.load_feedback()
    assert fb.speed_mech_rad_s == pytest.approx(speed, rel=1e-6) and speed > 10
    assert fb.torque_nm == 2.5 == torque
    assert fb.enabled and not fb.fault
    i_sy = device.latest[8]
    assert i_sy == pytest.approx(2.5)                   # the toy drive carries the load in its torque current
    link.set_load(LoadMode.VISCOUS, 0.1)
    assert link.feedback().torque_nm == pytest.approx(0.1 * speed, rel=1e-6)
    link.zero_and_disable()
    assert device.load.value == 0.0 and not device.load.enabled
    assert link.feedback().torque_nm == 0.0


def test_out_of_range_setpoint_is_refused_naming_the_registers(machine):
    device, server, link = machine
    link.open()
    with pytest.raises(LinkError, match=r"write_registers of registers 1..3 \(mode, setpoint\) refused: "
                                        r"Modbus exception 3 \(illegal data value\)"):
        link.set_load(LoadMode.TORQUE, TORQUE_LIMIT_NM * 2)
    with pytest.raises(LinkError, match="exception 3"):
        link.set_load(LoadMode.BRAKE, -1.0)              # a passive brake cannot motor
    with pytest.raises(LinkError, match="exception 3"):
        link.set_load(LoadMode.TORQUE, float("nan"))
    assert device.load.value == 0.0                      # nothing half-applied
    assert server.registers.rejected[-1] == (16, 1, 3)


def test_illegal_addresses_are_refused_naming_the_register(machine):
    _, _, link = machine
    link.open()
    with pytest.raises(LinkError, match=r"registers 16..17 \(speed\) refused: Modbus exception 2 "
                                        r"\(illegal data address\)"):
        link._call("write_registers", 16, values=[0, 0])      # read-only feedback
    with pytest.raises(LinkError, match=r"register 8 \(unmapped\) refused: Modbus exception 2"):
        link._call("read_holding_registers", 8, count=1)
    with pytest.raises(LinkError, match=r"register 2 \(setpoint\) refused: Modbus exception 2"):
        link._call("write_register", 2, value=0x4020)         # half a float32 pair
    with pytest.raises(LinkError, match=r"register 1 \(mode\) refused: Modbus exception 3"):
        link._call("write_register", 1, value=7)              # no such LoadMode


def test_fault_is_reported_blocks_enable_and_resets(machine):
    device, _, link = machine
    link.open()
    link.enable(True)
    with device.lock:
        device.load.fault = 0x0042
        device.set_load(enabled=False)
    fb = link.feedback()
    assert fb.fault and not fb.enabled
    assert link.read(link.map["fault_code"]) == 0x0042
    with pytest.raises(LinkError, match=r"register 0 \(enable\) refused: Modbus exception 4"):
        link.enable(True)
    link.reset_fault()
    assert device.load.fault == 0 and link.read(link.map["fault_reset"]) == 0   # fault_reset reads back 0
    link.enable(True)
    assert link.feedback().enabled


def test_server_stops_cleanly_and_link_then_errors():
    device = SimulatedDevice(ToyDrive())
    server = start_modbus_tcp(device)
    link = ModbusLoadLink({"transport": "modbus-tcp", "host": "127.0.0.1", "port": server.port,
                           "timeout_s": 0.3, "retries": 0, "map": SIM_MAP}, ROOT)
    link.open()
    server.stop()
    with pytest.raises(LinkError, match="load machine modbus-tcp"):
        link.feedback()
    link.close()
    assert not server._loop.thread.is_alive()


@pytest.mark.slow
def test_the_machine_stops_itself_when_the_bench_goes_silent():
    """The watchdog the link armed at connect: while the bench process lives its keep-alive feeds it; when the
    bench dies (here: the keep-alive stopped, nothing sent any more) the machine takes its torque off within the
    timeout, by itself."""
    device = SimulatedDevice(ToyDrive())
    server = start_modbus_tcp(device)
    link = ModbusLoadLink({"transport": "modbus-tcp", "host": "127.0.0.1", "port": server.port, "timeout_s": 2.0,
                           "map": SIM_MAP}, ROOT)
    try:
        link.open()
        assert link.report["watchdog"].startswith("armed: 1000 ms")
        link.set_load(LoadMode.TORQUE, 3.0)
        link.enable(True)
        time.sleep(1.5)                                   # longer than the timeout: the keep-alive holds it
        assert device.load.enabled and device.load.value == 3.0
        link._keepalive_stop.set()                        # the bench process dies: nothing more on the wire
        silent = time.monotonic()
        while device.load.enabled:
            assert time.monotonic() - silent < 1.0 + 0.5, "the machine kept its torque"
            time.sleep(0.01)
        assert time.monotonic() - silent >= 1.0 - 0.3   # the keep-alive's last read can be up to 0.25 s earlier
        assert device.load.value == 0.0 and "no Modbus request" in device.faults.self_stops[-1]
    finally:
        link.close()
        server.stop()
        device.stop_watchdogs()
