"""Safety supervisor end to end: trips recorded (what, when, values), the reaction sequence, operator abort once.

The subprocess tests run the real CLI against the in-process simulator (`sim_backend.rig:start`)
and count what arrived at the simulated drive (controlwords over the CAN bus) and load machine (Modbus writes).
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from bench.run.orchestrator import run_scenario
from bench.run.supervisor import SafeStop
from drivers.api import LoadFeedback
from tests.fakes import SAFE_STOP, FakeRig, write_case

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
from benchmarks.fault_campaign import write_bench, write_scenario  # noqa: E402


def run_fake(tmp_path, rig, **case):
    return run_scenario(write_case(tmp_path, **case), out_root=tmp_path / "runs", rerun_mode="off",
                        links=rig.links())


def test_overspeed_trip_is_recorded_with_time_values_and_the_reaction_sequence(tmp_path):
    rig = FakeRig(overspeed_offset=1000.0)
    result = run_fake(tmp_path, rig)
    rec = result.record
    assert result.verdict == "aborted"
    trip = rec["trips"][0]
    assert trip["reason"] == "overspeed" and trip["t_s"] is not None and trip["t_s"] < 0.1
    assert trip["values"]["speed_true_mech_rad_s"] > trip["values"]["limit"]
    assert trip["utc"] and "overspeed" in rec["abort_reason"]
    assert [c for c in rig.names() if c in SAFE_STOP] == SAFE_STOP      # load first, then quick stop, disable


def test_load_machine_fault_trips(tmp_path):
    rig = FakeRig()
    real = rig.load.feedback

    def faulted() -> LoadFeedback:
        fb = real()
        return LoadFeedback(fb.speed_mech_rad_s, fb.torque_nm, fb.enabled, rig.model.time_s > 0.3)

    rig.load.feedback = faulted
    result = run_fake(tmp_path, rig)
    assert result.verdict == "aborted"
    assert result.record["trips"][0]["reason"] == "load_fault"
    assert 0.3 < result.record["trips"][0]["t_s"] < 0.5       # polled every 0.1 s of drive time


def test_drive_fault_and_emcy_are_in_the_trips(tmp_path):
    result = run_fake(tmp_path, FakeRig(fault_at_s=0.25))
    trip = result.record["trips"][0]
    assert result.verdict == "aborted" and trip["reason"] == "fault" and "0x2310" in trip["message"]


def test_a_hanging_safe_stop_step_is_abandoned_and_the_others_still_run():
    rig = FakeRig()
    never = threading.Event()

    def hangs():
        rig.calls.append(("load.zero_and_disable", ()))
        never.wait()

    rig.load.zero_and_disable = hangs
    stop = SafeStop(rig.drive, rig.load, step_timeout_s=0.3)
    started = time.monotonic()
    errors = stop.run()
    assert time.monotonic() - started < 5.0
    assert rig.names() == SAFE_STOP
    assert len(errors) == 1 and errors[0].startswith("load zero torque and disabled: no answer within 0.3 s")
    assert stop.steps == ["drive quick stop commanded", "drive quick stop", "drive disabled"]
    never.set()


CHILD = """
import contextlib, json, sys
import bench.run.orchestrator as orchestrator
import sim_backend.rig as rig_module
from bench.faces.cli import main
from sim_backend import faults

built = []
real_build = rig_module.build

@contextlib.contextmanager
def build(spec, device=None):          # keep the rig the CLI builds, to ask its device afterwards
    with real_build(spec, device) as rig:
        built.append(rig)
        yield rig

rig_module.build = build

real_make_links = orchestrator.make_links

def make_links(cfg, base):
    drive, load = real_make_links(cfg, base)
    first_step = load.zero_and_disable
    def gated():
        print("SAFE-STOP-BEGIN", file=sys.stderr, flush=True)
        sys.stdin.readline()          # the test sends more signals now, then lets the stop go on
        first_step()
    load.zero_and_disable = gated
    return drive, load

orchestrator.make_links = make_links
code = main(sys.argv[1:])
device = built[-1].device
print("DEVICE " + json.dumps({"counts": dict(device.faults.counts), "safe": faults.safe_state(device)}),
      file=sys.stderr, flush=True)
