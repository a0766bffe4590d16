"""The sans-I/O Modbus TCP codec: framing under any segmentation, request decoding and
reply encoding, byte for byte (Modbus application protocol v1.1b3, messaging on TCP/IP
v1.0b), without sockets."""

from __future__ import annotations

import struct

import pytest

from geo_server.transports.modbus.codec import (
    DeviceIdRequest,
    Frame,
    MbapFramer,
    ReadRequest,
    Refused,
    WriteRequest,
    adu,
    device_id_pdu,
    exception_pdu,
    parse_pdu,
    read_bits_pdu,
    read_registers_pdu,
    write_reply_pdu,
)


def test_frames_survive_any_split_and_coalescing():
    frames = [Frame(1, 3, b"\x03\x01\x0c\x00\x04"), Frame(0xFFFF, 0, b"\x2b\x0e\x01\x00")]
    stream = b"".join(adu(f.transaction, f.unit, f.pdu) for f in frames)
    assert stream[:7] == b"\x00\x01\x00\x00\x00\x06\x03"  # tid 1, pid 0, length 6, unit 3
    for chunk in (1, 2, 5, 7, len(stream)):
        framer, got = MbapFramer(), []
        for i in range(0, len(stream), chunk):
            got += framer.feed(stream[i : i + chunk])
        assert got == frames, chunk
        assert framer.pending == 0


def test_a_broken_header_stops_the_stream_after_the_good_frames():
    framer = MbapFramer()
    good = adu(7, 1, b"\x03\x00\x00\x00\x01")
    got = framer.feed(good + struct.pack(">HHHB", 8, 5, 6, 1) + b"\x03\x00\x00\x00\x01")
    assert got == [Frame(7, 1, b"\x03\x00\x00\x00\x01")]
    assert framer.error is not None and "protocol id 5" in framer.error
    assert framer.feed(good) == []  # nothing more is read
    assert framer.pending == 0


@pytest.mark.parametrize(
    ("pdu", "expected"),
    [
        (b"\x01\x00\x41\x00\x01", ReadRequest(1, 0x41, 1)),
        (b"\x03\x01\x0c\x00\x7d", ReadRequest(3, 268, 125)),
        (b"\x04\x01\x0c\x00\x04", ReadRequest(4, 268, 4)),
        (b"\x05\x00\x41\xff\x00", WriteRequest(5, 0x41, (True,))),
        (b"\x05\x00\x41\x00\x00", WriteRequest(5, 0x41, (False,))),
        (b"\x06\x01\x0c\xab\xcd", WriteRequest(6, 268, (0xABCD,))),
        (
            b"\x0f\x00\x41\x00\x0a\x02\x05\x02",
            WriteRequest(15, 0x41, (True, False, True) + (False,) * 6 + (True,)),
        ),
        (b"\x10\x01\x0c\x00\x02\x04\x00\x01\x00\x02", WriteRequest(16, 268, (1, 2))),
        (b"\x2b\x0e\x01\x00", DeviceIdRequest(1, 0)),
        (b"\x2b\x0e\x04\x05", DeviceIdRequest(4, 5)),
    ],
)
def test_requests_decode(pdu, expected):
    assert parse_pdu(pdu) == expected


@pytest.mark.parametrize(
    ("pdu", "fc", "code"),
    [
        (b"\x03\x00\x00\x00\x00", 3, 3),  # quantity 0
        (b"\x03\x00\x00\x00\x7e", 3, 3),  # quantity 126
        (b"\x01\x00\x00\x07\xd1", 1, 3),  # quantity 2001
        (b"\x10\x00\x00\x00\x7c\x00", 16, 3),  # quantity 124
        (b"\x10\x00\x00\x00\x02\x03\x00\x01\x00", 16, 3),  # byte count 3 for 2 registers
        (b"\x0f\x00\x00\x00\x09\x01\xff", 15, 3),  # 9 coils need 2 bytes
        (b"\x05\x00\x41\x12\x34", 5, 3),  # neither 0xFF00 nor 0x0000
        (b"\x03\x00\x00\x00", 3, 3),  # one byte short
        (b"\x08\x00\x00\x12\x34", 8, 1),  # diagnostics: not served
        (b"\x81\x00", 0x81, 1),  # exception function codes are not requests
        (b"\x2b\x0d\x01\x00", 43, 1),  # another MEI type
        (b"\x2b\x0e\x00\x00", 43, 3),  # read device id code 0
    ],
)
def test_refused_by_the_protocol(pdu, fc, code):
    got = parse_pdu(pdu)
    assert isinstance(got, Refused)
    assert (got.function, got.code) == (fc, code)


def test_reply_encoding():
    assert exception_pdu(3, 2) == b"\x83\x02"
    assert exception_pdu(0x81, 1) == b"\x81\x01"  # the high bit is already set
    assert read_bits_pdu(1, [True, False, True] + [False] * 6 + [True]) == b"\x01\x02\x05\x02"
    assert read_registers_pdu(3, [0x4029, 0x4000, 0, 0]) == b"\x03\x08\x40\x29\x40\x00" + bytes(4)
    assert write_reply_pdu(WriteRequest(5, 0x41, (True,))) == b"\x05\x00\x41\xff\x00"
    assert write_reply_pdu(WriteRequest(6, 268, (7,))) == b"\x06\x01\x0c\x00\x07"
    assert write_reply_pdu(WriteRequest(16, 268, (1, 2, 3, 4))) == b"\x10\x01\x0c\x00\x04"
    assert device_id_pdu(1, [(0, b"ab"), (2, b"1")], 0x82) == (
        b"\x2b\x0e\x01\x82\x00\x00\x02" + b"\x00\x02ab" + b"\x02\x011"
    )
    assert adu(0x1234, 2, b"\x83\x02") == b"\x12\x34\x00\x00\x00\x03\x02\x83\x02"
