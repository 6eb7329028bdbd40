"""The real-drive path against a generic CiA 402 drive built from each third-party EDS (config/od/third-party): units
read from the drive or stated, never assumed; remappable and fixed PDO mappings; the drive's own settings restored;
its reaction to a dead bench; the read-only probe and the node scan."""

from __future__ import annotations

import math
import time
from pathlib import Path

import can
import pytest

from drivers.contract.errors import LinkError
from drivers.api import LinkSettings
from drivers.contract import objects as o
from drivers.canopen.probe import probe, scan
from sim_backend.canopen.generic import DriveSpec
from sim_backend.rig import RigSpec, build
from tests.canopen_helpers import LIVE, eds_path, generic_link, sync_for

REPO = Path(__file__).resolve().parents[2]

# eds, what the simulated drive uses, what the bench config must state (the EDS has no 0x60A9 / 0x608F / 0x6091)
DRIVES = {
    ("e35", "rpm"): (DriveSpec(velocity_unit="rpm", rated_current_a=3.5355, rated_torque_nm=3.9), {}),
    ("e35", "inc/s"): (DriveSpec(velocity_unit="inc/s", encoder_increments_per_rev=4096, rated_current_a=3.5355,
                                 rated_torque_nm=3.9), {}),
    ("technosoft", "rpm"): (DriveSpec(velocity_unit="rpm"), {"velocity_unit": "rpm"}),
    ("technosoft", "inc/s"): (DriveSpec(velocity_unit="inc/s", encoder_increments_per_rev=4096),
                              {"velocity_unit": "inc/s", "encoder_increments_per_rev": 4096, "gear_ratio": [1, 1]}),
    ("cia402_slave", "rpm"): (DriveSpec(velocity_unit="rpm"), {"velocity_unit": "rpm"}),
    ("cia402_slave", "inc/s"): (DriveSpec(velocity_unit="inc/s", encoder_increments_per_rev=4096),
                                {"velocity_unit": "inc/s", "gear_ratio": [1, 1]}),
}


@pytest.mark.parametrize("fixed", [False, True], ids=["remap", "fixed"])
@pytest.mark.parametrize("eds, unit", list(DRIVES))
def test_a_commanded_20_rad_s_reaches_the_shaft_within_1_percent(eds, unit, fixed):
    spec, stated = DRIVES[(eds, unit)]
    spec = DriveSpec(**{**spec.__dict__, "fixed_pdo_mapping": fixed})
    with generic_link(eds, spec, **stated) as (link, rig):
        identity = link.open()
        assert not identity.has_trace_recorder and link.profile.kind == "cia402"
        assert link.profile.velocity.unit.name == {"rpm": "rev/min", "inc/s": "inc/s"}[unit]
        link.configure(LIVE, [], 1)
        assert link.plan.policy == ("device" if fixed else "remap")
        assert "speed_est_mech_rad_s" in link.measured_signals()
        link.enable_velocity_mode()
        link.set_speed_ref(20.0)
        samples = sync_for(link, 3.0)
        true_speed = rig.device.model.load_feedback()[0]
        assert true_speed == pytest.approx(20.0, rel=0.01)
        assert samples[-1].values["speed_est_mech_rad_s"] == pytest.approx(20.0, rel=0.01)
        assert samples[-1].t_s == pytest.approx(3.0)          # SYNCs x period: no drive clock on these drives
        link.quick_stop()
        link.disable()
        assert link.report["stop"]["standstill"] and not rig.device.device.power_enabled


