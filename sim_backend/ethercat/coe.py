"""The mailbox and its CoE SDO server (ETG.1000.6 5.6, ETG.1000.5 CoE): expedited, normal and segmented upload,
expedited and normal download, aborts, over an object store that answers get(index, sub) -> bytes and
set(index, sub, bytes) or raises SdoAbort."""

from __future__ import annotations

import struct
from typing import Callable

MBX_HEADER = struct.Struct("<HHBB")          # length, address, channel/priority, type | counter << 4
MBX_ERR, MBX_COE = 0x00, 0x03
MBX_ERR_UNSUPPORTED_PROTOCOL = 0x0002
COE_SDO_REQUEST, COE_SDO_RESPONSE = 2, 3
ABORT_TOGGLE, ABORT_COMMAND, ABORT_UNSUPPORTED = 0x05030000, 0x05040001, 0x06010000
ABORT_LENGTH, ABORT_STATE = 0x06070010, 0x08000022


class SdoAbort(Exception):
    def __init__(self, code: int):
        super().__init__(f"SDO abort 0x{code:08X}")
        self.code = code


class CoeServer:
    """One SDO server behind the slave's mailbox; `post` sends a mailbox message to the master (SM1)."""

    def __init__(self, get: Callable[[int, int], bytes], set_: Callable[[int, int, bytes], None],
                 post: Callable[[bytes], None], mailbox_size: int):
        self.get, self.set, self.post = get, set_, post
        self.size = mailbox_size
        self.counter = 0
        self._upload: tuple[int, int, bytes, int] | None = None     # index, sub, remaining data, toggle
        self.requests = 0

    def _send(self, mbx_type: int, body: bytes) -> None:
        self.counter = self.counter % 7 + 1
        self.post(MBX_HEADER.pack(len(body), 0, 0, mbx_type | self.counter << 4) + body)

    def _sdo(self, command: int, index: int, sub: int, data: bytes, service: int = COE_SDO_RESPONSE) -> None:
        self._send(MBX_COE, struct.pack("<HBHB", service << 12, command, index, sub) + data)

    def abort(self, index: int, sub: int, code: int) -> None:
        """An abort travels as an SDO *request* (CoE service 2) in either direction (ETG.1000.6 5.6.2.7)."""
        self._upload = None
        self._sdo(0x80, index, sub, struct.pack("<I", code), COE_SDO_REQUEST)

    def received(self, message: bytes) -> None:
        length, _address, _channel, kind = MBX_HEADER.unpack_from(message)
        body = message[MBX_HEADER.size:MBX_HEADER.size + length]
        if kind & 0x0F != MBX_COE:
            self._send(MBX_ERR, struct.pack("<HH", 0x0001, MBX_ERR_UNSUPPORTED_PROTOCOL))
            return
        if len(body) < 2 or struct.unpack_from("<H", body)[0] >> 12 != COE_SDO_REQUEST or len(body) < 6:
            return                               # not an SDO request (no PDO over mailbox, no SDO info): ignored
        self.requests += 1
        command = body[2]
        index, sub = struct.unpack_from("<HB", body, 3)
        try:
            if command & 0xE0 == 0x60 and self._upload is not None:
                self._segment(command)
            elif command & 0xE0 == 0x40:
                self._initiate_upload(command, index, sub)
            elif command & 0xE0 == 0x20:
                self._download(command, index, sub, body[6:])
            elif command & 0xE0 == 0x80:
                self._upload = None
            else:
                raise SdoAbort(ABORT_COMMAND)
        except SdoAbort as exc:
            self.abort(index, sub, exc.code)

    def _initiate_upload(self, command: int, index: int, sub: int) -> None:
        if command & 0x10:
            raise SdoAbort(ABORT_UNSUPPORTED)    # complete access is not offered (SII CoE details)
        data = self.get(index, sub)
        n = len(data)
        if 0 < n <= 4:
            self._sdo(0x43 | (4 - n) << 2, index, sub, data.ljust(4, b"\x00"))
            return
        room = self.size - MBX_HEADER.size - 10
        if n <= room:
            self._sdo(0x41, index, sub, struct.pack("<I", n) + data)
            return
        self._sdo(0x41, index, sub, struct.pack("<I", n) + data[:room])
        self._upload = (index, sub, data[room:], 0x00)

    def _segment(self, command: int) -> None:
        index, sub, rest, toggle = self._upload
        if command & 0x10 != toggle:
            raise SdoAbort(ABORT_TOGGLE)
        room = self.size - MBX_HEADER.size - 3
        chunk, rest = rest[:room], rest[room:]
        last = not rest
        pad = 7 - len(chunk) if len(chunk) < 7 else 0
        flags = toggle | (1 if last else 0) | (pad << 1 if last else 0)
        self._send(MBX_COE, struct.pack("<HB", COE_SDO_RESPONSE << 12, flags) + chunk + bytes(pad))
        self._upload = None if last else (index, sub, rest, toggle ^ 0x10)

    def _download(self, command: int, index: int, sub: int, payload: bytes) -> None:
        if command & 0x10:
            raise SdoAbort(ABORT_UNSUPPORTED)
        if command & 0x02:                       # expedited
            n = 4 - (command >> 2 & 0x03) if command & 0x01 else 4
            data = payload[:n]
        else:
            (n,) = struct.unpack_from("<I", payload)
            data = payload[4:4 + n]
            if len(data) != n:
                raise SdoAbort(ABORT_COMMAND)    # a segmented download: longer than this mailbox takes
        self.set(index, sub, data)
        self._sdo(0x60, index, sub, bytes(4))