sys.exit(code)
"""


def _start_child(tmp_path: Path, duration: float = 30.0) -> tuple[subprocess.Popen, Path]:
    bench = write_bench(tmp_path, "canopen", sync_period_s=0.002)
    scenario = write_scenario(tmp_path, bench, "operator-abort", [], duration_s=duration)
    out = tmp_path / "runs"
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, "run", str(scenario), "--out", str(out), "--rerun", "off", "--json"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO), "DRIVEBENCH_DEBUG": ""})
    return child, out


def _wait_running(child: subprocess.Popen, out: Path, timeout: float = 90.0) -> None:
    deadline = time.monotonic() + timeout
    while not list(out.glob("*/telemetry.arrows")):      # the first telemetry block: the drive is running
        assert child.poll() is None, child.communicate()[1]
        assert time.monotonic() < deadline, "the run never started"
        time.sleep(0.05)


def _wait_line(stream, needle: str, timeout: float = 60.0) -> list[str]:
    lines: list[str] = []

    def read():
        for line in stream:
            lines.append(line)
            if needle in line:
                return

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    reader.join(timeout)
    assert lines and needle in lines[-1], lines
    return lines


@pytest.mark.slow
@pytest.mark.parametrize("signals", [(signal.SIGINT, signal.SIGINT), (signal.SIGTERM, signal.SIGINT, signal.SIGTERM)])
def test_operator_abort_twice_runs_the_reaction_sequence_once(tmp_path, signals):
    child, out = _start_child(tmp_path)
    try:
        _wait_running(child, out)
        child.send_signal(signals[0])
        _wait_line(child.stderr, "SAFE-STOP-BEGIN")
        for sig in signals[1:]:                 # pressed again while the safe stop is running
            child.send_signal(sig)
        child.stdin.write("go\n")
        child.stdin.flush()
        stdout, stderr = child.communicate(timeout=90)
    finally:
        if child.poll() is None:
            child.kill()
    assert child.returncode == 1, stderr
    assert "Traceback" not in stderr
    record = json.loads(stdout)
    first = "Ctrl-C" if signals[0] == signal.SIGINT else "SIGTERM"
    assert record["verdict"] == "aborted" and first in record["abort_reason"]
    assert record["trips"][0]["reason"] == "operator"
    assert record["signals_ignored_while_stopping"] == len(signals) - 1
    assert record["safe_stop"]["errors"] == []
    device = json.loads(stderr.split("DEVICE ", 1)[1])
    counts = device["counts"]
    # on the wire, once each: load setpoint 0 and load disabled (Modbus), quick stop and disable voltage (RPDO)
    assert counts["load mode=None value=0.0 enabled=None"] == 1
    assert counts["load mode=None value=None enabled=False"] == 1
    assert counts["controlword 0x0002"] == 1
    assert counts["controlword 0x0000"] == 1
    assert device["safe"]["power_stage_on"] is False and device["safe"]["load_enabled"] is False


def unit_check_run(k: float, noise=None, nan_at=(), period_s=0.01, ramp_s=0.5, target=20.0, check=None, samples=200):
    """The drive's own speed follows a ramp to `target`; the reference sensor sees k times it (a unit error of k).
    Returns (trip, the reference speed when it tripped, the check)."""
    from bench.run.supervisor import UnitCheck

    check = check or UnitCheck()
    for n in range(1, samples):
        t = n * period_s
        est = target * min(1.0, t / ramp_s)
        true = k * est
        if noise is not None:
            est += noise[n]
        if n in nan_at:
            est = float("nan")
        trip = check.check(t, {"speed_est_mech_rad_s": est, "speed_true_mech_rad_s": true})
        if trip is not None:
            return trip, true, check
    return None, None, check


def angle_trip_s(k: float, hold_s: float = 0.03) -> float:
    """When the angle test must have tripped for the ramp below: the drive travels 20 t^2 rad, the shaft 20 k t^2,
    apart by more than 5 % of the larger + 0.1 rad from t = sqrt(0.1 / (20 |k - 1| - 0.05 x 20 max(k, 1)))."""
    return math.sqrt(0.1 / (20 * abs(k - 1) - 0.05 * 20 * max(k, 1.0))) + hold_s


@pytest.mark.parametrize("k, by_s", [(10.0, 0.02), (0.1, 0.03), (1.5, angle_trip_s(1.5)),
                                     (1 / 1.5, angle_trip_s(1 / 1.5)), (1.1, angle_trip_s(1.1)),
                                     (1 / 1.1, angle_trip_s(1 / 1.1))])
def test_the_unit_check_sees_a_factor_of_1_1_to_10_either_way(k, by_s):
    """A ramp to 20 rad/s in 0.5 s (40 rad/s^2 commanded; 400 rad/s^2 on the shaft for k = 10), one sample per 10 ms:
    a factor of 10 either way by the gross test within two samples of first motion, with the shaft still below
    10 rad/s; 1.5 and 1.1 by the angle test (1.1: after ~0.35 s, the shaft at ~15 rad/s)."""
    trip, true, _ = unit_check_run(k)
    assert trip is not None and trip.reason == "unit_mismatch"
    assert "velocity_side" in trip.message
    assert by_s - 0.05 < trip.t_s <= by_s + 1e-9
    if k == 10.0:
        assert abs(true) < 10.0


def test_the_unit_check_passes_a_sensorless_estimate_within_its_noise():
    import numpy as np

    noise = np.random.default_rng(3).normal(0.0, 0.15, 200)       # sigma 0.15 rad/s, peaks ~0.5 rad/s
    trip, _, check = unit_check_run(1.0, noise=noise)
    assert trip is None and check.done and check.summary()["state"] == "agreed"
    assert check.judged >= 99 and check.worst_excess < 1.0
    trip, _, _ = unit_check_run(1.04, noise=noise)                 # a 4 % gain error is not a unit error
    assert trip is None


def test_a_missing_speed_never_counts_as_agreement():
    trip, _, check = unit_check_run(1.0, nan_at=range(10, 200))     # the drive's speed stops arriving
    assert trip is not None and trip.reason == "feedback_lost" and "missing" in trip.message
    assert check.missing == 3
    # a NaN between two disagreeing samples does not reset the count: 1.5x trips as soon as without the NaN
    plain, _, _ = unit_check_run(1.5)
    with_nan, _, _ = unit_check_run(1.5, nan_at={round(plain.t_s / 0.01) - 1})
    assert with_nan is not None and with_nan.t_s <= plain.t_s


def test_a_slow_first_motion_is_judged_until_the_shaft_has_travelled_far_enough():
    """A ramp to 20 rad/s in 2 s, with a real-time skew allowance of 20 ms: a 1.1 factor shows only after ~1.4 s; the
    check runs past its 1 s until the reference has travelled 20 rad, and trips."""
    from bench.run.supervisor import UnitCheck

    trip, _, check = unit_check_run(1.1, ramp_s=2.0, check=UnitCheck(skew_s=0.02), samples=400)
    assert trip is not None and trip.reason == "unit_mismatch" and 1.2 < trip.t_s < 1.8
    trip, _, check = unit_check_run(1.0, ramp_s=2.0, check=UnitCheck(skew_s=0.02), samples=400)
    assert trip is None and check.done and abs(check._angle_true) >= 20.0