def test_the_drive_s_own_pdo_settings_are_restored_and_no_pdo_is_left_invalid():
    """e35 TPDOs are valid by default: after a remapped run every PDO parameter reads back as before; on a fixed
    mapping the refused remap leaves no PDO invalidated and only the communication parameters are touched."""
    for fixed in (False, True):
        spec = DriveSpec(velocity_unit="rpm", rated_current_a=3.5, rated_torque_nm=3.9, fixed_pdo_mapping=fixed)
        with generic_link("e35", spec) as (link, rig):
            link.open()
            link.configure(LIVE, [], 1)
            snap = link._snapshot
            assert snap is not None
            during = {k: rig.node.node.get_data(*k) for k in snap.values}
            if fixed:
                assert "pdo_remap_refused" in link.report
                for n in range(4):                 # mappings untouched, every used TPDO valid
                    assert during[(o.TPDO_MAP + n, 0)] == snap.values[(o.TPDO_MAP + n, 0)]
                for tpdo in link.plan.tpdos:
                    assert not int.from_bytes(during[(o.TPDO_COMM + tpdo.number - 1, 1)], "little") & o.COB_ID_INVALID
            else:
                assert during != snap.values       # the bench's mapping is in place
            link.enable_velocity_mode()
            sync_for(link, 0.2)
            link.quick_stop()
            link.disable()
            link.close()
            after = {k: rig.node.node.get_data(*k) for k in snap.values}
            assert after == snap.values


def test_units_the_drive_reports_and_the_config_states_must_agree():
    spec = DriveSpec(velocity_unit="inc/s", encoder_increments_per_rev=4096, rated_current_a=3.5, rated_torque_nm=3.9)
    with generic_link("e35", spec, velocity_unit="rpm") as (link, rig):
        with pytest.raises(LinkError, match=r"the drive reports inc/s \(0x60A9 = 0x00B50300\), the bench config "
                                            r"states rev/min"):
            link.open()
        assert not rig.device.device.power_enabled


def test_no_enable_while_the_velocity_unit_is_unknown():
    with generic_link("technosoft", DriveSpec(velocity_unit="rpm")) as (link, rig):
        with pytest.raises(LinkError, match="velocity unit unknown: the drive has no SI unit velocity"):
            link.open()
        assert rig.device.device.state.name == "SWITCH_ON_DISABLED"


def test_fault_reset_policy_is_honoured_on_a_third_party_drive():
    spec = DriveSpec(velocity_unit="rpm", rated_current_a=3.5, rated_torque_nm=3.9)
    with generic_link("e35", spec, settings=LinkSettings(fault_reset="never")) as (link, rig):
        link.open()
        link.configure(LIVE, [], 1)
        with rig.device.lock:
            rig.device.device.fault(0x2310)
        with pytest.raises(LinkError, match=r"drive is in FAULT \(error code 0x2310\) and the fault-reset policy "
                                            r"is 'never'"):
            link.enable_velocity_mode()
        assert rig.device.device.state.name == "FAULT"
        link.fault_reset_policy = "once"
        link.enable_velocity_mode()
        assert rig.device.device.state.name == "OPERATION_ENABLED"


def test_a_drive_found_running_is_disabled_before_the_run_enables_it():
    spec = DriveSpec(velocity_unit="rpm")
    with generic_link("cia402_slave", spec, velocity_unit="rpm") as (link, rig):
        link.open()
        link.configure(LIVE, [], 1)
        for word in (0x06, 0x07, 0x0F):                     # someone left it running
            rig.device.write_controlword(word)
        rig.device.target_speed_mech_rad_s = 10.0
        link.enable_velocity_mode()
        words = [str(e) for _, e in rig.device.faults.events if str(e).startswith("controlword")]
        assert words[-4:] == ["controlword 0x0000", "controlword 0x0006", "controlword 0x0007", "controlword 0x000F"]
        assert rig.device.target_speed_mech_rad_s == 0.0   # the new run starts from a zero target


