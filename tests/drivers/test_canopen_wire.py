"""Bytes on the wire between the bench's CANopen link and the simulated node (CiA 301 / CiA 402)."""

from __future__ import annotations

import struct
import time

import can
import canopen
import numpy as np
import pytest

from drivers.contract.errors import LinkError
from drivers.contract.trace_format import decode_rows, mask_for
from sim_backend.canopen.node import start_node
from sim_backend.device import SimulatedDevice
from sim_backend.rig import private_channel
from sim_backend.toy import ToyDrive
from tests.canopen_helpers import EDS, Sniffer, rig

LIVE = ["speed_ref_mech_rad_s", "speed_est_mech_rad_s"]


def test_sdo_download_frame_for_a_hook_write():
    with rig() as r:
        r.sniffer.frames()
        r.link.write_parameter("flux_est_scale", 0.5)
        frames = [(m.arbitration_id, bytes(m.data)) for m in r.sniffer.frames()]
        # expedited download, 4 bytes: ccs=1 e=1 s=1 n=0 -> 0x23; index 0x2200 little endian; REAL32 0.5
        assert frames == [(0x601, bytes.fromhex("23002200") + struct.pack("<f", 0.5)),
                          (0x581, bytes.fromhex("6000220000000000"))]


def test_sync_and_tpdo_payloads_for_known_values():
    with rig() as r:
        r.link.configure(LIVE, LIVE, 1)
        r.link.enable_velocity_mode()
        r.link.set_speed_ref(12.5)
        r.sniffer.frames()
        r.link.sync()
        frames = [(m.arbitration_id, bytes(m.data)) for m in r.sniffer.frames()]
        assert frames[0] == (0x080, b"")                      # SYNC without counter
        tpdo1 = dict(frames)[0x181]
        statusword, mode, step = struct.unpack("<HbL", tpdo1)
        assert statusword & 0x6F == 0x27 and statusword & 0x0200   # OPERATION ENABLED, remote
        assert (mode, step) == (3, r.device.step_count)
        latest = r.device.latest
        assert dict(frames)[0x281] == struct.pack("<ff", latest[0], latest[1])
        assert struct.unpack("<ff", dict(frames)[0x281])[0] == 12.5


def test_rpdo_carries_controlword_target_velocity_in_mrad_s_and_mode():
    with rig() as r:
        r.link.configure(LIVE, LIVE, 1)
        r.link.enable_velocity_mode()
        r.sniffer.frames()
        r.link.set_speed_ref(-1.2345)
        assert r.sniffer.with_id(0x201) == [struct.pack("<HlB", 0x000F, -1234, 3)]
        r.link.sync()                                         # the node has handled the RPDO by then
        assert r.device.target_speed_mech_rad_s == pytest.approx(-1.234)


def test_heartbeat_frames_carry_the_nmt_state():
    channel = private_channel()
    sniffer = Sniffer(channel)
    node = start_node(SimulatedDevice(ToyDrive()), EDS, 5, interface="virtual", channel=channel)
    try:
        frames = [(m.arbitration_id, bytes(m.data)) for m in sniffer.frames()]
        assert frames[0] == (0x705, b"\x00")                  # boot-up
        assert (0x705, b"\x7f") in frames                     # heartbeat, PRE-OPERATIONAL
        master = canopen.Network(can.Bus(interface="virtual", channel=channel))
        master.NOTIFIER_CYCLE = 0.1
        master.connect()
        master.send_message(0x000, bytes([0x01, 5]))          # NMT start node 5
        node.node.nmt.update_heartbeat()
        msg = None
        for _ in range(200):
            msg = sniffer.bus.recv(1.0)
            if msg.arbitration_id == 0x705 and msg.data[0] == 0x05:
                break
        assert msg is not None and bytes(msg.data) == b"\x05"   # OPERATIONAL
        master.disconnect()
    finally:
        node.stop()
        sniffer.close()


def test_emcy_frame_has_error_code_register_and_drive_clock():
    with rig() as r:
        r.link.configure(LIVE, LIVE, 1)
        r.link.enable_velocity_mode()
        r.link.sync()
        r.toy.raise_fault(0x2310)
        r.sniffer.frames()
        r.link.sync()
        emcy = r.sniffer.with_id(0x081)
        # code 0x2310 LE, error register generic|current, manufacturer field = drive step count
        assert emcy == [bytes.fromhex("1023 03") + struct.pack("<L", r.device.step_count) + b"\x00"]
        r.toy.reset_fault()
        r.link.fault_reset()
        assert r.sniffer.with_id(0x081)[-1] == bytes(8)       # EMCY "error reset / no error"


def test_unknown_index_is_answered_with_sdo_abort_06020000():
    with rig() as r:
        r.sniffer.frames()
        with pytest.raises(LinkError, match="0x5FFF"):
            r.link.sdo_upload(0x5FFF, 0)
        frames = [(m.arbitration_id, bytes(m.data)) for m in r.sniffer.frames()]
        assert frames[0] == (0x601, bytes.fromhex("40ff5f0000000000"))
        assert frames[1] == (0x581, bytes.fromhex("80ff5f0000000206"))


