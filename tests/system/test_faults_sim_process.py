"""The out-of-process simulator (`drivebench sim serve`) SIGKILLed in the middle of a `drivebench run`: the bench
notices within its link timeouts, still attempts every safe-stop step on every link (each bounded), finishes the
record with the cause and the failed steps, and exits without a traceback."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import pytest

from tests.sim_process import read_endpoints, serve_sim

REPO = Path(__file__).resolve().parents[2]

SERVE = """
[simulator]
motor = "toy"
[simulator.serve]
serial_tcp = "127.0.0.1:0"
modbus_tcp = "127.0.0.1:0"
[drive]
eds = "{eds}"
"""

BENCH = """
[bench]
name = "killed-sim"
timing = "lockstep"
served_by = "drivebench sim serve"     # a served simulator: lockstep allowed
plant_injections = true
fault_reset = "once"

[drive]
transport = "serial"
port = "{serial}"
timeout_s = 0.5
sync_period_s = 0.001
trace_decimation = 1

[load]
transport = "modbus-tcp"
map = "config/load-machines/drivebench-sim.toml"
host = "127.0.0.1"
port = {modbus}
unit_id = 1
timeout_s = 0.5
"""

SCENARIO = """
schema_version = 1
name = "killed-sim"
bench = "{bench}"
duration_s = 60.0

[[speed]]
kind = "ramp"
start_s = 0.0
end_s = 1.0
speed_mech_rad_s = 20.0

[limits]
overspeed_mech_rad_s = 200.0
overcurrent_a = 100.0
"""


@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGSTOP], ids=["killed", "frozen"])
def test_simulator_process_killed_mid_run(tmp_path, how):
    """SIGKILL: the sockets close, the bench sees it at once. SIGSTOP: a hung simulator, only timeouts tell."""
    serve_cfg = tmp_path / "serve.toml"
    serve_cfg.write_text(SERVE.format(eds=REPO / "config/od/drivebench-pmsm.eds"))
    sim = serve_sim(serve_cfg)
    try:
        lines = read_endpoints(sim)
        serial = next(line.split()[1] for line in lines if line.startswith("serial "))
        modbus = int(re.search(r"modbus tcp://127.0.0.1:(\d+)", "\n".join(lines)).group(1))
        bench = tmp_path / "bench.toml"
        bench.write_text(BENCH.format(serial=serial, modbus=modbus))
        scenario = tmp_path / "scenario.toml"
        scenario.write_text(SCENARIO.format(bench=bench))
        out = tmp_path / "runs"
        run = subprocess.Popen([sys.executable, "-m", "bench", "run", str(scenario), "--out", str(out), "--rerun",
                                "off", "--json"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, env={**os.environ, "DRIVEBENCH_DEBUG": ""})
        deadline = time.monotonic() + 90
        while not list(out.glob("*/telemetry.arrows")):         # running: the first block is recorded
            assert run.poll() is None, run.communicate()
            assert time.monotonic() < deadline
            time.sleep(0.05)
        killed_at = datetime.now(timezone.utc)
        sim.send_signal(how)
        stdout, stderr = run.communicate(timeout=120)
    finally:
        if sim.poll() is None:
            sim.kill()                       # SIGKILL also ends a stopped process
        sim.wait(timeout=30)
    assert "Traceback" not in stderr
    assert run.returncode == 2, stderr                          # a dead rig is an error, not a verdict
    record = json.loads(stdout)
    assert record["verdict"] == "error" and record["complete"]
    trip = record["trips"][0]
    assert trip["reason"] in ("drive_link", "load_link"), trip
    detection_s = (datetime.fromisoformat(trip["utc"]) - killed_at).total_seconds()
    print(f"sim process {how.name} -> trip after {detection_s:.3f} s")
    assert 0 <= detection_s < 5.0, detection_s                  # serial: 4 attempts x 0.5 s at most
    stop = record["safe_stop"]
    labels = ("drive quick stop commanded", "load zero torque and disabled", "drive quick stop", "drive disabled")
    assert stop["steps"] == []                                   # nothing could be done...
    assert [e.split(":")[0] for e in stop["errors"]] == [*labels, "last resort"]   # ...every step tried, in order,
    assert "MOTOR STILL TURNING at an unknown speed: use the E-stop" in stop["errors"][-1]   # then said: may turn
    assert "safe stop incomplete" in record["abort_reason"]
    assert record["telemetry"]["rows"] > 0