def test_the_drive_stops_itself_when_the_bench_goes_silent():
    """What the bench armed (0x1016 = its node id and consumer time, 0x6007 = quick stop): the bench's heartbeat
    stops as if the bench process died, and the drive brakes to standstill and switches off on its own."""
    spec = DriveSpec(velocity_unit="rpm", rated_current_a=3.5, rated_torque_nm=3.9)
    with generic_link("e35", spec, consumer_time_ms=300) as (link, rig):
        link.open()
        link.configure(LIVE, [], 1)
        report = link.report["comm_loss"]
        assert report["consumer_heartbeat_0x1016"] == "sub 1 = 0x007F012C (300 ms)"
        assert report["abort_connection_0x6007"] == "3 (quick stop)"
        link.enable_velocity_mode()
        link.set_speed_ref(20.0)
        sync_for(link, 1.0)
        time.sleep(0.2)                                      # a few heartbeats
        link._guard._task.stop()                             # the bench dies: no heartbeat, no SYNC, nothing
        silent = time.monotonic()
        while rig.device.device.power_enabled:
            assert time.monotonic() - silent < 0.3 + 1.0, rig.device.device.state
            time.sleep(0.01)
        assert time.monotonic() - silent >= 0.3 - 0.075 - 0.02   # not before: last heartbeat + consumer time
        # braked from 20 rad/s, then switched off: the drive judges standstill by its sensorless estimate, which near
        # zero speed is off by up to ~2.5 rad/s on this motor (the estimators' low-speed limit, docs/firmware-pmsm.md)
        assert abs(rig.device.model.load_feedback()[0]) < 5.0
        assert "0x6007 = 3 (quick stop)" in rig.device.faults.self_stops[-1]


def test_a_drive_that_cannot_stop_itself_is_refused_unless_the_rig_says_it_stops_it():
    spec = DriveSpec(velocity_unit="rpm", rated_current_a=3.5, rated_torque_nm=3.9, comm_loss_objects=False)
    with generic_link("e35", spec) as (link, rig):
        link.open()
        with pytest.raises(LinkError, match=r"no consumer heartbeat \(0x1016\): it cannot stop itself"):
            link.configure(LIVE, [], 1)
    with generic_link("e35", spec, comm_loss="external") as (link, rig):
        link.open()
        link.configure(LIVE, [], 1)
        assert link.report["comm_loss"]["mode"] == "external"


@pytest.mark.slow
def test_probe_is_read_only_and_says_what_to_fix():
    with build(RigSpec(motor="toy", eds=eds_path("technosoft"), node_id=5, drive=DriveSpec(velocity_unit="rpm"))) \
            as rig:
        sniffer = can.Bus(interface="virtual", channel=rig.channel, receive_own_messages=False)
        try:
            section = dict(transport="canopen", interface="virtual", channel=rig.channel, node_id=5,
                           eds=str(eds_path("technosoft")))
            report = probe(section, REPO)
            requests = []
            while (msg := sniffer.recv(0)) is not None:
                if msg.arbitration_id == o.SDO_RX + 5:
                    requests.append(msg.data[0] & 0xE0)
        finally:
            sniffer.shutdown()
        assert requests and set(requests) == {0x40}          # SDO upload requests only: nothing written
        assert report["device_type"]["cia402"] and report["identity"]["device_name"] == "iPOS"
        assert report["units"]["velocity_0x60A9"] == "not on this drive"
        assert "velocity unit unknown" in report["profile"]["error"]
        assert [t["valid"] for t in report["tpdos"]] == [True, True, False, False]
        assert "0x606C:00 Velocity actual value (32 bit)" in report["tpdos"][3]["objects"]


def test_scan_finds_the_nodes_on_the_bus():
    with build(RigSpec(motor="toy", eds=eds_path("cia402_slave"), node_id=3, drive=DriveSpec(velocity_unit="rpm"))) \
            as rig:
        found = scan(dict(interface="virtual", channel=rig.channel), range(1, 8))
    assert [n["node_id"] for n in found] == [3] and found[0]["cia402"]


