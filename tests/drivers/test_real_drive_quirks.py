"""Issue 32 items 3-10 on the link: simulated e35 drives with the quirks real drives have, each run the way a lab
would (probe, drill, enable), each either running or refused with one line naming the cause in CiA terms."""

from __future__ import annotations

import contextlib
import time
from pathlib import Path

import pytest

from bench.faces import checklist
from bench.run.supervisor import check_status
from drivers.api import LinkSettings
from drivers.canopen.link import CanopenDriveLink
from drivers.canopen.probe import probe
from drivers.contract.errors import LinkError
from sim_backend.canopen.generic import DriveSpec
from sim_backend.rig import RigSpec, build

REPO = Path(__file__).resolve().parents[2]
MOTOR = REPO / "config/motors/pmsm-paper.toml"
E35 = REPO / "config/od/third-party/e35.eds"
LIVE = ["speed_ref_mech_rad_s", "speed_est_mech_rad_s", "i_sy_a", "vdc_v"]
E35_SPEC = dict(velocity_unit="rpm", rated_current_a=3.5355, rated_torque_nm=3.9)


def section(channel: str, **extra) -> dict:
    return dict(transport="canopen", interface="virtual", channel=channel, node_id=1, eds=str(E35),
                sync_period_s=0.01, heartbeat_timeout_s=2.0, sdo_timeout_s=2.0, consumer_time_ms=300) | extra


@contextlib.contextmanager
def e35(**quirks):
    with build(RigSpec(motor=MOTOR, seed=1, eds=E35, drive=DriveSpec(**E35_SPEC, **quirks))) as rig:
        link = CanopenDriveLink(section(rig.channel), REPO, LinkSettings())
        try:
            yield link, rig
        finally:
            link.close()


def run_at(link, speed: float, seconds: float) -> None:
    link.set_speed_ref(speed)
    for _ in range(round(seconds / link.sync_period_s)):
        link.sync()


def test_3_a_mode_shown_late_in_0x6061_is_waited_for():
    with e35(mode_display_delay_s=0.04) as (link, rig):
        rig.device.mode_of_operation = 0                  # powered up with no mode selected
        link.open()
        link.configure(LIVE, [], 1)
        link.enable_velocity_mode()
        assert link.report["mode_display_after_ms"] >= 35.0, link.report
        run_at(link, 10.0, 1.0)
        assert abs(rig.device.model.load_feedback()[0] - 10.0) < 1.0


def test_3_a_mode_never_shown_is_refused_after_the_timeout():
    with e35(mode_display_delay_s=5.0) as (link, rig):
        rig.device.mode_of_operation = 0
        link.open()
        link.configure(LIVE, [], 1)
        with pytest.raises(LinkError, match=r"0x6061 \(mode of operation display\) is still 0 500 ms after 0x6060"):
            link.enable_velocity_mode()


def test_4_a_warning_emcy_while_enabled_is_not_a_trip():
    with e35(warning_emcy_after_s=0.3) as (link, rig):
        link.open()
        link.configure(LIVE, [], 1)
        link.enable_velocity_mode()
        run_at(link, 10.0, 0.6)
        status = link.status()
        assert status.state == "OPERATION ENABLED" and status.warning, status
        assert [code for code, _ in status.emcy] == [0x4310], status.emcy
        assert check_status(0.6, status) is None                        # recorded and shown, not a trip
        assert rig.device.device.power_enabled


def test_6_a_target_refused_by_sdo_outside_operation_enabled_goes_by_rpdo():
    with e35(target_sdo_only_enabled=True) as (link, rig):
        link.open()
        link.configure(LIVE, [], 1)
        link.enable_velocity_mode()
        assert "0x08000022" in link.report["target_zero"] and "RPDO" in link.report["target_zero"], link.report
        run_at(link, 20.0, 1.5)
        assert abs(rig.device.model.load_feedback()[0] - 20.0) < 1.0


def test_7_local_control_from_power_on_is_named_and_the_probe_reports_bit_9():
    with e35(local_control=True) as (link, rig):
        report = probe(section(rig.channel), REPO)
        assert report["remote_bit9"] is False
        item = checklist._remote(report)
        assert item.status == "fix" and "bit 9 (remote) = 0: the drive is in local control" in item.detail
        link.open()
        link.configure(LIVE, [], 1)
        with pytest.raises(LinkError, match=r"statusword bit 9 \(remote\) = 0: the drive is in local control"):
            link.enable_velocity_mode()
        assert not rig.device.device.power_enabled


def test_8_node_guarding_instead_of_heartbeat_is_refused_with_one_line():
    with e35(node_guarding=True) as (link, rig):
        with pytest.raises(LinkError) as exc:
            link.open()
        text = str(exc.value)
        assert "node guarding (0x100C guard time, 0x100D life time factor)" in text
        assert "no heartbeat (0x1016 consumer, 0x1017 producer)" in text and "enable the drive's heartbeat" in text
        assert "0x06020000" not in text


@pytest.mark.slow
def test_10_a_late_comm_loss_reaction_is_reported_as_late_not_as_none():
    with e35(comm_loss_delay_s=2.0) as (link, rig):
        link.open()
        link.configure(LIVE, [], 1)
        result = link.drill()
        assert result["result"] == "failed"
        refusal = result["refusal"]
        assert "reacted after 2." in refusal and "later than the margin" in refusal, refusal
        assert "no CiA 402 reaction" not in refusal and "noticed" not in refusal


