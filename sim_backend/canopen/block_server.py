"""canopen's SDO server plus SDO block upload (CiA 301 7.2.4.3.9-15), which it does not implement, and the local node
that uses it."""

from __future__ import annotations

import binascii
import struct

import numpy as np
from canopen.node import LocalNode
from canopen.sdo import SdoAbortedError, SdoServer

from drivers.contract import objects as o
from sim_backend.canopen.virtual_bus import send_frames


class BlockSdoServer(SdoServer):
    """canopen's SdoServer plus SDO block upload (CiA 301 7.2.4.3.9-15), which it does not implement."""

    def __init__(self, rx_cobid, tx_cobid, node):
        super().__init__(rx_cobid, tx_cobid, node)
        self._blk: dict | None = None
        self.on_upload_complete = lambda index, subindex: None

    def block_upload(self, data):
        cs = data[0] & o.BLOCK_SUBCOMMAND_MASK
        if cs == o.BLOCK_UPLOAD_INITIATE & o.BLOCK_SUBCOMMAND_MASK:
            _, index, subindex, blksize = struct.unpack_from("<BHBB", data)
            self._index, self._subindex = index, subindex
            if not 0 < blksize < 128:
                raise SdoAbortedError(o.ABORT_BLOCK_SIZE)
            payload = bytes(self._node.get_data(index, subindex, check_readable=True))
            if not payload:
                raise SdoAbortedError(o.ABORT_NO_DATA)
            crc = bool(data[0] & o.BLOCK_CRC_SUPPORTED)
            self._blk = {"data": payload, "pos": 0, "sent_from": 0, "blksize": blksize, "crc": crc,
                         "ended": False}
            response = struct.pack("<BHBL", o.BLOCK_RESPONSE_INITIATE | (o.BLOCK_CRC_SUPPORTED if crc else 0) | o.BLOCK_SIZE_INDICATED, index, subindex, len(payload))
            self.send_response(response)
        elif self._blk is None:
            raise SdoAbortedError(o.ABORT_COMMAND)
        elif cs == o.BLOCK_UPLOAD_START & o.BLOCK_SUBCOMMAND_MASK:
            self._send_block()
        elif cs == o.BLOCK_UPLOAD_ACK & o.BLOCK_SUBCOMMAND_MASK:
            ackseq, blksize = data[1], data[2]
            blk = self._blk
            blk["pos"] = min(blk["sent_from"] + 7 * ackseq, len(blk["data"]))
            if 0 < blksize < 128:
                blk["blksize"] = blksize
            if blk["pos"] >= len(blk["data"]):
                n_unused = (7 - len(blk["data"]) % 7) % 7
                crc = binascii.crc_hqx(blk["data"], 0) if blk["crc"] else 0
                blk["ended"] = True
                self.send_response(struct.pack("<BH5x", o.BLOCK_RESPONSE_END | (n_unused << 2), crc))
            else:
                self._send_block()
        elif cs == o.BLOCK_UPLOAD_END & o.BLOCK_SUBCOMMAND_MASK:
            done = self._blk["ended"]
            self._blk = None
            if done:
                self.on_upload_complete(self._index, self._subindex)

    def _send_block(self) -> None:
        blk = self._blk
        data, pos = blk["data"], blk["pos"]
        blk["sent_from"] = pos
        n = min(blk["blksize"], -(-(len(data) - pos) // 7))
        body = np.zeros(7 * n, dtype=np.uint8)
        chunk = np.frombuffer(data, dtype=np.uint8, count=min(7 * n, len(data) - pos), offset=pos)
        body[:len(chunk)] = chunk
        segments = np.empty((n, 8), dtype=np.uint8)
        segments[:, 1:] = body.reshape(n, 7)
        segments[:, 0] = np.arange(1, n + 1)
        if pos + 7 * n >= len(data):
            segments[-1, 0] |= o.BLOCK_LAST_SEGMENT                   # last segment of the transfer
        raw = segments.tobytes()
        cob = self.tx_cobid
        send_frames(self.network, [(cob, raw[k:k + 8]) for k in range(0, 8 * n, 8)])

    def segmented_upload(self, command):
        super().segmented_upload(command)
        if not self._buffer:
            self.on_upload_complete(self._index, self._subindex)

    def request_aborted(self, data):
        self._blk = None
        super().request_aborted(data)


class DriveLocalNode(LocalNode):
    def __init__(self, node_id, od):
        super().__init__(node_id, od)
        self.sdo = BlockSdoServer(o.SDO_RX + node_id, o.SDO_TX + node_id, self)
        self.after_write = lambda index, subindex: None

    def set_data(self, index, subindex, data, check_writable=False):
        super().set_data(index, subindex, data, check_writable)
        self.after_write(index, subindex)