@pytest.mark.slow
@pytest.mark.parametrize("bench", ["sim-generic-e35", "sim-generic-technosoft", "sim-generic-cia402-slave"])
def test_the_rig_scenario_passes_on_each_third_party_drive(tmp_path, bench):
    """Through the whole bench: the drive's velocity unit read (e35, rpm where its EDS says inc/s) or stated
    (technosoft in inc/s with a fixed mapping, cia402_slave in rpm with a fixed mapping), the reference sensor on
    the load machine, fault_reset = "never"; what was read and set is in the record."""
    from bench.run.orchestrator import run_scenario

    result = run_scenario(REPO / "scenarios/rig/speed-step-20rads.toml", REPO / f"config/benches/{bench}.toml",
                          out_root=tmp_path, rerun_mode="off")
    record = result.record
    assert result.verdict == "pass", [(c["name"], c["value"], c.get("detail")) for c in record["criteria"]]
    first = record["criteria"][0]
    assert first["signal"] == "speed_true_mech_rad_s" and first["value"] < 1.0       # 20 rad/s within 1 % on the shaft
    settings = record["drive_settings"]
    assert settings["profile"]["kind"] == "cia402" and settings["comm_loss"]["mode"] == "heartbeat"
    assert settings["pdo"]["policy"] == ("remap" if bench == "sim-generic-e35" else "device")
    assert settings["stop"]["standstill"]
    assert {"speed_est_mech_rad_s", "speed_true_mech_rad_s", "torque_load_nm"} <= set(record["measured_signals"])
    assert record["load_settings"]["watchdog"].startswith("armed")
    assert record["data_source"] == "pdo"


@pytest.mark.slow
@pytest.mark.parametrize("drive_unit, stated_unit", [("inc/s", "rpm"), ("rpm", "inc/s")],
                         ids=["shaft-too-slow", "shaft-too-fast"])
def test_a_wrong_unit_in_the_bench_config_trips_at_first_motion(tmp_path, drive_unit, stated_unit):
    """technosoft has no 0x60A9: the bench config must state the unit. When it states the wrong one the drive's own
    speed, converted through it, disagrees with the reference sensor by a large factor at first motion, and the run
    trips and stops before the shaft goes anywhere dangerous (rpm taken for inc/s would be 13,000 rpm)."""
    from bench.run.orchestrator import run_scenario

    bench = tmp_path / "bench.toml"
    text = (REPO / "config/benches/sim-generic-technosoft.toml").read_text()
    text = text.replace('velocity_unit = "inc/s"          # the EDS', f'velocity_unit = "{stated_unit}"          # the EDS')
    text = text.replace('velocity_unit = "inc/s"\n', f'velocity_unit = "{drive_unit}"\n')     # what the drive uses
    bench.write_text(text)
    result = run_scenario(REPO / "scenarios/rig/speed-step-20rads.toml", bench, out_root=tmp_path / "runs",
                          rerun_mode="off")
    trip = result.record["trips"][0]
    assert result.verdict == "aborted" and trip["reason"] == "unit_mismatch", trip
    assert "check the drive's velocity unit" in result.record["abort_reason"]
    assert trip["t_s"] < 0.1                                  # within a few SYNCs of first motion
    assert result.record["safe_stop"]["errors"] == [] and result.record["drive_settings"]["stop"]["standstill"]


