"""The sans-I/O ADS codec, driven with bytes only (no sockets, no service)."""

from __future__ import annotations

import struct

import pytest

from geo_server.errors import AdsErrorCode
from geo_server.transports.ads import codec
from geo_server.transports.ads.codec import (
    AddNotificationRequest,
    AmsAddr,
    AmsHeader,
    AmsPacket,
    BadPacket,
    Command,
    DeleteNotificationRequest,
    DeviceNotificationRequest,
    Dropped,
    Framer,
    PayloadError,
    ReadDeviceInfoRequest,
    ReadRequest,
    ReadStateRequest,
    ReadWriteRequest,
    Sample,
    Stamp,
    StateFlags,
    StreamError,
    UnknownCommandRequest,
    WriteControlRequest,
    WriteRequest,
)

SERVER = AmsAddr("127.0.0.1.1.1", 551)
CLIENT = AmsAddr("10.0.0.7.1.1", 30001)


def frame(command: int, data: bytes = b"", invoke: int = 1) -> bytes:
    return codec.request_frame(SERVER, CLIENT, command, data, invoke)


def read_frame(invoke: int = 1, ig: int = 0x120300, io: int = 0x10043, n: int = 8) -> bytes:
    return frame(Command.READ, codec.read_request(ig, io, n), invoke)


def packets(events: list) -> list[AmsPacket]:
    return [e for e in events if isinstance(e, AmsPacket)]


# ---------------------------------------------------------------------- headers


def test_netid_round_trip_and_errors() -> None:
    assert codec.netid_to_bytes("127.0.0.1.1.1") == bytes([127, 0, 0, 1, 1, 1])
    assert codec.netid_from_bytes(bytes([5, 6, 7, 8, 1, 1])) == "5.6.7.8.1.1"
    for bad in ("127.0.0.1", "1.2.3.4.5.256", "a.b.c.d.e.f", ""):
        with pytest.raises(ValueError):
            codec.netid_to_bytes(bad)


def test_request_frame_layout() -> None:
    raw = read_frame(invoke=0xDEADBEEF)
    reserved, length = struct.unpack_from("<HI", raw)
    assert (reserved, length) == (0, 32 + 12)
    assert len(raw) == 6 + 32 + 12
    h = AmsHeader.unpack(raw[6:38])
    assert h.target == SERVER and h.source == CLIENT
    assert h.command == Command.READ and h.state_flags == StateFlags.REQUEST
    assert h.data_length == 12 and h.error_code == 0 and h.invoke_id == 0xDEADBEEF
    assert not h.is_response


def test_response_frame_swaps_addresses_and_echoes_invoke_id() -> None:
    (req,) = packets(Framer().feed(read_frame(invoke=77)))
    raw = codec.response_frame(req.header, codec.read_response(0, b"12345678"))
    (resp,) = packets(Framer().feed(raw))
    h = resp.header
    assert h.target == CLIENT and h.source == SERVER
    assert h.command == Command.READ and h.invoke_id == 77
    assert h.state_flags == StateFlags.RESPONSE and h.is_response
    assert codec.parse_read_response(resp.data) == (0, b"12345678")


def test_response_frame_bytes() -> None:
    """Byte for byte: AMS/TCP header (0, 32 + 12), the request's source as target and its
    target as source, command 2, state flags 0x0005, 12 data bytes, error 0, invoke id."""
    (req,) = packets(Framer().feed(read_frame(invoke=0x01020304)))
    raw = codec.response_frame(req.header, codec.read_response(0, b"\x01\x02\x03\x04"))
    assert raw == bytes.fromhex(
        "0000"
        "2c000000"  # AMS/TCP: reserved, length 44
        "0a0000070101"
        "3175"  # target: the client 10.0.0.7.1.1:30001
        "7f0000010101"
        "2702"  # source: the server 127.0.0.1.1.1:551
        "0200"
        "0500"
        "0c000000"
        "00000000"
        "04030201"  # Read, response, 12 bytes, invoke
        "00000000"
        "04000000"
        "01020304"  # result 0, length 4, data
    )


