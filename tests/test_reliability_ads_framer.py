"""The AMS/TCP `Framer` against memory abuse, without I/O:
the request-size limit derived from the protocol, when an unfinished frame began, and
that the framer lets go of its buffer."""

from __future__ import annotations

import struct
import tracemalloc

from geo_server.dictionary import TYPES, load_dictionary
from geo_server.transports.ads import codec
from geo_server.transports.ads.codec import (
    AmsAddr,
    AmsPacket,
    Command,
    Framer,
    StreamError,
    SumGroup,
)
from geo_server.transports.ads.server import AdsOptions

SERVER = AmsAddr("127.0.0.1.1.1", 551)
CLIENT = AmsAddr("10.1.2.3.1.1", 32905)


def frame(data: bytes = b"", invoke: int = 1, command: int = Command.READ_WRITE) -> bytes:
    return codec.request_frame(SERVER, CLIENT, command, data, invoke)


def largest_sum_request() -> bytes:
    """A sum read-write (0xF082) of TwinCAT's 500 sub-requests, each writing the largest
    object of the dictionary: the largest request a server must accept."""
    n, size = codec.SUM_COMMAND_LIMIT, codec.LARGEST_OBJECT
    items = [(0x120300, 0x10043, size, b"\x01" * size) for _ in range(n)]
    return codec.read_write_request(
        SumGroup.READ_WRITE, n, 8 * n, codec.sum_read_write_request(items)
    )


def test_request_limit_is_derived_from_the_protocol_and_the_dictionary() -> None:
    assert codec.SUM_COMMAND_LIMIT == 500
    assert codec.LARGEST_OBJECT == max(t.size for t in TYPES.values()) == 256
    assert max(o.length for o in load_dictionary().objects) <= codec.LARGEST_OBJECT
    # AMS header + ReadWrite head + 500 × (16-byte sub-request head + 256 bytes)
    assert codec.MAX_REQUEST_FRAME == 32 + 16 + 500 * (16 + 256) == 136_048
    assert AdsOptions().max_frame == codec.MAX_REQUEST_FRAME
    assert codec.MAX_REQUEST_FRAME < codec.MAX_FRAME  # a client's framer may take more


def test_the_largest_legal_request_fits_exactly() -> None:
    big = frame(largest_sum_request())
    assert len(big) == codec.AMS_TCP_HEADER_SIZE + codec.MAX_REQUEST_FRAME
    (pkt,) = Framer(codec.MAX_REQUEST_FRAME).feed(big)
    assert isinstance(pkt, AmsPacket)
    assert len(codec.parse_sum_read_write(codec.SUM_COMMAND_LIMIT, pkt.data[16:])) == 500


def test_a_header_announcing_more_fails_before_any_data() -> None:
    f = Framer(codec.MAX_REQUEST_FRAME)
    (ev,) = f.feed(struct.pack("<HI", 0, codec.MAX_REQUEST_FRAME + 1))
    assert isinstance(ev, StreamError)
    assert f.buffered == 0 and f.incomplete_since is None
    assert f.feed(b"\0" * 1000) == []  # and nothing more is kept


def test_incomplete_since_is_the_first_byte_of_the_unfinished_frame() -> None:
    one, two = frame(b"a" * 20, 1), frame(b"b" * 20, 2)
    f = Framer()
    assert f.feed(one[:3], now=1.0) == [] and f.incomplete_since == 1.0
    assert f.feed(one[3:10], now=2.0) == [] and f.incomplete_since == 1.0  # trickling
    # the first frame completes; the second began in this same segment
    (pkt,) = f.feed(one[10:] + two[:5], now=3.0)
    assert pkt.header.invoke_id == 1 and f.incomplete_since == 3.0
    (pkt,) = f.feed(two[5:], now=4.0)
    assert pkt.header.invoke_id == 2
    assert f.incomplete_since is None and f.buffered == 0
    # whole frames leave nothing unfinished
    assert len(f.feed(one + two, now=5.0)) == 2 and f.incomplete_since is None


def test_the_buffer_is_released_when_frames_complete_and_on_close() -> None:
    """A framer that held a large frame keeps no allocation once it completed, nor after
    `close()` (the connection is gone) — measured with tracemalloc, i.e. the Python heap
    of this process."""
    big = frame(largest_sum_request())
    tracemalloc.start()
    try:
        f = Framer(codec.MAX_REQUEST_FRAME)
        base = tracemalloc.get_traced_memory()[0]
        for i in range(0, len(big) - 1000, 997):
            f.feed(big[i : i + 997])  # grown piece by piece, as TCP delivers it
        held = tracemalloc.get_traced_memory()[0] - base
        assert held >= 100_000  # the unfinished frame is there
        f.close()
        assert f.buffered == 0 and f.incomplete_since is None
        assert tracemalloc.get_traced_memory()[0] - base < 10_000
        assert f.feed(big) == []  # a closed framer ignores input

        g = Framer(codec.MAX_REQUEST_FRAME)
        base = tracemalloc.get_traced_memory()[0]
        for i in range(0, len(big), 4096):
            events = g.feed(big[i : i + 4096])
        assert isinstance(events[-1], AmsPacket)
        del events
        assert tracemalloc.get_traced_memory()[0] - base < 10_000
    finally:
        tracemalloc.stop()
