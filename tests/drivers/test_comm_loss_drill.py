"""The bench-death drill and the simulated vendor quirks it exists for (issue 21): before the first motion the bench
proves, on the wire, that the drive leaves OPERATION ENABLED when the bench's heartbeat stops and that the load
machine disables when nobody feeds its watchdog; a drive or dyno that cannot is refused with one line naming the
config line to write; an external stop chain is stated and shown as unverified. Also the other holes: a drive found
running, lockstep on a rig, a TPDO that stops, the statusword's warning bit."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from drivers.contract import cia402
from sim_backend.canopen.generic import DriveSpec
from tests.canopen_helpers import LIVE, generic_link, sync_for

REPO = Path(__file__).resolve().parents[2]
SCENARIO = REPO / "scenarios/rig/speed-step-20rads.toml"
UNITS = {"e35": {}, "technosoft": {"velocity_unit": "rpm"}, "cia402_slave": {"velocity_unit": "rpm"}}
CONSUMER_MS = 300


def spec(**quirks) -> DriveSpec:
    return DriveSpec(velocity_unit="rpm", rated_current_a=3.5355, rated_torque_nm=3.9, **quirks)


def controlwords(rig) -> list[int]:
    return [e.word for _, e in rig.device.faults.events if hasattr(e, "word")]


@pytest.mark.parametrize("eds", list(UNITS))
def test_the_drill_sees_each_vendor_drive_stop_itself_and_the_run_goes_on(eds):
    with generic_link(eds, spec(), consumer_time_ms=CONSUMER_MS, **UNITS[eds]) as (link, rig):
        link.open()
        link.configure(LIVE, [], 1)
        result = link.drill()
        print(f"{eds}: left OPERATION ENABLED {result['left_operation_enabled_ms']} ms after the heartbeat stopped")
        assert result["result"] == "passed", result
        # the drive's timer runs from the bench's last heartbeat, up to one producer period before the withhold
        assert CONSUMER_MS - 75 - 15 <= result["left_operation_enabled_ms"] <= CONSUMER_MS + result["margin_ms"]
        assert result["emcy"] and result["emcy"][0].startswith("0x8130")     # heartbeat error, at once
        assert "0x6007 = 3 (quick stop)" in rig.device.faults.self_stops[-1]
        # re-armed: power stage off, the bench's heartbeat watched again, the run can enable and move
        assert not rig.device.device.power_enabled and not rig.device.master_watchdog.tripped
        link.enable_velocity_mode()
        link.set_speed_ref(5.0)
        samples = sync_for(link, 1.0)
        assert samples[-1].values["speed_est_mech_rad_s"] == pytest.approx(5.0, rel=0.05)
        link.quick_stop()
        link.disable()


@pytest.mark.slow
def test_a_drive_that_notices_but_does_not_stop_fails_the_drill_and_is_left_off():
    """Quirk: 0x1016 watched, EMCY 0x8130 and NMT pre-operational (0x1029), no 0x6007 and no CiA 402 reaction."""
    with generic_link("e35", spec(comm_loss_reaction=False), consumer_time_ms=CONSUMER_MS) as (link, rig):
        link.open()
        link.configure(LIVE, [], 1)
        assert link.report["comm_loss"]["abort_connection_0x6007"].startswith("not on this drive")
        result = link.drill()
        assert result["result"] == "failed" and result["left_operation_enabled_ms"] is None
        assert "noticed the lost heartbeat (EMCY 0x8130" in result["refusal"]
        assert "stayed OPERATION ENABLED" in result["refusal"]
        assert 'comm_loss = "external" and external_stop = ' in result["refusal"]
        assert "no CiA 402 reaction" in rig.device.faults.self_stops[-1]
        assert not rig.device.device.power_enabled          # the bench switched it off itself after the drill


def test_a_drive_found_running_is_braked_to_standstill_before_any_enable():
    """Quirk: enabled and turning at 52 rad/s when the bench connects. Before: disabled at 52 rad/s and enabled again
    1.2 ms later onto the spinning shaft. Now: quick stop, wait for standstill on the drive's speed and the reference
    sensor, and only then the enable sequence."""
    with generic_link("e35", spec(found_running_mech_rad_s=52.0)) as (link, rig):
        assert rig.device.device.state is cia402.State.OPERATION_ENABLED
        assert rig.device.model.load_feedback()[0] == pytest.approx(52.0, rel=0.03)
        shaft_at = []
        write = rig.device.write_controlword

        def watched(word: int) -> None:
            shaft_at.append((word, abs(rig.device.model.load_feedback()[0])))
            write(word)
        rig.device.write_controlword = watched
        link.set_reference_speed(lambda: rig.device.model.load_feedback()[0])
        link.open()
        link.configure(LIVE, [], 1)
        link.enable_velocity_mode()
        words = [w for w, _ in shaft_at]
        assert words[0] == 0x0002                              # quick stop first
        enable_from = words.index(0x0006)
        assert all(speed <= link.standstill_mech_rad_s for _, speed in shaft_at[enable_from:]), shaft_at
        found = link.report["found_running"]
        assert found["speed_mech_rad_s"] == pytest.approx(52.0, rel=0.03) and found["standstill"]
        assert rig.device.device.state is cia402.State.OPERATION_ENABLED
        link.disable()


def test_a_drive_that_cannot_reach_standstill_is_not_enabled():
    with generic_link("e35", spec(found_running_mech_rad_s=52.0), stop_timeout_s=0.05) as (link, rig):
        link.open()
        link.configure(LIVE, [], 1)
        with pytest.raises(Exception, match=r"found running at 5\d\.\d rad/s did not come to standstill within "
                                            r"0.05 s .*not enabling onto a turning shaft"):
            link.enable_velocity_mode()
        assert rig.device.device.state is not cia402.State.OPERATION_ENABLED


def test_the_statusword_warning_bit_reaches_the_bench():
    with generic_link("e35", spec()) as (link, rig):
        link.open()
        link.configure(LIVE, [], 1)
        sync_for(link, 0.05)
        assert link.status().warning is False
        rig.device.device.warning = True
        sync_for(link, 0.05)                                  # the statusword in TPDO1
        assert link.status().warning is True


# -- through the whole bench ---------------------------------------------------------------------------------------

def bench_with(tmp_path: Path, base: str = "sim-generic-e35", simulator: str = "", drive: str = "", load: str = "",
               replace: tuple[str, str] | None = None) -> Path:
    text = (REPO / f"config/benches/{base}.toml").read_text()
    if replace:
        text = text.replace(*replace)
    text = text.replace("[load]\n", f"[load]\n{load}", 1).replace("[simulator]\n", f"[simulator]\n{simulator}", 1)
    text = text.replace("[drive]\n", f"[drive]\n{drive}", 1)
    path = tmp_path / "bench.toml"
    path.write_text(text)
    return path


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bench", *args], capture_output=True, text=True, cwd=REPO,
                          timeout=300)


@pytest.mark.slow
def test_a_run_on_a_drive_without_reaction_is_refused_before_motion(tmp_path):
    bench = bench_with(tmp_path, simulator="comm_loss_reaction = false\n", drive="consumer_time_ms = 300\n",
                       replace=("consumer_time_ms = 2000", "# consumer"))
    out = cli("run", str(SCENARIO), "--bench", str(bench), "--out", str(tmp_path / "runs"), "--rerun", "off", "--json")
    assert out.returncode == 2, out.stderr
    record = json.loads(out.stdout)
    assert record["verdict"] == "error" and record["trips"][0]["reason"] == "comm_loss_drill"
    assert "comm-loss drill failed" in record["abort_reason"] and "external_stop" in record["abort_reason"]
    assert record["comm_loss"]["drive"]["result"] == "failed" and record["comm_loss"]["load"]["result"] == "passed"
    assert record["telemetry"]["rows"] == 0                    # nothing moved: refused before the first motion
    assert "controlword 0x000F" not in json.dumps(record.get("injections_applied", []))


@pytest.mark.slow
def test_an_external_stop_chain_must_be_stated_and_is_shown_unverified(tmp_path):
    bench = bench_with(tmp_path, drive='comm_loss = "external"\n')
    out = cli("validate", str(bench))
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [
        f"{bench}: drive.external_stop: comm_loss = \"external\" needs the rig's stop chain stated, e.g. "
        "external_stop = \"STO relay on watchdog K3\": the bench cannot check it and shows the run as unverified "
        "comm-loss reaction"]
    bench = bench_with(tmp_path, drive='comm_loss = "external"\nexternal_stop = "STO relay on watchdog K3"\n')
    out = cli("run", str(SCENARIO), "--bench", str(bench), "--out", str(tmp_path / "runs"), "--rerun", "off")
    assert out.returncode == 0, out.stdout + out.stderr
    assert "UNVERIFIED COMM-LOSS REACTION: drive: stopped by the rig's own chain (STO relay on watchdog K3)" in (
        " ".join(out.stdout.split()))
    record = json.loads(next((tmp_path / "runs").glob("*/record.json")).read_text())
    assert record["comm_loss"]["verified"] is False and record["comm_loss"]["drive"]["result"] == "unverified"
    assert record["comm_loss"]["load"]["result"] == "passed"          # the load machine is still drilled
    assert record["comm_loss_unverified"].startswith("unverified comm-loss reaction: drive:")


@pytest.mark.slow
def test_a_dyno_without_watchdog_register_is_refused_unless_the_rig_states_its_stop(tmp_path):
    dyno = tmp_path / "no-watchdog.toml"
    text = (REPO / "config/load-machines/drivebench-sim.toml").read_text()
    start = text.index("[registers.watchdog]")
    dyno.write_text(text[:start] + text[text.index("[registers.speed]"):])
    bench = bench_with(tmp_path, replace=('map = "config/load-machines/drivebench-sim.toml"', f'map = "{dyno}"'))
    out = cli("validate", str(SCENARIO), "--bench", str(bench))
    assert out.returncode == 2
    assert f"{bench}: load.map: {dyno}: no communication watchdog register: the machine keeps its torque when the " \
           "bench dies" in out.stderr
    assert 'write [load] comm_loss = "external" and external_stop = ' in out.stderr
    bench = bench_with(tmp_path, replace=('map = "config/load-machines/drivebench-sim.toml"', f'map = "{dyno}"'),
                       load='comm_loss = "external"\nexternal_stop = "dyno drive STO on the E-stop loop"\n')
    out = cli("run", str(SCENARIO), "--bench", str(bench), "--out", str(tmp_path / "runs"), "--rerun", "off",
              "--json")
    assert out.returncode == 0, out.stderr
    record = json.loads(out.stdout)
    assert record["comm_loss"]["load"]["result"] == "unverified"
    assert record["comm_loss"]["drive"]["result"] == "passed"
    assert "load machine: stopped by the rig's own chain" in record["comm_loss_unverified"]


@pytest.mark.slow
def test_lockstep_is_refused_on_a_bench_config_without_services(tmp_path):
    bench = bench_with(tmp_path, replace=('[services]\nstart = "sim_backend.rig:start"\n', ""))
    out = cli("validate", str(bench))
    assert out.returncode == 2
    assert out.stderr.strip() == (f"{bench}: bench.timing: \"lockstep\" is for simulators only (they advance on the "
                                  "bench's SYNC) and this config has no [services]: a real rig runs timing = "
                                  "\"realtime\" (a simulator served elsewhere says so: [bench] served_by = "
                                  "\"drivebench sim serve ...\")")


@pytest.mark.slow
@pytest.mark.parametrize("stops", [2, 0], ids=["one-tpdo", "every-tpdo"])
def test_a_tpdo_that_stops_in_real_time_trips_feedback_lost_and_stops_the_run(tmp_path, stops):
    """Quirk: the drive's TPDO goes silent 1 s into the run (real time). Before: 3 s of NaN rows at 20 rad/s."""
    from bench.run.orchestrator import run_scenario

    bench = bench_with(tmp_path, simulator=f"tpdo_stops_after_s = 1.0\ntpdo_stops = {stops}\n",
                       replace=('timing = "lockstep"', 'timing = "realtime"'))
    result = run_scenario(SCENARIO, bench, out_root=tmp_path / "runs", rerun_mode="off")
    record = result.record
    trip = record["trips"][0]
    assert result.verdict == "aborted" and trip["reason"] == "feedback_lost", record["trips"]
    # the TPDO stops 1 s after the drive went operational (the enable's SDO steps come before the run's t = 0):
    # the trip follows within 5 SYNC periods of it (or 0.5 s of silence, plus a loaded host's scheduling when every
    # TPDO stops), long before the 3 s run would have ended on NaN rows
    assert 0.7 <= trip["t_s"] <= 2.5, trip
    assert record["safe_stop"]["errors"] == [] and record["drive_settings"]["stop"]["standstill"]