def test_rpdo_of_wrong_length_is_refused_with_emcy_8210():
    with rig() as r:
        r.link.configure(LIVE, LIVE, 1)
        r.link.enable_velocity_mode()
        r.sniffer.frames()
        r.sniffer.inject(0x201, bytes.fromhex("0000"))       # mapping needs 7 bytes
        r.link.sync()
        # code 0x8210 (PDO length error), register generic|communication, drive clock before this SYNC
        assert r.sniffer.with_id(0x081) == [bytes.fromhex("108211") +
                                            struct.pack("<L", r.device.step_count - 100) + b"\x00"]
        assert r.link.status().state == "OPERATION ENABLED"  # the bad frame changed nothing
        assert r.node.rpdo_length_errors == 1


def test_tpdo_of_wrong_length_is_a_link_error():
    with rig() as r:
        r.link.configure(LIVE, LIVE, 1)
        r.sniffer.inject(0x281, b"\x01\x02\x03")
        with pytest.raises(LinkError, match="TPDO 0x281 has 3 bytes, its mapping needs 8"):
            r.link.sync()


def test_pdo_mapping_of_a_non_mappable_object_is_refused():
    with rig() as r:
        with pytest.raises(LinkError, match="0x06040041"):
            r.link.sdo.write(0x1A01, 1, 0x10080020)          # device name into a TPDO


def test_block_upload_frames_and_canopen_client_interop():
    with rig() as r:
        r.link.configure(LIVE, LIVE, 1)
        for _ in range(5):
            r.link.sync()
        r.sniffer.frames()
        # canopen's own block-upload client (BlockUploadStream) against our server
        with r.link.node.sdo.open(0x2101, 0, "rb", buffering=0, block_transfer=True) as stream:
            data = stream.readall()
        rows = decode_rows(data, mask_for(LIVE), 1e-4)
        assert np.allclose(np.diff(rows["t_s"]), 1e-4) and len(rows["t_s"]) == 500
        frames = [bytes(m.data) for m in r.sniffer.frames()]
        assert frames[0][:4] == bytes.fromhex("a4012100") and frames[0][4] == 127   # initiate, CRC, blksize
        assert frames[1][:4] == bytes.fromhex("c6012100")                           # size + CRC supported
        assert struct.unpack_from("<L", frames[1], 4)[0] == len(data) == 500 * 12
        assert frames[2][0] == 0xA3                                                  # start
        assert [f[0] for f in frames[3:3 + 127]] == list(range(1, 128))              # sequence numbers
        assert frames[130][:3] == bytes([0xA2, 127, 127])                            # block ack
        assert r.link.fetch_trace()["t_s"].size == 0      # the completed upload removed the rows


def test_python_can_loggers_capture_the_run(tmp_path):
    with rig() as r:
        paths = [tmp_path / "run.asc", tmp_path / "run.blf"]
        loggers = [can.Logger(str(p)) for p in paths]
        notifier = can.Notifier(r.sniffer.bus, loggers, timeout=0.1)
        r.link.configure(LIVE, LIVE, 1)
        r.link.enable_velocity_mode()
        r.link.set_speed_ref(3.0)
        sent = [s for _ in range(25) for s in r.link.sync()]
        r.link.disable()
        # python-can's Notifier drops what it has not read when stopped; a lockstep link in-process never waits on
        # another thread, so the loggers' thread may not have had its turn yet: let it read what is queued first
        deadline = time.monotonic() + 5.0
        while r.sniffer.bus.queue.qsize() and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.1)                                       # the last frame taken is being written
        notifier.stop()                                       # stops (and closes) the loggers too
        for path in paths:
            frames = list(can.LogReader(str(path)))
            syncs = [m for m in frames if m.arbitration_id == 0x080]
            tpdo2 = [struct.unpack("<ff", bytes(m.data)) for m in frames if m.arbitration_id == 0x281]
            assert len(syncs) == 25, path.suffix
            assert [v[1] for v in tpdo2] == pytest.approx([s.values["speed_est_mech_rad_s"] for s in sent])


def test_segmented_upload_of_the_trace_and_an_aborted_block_upload_loses_nothing():
    with rig() as r:
        r.link.configure(LIVE, LIVE, 1)
        for _ in range(3):
            r.link.sync()
        data = r.link.node.sdo.upload(0x2101, 0)             # canopen's segmented upload also works
        assert len(data) == 300 * 12
        for _ in range(2):
            r.link.sync()
        # a block upload the client abandons after the first block: the rows are served again
        r.sniffer.inject(0x601, bytes.fromhex("a40121007f000000"))
        r.sniffer.inject(0x601, bytes.fromhex("a300000000000000"))
        r.sniffer.inject(0x601, bytes.fromhex("8001210000000405"))   # abort 0x05040000
        r.link.sync()
        trace = r.link.fetch_trace()
        t = np.round(trace["t_s"] / 1e-4).astype(int)
        assert list(t) == list(range(301, 601))                  # 6 SYNCs x 100 steps, first 300 read before