def test_a_peer_inventing_addresses_grows_no_table() -> None:
    """A header's addresses are decoded once per address and remembered, at most 1024 of
    them: a client sending from 5000 made-up NetIds leaves no more."""
    for i in range(5000):
        src = AmsAddr(f"10.{i >> 8 & 255}.{i & 255}.7.1.1", 30000 + i % 7)
        (p,) = packets(Framer().feed(codec.request_frame(SERVER, src, Command.READ, b"")))
        assert p.header.source == src
    assert len(codec._ADDRS) <= 1024


def test_ams_error_response_has_empty_payload() -> None:
    (req,) = packets(Framer().feed(read_frame()))
    (resp,) = packets(Framer().feed(codec.response_frame(req.header, b"", 0x6)))
    assert resp.header.error_code == 0x6 and resp.data == b""


def test_notification_frame_addressing() -> None:
    """Source = server NetId and AMS port, target = the client's port (AdsLib dispatch)."""
    payload = codec.device_notification([Stamp(1, (Sample(3, b"\x01\x00\x00\x00"),))])
    (pkt,) = packets(Framer().feed(codec.notification_frame(SERVER, CLIENT, payload, 9)))
    assert pkt.header.source == SERVER and pkt.header.target == CLIENT
    assert pkt.header.command == Command.DEVICE_NOTIFICATION
    assert pkt.header.state_flags == StateFlags.REQUEST


# ---------------------------------------------------------------------- framing


def test_partial_frames_byte_by_byte() -> None:
    raw = read_frame(invoke=5)
    f = Framer()
    events = []
    for i in range(len(raw)):
        got = f.feed(raw[i : i + 1])
        if i < len(raw) - 1:
            assert got == []
        events += got
    (pkt,) = packets(events)
    assert pkt.header.invoke_id == 5 and f.buffered == 0


@pytest.mark.parametrize("cut", range(1, 50, 3))
def test_split_anywhere_in_coalesced_stream(cut: int) -> None:
    stream = b"".join(read_frame(invoke=i) for i in range(1, 4))
    f = Framer()
    events = f.feed(stream[:cut]) + f.feed(stream[cut:])
    assert [p.header.invoke_id for p in packets(events)] == [1, 2, 3]
    assert f.buffered == 0


def test_coalesced_frames_in_one_segment() -> None:
    stream = b"".join(read_frame(invoke=i) for i in range(10)) + read_frame(invoke=99)[:20]
    f = Framer()
    assert [p.header.invoke_id for p in packets(f.feed(stream))] == list(range(10))
    assert f.buffered == 20


def test_oversized_length_is_fatal_and_sticky() -> None:
    f = Framer(max_frame=1024)
    events = f.feed(read_frame(invoke=1) + struct.pack("<HI", 0, 1025) + b"x" * 10)
    assert isinstance(events[0], AmsPacket)
    assert isinstance(events[1], StreamError) and "1025" in events[1].reason
    assert f.failed is not None
    assert f.feed(read_frame()) == []


def test_default_limit_is_one_mebibyte() -> None:
    assert codec.MAX_FRAME == 1 << 20
    assert isinstance(Framer().feed(struct.pack("<HI", 0, (1 << 20) + 1))[0], StreamError)
    # exactly at the limit: waits for the data
    assert Framer().feed(struct.pack("<HI", 0, 1 << 20)) == []


def test_unknown_tcp_header_kind_is_fatal() -> None:
    (ev,) = Framer().feed(b"\xde\xad" + b"\x00" * 40)
    assert isinstance(ev, StreamError)


def test_router_command_is_its_own_event() -> None:
    router = struct.pack("<HI", 0x1000, 2) + b"\x00\x00"
    events = Framer().feed(router + read_frame(invoke=4))
    assert events[0] == codec.RouterCommand(0x1000, b"\x00\x00")
    assert packets(events)[0].header.invoke_id == 4


def test_router_command_longer_than_any_router_frame_fails_the_stream() -> None:
    (ev,) = Framer().feed(struct.pack("<HI", 0x1000, 65) + b"\x00" * 65)
    assert isinstance(ev, StreamError) and "0x1000" in ev.reason


def test_frame_shorter_than_ams_header_is_skipped() -> None:
    events = Framer().feed(struct.pack("<HI", 0, 5) + b"12345" + read_frame(invoke=2))
    assert isinstance(events[0], Dropped)
    assert packets(events)[0].header.invoke_id == 2