def test_warning_events_are_recorded_and_shown(tmp_path):
    from bench.faces.cli import print_record
    from rich.console import Console
    from tests.fakes import FakeRig, run_fake as run

    rig = FakeRig()
    status = rig.drive.status

    def warning_status():
        s = status()
        s.warning = rig.model.time_s >= 0.5
        return s
    rig.drive.status = warning_status
    result = run(tmp_path, rig)
    events = result.record["drive_warnings"]
    assert [e["warning"] for e in events] == [True] and 0.5 <= events[0]["t_s"] <= 0.55
    console = Console(record=True, width=200)
    print_record(console, result.record, tmp_path)
    assert "drive warning (statusword bit 7) set 1 time(s), first at t=0.5" in console.export_text()


def test_a_failed_or_unverified_drill_reaches_the_record_with_fake_links(tmp_path):
    from tests.fakes import FakeRig, run_fake as run

    rig = FakeRig(drill_result="failed")
    result = run(tmp_path, rig)
    assert result.verdict == "error" and result.record["trips"][0]["reason"] == "comm_loss_drill"
    assert "drive.enable_velocity_mode" not in rig.names()               # never enabled for the run
    assert rig.names().index("drive.drill") < rig.names().index("load.zero_and_disable")
    rig = FakeRig(drill_result="unverified")
    (tmp_path / "b").mkdir()
    result = run(tmp_path / "b", rig)
    assert result.verdict == "pass" and result.record["comm_loss"]["verified"] is False
    assert "fake STO relay" in result.record["comm_loss_unverified"]


