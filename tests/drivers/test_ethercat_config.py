"""The EtherCAT transport as a registered plugin and its bad input, through the CLI: one line, exit 2."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from drivers.contract.errors import ContentError
from drivers.ethercat.esi import match, read_esi
from drivers.transports import DRIVE_TRANSPORTS

ROOT = Path(__file__).resolve().parents[2]


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bench", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)


def bench(tmp_path: Path, drive: str) -> Path:
    path = tmp_path / "rig.toml"
    path.write_text(f'[bench]\nname = "lab"\ntiming = "realtime"\n\n[drive]\n{drive}\n')
    return path


def test_registered_by_entry_point():
    assert {"canopen", "serial", "ethercat"} <= set(DRIVE_TRANSPORTS)
    assert DRIVE_TRANSPORTS["ethercat"].link == "drivers.ethercat.link:EthercatDriveLink"
    source = (ROOT / "drivers/transports.py").read_text()
    assert not any(name in source for name in ('"canopen"', '"serial"', '"ethercat"', '"modbus', "drivers.canopen",
                                               "drivers.serial", "drivers.ethercat", "drivers.modbus"))


def test_unregistered_transport_one_line(tmp_path):
    done = cli("probe", "--bench", str(bench(tmp_path, 'transport = "profinet"')))
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert lines == [f"{tmp_path / 'rig.toml'}: drive.transport: must be one of 'canopen', 'ethercat', 'serial', "
                     f"got 'profinet'"]


def test_wrong_interface_one_line(tmp_path):
    done = cli("probe", "--bench", str(bench(tmp_path, 'transport = "ethercat"\ninterface = "nosuchif0"')))
    assert done.returncode == 2 and "Traceback" not in done.stderr
    (line,) = done.stderr.strip().splitlines()
    assert "no network interface 'nosuchif0'" in line and "set [drive] interface" in line


def test_esi_read_and_matched(tmp_path):
    (device,) = read_esi(ROOT / "config/esi/drivebench-pmsm.xml")
    assert (device.vendor_id, device.product_code, device.revision, device.profile) == (0xDB0001, 0x4020001,
                                                                                        0x10000, 402)
    assert match([device], 0xDB0001, 0x4020001, 0x10000) is device
    assert match([device], 0xDB0001, 0x4020001, 0x10001) is None
    bad = tmp_path / "bad.xml"
    bad.write_text("<EtherCATInfo><Vendor><Id>#xZZ</Id></Vendor></EtherCATInfo>")
    with pytest.raises(ContentError, match="Vendor/Id: '#xZZ' is not a number"):
        read_esi(bad)
