"""Issue 32 item 1 on the serial drive: the same remote-bit watch and last resort as over CANopen — the drive leaves
remote control mid-run, the bench's stop is not obeyed, and close() leaves its WATCHDOG armed and goes silent, so the
drive stops itself. Watched from the simulated drive's side."""

from __future__ import annotations

from pathlib import Path

import pytest

from drivers.api import LinkSettings
from drivers.contract.errors import LinkError
from drivers.serial_link import SerialDriveLink
from sim_backend.device import SimulatedDevice
from sim_backend.serial_server import start_serial_tcp
from sim_backend.toy import ToyDrive

LIVE = ["speed_ref_mech_rad_s", "speed_est_mech_rad_s", "i_sy_a", "torque_load_nm"]


def test_serial_drive_leaving_remote_control_is_stopped_by_its_own_watchdog(capsys):
    device = SimulatedDevice(ToyDrive())
    device.remote_drops_after_s = 0.2
    server = start_serial_tcp(device)
    link = SerialDriveLink({"transport": "serial", "port": server.url, "timeout_s": 2.0, "sync_period_s": 0.001,
                            "consumer_time_ms": 300}, Path("."), LinkSettings())
    try:
        link.open()
        link.configure(LIVE, [], 1)
        link.enable_velocity_mode()
        link.set_speed_ref(20.0)
        for _ in range(400):
            link.sync()
        status = link.status()
        assert status.control_lost and "bit 9 (remote) dropped" in status.control_lost
        with pytest.raises(LinkError, match="not obeyed"):
            link.begin_quick_stop()
        assert device.device.power_enabled and device.master_watchdog.timeout_s > 0
        link.close()
        assert not device.device.power_enabled, device.device.state
        assert device.master_watchdog.trips == 1                     # its own watchdog did it (then switched off)
        assert link.report["last_resort"]["outcome"] == "stopped itself", link.report["last_resort"]
        assert any("0x6007 = 3" in s for s in device.faults.self_stops), device.faults.self_stops
    finally:
        server.stop()
    assert "stopped itself" in capsys.readouterr().err