@pytest.mark.slow
def test_probe_drill_reports_and_refuses(tmp_path):
    bench = bench_with(tmp_path, simulator="comm_loss_reaction = false\n", drive="consumer_time_ms = 300\n",
                       replace=("consumer_time_ms = 2000", "# consumer"))
    out = cli("probe", "--bench", str(bench), "--drill", "--json")
    assert out.returncode == 1, out.stderr
    drill = json.loads(out.stdout)["drill"]
    assert drill["verified"] is False and drill["drive"]["result"] == "failed"
    assert drill["load"]["result"] == "passed" and drill["load"]["disabled_within_ms"] <= 1000 + 100 + 500
    out = cli("probe", "--bench", str(bench_with(tmp_path, drive="consumer_time_ms = 300\n",
                                                 replace=("consumer_time_ms = 2000", "# consumer"))), "--drill")
    assert out.returncode == 0, out.stderr
    assert "comm-loss drill passed: drive left OPERATION ENABLED" in " ".join(out.stdout.split())


def test_the_service_runs_an_unverified_rig_only_when_an_admin_marked_it(tmp_path):
    from drivers.contract.errors import InputError
    from bench.service.rigs import load_rigs

    bench = bench_with(tmp_path, drive='comm_loss = "external"\nexternal_stop = "STO relay on watchdog K3"\n')
    rigs = tmp_path / "rigs.toml"
    rigs.write_text(f'[[rig]]\nname = "lab-a"\nbench = "{bench}"\n')
    with pytest.raises(InputError) as refused:
        load_rigs(rigs)
    assert refused.value.problems == [
        f"{rigs}: rig[0].allow_unverified_comm_loss: its bench config states an external stop chain instead of the "
        "drill (unverified comm-loss reaction: the rig's own stop chain, stated, not proved (drive: STO relay on "
        "watchdog K3)); the service runs it only when an admin sets allow_unverified_comm_loss = true on this rig"]
    rigs.write_text(f'[[rig]]\nname = "lab-a"\nbench = "{bench}"\nallow_unverified_comm_loss = true\n')
    (rig,) = load_rigs(rigs)
    assert rig.comm_loss_unverified.startswith("unverified comm-loss reaction: the rig's own stop chain")


