"""Serial protocol framing: exact bytes, CRCs against bitwise reference implementations, resync."""

import struct

from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.contract.serial_frames import Cmd, Frame, FrameDecoder, crc8, crc32, encode_frame


def crc8_reference(data: bytes) -> int:
    """CRC-8/SMBUS, bit by bit (poly 0x07, init 0, no reflection, no xorout)."""
    crc = 0
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def crc32_reference(data: bytes) -> int:
    """CRC-32/IEEE, bit by bit (reflected poly 0xEDB88320, init and xorout 0xFFFFFFFF)."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xEDB88320 if crc & 1 else crc >> 1
    return crc ^ 0xFFFFFFFF


def test_crc_check_values():
    assert crc8_reference(b"123456789") == 0xF4 == crc8(b"123456789")
    assert crc32_reference(b"123456789") == 0xCBF43926 == crc32(b"123456789")


def test_sync_frame_exact_bytes():
    frame = encode_frame(1, Cmd.SYNC, struct.pack("<I", 10))
    assert frame == bytes.fromhex("A55A 0400 01 42 84 0A000000 7BE9BA67")
    assert frame[6] == crc8_reference(bytes.fromhex("04000142"))
    assert struct.unpack("<I", frame[-4:])[0] == crc32_reference(bytes.fromhex("04000142 0A000000"))


def test_controlword_frame_exact_bytes():
    frame = encode_frame(0xFE, Cmd.CONTROLWORD, struct.pack("<H", 0x000F))
    head = bytes.fromhex("0200FE10")
    expected = (b"\xa5\x5a" + head + bytes([crc8_reference(head)]) + b"\x0f\x00"
                + struct.pack("<I", crc32_reference(head + b"\x0f\x00")))
    assert frame == expected


def test_decoder_split_feeds_and_garbage():
    a = encode_frame(3, Cmd.SAMPLE)
    b = encode_frame(4, Cmd.TARGET_VELOCITY, struct.pack("<d", 12.5))
    stream = b"\x00\xa5\x13" + a + b"\xa5" + b
    dec = FrameDecoder()
    got = []
    for i in range(len(stream)):
        got += dec.feed(stream[i:i + 1])
    assert got == [Frame(3, Cmd.SAMPLE, b""), Frame(4, Cmd.TARGET_VELOCITY, struct.pack("<d", 12.5))]
    assert dec.crc_errors == 0 and not dec.buffer


def test_corrupted_payload_is_counted_and_next_frame_found():
    bad = bytearray(encode_frame(5, Cmd.SYNC, struct.pack("<I", 10)))
    bad[8] ^= 0x40
    good = encode_frame(6, Cmd.STATUS)
    dec = FrameDecoder()
    assert dec.feed(bytes(bad) + good) == [Frame(6, Cmd.STATUS, b"")]
    assert dec.crc_errors == 1


def test_corrupted_length_does_not_stall():
    bad = bytearray(encode_frame(5, Cmd.SYNC, struct.pack("<I", 10)))
    bad[3] = 0xF0            # LEN now 0xF004: the header CRC catches it at once
    good = encode_frame(6, Cmd.STATUS)
    dec = FrameDecoder()
    assert dec.feed(bytes(bad) + good) == [Frame(6, Cmd.STATUS, b"")]
    assert dec.crc_errors >= 1


def test_good_frame_inside_a_truncated_one_is_found():
    truncated = encode_frame(1, Cmd.TRACE_READ, b"\xff\xff")[:-3]
    good = encode_frame(2, Cmd.SAMPLE)
    dec = FrameDecoder()
    assert dec.feed(truncated + good) == [Frame(2, Cmd.SAMPLE, b"")]


def test_bytes_wanted_never_overshoots_a_frame():
    frame = encode_frame(9, Cmd.SYNC, struct.pack("<I", 10))
    dec = FrameDecoder()
    pos = 0
    while pos < len(frame):
        want = dec.bytes_wanted()
        assert pos + want <= len(frame)
        out = dec.feed(frame[pos:pos + want])
        pos += want
    assert out == [Frame(9, Cmd.SYNC, struct.pack("<I", 10))]


@settings(max_examples=60, deadline=None)
@given(payloads=st.lists(st.binary(max_size=300), min_size=1, max_size=5),
       junk=st.binary(max_size=20), chunk=st.integers(1, 64))
def test_frames_survive_junk_and_any_chunking(payloads, junk, chunk):
    frames = [Frame(i, 0x41, p) for i, p in enumerate(payloads)]
    stream = junk + b"".join(encode_frame(f.seq, f.cmd, f.payload) for f in frames)
    dec = FrameDecoder()
    got = []
    for i in range(0, len(stream), chunk):
        got += dec.feed(stream[i:i + chunk])
    assert got[-len(frames):] == frames


def test_resync_after_quiet_line_finds_the_frame_behind_a_lying_header():
    head = struct.pack("<HBB", 60000, 1, 0x41)
    lying = b"\xa5\x5a" + head + bytes([crc8(head)])       # passes its CRC-8, promises 60000 bytes
    good = encode_frame(2, Cmd.SAMPLE)
    dec = FrameDecoder()
    assert dec.feed(lying + good) == []                      # waits for the promised payload...
    assert dec.resync() == [Frame(2, Cmd.SAMPLE, b"")]       # ...until the line goes quiet
    assert dec.crc_errors == 1 and not dec.buffer
    assert dec.resync() == [] and dec.crc_errors == 1        # nothing buffered: nothing counted