def test_inconsistent_ams_length_is_answered_with_0xE() -> None:
    raw = bytearray(read_frame(invoke=3))
    struct.pack_into("<I", raw, 6 + 20, 99)  # AMS header data length lies
    events = Framer().feed(bytes(raw) + read_frame(invoke=4))
    assert isinstance(events[0], BadPacket)
    assert events[0].error_code == AdsErrorCode.INVALID_AMS_LENGTH
    assert events[0].header.invoke_id == 3
    assert packets(events)[0].header.invoke_id == 4


def test_empty_feed_and_header_only() -> None:
    f = Framer()
    assert f.feed(b"") == []
    assert f.feed(struct.pack("<HI", 0, 32)) == []
    assert f.buffered == 6


# ---------------------------------------------------------------------- requests


def parse(command: int, data: bytes = b"") -> codec.Request:
    (pkt,) = packets(Framer().feed(frame(command, data)))
    return codec.parse_request(pkt)


def test_parse_every_request() -> None:
    assert parse(Command.READ_DEVICE_INFO) == ReadDeviceInfoRequest()
    assert parse(Command.READ_STATE) == ReadStateRequest()
    assert parse(Command.READ, codec.read_request(1, 2, 3)) == ReadRequest(1, 2, 3)
    assert parse(Command.WRITE, codec.write_request(1, 2, b"ab")) == WriteRequest(1, 2, b"ab")
    assert parse(Command.READ_WRITE, codec.read_write_request(1, 2, 8, b"xyz")) == (
        ReadWriteRequest(1, 2, 8, b"xyz")
    )
    assert parse(
        Command.ADD_DEVICE_NOTIFICATION, codec.add_notification_request(1, 2, 4, 4, 10, 20)
    ) == (AddNotificationRequest(1, 2, 4, 4, 10, 20))
    assert parse(Command.DELETE_DEVICE_NOTIFICATION, codec.delete_notification_request(7)) == (
        DeleteNotificationRequest(7)
    )
    assert parse(Command.WRITE_CONTROL, struct.pack("<HHI", 5, 0, 1) + b"z") == (
        WriteControlRequest(5, 0, b"z")
    )
    assert parse(0x77) == UnknownCommandRequest(0x77)
    note = codec.device_notification([Stamp(5, (Sample(1, b"ab"),))])
    assert parse(Command.DEVICE_NOTIFICATION, note) == DeviceNotificationRequest(
        (Stamp(5, (Sample(1, b"ab"),)),)
    )


def test_add_notification_payload_is_40_bytes() -> None:
    assert len(codec.add_notification_request(1, 2, 3)) == 40


@pytest.mark.parametrize(
    ("command", "data"),
    [
        (Command.READ, b"\x00" * 8),
        (Command.READ, b"\x00" * 13),
        (Command.WRITE, codec.write_request(1, 2, b"abcd")[:-1]),
        (Command.WRITE, codec.write_request(1, 2, b"abcd") + b"!"),
        (Command.READ_WRITE, codec.read_write_request(1, 2, 4, b"ab")[:-1]),
        (Command.READ_WRITE, b"\x00" * 15),
        (Command.ADD_DEVICE_NOTIFICATION, b"\x00" * 20),
        (Command.DELETE_DEVICE_NOTIFICATION, b"\x00" * 3),
        (Command.WRITE_CONTROL, b"\x00" * 7),
        (Command.DEVICE_NOTIFICATION, b"\x00" * 7),
    ],
)
def test_truncated_or_padded_payload_is_0x705(command: int, data: bytes) -> None:
    with pytest.raises(PayloadError) as exc:
        parse(command, data)
    assert exc.value.code == 0x705


# ---------------------------------------------------------------------- responses


def test_response_payloads() -> None:
    assert codec.result_response(0x702) == b"\x02\x07\x00\x00"
    assert codec.read_response(0, b"ab") == struct.pack("<II", 0, 2) + b"ab"
    assert codec.parse_read_state_response(codec.read_state_response(0, 5, 0)) == (0, 5, 0)
    info = codec.read_device_info_response(0, 0, 1, 2, "geo-server")
    assert len(info) == 24
    assert codec.parse_read_device_info_response(info) == (0, 0, 1, 2, "geo-server")
    # the device name field is char[16]: at most 15 characters plus NUL
    long = codec.read_device_info_response(0, 1, 2, 3, "x" * 40)
    assert codec.parse_read_device_info_response(long)[4] == "x" * 15
    assert codec.parse_add_notification_response(codec.add_notification_response(0, 9)) == (0, 9)