@pytest.mark.slow
def test_validate_says_which_criteria_a_bench_cannot_judge_and_run_agrees(tmp_path):
    """fig11 judges the position error: no third-party drive measures it. validate says so before the run; the run
    ends incomplete with the same criteria not judged (exit 1), never pass."""
    import subprocess
    import sys as _sys

    scenario = REPO / "scenarios/pmsm/fig11-no-load-reversal.toml"
    bench = REPO / "config/benches/sim-generic-e35.toml"
    out = subprocess.run([_sys.executable, "-m", "bench", "validate", str(scenario), "--bench", str(bench)],
                         capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 0, out.stderr
    flagged = [line for line in out.stdout.splitlines() if "not judged on bench" in line]
    assert len(flagged) == 3 and all("pos_err_elec_rad not measured" in line for line in flagged)
    run = subprocess.run([_sys.executable, "-m", "bench", "run", str(scenario), "--bench", str(bench), "--out",
                          str(tmp_path), "--rerun", "off", "--json"], capture_output=True, text=True, cwd=REPO)
    assert run.returncode == 1, run.stderr
    import json as _json
    record = _json.loads(run.stdout)
    assert record["verdict"] == "incomplete"
    assert sorted(c["name"] for c in record["criteria"] if c["status"] == "not_judged") == sorted(
        line.split("(", 1)[1].split(")", 1)[0] for line in flagged)


@pytest.mark.slow
def test_probe_command_reports_and_scans(tmp_path):
    import json as _json
    import subprocess
    import sys as _sys

    out = subprocess.run([_sys.executable, "-m", "bench", "probe", "--bench",
                          str(REPO / "config/benches/sim-generic-technosoft.toml"), "--scan", "--json"],
                         capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 0, out.stderr
    report = _json.loads(out.stdout)
    assert report["drive"]["identity"]["device_name"] == "iPOS"
    assert report["drive"]["profile"]["units_from"]["velocity_unit"].startswith("stated in the bench config")
    assert report["nodes"] == [{"node_id": 1, "device_type": "0x00060192", "cia402": True}]


# -- gear ratio and which shaft the velocity unit counts (issue 21 item 2) -------------------------------------------

GEARED = DriveSpec(velocity_unit="rpm", gear_ratio=(3, 2), velocity_side="motor", rated_current_a=3.5355,
                   rated_torque_nm=3.9)


def test_a_gear_on_the_motor_side_is_refused_until_the_config_says_which_shaft_the_unit_counts():
    """e35 reports 0x6091 = 3:2 and rpm (0x60A9); no object says whose rpm. Nothing enabled, one line naming the
    object and the config line to write."""
    with generic_link("e35", GEARED) as (link, rig):
        with pytest.raises(LinkError) as refused:
            link.open()
        message = str(refused.value)
        assert "\n" not in message and "0x6091" in message and "rev/min" in message
        assert 'velocity_side = "motor"' in message and '"shaft"' in message
        assert rig.device.device.state.name == "SWITCH_ON_DISABLED"


@pytest.mark.parametrize("eds, stated", [("e35", {"velocity_side": "motor"}),
                                         ("technosoft", {"velocity_unit": "rpm", "velocity_side": "motor",
                                                         "gear_ratio": [3, 2]})])
def test_a_gear_on_the_motor_side_runs_the_shaft_at_the_commanded_speed(eds, stated):
    """With the side said (and the gear read from 0x6091, or stated where the EDS has none) 20 rad/s commanded is
    20 rad/s on the dynamometer's encoder (the issue saw 13.33), and the drive's motor rpm reads back as shaft
    speed; the record says where each factor came from."""
    with generic_link(eds, GEARED, **stated) as (link, rig):
        link.open()
        profile = link.report["profile"]
        assert profile["velocity_side"] == "motor" and profile["gear_ratio_motor_shaft"] == [3.0, 2.0]
        assert profile["units_from"]["gear_ratio"] == ("read from the drive (0x6091)" if eds == "e35" else
                                                       "stated in the bench config (the drive has no such object)")
        assert profile["units_from"]["velocity_side"].startswith("motor: stated in the bench config")
        assert profile["rad_s_per_unit"] == pytest.approx(2 * math.pi / 60 * 2 / 3)
        link.configure(LIVE, [], 1)
        link.enable_velocity_mode()
        link.set_speed_ref(20.0)
        samples = sync_for(link, 2.0)
        assert link._target == round(20.0 * 1.5 * 60 / (2 * math.pi))          # motor rpm on the wire: 286
        assert rig.device.model.load_feedback()[0] == pytest.approx(20.0, rel=0.01)
        assert samples[-1].values["speed_est_mech_rad_s"] == pytest.approx(20.0, rel=0.01)
        link.quick_stop()
        link.disable()


@pytest.mark.slow
def test_validate_refuses_a_stated_gear_without_a_side(tmp_path):
    import subprocess
    import sys as _sys

    bench = tmp_path / "bench.toml"
    text = (REPO / "config/benches/sim-generic-cia402-slave.toml").read_text()
    bench.write_text(text.replace('velocity_unit = "rpm"            # the EDS', 'gear_ratio = [3, 2]\n'
                                  'velocity_unit = "rpm"            # the EDS', 1))
    scenario = REPO / "scenarios/rig/speed-step-20rads.toml"
    out = subprocess.run([_sys.executable, "-m", "bench", "validate", str(scenario), "--bench", str(bench)],
                         capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "drive.velocity_side: rev/min with gear_ratio = [3, 2]" in out.stderr


def unit_case(tmp_path, rig, case, scenario=None, on_build=None):
    import sys as _sys

    _sys.path.insert(0, str(REPO))
    from benchmarks import unit_trip

    scenario = unit_trip.step_scenario(tmp_path) if scenario == "step" else unit_trip.SCENARIO
    return unit_trip.run_case(rig, case, tmp_path, scenario, on_build)


@pytest.mark.slow
@pytest.mark.parametrize("rig", ["e35", "technosoft", "cia402-slave"])
def test_a_told_gear_passes_on_each_third_party_drive(tmp_path, rig):
    """The simulated drive counts motor rpm (or increments) behind a 3:2 gear; told so (e35: side only, 0x6091 read;
    the others: gear and side), the rig scenario passes with the shaft at 20 rad/s."""
    row = unit_case(tmp_path, rig, "ok-3:2")
    assert row["verdict"] == "pass", row
    assert row["shaft_error_pct"] < 1.0                     # the dynamometer's encoder at 20 rad/s within 1 %


@pytest.mark.slow
@pytest.mark.parametrize("case", ["1.5", "1.1", "10"])
@pytest.mark.parametrize("rig", ["e35", "technosoft", "cia402-slave"])
def test_a_unit_error_trips_unit_mismatch_before_the_shaft_overspeeds(tmp_path, rig, case):
    """The drive's unit counts the motor behind a gear the bench does not apply (e35: told "shaft" wrongly; the
    others: gear [1, 1] or none stated): the shaft turns 1.5, 1.1 or 10 times faster than commanded. unit_mismatch
    trips, the drive gets its quick stop, and the shaft never reaches the 40 rad/s overspeed limit (a 10x error:
    never 20 rad/s). Measured (lockstep, 10 ms SYNC): 1.5x trip at 0.14 s, 1.1x at 0.39 s, 10x at 0.03 s
    (benchmarks/unit_trip.py)."""
    row = unit_case(tmp_path, rig, case)
    assert row["verdict"] == "aborted" and row["reason"] == "unit_mismatch", row
    trip_by, peak_below = {"1.5": (0.2, 15.0), "1.1": (0.5, 25.0), "10": (0.05, 20.0)}[case]
    assert row["trip_t_s"] <= trip_by and row["peak"] < peak_below < 40.0, row
    assert row["stop_order"] == "drive quick stop/load zero" and row["load_after_qs_steps"] == 0, row


@pytest.mark.slow
def test_the_safe_stop_quick_stops_the_drive_before_the_load_is_zeroed_on_the_wire(tmp_path):
    """A 10x unit error on a step (the issue's case): the drive's quick-stop controlword (SDO download 0x6040 =
    0x0002) is on the CAN bus before the load machine's zero-torque Modbus write reaches it, with no SYNC between
    (the same SYNC period)."""
    sniffers = []

    def sniff(rig):
        sniffers.append(can.Bus(interface="virtual", channel=rig.channel, receive_own_messages=False))

    try:
        row = unit_case(tmp_path, "e35", "10", scenario="step", on_build=sniff)
        frames = []
        while (msg := sniffers[0].recv(0)) is not None:
            frames.append(msg)
    finally:
        for bus in sniffers:
            bus.shutdown()
    assert row["reason"] == "unit_mismatch" and row["peak"] < 60.0, row
    quick_stop = next(m for m in frames if m.arbitration_id == o.SDO_RX + 1
                      and bytes(m.data[:6]) == bytes([0x2B, 0x40, 0x60, 0x00, 0x02, 0x00]))
    assert quick_stop.timestamp < row["load_zero_wall"]
    syncs_between = [m for m in frames if m.arbitration_id == o.SYNC
                     and quick_stop.timestamp < m.timestamp < row["load_zero_wall"]]
    assert syncs_between == []


FREE_SHAFT_SCENARIO = """schema_version = 1
name = "free-shaft-20rads"
description = "20 rad/s on a free shaft, judged on the drive's own speed"
duration_s = 1.5
seed = 1

[[speed]]
kind = "ramp"
start_s = 0.0
end_s = 0.5
speed_mech_rad_s = 20.0

[limits]
overspeed_mech_rad_s = 40.0
overcurrent_a = 8.0

[[criteria]]
name = "the drive reports 20 rad/s"
kind = "steady_state_error"
signal = "speed_est_mech_rad_s"
window_s = [1.0, 1.5]
target = 20.0
percent = true
limit = 1.0
"""


def free_shaft_bench(tmp_path, rig: str, confirmed: str | None = None) -> Path:
    text = (REPO / f"config/benches/sim-generic-{rig}.toml").read_text()
    head, _, rest = text.partition("\n[load]\n")
    rest = rest[rest.index("[simulator]"):]                     # no [load], no [reference]: a free shaft
    if confirmed is not None:
        head = head.replace("sync_period_s =", f'units_confirmed = "{confirmed}"\nsync_period_s =', 1)
    bench = tmp_path / f"{rig}-free.toml"
    bench.write_text(head + rest)
    return bench


@pytest.mark.slow
def test_a_free_shaft_rig_runs_only_on_units_read_from_the_drive_or_confirmed(tmp_path):
    """No reference sensor: nothing can check the drive's units at first motion. technosoft's inc/s, resolution and
    gear are stated (its EDS has no 0x60A9/0x608F/0x6091): refused before anything moves, one line naming
    units_confirmed; with units_confirmed the run goes on and the record says what was confirmed. e35 reports its
    unit and a 1:1 gear: nothing to confirm."""
    from bench.run.orchestrator import run_scenario

    scenario = tmp_path / "free.toml"
    scenario.write_text(FREE_SHAFT_SCENARIO)
    refused = run_scenario(scenario, free_shaft_bench(tmp_path, "technosoft"), out_root=tmp_path / "runs",
                           rerun_mode="off")
    assert refused.verdict == "error"
    assert "drive.units_confirmed: this rig has no reference sensor" in refused.error
    assert "velocity_unit, encoder_increments_per_rev, gear_ratio" in refused.error
    assert refused.record["drive_settings"]["stop"]["standstill"]          # never moved: stopped at once
    confirmed = run_scenario(scenario, free_shaft_bench(tmp_path, "technosoft", "hand tachometer: 191 rpm at 20 rad/s"),
                             out_root=tmp_path / "runs", rerun_mode="off")
    assert confirmed.verdict == "pass", confirmed.record["abort_reason"]
    assert confirmed.record["unit_check"]["units_confirmed"] == "hand tachometer: 191 rpm at 20 rad/s"
    read = run_scenario(scenario, free_shaft_bench(tmp_path, "e35"), out_root=tmp_path / "runs", rerun_mode="off")
    assert read.verdict == "pass", read.record["abort_reason"]
    assert read.record["unit_check"]["velocity_factors_not_read"] == []
