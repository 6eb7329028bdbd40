"""ESI files (EtherCAT Slave Information, ETG.2000 XML) read the way EDS files are: the vendor, and each device's
product code, revision and name, to check a slave's SII identity against the file the bench config names."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from drivers.contract.errors import ContentError


@dataclass(frozen=True)
class EsiDevice:
    vendor_id: int
    product_code: int
    revision: int
    name: str
    profile: int | None          # 402 for a CiA 402 drive


def _hex(text: str | None, where: str) -> int:
    """ESI numbers: '#x00DB0001' (hex) or decimal."""
    if text is None:
        raise ContentError(f"{where}: missing")
    text = text.strip()
    try:
        return int(text[2:], 16) if text.lower().startswith("#x") else int(text, 0)
    except ValueError:
        raise ContentError(f"{where}: {text!r} is not a number") from None


def read_esi(path: str | Path) -> list[EsiDevice]:
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise ContentError(f"{path}: not ESI XML: {exc}") from None
    vendor = _hex(root.findtext("Vendor/Id"), f"{path}: Vendor/Id")
    devices = []
    for k, dev in enumerate(root.findall("Descriptions/Devices/Device")):
        typ = dev.find("Type")
        if typ is None:
            raise ContentError(f"{path}: Device {k + 1}: no Type")
        profile = dev.findtext("Profile/ProfileNo")
        devices.append(EsiDevice(vendor, _hex(typ.get("ProductCode"), f"{path}: Device {k + 1}: ProductCode"),
                                 _hex(typ.get("RevisionNo"), f"{path}: Device {k + 1}: RevisionNo"),
                                 (dev.findtext("Name") or typ.text or "").strip(),
                                 int(profile) if profile and profile.strip().isdigit() else None))
    if not devices:
        raise ContentError(f"{path}: no Descriptions/Devices/Device")
    return devices


def match(devices: list[EsiDevice], vendor_id: int, product_code: int, revision: int) -> EsiDevice | None:
    for dev in devices:
        if (dev.vendor_id, dev.product_code, dev.revision) == (vendor_id, product_code, revision):
            return dev
    return None
