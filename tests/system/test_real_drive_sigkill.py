"""`drivebench run` SIGKILLed mid-run against a third-party drive and a dynamometer served out of process (as a real
rig is: no [services], real-time timing): the drive stops itself within its consumer heartbeat time and the load
machine takes its torque off within its watchdog time — nothing on the bench side runs after the kill. Watched by
a second CANopen master and a second Modbus client, as a lab would watch with its own tools."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import canopen
from pymodbus.client import ModbusTcpClient

from drivers.contract import cia402
from tests.sim_process import read_endpoints, serve_sim

REPO = Path(__file__).resolve().parents[2]
EDS = REPO / "config/od/third-party/e35.eds"
CONSUMER_TIME_S = 0.3          # the bench's default consumer heartbeat time
WATCHDOG_S = 1.0               # the simulated load machine's register map arms 1000 ms

SERVE = f"""[simulator]
motor = "{REPO}/config/motors/pmsm-paper.toml"
drive = "generic"
velocity_unit = "rpm"
rated_current_a = 3.5355
rated_torque_nm = 3.9
[simulator.serve]
canopen_socketcand = "127.0.0.1:0"
modbus_tcp = "127.0.0.1:0"
one_bench = false                 # the test's monitor is a second master (SDO reads of the drive's state)
[drive]
node_id = 1
eds = "{EDS}"
"""

BENCH = """[bench]
name = "killed rig"
timing = "realtime"
fault_reset = "never"

[drive]
transport = "canopen"
interface = "socketcand"
channel = "can0@127.0.0.1:{can_port}"
node_id = 1
eds = "{eds}"
sync_period_s = 0.01
heartbeat_timeout_s = 2.0
sdo_timeout_s = 2.0

[load]
transport = "modbus-tcp"
map = "config/load-machines/drivebench-sim.toml"
host = "127.0.0.1"
port = {modbus_port}
timeout_s = 2.0

