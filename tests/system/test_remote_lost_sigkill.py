"""Issue 32 item 1 out of process, as a real rig: a served e35 whose statusword bit 9 (remote) drops mid-run and which
then ignores the controlword and keeps its 20 rad/s target. The bench (real time, socketcand) is SIGKILLed right after
the drop: nothing on the bench side runs any more, and the drive must stop itself by its comm-loss reaction to the
silent heartbeat (0x1016 left armed). Watched by a second CANopen master, as a lab would watch with its own tools."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import canopen
import pytest

from drivers.contract import cia402
from tests.sim_process import read_endpoints, serve_sim

REPO = Path(__file__).resolve().parents[2]
EDS = REPO / "config/od/third-party/e35.eds"
CONSUMER_TIME_S = 0.3          # the bench's default consumer heartbeat time

SERVE = f"""[simulator]
motor = "{REPO}/config/motors/pmsm-paper.toml"
drive = "generic"
velocity_unit = "rpm"
rated_current_a = 3.5355
rated_torque_nm = 3.9
remote_drops_after_s = 2.0
[simulator.serve]
canopen_socketcand = "127.0.0.1:0"
modbus_tcp = "127.0.0.1:0"
one_bench = false
[drive]
node_id = 1
eds = "{EDS}"
"""

BENCH = """[bench]
name = "remote lost rig"
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
name = "remote-lost"
bench = "{bench}"
duration_s = 60.0
[[speed]]
kind = "ramp"
start_s = 0.0
end_s = 0.5
speed_mech_rad_s = 20.0
[limits]
overspeed_mech_rad_s = 40.0
overcurrent_a = 8.0
max_duration_s = 120.0
"""


@pytest.mark.slow
def test_sigkilled_after_remote_lost_the_drive_stops_itself(tmp_path):
    serve_cfg = tmp_path / "serve.toml"
    serve_cfg.write_text(SERVE)
    server = serve_sim(serve_cfg)
    monitor = canopen.Network()
    bench_proc = None
    try:
        lines = read_endpoints(server, timeout=120.0)
        can_port = next(l for l in lines if l.startswith("canopen ")).split(":")[2].split("/")[0]
        modbus_port = int(next(l for l in lines if l.startswith("modbus ")).split(":")[2].split()[0])
        bench = tmp_path / "bench.toml"
        bench.write_text(BENCH.format(can_port=can_port, eds=EDS, modbus_port=modbus_port))
        scenario = tmp_path / "remote.toml"
        scenario.write_text(SCENARIO.format(bench=bench))
        out = tmp_path / "runs"
        bench_proc = subprocess.Popen([sys.executable, "-m", "bench", "run", str(scenario), "--out", str(out),
                                       "--rerun", "off"], cwd=REPO, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.PIPE, text=True, env={**os.environ, "DRIVEBENCH_DEBUG": ""})
        deadline = time.monotonic() + 90
        while not list(out.glob("*/telemetry.arrows")):
            assert bench_proc.poll() is None, bench_proc.communicate()[1]
            assert time.monotonic() < deadline, "the run never started"
            time.sleep(0.05)
        monitor.connect(interface="socketcand", channel="can0", host="127.0.0.1", port=int(can_port))
        node = monitor.add_node(1, str(EDS))
        node.sdo.RESPONSE_TIMEOUT = 2.0
        while True:                                   # bit 9 drops 2 s into OPERATION ENABLED
            word = node.sdo[0x6041].raw
            if not word & cia402.StatusBit.REMOTE:
                break
            assert time.monotonic() < deadline, "bit 9 never dropped"
            time.sleep(0.005)
        assert cia402.decode(word) is cia402.State.OPERATION_ENABLED
        assert node.sdo[0x606C].raw > 150                       # rpm: at 20 rad/s (191 rpm)
        bench_proc.send_signal(signal.SIGKILL)
        killed = time.monotonic()
        bench_proc.wait(10)
        off = None
        while time.monotonic() - killed < CONSUMER_TIME_S + 5.0 and off is None:
            if cia402.decode(node.sdo[0x6041].raw) not in cia402.POWERED_STATES:
                off = time.monotonic() - killed
            time.sleep(0.02)
        print(f"power stage off {off} s after the SIGKILL")
        assert off is not None and off <= CONSUMER_TIME_S + 3.0, off      # its own quick stop, then off
        assert abs(node.sdo[0x606C].raw) <= 30                             # rpm: at rest (3 rad/s)
        time.sleep(1.0)
        assert cia402.decode(node.sdo[0x6041].raw) not in cia402.POWERED_STATES   # and stays off
    finally:
        if bench_proc is not None and bench_proc.poll() is None:
            bench_proc.kill()
        with contextlib.suppress(Exception):
            monitor.disconnect()
        server.send_signal(signal.SIGINT)
        try:
            server.wait(30)
        except subprocess.TimeoutExpired:
            server.kill()