def test_10_0x1017_is_written_back_at_close():
    with e35() as (link, rig):
        rig.node.node.sdo[0x1017].raw = 1000                  # the drive's own producer heartbeat time
        link.open()
        assert rig.node.node.sdo[0x1017].raw == 500           # the bench's: a quarter of heartbeat_timeout_s
        link.configure(LIVE, [], 1)
        link.close()
        assert rig.node.node.sdo[0x1017].raw == 1000


def test_10_the_probe_tells_a_csv_only_drive_it_runs_in_csv():
    with e35(csv_only=True) as (link, rig):
        report = probe(section(rig.channel), REPO)
        item = checklist._mode(report)
        assert item.status == "ok" and "runs it in CSV" in item.detail, item
        assert "this bench drives profile velocity" not in item.detail


def test_10_probe_on_a_booting_drive_gives_the_boot_timeout_hint():
    with build(RigSpec(motor=MOTOR, seed=1, eds=E35, drive=DriveSpec(**E35_SPEC, boot_delay_s=5.0))) as rig:
        started = time.monotonic()
        with pytest.raises(LinkError, match="boot_timeout_s = 5"):
            probe(section(rig.channel, sdo_timeout_s=0.2), REPO)
        assert time.monotonic() - started < 3.0


def test_5_the_unit_check_allows_a_stated_velocity_filter_and_skips_stale_reference_samples():
    """The unit check fed as a run feeds it: a drive reporting the shaft through a 100 ms first-order filter trips
    unit_mismatch when nothing says so (the message names lag and the line to write), agrees when velocity_filter_s
    states it, and still catches a 1.1 factor with it stated. A reference reading held over a stall is not judged."""
    import math as m

    from bench.run.supervisor import UnitCheck

    def feed(check, k=1.0, tau=0.1, stall=None):
        dt, est, trip = 0.01, 0.0, None
        for n in range(1, 900):
            t = n * dt
            true = min(t / 0.5, 1.0) * 20.0                        # the rig scenario's ramp to 20 rad/s
            est += (1 - m.exp(-dt / tau)) * (k * true - est) if tau else k * true - est
            values = {"speed_est_mech_rad_s": est, "speed_true_mech_rad_s": true, "reference_age_s": 0.0}
            if stall is not None and stall[0] <= t < stall[1]:
                values.update(speed_true_mech_rad_s=min(stall[0] / 0.5, 1.0) * 20.0, reference_age_s=t - stall[0])
            trip = check.check(t, values)
            if trip is not None:
                return trip
        return None

    unstated = feed(UnitCheck())
    assert unstated is not None and unstated.reason == "unit_mismatch"
    assert "or a lag" in unstated.message and "velocity_filter_s = 0.1" in unstated.message
    assert feed(UnitCheck(lag_s=0.1)) is None
    assert feed(UnitCheck(lag_s=0.05), tau=0.05) is None
    factor = feed(UnitCheck(lag_s=0.1), k=1.1)
    assert factor is not None and factor.reason == "unit_mismatch"
    stale = UnitCheck(stale_s=0.025)
    assert feed(stale, tau=0.0, stall=(0.1, 0.2)) is None and stale.skipped_stale >= 7
    assert feed(UnitCheck(), tau=0.0, stall=(0.1, 0.2)) is not None       # judged on the held reading: false trip


def test_5_a_filtered_0x606c_lags_the_shaft():
    with e35(velocity_filter_s=0.1) as (link, rig):
        link.open()
        link.configure(LIVE, [], 1)
        link.enable_velocity_mode()
        link.set_speed_ref(20.0)
        reported = [s.values["speed_est_mech_rad_s"] for s in (link.sync()[-1] for _ in range(20))]
        shaft = abs(rig.device.model.load_feedback()[0])
        assert shaft - reported[-1] > 2.0, (shaft, reported[-1])


@pytest.mark.parametrize("drop", [True, False], ids=["bus-drop", "healthy"])
def test_9_a_200_ms_bus_drop_with_the_drive_operational_is_named(drop):
    quirks = dict(bus_drop_at_s=0.5, bus_drop_s=0.2) if drop else {}
    with build(RigSpec(motor=MOTOR, seed=1, eds=E35, drive=DriveSpec(**E35_SPEC, **quirks))) as rig:
        link = CanopenDriveLink(section(rig.channel), REPO, LinkSettings(timing="realtime"))
        try:
            link.open()
            link.configure(LIVE, [], 1)
            link.enable_velocity_mode()
            link.set_speed_ref(10.0)
            started = time.monotonic()
            while time.monotonic() - started < 2.0 and link.status().bus_drop is None:
                link.sync()
            status = link.status()
            if drop:
                assert status.bus_drop is not None, link.sync_report()
                assert "the CAN bus dropped for" in status.bus_drop and "still NMT OPERATIONAL" in status.bus_drop
                gap_ms = float(status.bus_drop.split("dropped for ")[1].split(" ms")[0])
                assert 150 <= gap_ms <= 400, status.bus_drop
                trip = check_status(1.0, status)
                assert trip.reason == "bus_drop"
            else:
                assert status.bus_drop is None
            link.quick_stop()
            link.disable()
        finally:
            link.close()
