"""Faults injected in the simulator from scenarios, through the real bench path (in-process CANopen + Modbus, and
the serial protocol): each is detected within its stated time, the run ends with the simulated drive's power
stage off and the load machine disabled at zero torque, no sample before the fault is lost, and the record
names the cause."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from drivers.contract.errors import InputError
from bench.inputs.scenario import load_scenario
from drivers.contract import parameters
from drivers.contract.parameters import ParamKind
from sim_backend.faults import FaultState

FAULT_INJECTIONS = parameters.names_for("pmsm", ParamKind.DEVICE_FAULT, ParamKind.WIRE_FAULT)

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
from benchmarks.fault_campaign import lost_before, run_on_rig, run_one, write_bench, write_scenario  # noqa: E402

# kind, transport, value, trip reason in the record, words of the abort reason, detection bound (wall s; the
# docs/safety.md figures with a margin for a loaded 2-core machine)
CASES = [
    ("overcurrent", "canopen", 1.0, "fault", "EMCY 0x2310", 1.0),
    ("stop_heartbeat", "canopen", 1.0, "drive_link", "no heartbeat", 4.0),
    ("bus_error", "canopen", 1.0, "drive_link", "error passive", 1.0),
    ("kill_load", "canopen", 2.0, "load_link", "load machine", 3.0),
    ("load_machine", "canopen", 1.0, "load_fault", "load machine reports a fault", 1.0),
    ("freeze_estimator", "canopen", 1.0, "position_error", "position error", 2.0),
    ("kill_drive", "serial", 1.0, "drive_link", "serial drive", 3.0),
    ("corrupt_frames", "serial", 0.9, "drive_link", "CRC error", 3.0),
    ("overcurrent", "serial", 1.0, "fault", "overcurrent", 1.0),
]


@pytest.mark.slow
@pytest.mark.parametrize("kind, transport, value, reason, words, bound", CASES,
                         ids=[f"{c[0]}-{c[1]}" for c in CASES])
def test_injected_fault_detected_stopped_safely_and_recorded(tmp_path, kind, transport, value, reason, words, bound):
    # a lost heartbeat is judged on the wall clock; lockstep drive time may run faster: give it a long scenario
    duration = 10.0 if kind == "stop_heartbeat" else 1.2
    o = run_one(tmp_path, kind, transport, value, t_fault=0.6, seed=11, out_root=tmp_path / "runs",
                duration_s=duration)
    assert o.verdict in ("aborted", "error"), o.reason
    assert o.safe, o.safe_state                                  # power stage off, load disabled
    assert o.safe_state["load_setpoint"] == 0.0 or not o.safe_state["load_enabled"]
    assert o.lost_samples == 0
    # the first trip may be a symptom (a faulted drive loses its angle: position error); the cause is listed too
    assert reason in [trip["reason"] for trip in o.trips], o.trips
    assert words in o.reason
    assert o.detection_s is not None and o.detection_s < bound, o.detection_s
    assert o.rows > 0


def test_lost_sample_count_sees_gaps_and_a_missing_tail():
    period = 1e-4
    t = np.arange(1, 5001) * period                              # 0.5 s of trace
    assert lost_before(t, 0.5, period, 1e-3) == 0
    assert lost_before(np.delete(t, np.s_[100:110]), 0.5, period, 1e-3) > 0
    tail = 0.5 + np.arange(1, 201) * 1e-3                        # live rows after the last upload
    assert lost_before(np.concatenate([t, tail]), 0.7, period, 1e-3, tail_from_s=tail[0]) == 0
    assert lost_before(np.concatenate([t, np.delete(tail, [50])]), 0.7, period, 1e-3, tail_from_s=tail[0]) == 1
    assert lost_before(t, 0.7, period, 1e-3) == 200              # the tail is missing


def test_frame_fates_come_from_the_seed():
    def fates(seed):
        f = FaultState(seed=seed, drop_rate=0.3, corrupt_rate=0.2)
        return [f.frame_fate() for _ in range(200)]

    assert fates(5) == fates(5)
    assert fates(5) != fates(6)
    counts = {k: fates(5).count(k) for k in ("drop", "corrupt", "send")}
    assert 30 < counts["drop"] < 90 and 10 < counts["corrupt"] < 60


def test_fault_names_are_one_list_for_eds_serial_and_scenarios():
    import canopen

    od = canopen.import_od(str(REPO / "config/od/drivebench-pmsm.eds"), 1)
    for name in FAULT_INJECTIONS:
        assert name in parameters.names_for("pmsm") and name in parameters.names_for("spim")
        assert od[name].writable and 0x2480 <= od[name].index < 0x2500


def _scenario(tmp_path, plant: bool, name: str, value: float, wire: bool = True) -> Path:
    bench = write_bench(tmp_path, "canopen")
    if not plant:
        bench.write_text(bench.read_text().replace("plant_injections = true", "plant_injections = false"))
    if not wire:
        bench.write_text(bench.read_text().replace("wire_faults = true", "wire_faults = false"))
    return write_scenario(tmp_path, bench, "s", [(0.5, name, value)])


@pytest.mark.parametrize("name", FAULT_INJECTIONS)
def test_fault_injections_need_the_capability_their_kind_names(tmp_path, name):
    """Device faults need a bench that may change its plant; wire faults a rig with the fault wrappers. The bench
    declares both; validate refuses what the bench cannot honour, so validate and run agree."""
    value = 2.0 if name == "fault_kill_endpoint" else 1.0
    load_scenario(_scenario(tmp_path, True, name, value))
    wire = parameters.lookup(name).kind is ParamKind.WIRE_FAULT
    with pytest.raises(InputError) as err:
        load_scenario(_scenario(tmp_path, wire, name, value, wire=not wire))
    (line,) = err.value.problems
    if wire:
        assert "wire fault" in line and "wire_faults = false" in line
    else:
        assert "simulator-only" in line and "plant_injections = false" in line


@pytest.mark.parametrize("name, value", [("fault_drop_frames_rate", 1.5), ("fault_corrupt_frames_rate", -0.1),
                                         ("fault_delay_frames_s", -1.0), ("fault_kill_endpoint", 4.0),
                                         ("fault_stop_heartbeat", 0.5)])
def test_fault_values_are_checked(tmp_path, name, value):
    with pytest.raises(InputError) as err:
        load_scenario(_scenario(tmp_path, True, name, value))
    (line,) = err.value.problems
    assert name in line and "injection" in line


@pytest.mark.slow
def test_modbus_exception_mid_run_aborts_safely_with_the_exception_in_the_record(tmp_path):
    """The load machine refuses a setpoint beyond its rating (exception 3, illegal data value) at t = 0.6 s."""
    from bench.outputs.run_files import load_run
    from sim_backend import faults

    bench = write_bench(tmp_path, "canopen")
    scenario = write_scenario(tmp_path, bench, "modbus-exception", [], duration_s=1.2)
    scenario.write_text(scenario.read_text().replace('start_s = 0.2\ntorque_nm = 1.0',
                                                     'start_s = 0.2\nend_s = 0.6\ntorque_nm = 1.0\n\n'
                                                     '[[load]]\nkind = "torque"\nstart_s = 0.6\ntorque_nm = 500.0'))
    result, rig = run_on_rig(scenario, tmp_path / "runs")
    assert faults.is_safe(rig.device), faults.safe_state(rig.device)
    rec = result.record
    assert result.verdict == "error" and "Modbus exception 3 (illegal data value)" in rec["abort_reason"]
    assert rec["trips"][0]["reason"] == "load_link" and abs(rec["trips"][0]["t_s"] - 0.6) < 0.01
    assert rec["safe_stop"]["errors"] == []          # the load link itself still works: zero torque, disabled
    _, columns, _ = load_run(result.run_dir)
    assert lost_before(columns["t_s"], 0.6, 1e-4, 1e-3) == 0


def test_can_bus_state_and_error_frames_are_judged():
    import can

    from drivers.canopen.bus import BusErrorCounter as _BusErrorCounter

    class Bus:
        state = can.BusState.ACTIVE

    counter, bus = _BusErrorCounter(), Bus()
    assert counter.problem(bus) is None
    bus.state = can.BusState.PASSIVE
    assert "error passive" in counter.problem(bus)
    bus.state = can.BusState.ERROR
    assert "bus off" in counter.problem(bus)
    bus.state = can.BusState.ACTIVE
    good = can.Message(arbitration_id=0x181, data=bytes(8))
    error = can.Message(is_error_frame=True)
    for _ in range(15):                     # a few errors among good frames: a healthy bus recovers
        counter.on_message_received(error)
        for _ in range(8):
            counter.on_message_received(good)
    assert counter.problem(bus) is None
    for _ in range(16):                     # a burst: receive error count reaches 128 -> error passive
        counter.on_message_received(error)
    assert "error passive" in counter.problem(bus)


def test_wire_faults_are_refused_before_the_run_by_a_bench_without_the_wrappers(tmp_path):
    """A bench whose rig has no frame wrappers (wire_faults = false) refuses a wire fault at validation, so
    `validate` and `run` agree and no run directory is made."""
    from bench.run.orchestrator import run_scenario

    bench = write_bench(tmp_path, "canopen")
    bench.write_text(bench.read_text().replace("wire_faults = true", "wire_faults = false"))
    scenario = write_scenario(tmp_path, bench, "unwrapped", [(0.3, "fault_drop_frames_rate", 0.5)], duration_s=1.0)
    with pytest.raises(InputError) as err:
        run_scenario(scenario, out_root=tmp_path / "runs", rerun_mode="off")
    (line,) = err.value.problems
    assert line.startswith(f"{scenario}: injection[0].name: ") and "wire_faults = false" in line
    assert not (tmp_path / "runs").exists()


def test_a_simulated_drive_without_wrappers_refuses_a_wire_fault_it_is_sent_anyway(tmp_path):
    """The device side of the same rule: a wire fault written to a rig built without wrappers is refused (SDO
    abort), never silently ignored."""
    import canopen

    from sim_backend.rig import RigSpec, build

    with build(RigSpec(motor="toy", eds=REPO / "config/od/drivebench-pmsm.eds")) as rig:
        network = canopen.Network()
        network.connect(interface="virtual", channel=rig.channel, receive_own_messages=False)
        try:
            node = network.add_node(1, str(REPO / "config/od/drivebench-pmsm.eds"))
            with pytest.raises(canopen.SdoAbortedError) as err:
                node.sdo["fault_drop_frames_rate"].raw = 0.5
            assert err.value.code == 0x06090030
            node.sdo["fault_load_machine"].raw = 1.0          # a device fault needs no wrappers
            assert rig.device.load.fault != 0
        finally:
            network.disconnect()
