"""EtherCAT frames (ETG.1000.4): the Ethernet header with EtherType 0x88A4, the EtherCAT header and its datagrams.
Used by the simulated slave to answer a master and by tests to speak to it byte by byte."""

from __future__ import annotations

import struct
from dataclasses import dataclass

ETHERTYPE = 0x88A4
ETH_HEADER = struct.Struct("!6s6sH")
DATAGRAM_HEADER = struct.Struct("<BBHHHH")     # cmd, idx, adp, ado, len|flags, irq
MORE = 0x8000
CIRCULATED = 0x4000
LEN_MASK = 0x07FF

NOP, APRD, APWR, APRW, FPRD, FPWR, FPRW, BRD, BWR, BRW, LRD, LWR, LRW, ARMW, FRMW = range(15)
COMMAND_NAMES = ("NOP", "APRD", "APWR", "APRW", "FPRD", "FPWR", "FPRW", "BRD", "BWR", "BRW", "LRD", "LWR", "LRW",
                 "ARMW", "FRMW")


@dataclass
class Datagram:
    cmd: int
    idx: int
    adp: int
    ado: int
    data: bytearray
    wkc: int = 0
    irq: int = 0

    @property
    def logical(self) -> int:
        return self.adp | self.ado << 16


def parse(frame: bytes) -> tuple[bytes, list[Datagram]] | None:
    """(ethernet header, datagrams) of an EtherCAT frame; None for any other frame or a malformed one."""
    if len(frame) < ETH_HEADER.size + 2:
        return None
    if ETH_HEADER.unpack_from(frame)[2] != ETHERTYPE:
        return None
    (head,) = struct.unpack_from("<H", frame, ETH_HEADER.size)
    if head >> 12 != 1:               # type 1: EtherCAT datagrams
        return None
    pos, end = ETH_HEADER.size + 2, ETH_HEADER.size + 2 + (head & LEN_MASK)
    if end > len(frame):
        return None
    datagrams = []
    while pos + DATAGRAM_HEADER.size <= end:
        cmd, idx, adp, ado, lenflags, irq = DATAGRAM_HEADER.unpack_from(frame, pos)
        n = lenflags & LEN_MASK
        start = pos + DATAGRAM_HEADER.size
        if start + n + 2 > end:
            return None
        (wkc,) = struct.unpack_from("<H", frame, start + n)
        datagrams.append(Datagram(cmd, idx, adp, ado, bytearray(frame[start:start + n]), wkc, irq))
        pos = start + n + 2
        if not lenflags & MORE:
            break
    return frame[:ETH_HEADER.size], datagrams


def build(datagrams: list[Datagram], dst: bytes = b"\xff" * 6, src: bytes = b"\x01" * 6) -> bytes:
    body = bytearray()
    for k, d in enumerate(datagrams):
        flags = MORE if k < len(datagrams) - 1 else 0
        body += DATAGRAM_HEADER.pack(d.cmd, d.idx, d.adp, d.ado, len(d.data) | flags, d.irq)
        body += d.data + struct.pack("<H", d.wkc)
    frame = ETH_HEADER.pack(dst, src, ETHERTYPE) + struct.pack("<H", len(body) | 1 << 12) + body
    return frame + bytes(max(0, 60 - len(frame)))


def reply(eth_header: bytes, datagrams: list[Datagram]) -> bytes:
    """The frame as it leaves the slave: the source MAC's locally-administered bit set, as an ESC's port 0 does."""
    dst, src, _ = ETH_HEADER.unpack(eth_header)
    return build(datagrams, dst, bytes([src[0] | 0x02]) + src[1:])
