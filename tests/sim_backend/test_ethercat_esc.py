"""The simulated EtherCAT slave, frame by frame (no network): the bytes a master sends, the bytes and working counters
that come back, as SOEM's configuration sequence exercises them."""

from __future__ import annotations

import struct

import pytest

from sim_backend.device import SimulatedDevice
from sim_backend.ethercat import frames as f, sii
from sim_backend.ethercat.slave import Quirks, Slave
from sim_backend.rig import make_model

EDS = "config/od/drivebench-pmsm.eds"
STATION = 0x1001


@pytest.fixture
def slave():
    device = SimulatedDevice(make_model("toy", 0))
    s = Slave(device, EDS)
    yield s
    device.stop_watchdogs()


def one(slave, cmd, adp, ado, data=b"", n=None) -> f.Datagram:
    payload = bytearray(data) if n is None else bytearray(n)
    reply = slave.frame(f.build([f.Datagram(cmd, 0x42, adp, ado, payload)]))
    head, (d,) = f.parse(reply)
    assert head[6] & 0x02, "an ESC sets the locally administered bit of the source MAC"
    assert d.idx == 0x42
    return d


def u16(data) -> int:
    return struct.unpack("<H", bytes(data[:2]))[0]


def to_preop(slave) -> None:
    one(slave, f.APWR, 0, 0x0010, struct.pack("<H", STATION))
    sms = struct.pack("<HHBBBB", sii.MBX_OUT_ADDR, sii.MBX_SIZE, 0x26, 0, 1, 0)
    sms += struct.pack("<HHBBBB", sii.MBX_IN_ADDR, sii.MBX_SIZE, 0x22, 0, 1, 0)
    one(slave, f.FPWR, STATION, 0x0800, sms)
    one(slave, f.FPWR, STATION, 0x0120, struct.pack("<H", 0x02))


def sdo(slave, body: bytes) -> bytes:
    message = struct.pack("<HHBB", len(body), 0, 0, 0x13) + body
    assert one(slave, f.FPWR, STATION, sii.MBX_OUT_ADDR, message.ljust(sii.MBX_SIZE, b"\0")).wkc == 1
    status = one(slave, f.FPRD, STATION, 0x080D, n=1).data[0]
    assert status & 0x08, "the answer waits in SM1"
    answer = one(slave, f.FPRD, STATION, sii.MBX_IN_ADDR, n=sii.MBX_SIZE).data
    assert not one(slave, f.FPRD, STATION, 0x080D, n=1).data[0] & 0x08, "reading its last byte empties SM1"
    length = u16(answer)
    return bytes(answer[6:6 + length])


def test_broadcast_and_auto_increment_count_and_address(slave):
    d = one(slave, f.BRD, 0, 0x0000, n=2)
    assert (d.wkc, d.adp, d.data[0]) == (1, 1, 0x11)
    d = one(slave, f.APRD, 0xFFFF, 0x0000, n=2)
    assert (d.wkc, d.adp) == (0, 0), "auto-increment: position -1 is not this slave, the address still counts up"
    one(slave, f.APWR, 0, 0x0010, struct.pack("<H", STATION))
    assert u16(one(slave, f.FPRD, STATION, 0x0010, n=2).data) == STATION
    assert one(slave, f.FPRD, STATION + 1, 0x0010, n=2).wkc == 0
    d = one(slave, f.APRW, 0, 0x0012, struct.pack("<H", 7))
    assert (d.wkc, u16(d.data)) == (3, 0)
    d = one(slave, f.FRMW, STATION, 0x0012, n=2)
    assert (d.wkc, u16(d.data)) == (1, 7)


def test_sii_identity_by_eeprom_interface(slave):
    one(slave, f.APWR, 0, 0x0010, struct.pack("<H", STATION))
    assert u16(one(slave, f.FPRD, STATION, 0x0502, n=2).data) & 0x0040, "reads 8 bytes per command"
    words = {}
    for word in (0x08, 0x0A, 0x0C, 0x18, 0x1C):
        assert one(slave, f.FPWR, STATION, 0x0502, struct.pack("<HHH", 0x0100, word, 0)).wkc == 1
        assert not u16(one(slave, f.FPRD, STATION, 0x0502, n=2).data) & 0x8000
        words[word] = struct.unpack("<I", bytes(one(slave, f.FPRD, STATION, 0x0508, n=4).data))[0]
    assert (words[0x08], words[0x0A], words[0x0C]) == (0x00DB0001, 0x04020001, 0x00010000)
    assert words[0x18] == sii.MBX_OUT_ADDR | sii.MBX_SIZE << 16 and words[0x1C] & 0x04


def test_al_states_refused_with_status_codes(slave):
    one(slave, f.APWR, 0, 0x0010, struct.pack("<H", STATION))
    one(slave, f.FPWR, STATION, 0x0120, struct.pack("<H", 0x02))
    status, _r, code = struct.unpack("<HHH", bytes(one(slave, f.FPRD, STATION, 0x0130, n=6).data))
    assert (status, code) == (0x11, 0x0016), "PRE-OP without mailbox SyncManagers: invalid mailbox configuration"
    to_preop(slave)
    assert u16(one(slave, f.FPRD, STATION, 0x0130, n=2).data) == 0x02
    one(slave, f.FPWR, STATION, 0x0120, struct.pack("<H", 0x08))
    status, _r, code = struct.unpack("<HHH", bytes(one(slave, f.FPRD, STATION, 0x0130, n=6).data))
    assert (status, code) == (0x12, 0x0011), "PRE-OP -> OP is not a transition"
    one(slave, f.FPWR, STATION, 0x0120, struct.pack("<H", 0x04))
    status, _r, code = struct.unpack("<HHH", bytes(one(slave, f.FPRD, STATION, 0x0130, n=6).data))
    assert (status, code) == (0x12, 0x001D), "SAFE-OP without process-data SyncManagers: invalid output configuration"


