"""Issue 32 items 1-2: a drive that leaves remote control mid-run (statusword bit 9 drops, then it ignores the
controlword and keeps its target), and a drive found running when the drill comes. Checked from the simulator's side:
the drive must end not enabled and the shaft at rest, by its own comm-loss reaction (0x1016 left armed)."""

from __future__ import annotations

import contextlib
import time
from pathlib import Path

import pytest

import sim_backend.rig as sim_rig
from bench.run.orchestrator import run_scenario
from drivers.api import LinkSettings
from drivers.canopen.link import CanopenDriveLink
from drivers.contract import cia402
from drivers.contract import objects as o
from drivers.contract.errors import LinkError
from sim_backend.canopen.generic import DriveSpec
from sim_backend.rig import RigSpec, build

REPO = Path(__file__).resolve().parents[2]
MOTOR = REPO / "config/motors/pmsm-paper.toml"
E35 = REPO / "config/od/third-party/e35.eds"
LIVE = ["speed_ref_mech_rad_s", "speed_est_mech_rad_s", "i_sy_a", "vdc_v"]
E35_SPEC = dict(velocity_unit="rpm", rated_current_a=3.5355, rated_torque_nm=3.9)


@contextlib.contextmanager
def e35_link(spec: DriveSpec, **section):
    with build(RigSpec(motor=MOTOR, seed=1, eds=E35, drive=spec)) as rig:
        fields = dict(transport="canopen", interface="virtual", channel=rig.channel, node_id=1, eds=str(E35),
                      sync_period_s=0.01, heartbeat_timeout_s=2.0, sdo_timeout_s=2.0, consumer_time_ms=300)
        link = CanopenDriveLink(fields | section, REPO, LinkSettings())
        try:
            yield link, rig
        finally:
            link.close()


def test_a_drive_leaving_remote_control_is_a_trip_and_close_leaves_its_comm_loss_reaction_armed(capsys):
    spec = DriveSpec(**E35_SPEC, remote_drops_after_s=0.5)
    with e35_link(spec) as (link, rig):
        link.open()
        link.configure(LIVE, [], 1)
        link.enable_velocity_mode()
        link.set_speed_ref(20.0)
        for _ in range(100):                                 # 1 s: bit 9 drops at 0.5 s of OPERATION ENABLED
            link.sync()
        status = link.status()
        assert status.control_lost and "bit 9 (remote) dropped" in status.control_lost, status
        assert status.state == "OPERATION ENABLED"
        with pytest.raises(LinkError, match="not obeyed"):
            link.begin_quick_stop()                          # at once: no step timeout per step
        assert rig.device.device.state is cia402.State.OPERATION_ENABLED     # it really ignores the controlword
        started = time.monotonic()
        link.close()                                         # the bench's normal close
        took = time.monotonic() - started
        # from the simulator's side: the drive stopped itself, by its 0x6007 reaction to the withheld heartbeat
        assert not rig.device.device.power_enabled, rig.device.device.state
        assert abs(rig.device.model.load_feedback()[0]) < 5.0
        assert any("0x6007 = 3 (quick stop)" in s for s in rig.device.faults.self_stops), rig.device.faults.self_stops
        assert took < 0.3 + 5.0 + 1.0 + 1.0
        last = link.report["last_resort"]
        assert last["outcome"] == "stopped itself", last
        assert last["found_at_close"]["powered"] is True
    err = capsys.readouterr().err
    assert "with the bench's heartbeat withheld it stopped itself" in err


def test_close_never_writes_0x1016_while_the_drive_is_enabled():
    """The bug of the issue: close() wrote 0x1016:01 = 0 before stopping its heartbeat. Watched on the drive's side:
    every write of 0x1016 and the drive's power stage at that moment — the drive's value goes back only once the
    drive has stopped itself (power stage off, shaft at rest)."""
    spec = DriveSpec(**E35_SPEC, remote_drops_after_s=0.3)
    with e35_link(spec) as (link, rig):
        writes: list[tuple[int, int, bytes]] = []
        node = rig.node.node
        device = rig.device
        node.add_write_callback(lambda index, subindex, od, data: writes.append(
            (bytes(data), device.device.power_enabled, abs(device.model.load_feedback()[0])))
            if index == o.CONSUMER_HEARTBEAT else None)
        link.open()
        link.configure(LIVE, [], 1)
        link.enable_velocity_mode()
        link.set_speed_ref(20.0)
        for _ in range(60):
            link.sync()
        assert len(writes) == 1 and writes[0][0] != bytes(4) and writes[0][1] is False     # armed before motion
        assert rig.device.device.power_enabled
        link.close()
        assert not rig.device.device.power_enabled
        restore = writes[1:]
        assert restore and all(data == bytes(4) and not powered and speed < 5.0 for data, powered, speed in restore), \
            restore


def test_a_drive_that_obeys_gets_its_settings_back_at_close():
    with e35_link(DriveSpec(**E35_SPEC)) as (link, rig):
        link.open()
        link.configure(LIVE, [], 1)
        link.enable_velocity_mode()
        link.set_speed_ref(5.0)
        for _ in range(30):
            link.sync()
        link.quick_stop()
        link.disable()
        link.close()
        assert "last_resort" not in link.report
        assert rig.node.node.sdo[o.CONSUMER_HEARTBEAT][1].raw == 0          # the drive's own value back
        assert rig.node.node.sdo[o.PRODUCER_HEARTBEAT].raw == link.report.get(
            "producer_heartbeat_0x1017", {}).get("drive_had_ms", rig.node.node.sdo[o.PRODUCER_HEARTBEAT].raw)


def test_the_drill_is_not_done_at_speed_on_a_drive_found_running():
    """Found OPERATION ENABLED at 52 rad/s: quick-stopped to standstill first, then drilled at zero velocity."""
    spec = DriveSpec(**E35_SPEC, found_running_mech_rad_s=52.0)
    with e35_link(spec) as (link, rig):
        link.open()
        link.configure(LIVE, [], 1)
        assert abs(rig.device.model.load_feedback()[0]) > 40.0
        withheld_at: list[float] = []
        result = link.drill(before_withhold=lambda: withheld_at.append(abs(rig.device.model.load_feedback()[0])))
        assert result["result"] == "passed", result
        assert withheld_at and withheld_at[0] < 2.5, withheld_at        # at rest when the heartbeat stopped
        assert result["found_running"]["standstill"] is True
        assert not rig.device.device.power_enabled


def test_the_last_resort_sends_the_nmt_command_the_config_names():
    """[drive] last_resort_nmt = "stop": where the drive's manual says NMT STOPPED stops its power stage, the bench
    sends it with the heartbeat withheld (watched on the bus); the drive's own reaction still does the stopping."""
    import can

    spec = DriveSpec(**E35_SPEC, remote_drops_after_s=0.3)
    with e35_link(spec, last_resort_nmt="stop") as (link, rig):
        sniffer = can.Bus(interface="virtual", channel=rig.channel, receive_own_messages=False)
        try:
            link.open()
            link.configure(LIVE, [], 1)
            link.enable_velocity_mode()
            link.set_speed_ref(20.0)
            for _ in range(60):
                link.sync()
            while sniffer.recv(0) is not None:
                pass
            link.close()
            nmt = [bytes(m.data) for m in iter(lambda: sniffer.recv(0), None) if m.arbitration_id == 0x000]
        finally:
            sniffer.shutdown()
        assert bytes([0x02, 0x01]) in nmt, nmt                         # NMT stop remote node, node 1
        assert "NMT STOPPED sent" in link.report["last_resort"]["nmt"]
        assert not rig.device.device.power_enabled