[reference]
source = "load"
"""

SCENARIO = """schema_version = 1
name = "killed"
bench = "{bench}"
duration_s = 60.0
[[speed]]
kind = "ramp"
start_s = 0.0
end_s = 0.5
speed_mech_rad_s = 20.0
[[load]]
kind = "torque"
start_s = 0.5
torque_nm = 0.5
[limits]
overspeed_mech_rad_s = 40.0
overcurrent_a = 8.0
max_duration_s = 120.0
"""


def test_sigkilled_bench_leaves_the_drive_and_the_load_machine_to_stop_themselves(tmp_path):
    serve_cfg = tmp_path / "serve.toml"
    serve_cfg.write_text(SERVE)
    server = serve_sim(serve_cfg)
    monitor = canopen.Network()
    modbus = None
    bench_proc = None
    try:
        lines = read_endpoints(server, timeout=120.0)
        can_port = next(l for l in lines if l.startswith("canopen ")).split(":")[2].split("/")[0]
        modbus_port = int(next(l for l in lines if l.startswith("modbus ")).split(":")[2].split()[0])
        bench = tmp_path / "bench.toml"
        bench.write_text(BENCH.format(can_port=can_port, eds=EDS, modbus_port=modbus_port))
        scenario = tmp_path / "killed.toml"
        scenario.write_text(SCENARIO.format(bench=bench))
        out = tmp_path / "runs"
        bench_proc = subprocess.Popen([sys.executable, "-m", "bench", "run", str(scenario), "--out", str(out),
                                       "--rerun", "off"], cwd=REPO, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.PIPE, text=True, env={**os.environ, "DRIVEBENCH_DEBUG": ""})
        deadline = time.monotonic() + 90
        while not list(out.glob("*/telemetry.arrows")):      # running: telemetry is being journaled
            assert bench_proc.poll() is None, bench_proc.communicate()[1]
            assert time.monotonic() < deadline, "the run never started"
            time.sleep(0.05)
        time.sleep(2.0)                                     # at speed, under load

        monitor.connect(interface="socketcand", channel="can0", host="127.0.0.1", port=int(can_port))
        node = monitor.add_node(1, str(EDS))
        node.sdo.RESPONSE_TIMEOUT = 2.0
        modbus = ModbusTcpClient("127.0.0.1", port=modbus_port, timeout=2.0)
        assert modbus.connect()
        assert cia402.decode(node.sdo[0x6041].raw) is cia402.State.OPERATION_ENABLED
        assert node.sdo[0x606C].raw > 150                       # rpm: the shaft turns (20 rad/s = 191 rpm)
        assert modbus.read_holding_registers(20, count=1, device_id=1).registers[0] & 1    # load enabled
        assert modbus.read_holding_registers(18, count=2, device_id=1).registers != [0, 0]  # 0.5 N*m

        bench_proc.send_signal(signal.SIGKILL)
        killed = time.monotonic()
        bench_proc.wait(10)
        reacted = off = None
        while time.monotonic() - killed < CONSUMER_TIME_S + 3.0 and off is None:
            now = time.monotonic() - killed
            state = cia402.decode(node.sdo[0x6041].raw)   # SDO by another master: not the heartbeat it watches
            if reacted is None and state is not cia402.State.OPERATION_ENABLED:
                reacted = now
            if off is None and state not in cia402.POWERED_STATES:
                off = now
            time.sleep(0.02)
        print(f"drive reacted {reacted:.3f} s, power stage off {off:.3f} s after the SIGKILL")
        assert reacted is not None and reacted <= CONSUMER_TIME_S + 0.15, reacted   # its own quick stop
        assert off is not None and off <= CONSUMER_TIME_S + 0.35, off                # stopped, then switched off
        assert abs(node.sdo[0x606C].raw) <= 5                                          # at standstill (rpm)
        # any Modbus request feeds the machine's watchdog (as on real machines): look only once it must have acted
        time.sleep(max(0.0, killed + WATCHDOG_S + 0.5 - time.monotonic()))
        status = modbus.read_holding_registers(20, count=1, device_id=1).registers[0]
        torque = modbus.read_holding_registers(18, count=2, device_id=1).registers
        assert not status & 1 and torque == [0, 0]                                     # disabled, 0.0 N*m
    finally:
        if bench_proc is not None and bench_proc.poll() is None:
            bench_proc.kill()
        with contextlib.suppress(Exception):      # a failed monitor must not leave the served rig running
            if modbus is not None:
                modbus.close()
            monitor.disconnect()
        server.send_signal(signal.SIGINT)
        try:
            server.wait(30)
        except subprocess.TimeoutExpired:
            server.kill()


def test_a_served_drive_without_comm_loss_reaction_is_refused_before_motion(tmp_path):
    """The same rig with the quirk of a drive that watches the bench's heartbeat (EMCY, NMT change) but has no CiA 402
    reaction: SIGKILLing the bench mid-run would leave it running, so the drill refuses the run before the first
    motion. Watched by a second master: the shaft never turned, the drive is left switched off."""
    serve_cfg = tmp_path / "serve.toml"
    serve_cfg.write_text(SERVE.replace('drive = "generic"\n', 'drive = "generic"\ncomm_loss_reaction = false\n'))
    server = serve_sim(serve_cfg)
    monitor = canopen.Network()
    try:
        lines = read_endpoints(server, timeout=120.0)
        can_port = next(l for l in lines if l.startswith("canopen ")).split(":")[2].split("/")[0]
        modbus_port = int(next(l for l in lines if l.startswith("modbus ")).split(":")[2].split()[0])
        bench = tmp_path / "bench.toml"
        bench.write_text(BENCH.format(can_port=can_port, eds=EDS, modbus_port=modbus_port))
        scenario = tmp_path / "killed.toml"
        scenario.write_text(SCENARIO.format(bench=bench))
        monitor.connect(interface="socketcand", channel="can0", host="127.0.0.1", port=int(can_port))
        node = monitor.add_node(1, str(EDS))
        node.sdo.RESPONSE_TIMEOUT = 2.0
        frames: list[tuple[int, bytes]] = []     # a passive listener, as candump: every frame the bench sends
        monitor.subscribe(0x201, lambda cob, data, ts: frames.append((cob, bytes(data))))       # RPDO1
        monitor.subscribe(0x601, lambda cob, data, ts: frames.append((cob, bytes(data))))       # SDO requests
        started = time.monotonic()
        run = subprocess.run([sys.executable, "-m", "bench", "run", str(scenario), "--out", str(tmp_path / "runs"),
                              "--rerun", "off"], cwd=REPO, capture_output=True, text=True, timeout=120)
        assert run.returncode == 2, run.stdout + run.stderr
        text = " ".join((run.stdout + run.stderr).split())
        assert "comm-loss drill failed: the drive noticed the lost heartbeat (EMCY 0x8130" in text, text
        assert 'comm_loss = "external" and external_stop =' in text
        assert time.monotonic() - started < 60
        # never commanded to move: no non-zero target velocity by SDO (0x60FF) or in RPDO1 (controlword, target)
        targets = [d for cob, d in frames if cob == 0x601 and d[0] & 0xE0 == 0x20 and d[1:3] == b"\xFF\x60"]
        assert frames and targets and all(d[4:8] == bytes(4) for d in targets), targets
        assert all(d[2:6] == bytes(4) for cob, d in frames if cob == 0x201 and len(d) >= 6)
        assert abs(node.sdo[0x606C].raw) <= 5                               # rpm: standing still
        assert cia402.decode(node.sdo[0x6041].raw) is cia402.State.SWITCH_ON_DISABLED
    finally:
        with contextlib.suppress(Exception):
            monitor.disconnect()
        server.send_signal(signal.SIGINT)
        try:
            server.wait(30)
        except subprocess.TimeoutExpired:
            server.kill()