def test_coe_sdo_upload_download_and_abort(slave):
    to_preop(slave)
    answer = sdo(slave, struct.pack("<HBHB4x", 0x2000, 0x40, 0x6041, 0))
    service, command, index, sub = struct.unpack_from("<HBHB", answer)
    assert (service >> 12, command & 0xE3, index, sub) == (3, 0x43, 0x6041, 0)
    assert 4 - (command >> 2 & 3) == 2 and u16(answer[6:]) & 0x4F == 0x40, "statusword: switch on disabled"
    answer = sdo(slave, struct.pack("<HBHB4x", 0x2000, 0x40, 0x1008, 0))
    assert answer[2] == 0x41 and answer[10:10 + struct.unpack_from("<I", answer, 6)[0]] == b"drivebench simulated PMSM drive"
    answer = sdo(slave, struct.pack("<HBHBh2x", 0x2000, 0x2B, 0x6007, 0, 1))
    assert answer[2] == 0x60 and slave.device.abort_connection_option == 1
    answer = sdo(slave, struct.pack("<HBHB4x", 0x2000, 0x40, 0x5FFF, 0))
    assert answer[2] == 0x80 and struct.unpack_from("<I", answer, 6)[0] == 0x06020000
    assert u16(answer) >> 12 == 2, "an abort is a CoE SDO request, which SOEM tells from a response"
    answer = sdo(slave, struct.pack("<HBHBI", 0x2000, 0x23, 0x1600, 1, 0x60410010))
    assert answer[2] == 0x80 and struct.unpack_from("<I", answer, 6)[0] == 0x06040041, "a read-only object in an RxPDO"


def test_fixed_mapping_refuses_writes():
    device = SimulatedDevice(make_model("toy", 0))
    s = Slave(device, EDS, Quirks(fixed_mapping=True))
    try:
        to_preop(s)
        answer = sdo(s, struct.pack("<HBHBB3x", 0x2000, 0x2F, 0x1C12, 0, 0))
        assert answer[2] == 0x80 and struct.unpack_from("<I", answer, 6)[0] == 0x06010002
    finally:
        device.stop_watchdogs()


def test_process_data_to_op_and_the_sm_watchdog(slave):
    """SM2/SM3 and two FMMUs as SOEM programs them, SAFE-OP, OP, LRW with working counter 3; then silence: the SM
    watchdog (0x0420 x 100 us) takes the slave to SAFE-OP + ERROR 0x001B, and the LRW counts 1 (inputs only)."""
    import time

    to_preop(slave)
    rx, tx = slave.objects.mapping(0x1C12), slave.objects.mapping(0x1C13)
    out_len, in_len = sum(b for *_, b in rx) // 8, sum(b for *_, b in tx) // 8
    sms = struct.pack("<HHBBBB", sii.PD_OUT_ADDR, out_len, 0x64, 0, 1, 0)
    sms += struct.pack("<HHBBBB", sii.PD_IN_ADDR, in_len, 0x20, 0, 1, 0)
    one(slave, f.FPWR, STATION, 0x0810, sms)
    fmmus = struct.pack("<IHBBHBBB3x", 0, out_len, 0, 7, sii.PD_OUT_ADDR, 0, 2, 1)
    fmmus += struct.pack("<IHBBHBBB3x", out_len, in_len, 0, 7, sii.PD_IN_ADDR, 0, 1, 1)
    one(slave, f.FPWR, STATION, 0x0600, fmmus)
    one(slave, f.FPWR, STATION, 0x0420, struct.pack("<H", 500))          # 50 ms
    one(slave, f.FPWR, STATION, 0x0120, struct.pack("<H", 0x04))
    assert u16(one(slave, f.FPRD, STATION, 0x0130, n=2).data) == 0x04
    assert one(slave, f.LRW, 0, 0, n=out_len + in_len).wkc == 1, "SAFE-OP: inputs only"
    one(slave, f.FPWR, STATION, 0x0120, struct.pack("<H", 0x08))
    assert u16(one(slave, f.FPRD, STATION, 0x0130, n=2).data) == 0x08
    image = b""
    for word in (0x06, 0x07, 0x0F):
        image = struct.pack("<HiB", word, 0, 3) + bytes(out_len - 7 + in_len)
        d = one(slave, f.LRW, 0, 0, image)
        assert d.wkc == 3
    d = one(slave, f.LRW, 0, 0, image)
    assert u16(d.data[out_len:]) & 0x6F == 0x27, "statusword in the TxPDO: operation enabled"
    steps = slave.device.step_count
    one(slave, f.LRW, 0, 0, image)
    assert slave.device.step_count - steps == 10, "one 1 ms SM cycle of a 100 us control period per frame"
    time.sleep(0.2)
    status, _r, code = struct.unpack("<HHH", bytes(one(slave, f.FPRD, STATION, 0x0130, n=6).data))
    assert (status, code) == (0x14, 0x001B)
    assert slave.device.device.state.name in ("QUICK_STOP_ACTIVE", "SWITCH_ON_DISABLED"), "0x6007 = 3: quick stop"
    assert one(slave, f.FPRD, STATION, 0x0440, n=2).data[0] & 1 == 0 and one(slave, f.LRW, 0, 0, image).wkc == 1