def test_parse_read_response_rejects_inconsistent_length() -> None:
    with pytest.raises(PayloadError):
        codec.parse_read_response(struct.pack("<II", 0, 9) + b"short")


# ---------------------------------------------------------------------- notifications


def test_device_notification_round_trip() -> None:
    stamps = [
        Stamp(codec.unix_to_filetime(1.5), (Sample(1, b"\x01\x02\x03\x04"), Sample(2, b"\x05"))),
        Stamp(codec.unix_to_filetime(2.5), (Sample(1, b"\x06\x07\x08\x09"),)),
    ]
    raw = codec.device_notification(stamps)
    length, count = struct.unpack_from("<II", raw)
    assert length == len(raw) - 4 and count == 2
    assert codec.parse_device_notification(raw) == stamps


def test_device_notification_inconsistencies() -> None:
    raw = codec.device_notification([Stamp(1, (Sample(1, b"abcd"),))])
    for bad in (raw[:-1], raw + b"\x00", raw[:10]):
        with pytest.raises(PayloadError):
            codec.parse_device_notification(bad)


def test_filetime() -> None:
    assert codec.unix_to_filetime(0.0) == 116_444_736_000_000_000
    assert codec.filetime_to_unix(codec.unix_to_filetime(1_700_000_000.25)) == 1_700_000_000.25


# ---------------------------------------------------------------------- sum commands


def test_sum_read_parse_and_response() -> None:
    items = [(0x120300, 0x10043, 8), (0x120300, 0x10041, 1), (0x999, 0, 4)]
    subs = codec.parse_sum_read(3, codec.sum_read_request(items))
    assert [(s.index_group, s.index_offset, s.length) for s in subs] == items
    out = codec.sum_read_response([(0, b"A" * 8), (0, b"\x01"), (0x702, b"")], [8, 1, 4])
    assert len(out) == 3 * 4 + 8 + 1 + 4
    assert codec.parse_sum_read_response(out, [8, 1, 4]) == [
        (0, b"A" * 8),
        (0, b"\x01"),
        (0x702, b"\0" * 4),
    ]


def test_sum_read_pads_short_data_to_requested_length() -> None:
    out = codec.sum_read_response([(0, b"ab")], [4])
    assert out == b"\0\0\0\0ab\0\0"


def test_sum_write_parse_and_response() -> None:
    items = [(1, 2, b"abcd"), (3, 4, b""), (5, 6, b"z")]
    subs = codec.parse_sum_write(3, codec.sum_write_request(items))
    assert [(s.index_group, s.index_offset, s.data) for s in subs] == items
    assert codec.sum_write_response([0, 0x704]) == struct.pack("<II", 0, 0x704)
    with pytest.raises(PayloadError):
        codec.parse_sum_write(3, codec.sum_write_request(items)[:-1])
    with pytest.raises(PayloadError):
        codec.parse_sum_write(4, codec.sum_write_request(items))


def test_sum_read_write_parse_and_ex_responses() -> None:
    items = [(1, 2, 8, b""), (3, 4, 4, b"wxyz")]
    subs = codec.parse_sum_read_write(2, codec.sum_read_write_request(items))
    assert [(s.index_group, s.index_offset, s.read_length, s.data) for s in subs] == items
    out = codec.sum_read_ex_response([(0, b"12345678"), (0x703, b"")])
    assert codec.parse_sum_read_ex_response(out, 2) == [(0, b"12345678"), (0x703, b"")]
    padded = codec.sum_read_ex_response([(0, b"ab"), (0x703, b"")], [4, 2])
    assert padded[16:] == b"ab\0\0\0\0"


def test_sum_counts_are_checked() -> None:
    with pytest.raises(PayloadError):
        codec.parse_sum_read(2, codec.sum_read_request([(1, 2, 3)]))
    with pytest.raises(PayloadError):
        codec.parse_sum_read(codec.MAX_SUM_REQUESTS + 1, b"")
    assert codec.parse_sum_read(0, b"") == []