@pytest.mark.slow
def test_probe_checklist_runs_on_a_config_a_lab_writes_first(tmp_path):
    """Only interface, channel, node id (and here the EDS): no velocity unit yet. The probe still runs and says, one
    line per item, what is ok and what to write."""
    bench = tmp_path / "first.toml"
    bench.write_text(f"""[bench]
name = "first look"
[services]
start = "sim"
[drive]
transport = "canopen"
interface = "virtual"
channel = "x"
node_id = 1
eds = "{REPO}/config/od/third-party/technosoft.eds"
[simulator]
motor = "{REPO}/config/motors/pmsm-paper.toml"
drive = "generic"
velocity_unit = "rpm"
""")
    assert cli("validate", str(bench)).returncode == 2              # a run would be refused: no velocity unit
    out = cli("probe", "--bench", str(bench))
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert any(l.startswith("OK      402 device: device type 0x00060192") for l in lines), lines
    assert any(l.startswith("FIX     units: velocity unit unknown") and 'write: velocity_unit = "rpm"' in l
               for l in lines), lines
    assert any(l.startswith("UNKNOWN gear: no gear ratio object (0x6091)") for l in lines), lines
    assert any(l.startswith("OK      bench node id: 127: no node answers there") for l in lines), lines
    report = json.loads(cli("probe", "--bench", str(bench), "--json").stdout)
    assert {i["item"]: i["status"] for i in report["checklist"]}["units"] == "fix"


