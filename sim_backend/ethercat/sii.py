"""The slave's SII EEPROM image (ETG.1000.6 / ETG.2010): identity words, mailbox words and the categories a master
reads (strings, general, FMMU, SyncManager). Built from an SiiIdentity; words are little-endian."""

from __future__ import annotations

import struct
from dataclasses import dataclass

CAT_STRINGS, CAT_GENERAL, CAT_FMMU, CAT_SM, CAT_END = 10, 30, 40, 41, 0xFFFF
MBX_PROTO_COE = 0x0004
COE_DETAILS = 0x01 | 0x04 | 0x08      # SDO, PDO assign, PDO configuration (no complete access, no SDO info)

MBX_OUT_ADDR, MBX_IN_ADDR, MBX_SIZE = 0x1000, 0x1080, 128       # SM0 master->slave, SM1 slave->master
PD_OUT_ADDR, PD_IN_ADDR = 0x1100, 0x1400                        # SM2 outputs, SM3 inputs
SM_CONTROL = {0: 0x26, 1: 0x22, 2: 0x64, 3: 0x20}              # mailbox write/read; buffered write (+watchdog)/read


@dataclass(frozen=True)
class SiiIdentity:
    vendor_id: int
    product_code: int
    revision: int
    serial: int
    name: str
    order: str = ""
    group: str = "Drives"


def _crc8(data: bytes) -> int:
    """ETG.1000.6: CRC-8 (poly 0x07, init 0xFF) over the first 14 bytes of the ESC configuration area."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def _category(kind: int, data: bytes) -> bytes:
    if len(data) % 2:
        data += b"\x00"
    return struct.pack("<HH", kind, len(data) // 2) + data


def build_sii(ident: SiiIdentity, pd_out_len: int, pd_in_len: int) -> bytes:
    """The whole EEPROM image: 64 words of fixed area, then categories, then 0xFFFF."""
    config = bytearray(14)
    config[0:2] = struct.pack("<H", 0x0C08)          # PDI control: SPI slave, as many drives' ESCs
    head = bytes(config) + struct.pack("<H", _crc8(bytes(config)))
    head += struct.pack("<IIII", ident.vendor_id, ident.product_code, ident.revision, ident.serial)
    head += bytes(8)                                 # 0x10-0x13 reserved
    head += struct.pack("<HHHH", 0, 0, 0, 0)         # 0x14-0x17 bootstrap mailboxes: none
    head += struct.pack("<HHHH", MBX_OUT_ADDR, MBX_SIZE, MBX_IN_ADDR, MBX_SIZE)     # 0x18-0x1B standard mailboxes
    head += struct.pack("<H", MBX_PROTO_COE)         # 0x1C mailbox protocols
    head += bytes((0x3E - 0x1D) * 2)
    head += struct.pack("<HH", 0x0007, 0x0001)       # 0x3E size (8 kbit) - 1 in KiB units, 0x3F version 1
    assert len(head) == 0x80
    strings = [ident.name, ident.group, ident.order or ident.name]
    sdata = bytes([len(strings)]) + b"".join(bytes([len(s)]) + s.encode("ascii") for s in strings)
    general = bytes([2, 0, 3, 1, 0, COE_DETAILS, 0, 0, 0, 1, 0, 0]) + struct.pack("<h", 0) + bytes(18)
    fmmu = bytes([1, 2, 3, 0xFF])                    # outputs, inputs, mailbox status, unused
    sms = b"".join(struct.pack("<HHBBBB", start, length, SM_CONTROL[n], 0, 1, 0) for n, (start, length) in
                   enumerate(((MBX_OUT_ADDR, MBX_SIZE), (MBX_IN_ADDR, MBX_SIZE), (PD_OUT_ADDR, pd_out_len),
                              (PD_IN_ADDR, pd_in_len))))
    body = (_category(CAT_STRINGS, sdata) + _category(CAT_GENERAL, general) + _category(CAT_FMMU, fmmu)
            + _category(CAT_SM, sms) + struct.pack("<H", CAT_END))
    image = head + body
    return image + b"\xff" * (1024 - len(image)) if len(image) < 1024 else image
