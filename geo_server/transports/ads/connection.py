"""The sans-I/O side of one ADS connection (docs/design.md §9), as h11's `Connection` is
HTTP's: bytes in, typed events out (`receive`, over `codec.Framer`); a reply payload in,
the response frame's bytes out (`response`, `refusal`, `error_payload`). It holds what
the AMS router and the symbol service keep per connection: the AMS port a port connect
gave it and its symbol handles at each machine. No sockets, no event loop: the asyncio
protocol (`protocol.AdsConnection`) is this plus I/O.
"""

from __future__ import annotations

from collections.abc import Awaitable, Sequence
from dataclasses import dataclass, field

from geo_server.errors import AdsError, AdsErrorCode
from geo_server.transports.ads import codec, symbols
from geo_server.transports.ads.codec import AmsHeader, Command
from geo_server.transports.ads.repeats import Repeats

#: What a service handler returns: the response payload now or later.
Reply = bytes | Awaitable[bytes]
KNOWN_COMMANDS = frozenset(int(c) for c in Command)


def error_payload(command: int, code: int) -> bytes:
    """The response payload of `command` carrying only an error `code` (all fields the
    client parses present, zero)."""
    if command in (Command.READ, Command.READ_WRITE):
        return codec.read_response(code)
    if command == Command.ADD_DEVICE_NOTIFICATION:
        return codec.add_notification_response(code)
    if command == Command.READ_STATE:
        return codec.read_state_response(code)
    if command == Command.READ_DEVICE_INFO:
        return codec.read_device_info_response(code)
    return codec.result_response(code)


def fit_size(size: int, read_length: int, max_answer: int) -> None:
    """Never more bytes than requested: a too small read buffer is 0x705; so is an
    answer larger than `max_answer` (`AdsOptions.max_answer`)."""
    limit = min(read_length, max_answer)
    if size > limit:
        raise AdsError(
            AdsErrorCode.DEVICE_INVALIDSIZE,
            f"the answer has {size} bytes, the read length is {read_length}",
        )


def fixed(value: bytes, length: int, what: str) -> bytes:
    """A short fixed value: at most `length` bytes of it; 0 bytes asked is 0x705."""
    if length <= 0:
        raise AdsError(AdsErrorCode.DEVICE_INVALIDSIZE, f"read of {length} bytes of {what}")
    return value[:length]


@dataclass
class HandleTable:
    """The symbol handles one connection holds at one device (0xF003 -> symbol)."""

    handles: dict[int, symbols.Symbol] = field(default_factory=dict)
    next_handle: int = 0


class Connection:
    """One AMS/TCP connection's protocol state, without I/O."""

    def __init__(self, max_frame: int) -> None:
        self.framer = codec.Framer(max_frame)
        #: AMS port the router gave this client (port connect), None without
        self.ams_port: int | None = None
        #: symbol handles of this connection (0xF003), per device it talks to: one TCP
        #: connection may address every machine of a fleet
        self.tables: dict[int, HandleTable] = {}
        #: answers kept for Reads sent again, by the request less its invoke id
        #: (`repeats`)
        self.repeats: Repeats = {}

    def receive(self, data: bytes, now: float) -> Sequence[codec.FrameEvent]:
        """The complete frames (and framing events) `data` finishes."""
        return self.framer.feed(data, now)

    def table(self, device: object) -> HandleTable:
        """This connection's symbol handles at `device`."""
        t = self.tables.get(id(device))
        if t is None:
            t = self.tables[id(device)] = HandleTable()
        return t

    @staticmethod
    def response(h: AmsHeader, payload: bytes) -> bytes:
        """The response frame to `h` carrying `payload`. An unknown command id also
        carries 0x701 in the AMS header: a client cannot know the layout of a response
        to a command it should not have sent."""
        error = 0 if h.command in KNOWN_COMMANDS else AdsErrorCode.DEVICE_SRVNOTSUPP
        return codec.response_frame(h, payload, error)

    @staticmethod
    def refusal(h: AmsHeader, code: int) -> bytes:
        """An AMS-level refusal: `code` in the AMS header, no payload (0x6, 0x7, a bad
        packet's code)."""
        return codec.response_frame(h, b"", code)