@pytest.mark.slow
def test_probe_checklist_decodes_a_fault_and_sees_a_node_id_clash():
    from bench.faces.checklist import checklist
    from drivers.canopen.probe import probe
    from sim_backend.rig import RigSpec, build

    eds = REPO / "config/od/third-party/e35.eds"
    with build(RigSpec(motor="toy", eds=eds, node_id=5, drive=spec(comm_loss_reaction=False))) as rig:
        with rig.device.lock:
            rig.device.device.fault(0x2310)
        section = dict(transport="canopen", interface="virtual", channel=rig.channel, node_id=5, eds=str(eds),
                       bench_node_id=5)
        items = {i.item: i for i in checklist(probe(section, REPO), None)}
    assert items["fault state"].status == "fix" and "error code 0x2310 (Current)" in \
        items["fault state"].detail
    assert items["bench node id"].status == "fix" and "bench_node_id = 126" in items["bench node id"].config_line
    assert items["0x6007 abort connection"].status == "fix"               # the quirk's drive has none


def test_the_unit_cross_check_does_not_pass_on_missing_drive_speed():
    """The drive's speed NaN (its TPDO missing) while the shaft turns is no agreement: the check trips within three
    SYNC periods instead of letting the window run out on NaN and counting it as passed (before)."""
    from bench.run.supervisor import UnitCheck

    check = UnitCheck()
    nan = float("nan")
    for k in range(3):                          # first motion: three samples agree...
        assert check.check(k * 0.01, {"speed_est_mech_rad_s": 2.5, "speed_true_mech_rad_s": 2.5}) is None
    trips = [check.check(k * 0.01, {"speed_est_mech_rad_s": nan, "speed_true_mech_rad_s": 20.0})
             for k in range(3, 200)]            # ... then the drive's speed goes missing
    first = next(i for i, t in enumerate(trips) if t is not None)
    assert first <= 2 and trips[first].reason == "feedback_lost" and "missing" in trips[first].message
    assert not check.done                       # never passed


def test_an_operator_stop_during_the_drill_never_enables_the_drive_for_the_run(tmp_path):
    import os
    import signal as signals
    import time

    from tests.fakes import SAFE_STOP, FakeRig, run_fake as run

    rig = FakeRig()
    drill = rig.drive.drill

    def slow_drill(before_withhold=None):
        os.kill(os.getpid(), signals.SIGTERM)     # the operator, while the drive is being drilled
        time.sleep(0.5)
        return drill(before_withhold)
    rig.drive.drill = slow_drill
    result = run(tmp_path, rig)
    assert result.verdict == "aborted" and "SIGTERM" in result.record["abort_reason"]
    assert "drive.enable_velocity_mode" not in rig.names()
    assert [n for n in rig.names() if n in SAFE_STOP] == SAFE_STOP


@pytest.mark.slow
def test_a_passed_drill_holds_for_drill_valid_s_in_one_bench_process_and_says_so(tmp_path):
    """[bench] drill_valid_s: the second run of the same drive and settings in this process reuses the first one's
    proof (the record and the verdict line say when it was drilled); with 0 (a rig's default) every run drills."""
    from bench.faces.cli import print_record, make_console
    from bench.run.orchestrator import run_scenario

    held = bench_with(tmp_path, replace=("drill_valid_s = 3600", "drill_valid_s = 600"))
    first = run_scenario(SCENARIO, held, out_root=tmp_path / "a", rerun_mode="off").record["comm_loss"]
    second = run_scenario(SCENARIO, held, out_root=tmp_path / "b", rerun_mode="off").record["comm_loss"]
    assert "reused" not in first and first["drive"]["result"] == "passed"
    assert second["reused"]["drill_valid_s"] == 600 and second["reused"]["age_s"] < 600
    assert second["drive"] == first["drive"]                                # the proof it rests on, as it was
    console = make_console()
    with console.capture() as out:
        print_record(console, {"verdict": "pass", "scenario": {"name": "x"}, "criteria": [], "comm_loss": second},
                     tmp_path)
    assert "drilled" in out.get() and "s ago in this bench process" in out.get()
    every = tmp_path / "every"
    every.mkdir()
    each = bench_with(every, replace=("drill_valid_s = 3600", "drill_valid_s = 0"))
    records = [run_scenario(SCENARIO, each, out_root=every / f"r{k}", rerun_mode="off").record["comm_loss"]
               for k in range(2)]
    assert all("reused" not in r and r["drive"]["result"] == "passed" for r in records)
