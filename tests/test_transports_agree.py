"""One scenario, one bench code path, three ways to the simulated drive: in-process virtual CAN, socketcand
to `drivebench sim serve` in another process, and the serial protocol over a pty (Modbus TCP load machine
each time). The verdicts agree and the telemetry is equal bit for bit: every value the scenario sends is
exact in each protocol's encoding (INTEGER32 mrad/s and REAL32 on CANopen, float64 on serial)."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import numpy as np
import pytest

from bench.run.orchestrator import run_scenario
from bench.outputs.run_files import load_run
from tests.test_sim_serve import _endpoints as read_endpoints, _serve as start_sim_serve

REPO = Path(__file__).resolve().parents[1]
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


def _bench(tmp: Path, name: str, services: str, drive: str, load: str, simulator: str = "") -> Path:
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


def _serve_pmsm(tmp: Path) -> tuple[subprocess.Popen, dict[str, str]]:
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
    proc = start_sim_serve(config)
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


def test_virtual_can_socketcand_and_serial_pty_agree(tmp_path):
    benches = {
        "virtual-can": _bench(tmp_path, "virtual-can", '[services]\nstart = "sim_backend.rig:start"\n',
                              f'transport = "canopen"\ninterface = "virtual"\nchannel = "x"\nnode_id = 1\n'
                              f'eds = "{EDS}"\nsdo_timeout_s = 5.0\n', "port = 0"),
        "serial-pty": _bench(tmp_path, "serial-pty",
                             '[services]\nstart = "sim_backend.rig:start"\n',
                             'transport = "serial"\nport = "/dev/null"\ntimeout_s = 5.0\n', "port = 0",
                             'serial_line = "pty"\n'),
    }
    proc, endpoints = _serve_pmsm(tmp_path)
    try:
        benches["socketcand"] = _bench(          # a served simulator: lockstep only where the config says so
            tmp_path, "socketcand", 'served_by = "drivebench sim serve"\n',
            f'transport = "canopen"\ninterface = "socketcand"\nchannel = "can0@127.0.0.1:{endpoints["socketcand"]}"\n'
            f'node_id = 1\neds = "{EDS}"\nsdo_timeout_s = 5.0\n', f'port = {endpoints["modbus"]}')
        results = {}
        for name, bench in benches.items():
            scenario = tmp_path / f"scenario-{name}.toml"
            scenario.write_text(SCENARIO.format(bench=bench, seed=SEED))
            results[name] = run_scenario(scenario, out_root=tmp_path / "runs", rerun_mode="off")
    finally:
        proc.terminate()
        proc.wait(timeout=30)

    for name, result in results.items():
        assert result.verdict == "pass", (name, result.record.get("abort_reason"), result.error, [(c["name"], c["value"]) for c in result.record["criteria"]])
    verdicts = {name: [(c["name"], c["passed"]) for c in r.record["criteria"]] for name, r in results.items()}
    assert verdicts["socketcand"] == verdicts["virtual-can"] == verdicts["serial-pty"]

    data = {name: load_run(r.run_dir)[1] for name, r in results.items()}
    reference = data["virtual-can"]
    in_run = reference["t_s"] <= 1.5
    assert in_run.sum() >= 1400 and np.nanmax(np.abs(reference["torque_load_nm"][in_run])) == pytest.approx(1.0)
    for name in ("socketcand", "serial-pty"):
        other = data[name]
        assert np.array_equal(other["t_s"][in_run], reference["t_s"][in_run]), name
        for signal in results["virtual-can"].record["trace_signals"]:
            assert np.array_equal(other[signal][in_run], reference[signal][in_run], equal_nan=True), (name, signal)
