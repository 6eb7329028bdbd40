"""The simulator out of process (`python -m sim_backend.serve`, what `drivebench sim serve` runs): start it, read its
endpoints, and the paper-PMSM bench configs and scenario the transports-agree and Ray campaign tests run through it."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def serve_sim(config: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "sim_backend.serve", "--config", str(config)], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})


def read_endpoints(proc: subprocess.Popen, timeout: float = 60.0) -> list[str]:
    lines: list[str] = []

    def read():
        for line in proc.stdout:
            lines.append(line.strip())
            if line.startswith("ready"):
                return

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    reader.join(timeout)
    assert lines and lines[-1].startswith("ready"), f"no 'ready' line: {lines} {proc.poll()}"
    return lines


SEED = 7

SCENARIO = """
schema_version = 1
name = "transports-agree"
bench = "{bench}"
duration_s = 1.5
seed = {seed}

[[speed]]
kind = "step"
at_s = 0.0
speed_mech_rad_s = 20.0

[[load]]
kind = "torque"
start_s = 0.5
torque_nm = 1.0

[[injection]]
at_s = 1.0
name = "plant_rs"
value = 0.75

[limits]
overspeed_mech_rad_s = 60.0
overcurrent_a = 10.0

[[criteria]]
name = "speed estimate tracks"
kind = "speed_error_max_pct"
signal = "speed_est_mech_rad_s"
window_s = [0.8, 1.5]
limit = 10.0

[[criteria]]
name = "i_sx held at zero"
kind = "peak_abs"
signal = "i_sx_a"
window_s = [0.3, 1.5]
limit = 0.1
"""

COMMON_DRIVE = """sync_period_s = 0.01
heartbeat_timeout_s = 5.0
trace_decimation = 10
"""
MOTOR = REPO / "config/motors/pmsm-paper.toml"
EDS = REPO / "config/od/drivebench-pmsm.eds"


def sim_bench(tmp: Path, name: str, services: str, drive: str, load: str, simulator: str = "") -> Path:
    path = tmp / f"{name}.toml"
    path.write_text(f"""[bench]
name = "{name}"
timing = "lockstep"
plant_injections = true
{services}
[drive]
{drive}{COMMON_DRIVE}
[load]
transport = "modbus-tcp"
map = "config/load-machines/drivebench-sim.toml"
host = "127.0.0.1"
unit_id = 1
timeout_s = 5.0
{load}
[simulator]
motor = "{MOTOR}"
{simulator}""")
    return path


def serve_pmsm(tmp: Path) -> tuple[subprocess.Popen, dict[str, str]]:
    config = tmp / "serve.toml"
    config.write_text(f"""[simulator]
motor = "{MOTOR}"
seed = {SEED}
[simulator.serve]
canopen_socketcand = "127.0.0.1:0"
modbus_tcp = "127.0.0.1:0"
[drive]
node_id = 1
eds = "{EDS}"
""")
    proc = serve_sim(config)
    try:
        lines = read_endpoints(proc, timeout=120.0)
    except BaseException:
        proc.kill()
        raise
    endpoints = {}
    for line in lines:
        if m := re.fullmatch(r"canopen socketcand://127\.0\.0\.1:(\d+)/can0 node=1", line):
            endpoints["socketcand"] = m.group(1)
        if m := re.fullmatch(r"modbus tcp://127\.0\.0\.1:(\d+) unit=1", line):
            endpoints["modbus"] = m.group(1)
    return proc, endpoints
