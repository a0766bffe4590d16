"""Sans-I/O codec of ADS over AMS/TCP: bytes in, dataclasses out, and back.

Nothing here touches a socket, a clock or a thread; the asyncio server in
`geo_server.transports.ads.server` is a thin shell around these functions, and tests drive them with
bytes only (in the style of h11/wsproto).

Wire format (Beckhoff InfoSys "AMS/TCP packet", "AMS header"; `Beckhoff/ADS:AdsLib/
AmsHeader.h`), all integers little-endian:

=============  =====  =================================================================
part           bytes  fields
=============  =====  =================================================================
AMS/TCP header     6  reserved u16 (0 = AMS command; 0x1000…0x1002 router commands),
                      length u32 (= 32 + ADS data length)
AMS header        32  target NetId (6), target port u16, source NetId (6), source port
                      u16, command id u16, state flags u16 (0x0004 request, 0x0005
                      response, 0x0040 UDP), data length u32, error code u32, invoke id u32
ADS data           n  command specific (see the `*_request` / `*_response` helpers)
=============  =====  =================================================================

A server answers by swapping source and target and echoing command id and invoke id
(`response_frame`). If the AMS header error code is not 0 the AdsLib client (inside pyads)
skips the payload and returns that code, so AMS-level errors (0x6 target port not found,
0xE invalid AMS length) travel there with an empty payload; ADS-level errors (0x70x) travel
as the `result` field of the command's response payload.

The incremental `Framer` copes with partial and coalesced TCP segments: feed it whatever
`recv` returned and it yields every complete frame. A frame with a plausible length but
bad content is skipped (framing stays intact); only a length beyond `max_frame` or an
unknown AMS/TCP header kind is unrecoverable (the stream can no longer be delimited).
"""

from __future__ import annotations

import functools
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import NamedTuple

from geo_server.dictionary import TYPES as _dictionary_types
from geo_server.errors import AdsErrorCode, GeoError
from geo_server.snapshot import FILETIME_UNIX_OFFSET

# ---------------------------------------------------------------------- constants

AMS_TCP_HEADER = struct.Struct("<HI")
AMS_HEADER = struct.Struct("<6sH6sHHHIII")
AMS_TCP_HEADER_SIZE = AMS_TCP_HEADER.size  # 6
AMS_HEADER_SIZE = AMS_HEADER.size  # 32
#: Default AMS/TCP length limit of a `Framer` (AMS header + ADS data): a generous
#: ceiling for what a *client* receives (answers, notification frames of many samples).
#: Beyond it the connection is closed: a peer that sends such a length is broken or
#: hostile, and resynchronising an AMS/TCP stream is impossible (there is no frame marker).
MAX_FRAME = 1 << 20

# The largest request a server needs to receive. Every byte a server buffers for an
# unfinished frame is memory a client chose to make it hold, so the server accepts no
# AMS/TCP length beyond what the largest legal request needs:
#
#   AMS header + ReadWrite head (IG, IO, read length, write length)
#   + SUM_COMMAND_LIMIT x (sum sub-request head + the largest object)
#
# The largest request is a sum command (a ReadWrite to 0xF08x): TwinCAT serves at most
# 500 sub-requests in one, each with a 12-byte (0xF080/0xF081/0xF083/0xF084: IG, IO,
# length) or 16-byte (0xF082: IG, IO, read length, write length) head, and none writes
# more than the largest ADS type of the object dictionary (STRING, 256 bytes). Every
# other request is smaller (a Write carries one object after a 12-byte head). A sum
# command of more, smaller sub-requests still fits as long as its bytes do.

#: TwinCAT's documented limit of sub-requests in one ADS sum command.
SUM_COMMAND_LIMIT = 500
#: The largest value one (sub-)request carries: the largest ADS type of the dictionary.
LARGEST_OBJECT = max(t.size for t in _dictionary_types.values())
#: ReadWrite request head: IG, IO, read length, write length.
READ_WRITE_HEAD = struct.calcsize("<IIII")
#: The largest sum sub-request head (0xF082 read-write: IG, IO, read length, write length).
SUM_SUB_HEAD = max(struct.calcsize("<III"), struct.calcsize("<IIII"))
#: ADS data of the largest request a server accepts.
MAX_REQUEST_DATA = READ_WRITE_HEAD + SUM_COMMAND_LIMIT * (SUM_SUB_HEAD + LARGEST_OBJECT)
#: AMS/TCP length limit of a server's `Framer` (AMS header + the largest request data;
#: 136 048 bytes, 136 054 with the AMS/TCP header). The ADS server's default `max_frame`.
MAX_REQUEST_FRAME = AMS_HEADER_SIZE + MAX_REQUEST_DATA

#: AMS/TCP header `reserved` values (jisotalo/ads-client `ads-commons.ts`
#: `AMS_HEADER_FLAG`): 0 carries an AMS packet, the others are commands to the AMS router.
AMS_TCP_PORT_AMS_CMD = 0x0000
AMS_TCP_PORT_CLOSE = 0x0001  # u16 port: the client gives its AMS port back
AMS_TCP_PORT_CONNECT = 0x1000  # u16 port wanted (0: any) -> NetId (6) + port (u16)
AMS_TCP_ROUTER_NOTE = 0x1001  # router -> client only
AMS_TCP_GET_LOCAL_NETID = 0x1002  # -> NetId (6)
AMS_TCP_ROUTER_COMMANDS = frozenset(
    {AMS_TCP_PORT_CLOSE, AMS_TCP_PORT_CONNECT, AMS_TCP_ROUTER_NOTE, AMS_TCP_GET_LOCAL_NETID}
)
#: Largest router command frame: nothing a client sends the router carries more.
MAX_ROUTER_FRAME = 64

#: AMS port of the TwinCAT system service (ReadState, ReadDeviceInfo, WriteControl; the
#: port UDP discovery names).
SYSTEM_SERVICE_PORT = 10000


class Command(IntEnum):
    """ADS command ids (Beckhoff "ADS commands", AdsLib `AoEHeader`)."""

    INVALID = 0x0000
    READ_DEVICE_INFO = 0x0001
    READ = 0x0002
    WRITE = 0x0003
    READ_STATE = 0x0004
    WRITE_CONTROL = 0x0005
    ADD_DEVICE_NOTIFICATION = 0x0006
    DELETE_DEVICE_NOTIFICATION = 0x0007
    DEVICE_NOTIFICATION = 0x0008
    READ_WRITE = 0x0009


class StateFlags(IntEnum):
    """AMS header state flags (AdsLib `AoEHeader::AMS_REQUEST/AMS_RESPONSE/AMS_UDP`)."""

    RESPONSE_BIT = 0x0001
    REQUEST = 0x0004
    RESPONSE = 0x0005
    UDP = 0x0040


class SumGroup(IntEnum):
    """Sum commands: ReadWrite to these index groups, index offset = number of sub-requests
    (AdsDef.h `ADSIGRP_SUMUP_*`)."""

    READ = 0xF080
    WRITE = 0xF081
    READ_WRITE = 0xF082
    READ_EX = 0xF083
    READ_EX2 = 0xF084
    ADD_DEVICE_NOTIFICATION = 0xF085
    DELETE_DEVICE_NOTIFICATION = 0xF086


class TransMode(IntEnum):
    """`ADSTRANSMODE` (AdsDef.h). pyads' `NotificationAttrib` defaults to SERVERONCHA."""

    NOTRANS = 0
    CLIENTCYCLE = 1
    CLIENTONCHA = 2
    SERVERCYCLE = 3
    SERVERONCHA = 4
    SERVERCYCLE2 = 5
    SERVERONCHA2 = 6
    CLIENT1REQ = 10


class AdsState(IntEnum):
    """ADS states (pyads `constants.py`): what ReadState reports."""

    INVALID = 0
    IDLE = 1
    RESET = 2
    INIT = 3
    START = 4
    RUN = 5
    STOP = 6
    ERROR = 11


# ---------------------------------------------------------------------- addresses


@functools.lru_cache(maxsize=1024)  # a few NetIds per server: parsed once, not per frame
def netid_to_bytes(netid: str) -> bytes:
    """`"127.0.0.1.1.1"` -> 6 bytes; anything else raises ValueError."""
    parts = netid.split(".")
    if len(parts) != 6:
        raise ValueError(f"an AMS NetId has 6 dot-separated bytes, not {netid!r}")
    try:
        return bytes(int(p) for p in parts)
    except ValueError:
        raise ValueError(f"invalid AMS NetId {netid!r}") from None


@functools.lru_cache(maxsize=1024)
def netid_from_bytes(raw: bytes) -> str:
    return ".".join(str(b) for b in raw)


@dataclass(frozen=True, slots=True)
class AmsAddr:
    """An AMS address: NetId (6 bytes, written dotted) and AMS port."""

    netid: str
    port: int

    def __str__(self) -> str:
        return f"{self.netid}:{self.port}"


#: (an IntEnum member costs a class attribute lookup each time: ten times an int's)
_RESPONSE_BIT = int(StateFlags.RESPONSE_BIT)
_READ = int(Command.READ)
#: the shortest AMS/TCP frame with an AMS header
_ONE_FRAME_MIN = AMS_TCP_HEADER_SIZE + AMS_HEADER_SIZE

#: the AMS addresses of the frames seen, by their 8 bytes (a few clients per server):
#: a request's header is decoded without formatting its NetIds again
_ADDRS: dict[bytes, AmsAddr] = {}
MAX_ADDRESSES = 1024
_AMS_HEADER_RAW = struct.Struct("<8s8sHHIII")


def _addr(raw: bytes) -> AmsAddr:
    addr = _ADDRS.get(raw)
    if addr is None:
        if len(_ADDRS) >= MAX_ADDRESSES:  # (a peer inventing addresses: start afresh)
            _ADDRS.clear()
        addr = _ADDRS[raw] = AmsAddr(netid_from_bytes(raw[:6]), _U16.unpack_from(raw, 6)[0])
    return addr


# The header, the packet and a Read request are made for every request: named tuples,
# as immutable as a frozen dataclass and made in a seventh of its time (2.2 µs for the
# header's seven fields here, docs/benchmarks.md *Reads at rest*).


class AmsHeader(NamedTuple):
    """The 32-byte AMS header."""

    target: AmsAddr
    source: AmsAddr
    command: int
    state_flags: int
    data_length: int
    error_code: int
    invoke_id: int

    @property
    def is_response(self) -> bool:
        return bool(self.state_flags & _RESPONSE_BIT)

    def pack(self) -> bytes:
        return AMS_HEADER.pack(
            netid_to_bytes(self.target.netid),
            self.target.port,
            netid_to_bytes(self.source.netid),
            self.source.port,
            self.command,
            self.state_flags,
            self.data_length,
            self.error_code,
            self.invoke_id,
        )

    @classmethod
    def unpack(cls, raw: bytes | memoryview, offset: int = 0) -> AmsHeader:
        """The header at `offset` of `raw` (32 bytes from there)."""
        target, source, cmd, flags, length, err, invoke = _AMS_HEADER_RAW.unpack_from(raw, offset)
        return cls(_addr(target), _addr(source), cmd, flags, length, err, invoke)


class AmsPacket(NamedTuple):
    """One complete AMS packet: header plus its ADS data."""

    header: AmsHeader
    data: bytes


def encode_frame(header: AmsHeader, data: bytes = b"") -> bytes:
    """AMS/TCP header + AMS header + data. `header.data_length` is set from `data`."""
    h = AmsHeader(
        header.target,
        header.source,
        header.command,
        header.state_flags,
        len(data),
        header.error_code,
        header.invoke_id,
    )
    return AMS_TCP_HEADER.pack(0, AMS_HEADER_SIZE + len(data)) + h.pack() + data


def request_frame(
    target: AmsAddr, source: AmsAddr, command: int, data: bytes = b"", invoke_id: int = 0
) -> bytes:
    """A request frame (state flags 0x0004), as a client sends it."""
    return encode_frame(
        AmsHeader(target, source, command, StateFlags.REQUEST, len(data), 0, invoke_id), data
    )


def response_frame(request: AmsHeader, data: bytes = b"", error_code: int = 0) -> bytes:
    """The answer to `request`: source and target swapped, command id and invoke id echoed,
    state flags 0x0005 (as pyads' test server `construct_response` and TwinCAT do)."""
    src, tgt = request.source, request.target
    return (
        _RESPONSE_HEAD.pack(
            0,
            AMS_HEADER_SIZE + len(data),
            netid_to_bytes(src.netid),
            src.port,
            netid_to_bytes(tgt.netid),
            tgt.port,
            request.command,
            _RESPONSE_FLAGS,
            len(data),
            error_code,
            request.invoke_id,
        )
        + data
    )


#: where a frame's invoke id lies: the last field of its AMS header
INVOKE_ID_AT = AMS_TCP_HEADER_SIZE + AMS_HEADER_SIZE - 4
#: the size of a whole Read request's frame (index group, offset and length)
READ_FRAME_SIZE = AMS_TCP_HEADER_SIZE + AMS_HEADER_SIZE + 12


def without_invoke_id(frame: bytes) -> bytes:
    """`frame` less its invoke id: what a request sent again has in common with the
    first (`repeats`)."""
    return frame[:INVOKE_ID_AT] + frame[INVOKE_ID_AT + 4 :]


#: AMS/TCP header and AMS header of a frame in one (`response_frame`)
_RESPONSE_HEAD = struct.Struct(AMS_TCP_HEADER.format + AMS_HEADER.format.lstrip("<"))
_RESPONSE_FLAGS = int(StateFlags.RESPONSE)


def notification_frame(server: AmsAddr, client: AmsAddr, data: bytes, invoke_id: int = 0) -> bytes:
    """A DeviceNotification (command 8) from `server` to `client`.

    AdsLib routes command-8 frames by (target port, source AmsAddr) (`AmsConnection.cpp
    ReceiveNotification`): the source must be the NetId **and AMS port** the client
    registered with (e.g. `…:551`), the target the client's own port (30000+). The state
    flags are those of a request (0x0004); there is no response.
    """
    return encode_frame(
        AmsHeader(
            client,
            server,
            Command.DEVICE_NOTIFICATION,
            StateFlags.REQUEST,
            len(data),
            0,
            invoke_id,
        ),
        data,
    )


# ---------------------------------------------------------------------- framing


@dataclass(frozen=True, slots=True)
class RouterCommand:
    """An AMS/TCP frame for the router itself (`AMS_TCP_ROUTER_COMMANDS`), not an AMS
    packet: `command` is the AMS/TCP header's first field, `data` what follows."""

    command: int
    data: bytes


@dataclass(frozen=True, slots=True)
class Dropped:
    """A frame was skipped, framing intact (router command, too short for an AMS header,
    a response sent to the server). `size` is the number of bytes skipped."""

    reason: str
    size: int


@dataclass(frozen=True, slots=True)
class BadPacket:
    """An AMS header could be read but the frame is inconsistent: answer `error_code` in
    the AMS header of the response (e.g. 0xE invalid AMS length)."""

    header: AmsHeader
    reason: str
    error_code: int


@dataclass(frozen=True, slots=True)
class StreamError:
    """Unrecoverable: the byte stream can no longer be delimited. Close the connection."""

    reason: str


FrameEvent = AmsPacket | BadPacket | RouterCommand | Dropped | StreamError


class Framer:
    """Incremental AMS/TCP deframer.

    `feed(data)` accepts any slice of the TCP stream (one byte, half a header, three
    coalesced frames…) and returns the events it completed, in order. After a
    `StreamError` the framer is `failed` and ignores further input.

    Memory: only the bytes of the one unfinished frame are kept, never more than the
    `max_frame` its header may announce (a longer announcement fails at once, before its
    data arrives). When everything fed so far is consumed the buffer is replaced by an
    empty one, so a framer that once held a large frame does not keep its allocation;
    `close()` releases it for good.

    Time: the framer reads no clock, but `feed(data, now)` records in
    `incomplete_since` the `now` at which the first byte of the frame still unfinished
    arrived (None when nothing is buffered). The caller decides how long a frame may
    stay unfinished; counting from its first byte means a client that trickles one byte
    at a time cannot keep a buffer alive forever.
    """

    def __init__(self, max_frame: int = MAX_FRAME) -> None:
        self.max_frame = max_frame
        self._buf = bytearray()
        self.failed: str | None = None
        self.incomplete_since: float | None = None

    @property
    def idle(self) -> bool:
        """Nothing buffered and not failed: the next byte begins a frame."""
        return self.incomplete_since is None and self.failed is None

    @property
    def buffered(self) -> int:
        """Bytes waiting for the rest of their frame."""
        return len(self._buf)

    def close(self) -> None:
        """Release the buffer (the connection is gone); later input is ignored."""
        self._buf = bytearray()
        self.incomplete_since = None
        if self.failed is None:
            self.failed = "closed"

    def feed(self, data: bytes, now: float = 0.0) -> list[FrameEvent]:
        if self.failed is not None:
            return []
        buf = self._buf
        if not buf:
            one = self._one_frame(data)
            if one is not None:
                return one
        started_here = not buf  # the unfinished frame (if any) begins in `data`
        buf += data
        events: list[FrameEvent] = []
        pos = 0
        n = len(buf)
        while n - pos >= AMS_TCP_HEADER_SIZE:
            reserved, length = AMS_TCP_HEADER.unpack_from(buf, pos)
            if reserved != AMS_TCP_PORT_AMS_CMD and reserved not in AMS_TCP_ROUTER_COMMANDS:
                return self._fail(events, f"unknown AMS/TCP header kind 0x{reserved:04X}")
            if reserved != AMS_TCP_PORT_AMS_CMD and length > MAX_ROUTER_FRAME:
                return self._fail(
                    events, f"router command 0x{reserved:04X} announces {length} bytes"
                )
            if length > self.max_frame:
                return self._fail(
                    events, f"AMS/TCP length {length} exceeds the limit of {self.max_frame}"
                )
            end = pos + AMS_TCP_HEADER_SIZE + length
            if end > n:
                break  # wait for the rest of this frame
            start = pos + AMS_TCP_HEADER_SIZE
            pos = end
            if reserved != AMS_TCP_PORT_AMS_CMD:
                events.append(RouterCommand(reserved, bytes(buf[start:end])))
                continue
            if length < AMS_HEADER_SIZE:
                events.append(Dropped(f"AMS/TCP length {length} < AMS header", length + 6))
                continue
            header = AmsHeader.unpack(memoryview(buf)[start : start + AMS_HEADER_SIZE])
            if header.data_length != length - AMS_HEADER_SIZE:
                events.append(
                    BadPacket(
                        header,
                        f"AMS data length {header.data_length} but AMS/TCP carries "
                        f"{length - AMS_HEADER_SIZE} bytes",
                        AdsErrorCode.INVALID_AMS_LENGTH,
                    )
                )
                continue
            events.append(AmsPacket(header, bytes(buf[start + AMS_HEADER_SIZE : end])))
        if pos == n:
            # Everything consumed: start afresh rather than keep the grown allocation.
            self._buf = bytearray()
            self.incomplete_since = None
        else:
            if pos:
                del buf[:pos]
                started_here = True  # a frame completed here: the next one began in `data`
            if started_here or self.incomplete_since is None:
                self.incomplete_since = now
        return events

    def _one_frame(self, data: bytes) -> list[FrameEvent] | None:
        """The common case, `data` is one whole AMS packet and nothing is buffered: its
        event without a copy into the buffer; None for every other case (the loop of
        `feed` takes it, with the same checks)."""
        if len(data) < _ONE_FRAME_MIN:
            return None
        reserved, length = AMS_TCP_HEADER.unpack_from(data)
        if (
            reserved != AMS_TCP_PORT_AMS_CMD
            or len(data) != AMS_TCP_HEADER_SIZE + length
            or length > self.max_frame
        ):
            return None
        header = AmsHeader.unpack(data, AMS_TCP_HEADER_SIZE)
        if header.data_length != length - AMS_HEADER_SIZE:
            return None
        return [AmsPacket(header, bytes(data[_ONE_FRAME_MIN:]))]

    def _fail(self, events: list[FrameEvent], reason: str) -> list[FrameEvent]:
        self.failed = reason
        self._buf = bytearray()
        self.incomplete_since = None
        events.append(StreamError(reason))
        return events


# ---------------------------------------------------------------------- router commands


def router_frame(command: int, data: bytes = b"") -> bytes:
    """An AMS/TCP frame of a router command (no AMS header)."""
    return AMS_TCP_HEADER.pack(command, len(data)) + data


def port_connect_request(port: int = 0) -> bytes:
    """What a client sends to get an AMS port (0: the router chooses)."""
    return router_frame(AMS_TCP_PORT_CONNECT, _U16.pack(port))


def port_connect_response(netid: str, port: int) -> bytes:
    """The router's answer: the client's AMS address from now on."""
    return router_frame(AMS_TCP_PORT_CONNECT, netid_to_bytes(netid) + _U16.pack(port))


def local_netid_response(netid: str) -> bytes:
    return router_frame(AMS_TCP_GET_LOCAL_NETID, netid_to_bytes(netid))


def parse_router_port(cmd: RouterCommand) -> int:
    """The u16 port of a port connect / close; `PayloadError` when it is not 2 bytes."""
    if len(cmd.data) != 2:
        raise PayloadError(
            AdsErrorCode.DEVICE_INVALIDSIZE,
            f"router command 0x{cmd.command:04X} carries {len(cmd.data)} bytes, not 2",
        )
    return int(_U16.unpack(cmd.data)[0])


# ---------------------------------------------------------------------- requests


class PayloadError(GeoError):
    """The ADS data of a request does not fit its command (truncated, wrong length)."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code = int(code)
        self.message = message


@dataclass(frozen=True, slots=True)
class ReadDeviceInfoRequest:
    pass


class ReadRequest(NamedTuple):
    index_group: int
    index_offset: int
    length: int


@dataclass(frozen=True, slots=True)
class WriteRequest:
    index_group: int
    index_offset: int
    data: bytes


@dataclass(frozen=True, slots=True)
class ReadStateRequest:
    pass


@dataclass(frozen=True, slots=True)
class WriteControlRequest:
    ads_state: int
    device_state: int
    data: bytes


@dataclass(frozen=True, slots=True)
class AddNotificationRequest:
    """`max_delay` and `cycle_time` are 100 ns ticks on the wire: AdsLib's
    `AdsNotificationAttrib` documents 100 ns and pyads' `NotificationAttrib` sends
    `int(milliseconds * 1e4)` (the AMS spec page saying "unit is 1 ms" is wrong)."""

    index_group: int
    index_offset: int
    length: int
    trans_mode: int
    max_delay: int
    cycle_time: int


@dataclass(frozen=True, slots=True)
class DeleteNotificationRequest:
    handle: int


@dataclass(frozen=True, slots=True)
class ReadWriteRequest:
    index_group: int
    index_offset: int
    read_length: int
    data: bytes


@dataclass(frozen=True, slots=True)
class DeviceNotificationRequest:
    stamps: tuple[Stamp, ...]


@dataclass(frozen=True, slots=True)
class UnknownCommandRequest:
    command: int


Request = (
    ReadDeviceInfoRequest
    | ReadRequest
    | WriteRequest
    | ReadStateRequest
    | WriteControlRequest
    | AddNotificationRequest
    | DeleteNotificationRequest
    | ReadWriteRequest
    | DeviceNotificationRequest
    | UnknownCommandRequest
)

_U32 = struct.Struct("<I")
_U16 = struct.Struct("<H")
_IG_IO_LEN = struct.Struct("<III")
_READ_WRITE = struct.Struct("<IIII")
_WRITE_CONTROL = struct.Struct("<HHI")
_ADD_NOTIFICATION = struct.Struct("<IIIIII16s")


def _need(data: bytes, size: int, what: str, exact: bool = True) -> None:
    if len(data) < size or (exact and len(data) != size):
        raise PayloadError(
            AdsErrorCode.DEVICE_INVALIDSIZE,
            f"{what}: {len(data)} bytes of ADS data, expected {size}",
        )


def parse_request(packet: AmsPacket) -> Request:
    """Decode the ADS data of a request; `PayloadError` (0x705) when it does not fit.

    Request payloads (Beckhoff "ADS commands"): Read IG,IO,len; Write IG,IO,len,data;
    WriteControl adsState u16, devState u16, len, data; AddDeviceNotification IG,IO,len,
    transMode,maxDelay,cycleTime, reserved[16]; DeleteDeviceNotification handle; ReadWrite
    IG,IO,readLen,writeLen,data.
    """
    cmd, data = packet.header.command, packet.data
    if cmd == _READ:
        _need(data, 12, "Read")
        return ReadRequest(*_IG_IO_LEN.unpack(data))
    if cmd == Command.WRITE:
        _need(data, 12, "Write", exact=False)
        ig, io, length = _IG_IO_LEN.unpack_from(data)
        _need(data, 12 + length, "Write")
        return WriteRequest(ig, io, bytes(data[12:]))
    if cmd == Command.READ_WRITE:
        _need(data, 16, "ReadWrite", exact=False)
        ig, io, rlen, wlen = _READ_WRITE.unpack_from(data)
        _need(data, 16 + wlen, "ReadWrite")
        return ReadWriteRequest(ig, io, rlen, bytes(data[16:]))
    if cmd == Command.READ_DEVICE_INFO:
        return ReadDeviceInfoRequest()
    if cmd == Command.READ_STATE:
        return ReadStateRequest()
    if cmd == Command.ADD_DEVICE_NOTIFICATION:
        # TwinCAT ignores a short reserved tail; AdsLib always sends all 40 bytes.
        _need(data, 24, "AddDeviceNotification", exact=False)
        ig, io, length, mode, delay, cycle = struct.unpack_from("<IIIIII", data)
        return AddNotificationRequest(ig, io, length, mode, delay, cycle)
    if cmd == Command.DELETE_DEVICE_NOTIFICATION:
        _need(data, 4, "DeleteDeviceNotification")
        return DeleteNotificationRequest(_U32.unpack(data)[0])
    if cmd == Command.WRITE_CONTROL:
        _need(data, 8, "WriteControl", exact=False)
        st, dev, length = _WRITE_CONTROL.unpack_from(data)
        _need(data, 8 + length, "WriteControl")
        return WriteControlRequest(st, dev, bytes(data[8:]))
    if cmd == Command.DEVICE_NOTIFICATION:
        return DeviceNotificationRequest(tuple(parse_device_notification(data)))
    return UnknownCommandRequest(cmd)


# request payload builders (clients, tests, fuzzing)


def read_request(index_group: int, index_offset: int, length: int) -> bytes:
    return _IG_IO_LEN.pack(index_group, index_offset, length)


def write_request(index_group: int, index_offset: int, data: bytes) -> bytes:
    return _IG_IO_LEN.pack(index_group, index_offset, len(data)) + data


def read_write_request(index_group: int, index_offset: int, read_length: int, data: bytes) -> bytes:
    return _READ_WRITE.pack(index_group, index_offset, read_length, len(data)) + data


def add_notification_request(
    index_group: int,
    index_offset: int,
    length: int,
    trans_mode: int = TransMode.SERVERONCHA,
    max_delay: int = 0,
    cycle_time: int = 0,
) -> bytes:
    return _ADD_NOTIFICATION.pack(
        index_group, index_offset, length, trans_mode, max_delay, cycle_time, b""
    )


def delete_notification_request(handle: int) -> bytes:
    return _U32.pack(handle)


# ---------------------------------------------------------------------- responses


def result_response(result: int) -> bytes:
    """Write, WriteControl, DeleteDeviceNotification, unknown command: result u32."""
    return _U32.pack(result)


def read_response(result: int, data: bytes = b"") -> bytes:
    """Read and ReadWrite: result u32, length u32, data."""
    return struct.pack("<II", result, len(data)) + data


read_write_response = read_response


def read_state_response(result: int, ads_state: int = 0, device_state: int = 0) -> bytes:
    return struct.pack("<IHH", result, ads_state, device_state)


def read_device_info_response(
    result: int, major: int = 0, minor: int = 0, build: int = 0, name: str = ""
) -> bytes:
    """result u32, major u8, minor u8, build u16, device name char[16] (NUL padded)."""
    raw = name.encode("cp1252", errors="replace")[:15]
    return struct.pack("<IBBH16s", result, major & 0xFF, minor & 0xFF, build & 0xFFFF, raw)


def add_notification_response(result: int, handle: int = 0) -> bytes:
    return struct.pack("<II", result, handle)


def parse_result(data: bytes) -> int:
    """First u32 of a response payload (the ADS result)."""
    _need(data, 4, "response", exact=False)
    result: int = _U32.unpack_from(data)[0]
    return result


def parse_read_response(data: bytes) -> tuple[int, bytes]:
    """(result, data) of a Read/ReadWrite response."""
    _need(data, 8, "Read response", exact=False)
    result, length = struct.unpack_from("<II", data)
    _need(data, 8 + length, "Read response")
    return result, bytes(data[8:])


def parse_read_device_info_response(data: bytes) -> tuple[int, int, int, int, str]:
    _need(data, 24, "ReadDeviceInfo response")
    result, major, minor, build, name = struct.unpack("<IBBH16s", data)
    return result, major, minor, build, name.split(b"\0", 1)[0].decode("cp1252")


def parse_read_state_response(data: bytes) -> tuple[int, int, int]:
    _need(data, 8, "ReadState response")
    return struct.unpack("<IHH", data)


def parse_add_notification_response(data: bytes) -> tuple[int, int]:
    _need(data, 8, "AddDeviceNotification response")
    return struct.unpack("<II", data)


# ---------------------------------------------------------------------- notifications


@dataclass(frozen=True, slots=True)
class Sample:
    """One notification sample: handle and the value bytes (exactly the registered
    length — AdsLib drops the whole stamp when a sample size differs)."""

    handle: int
    data: bytes


@dataclass(frozen=True, slots=True)
class Stamp:
    """Samples taken at one moment; `timestamp` is a Windows FILETIME (100 ns since
    1601-01-01 UTC)."""

    timestamp: int
    samples: tuple[Sample, ...]


def unix_to_filetime(t: float) -> int:
    return round(t * 10_000_000) + FILETIME_UNIX_OFFSET


def filetime_to_unix(ft: int) -> float:
    return (ft - FILETIME_UNIX_OFFSET) / 10_000_000


def device_notification(stamps: Iterable[Stamp]) -> bytes:
    """DeviceNotification data: length u32, stamps u32, stamps × {timestamp u64,
    samples u32, samples × {handle u32, size u32, data}} (`length` counts what follows
    it, as AdsLib's `ReceiveNotification` checks)."""
    body = bytearray()
    count = 0
    for stamp in stamps:
        count += 1
        body += struct.pack("<QI", stamp.timestamp, len(stamp.samples))
        for s in stamp.samples:
            body += struct.pack("<II", s.handle, len(s.data))
            body += s.data
    return struct.pack("<II", len(body) + 4, count) + bytes(body)


def parse_device_notification(data: bytes) -> list[Stamp]:
    """Inverse of `device_notification`; PayloadError on any inconsistency."""
    _need(data, 8, "DeviceNotification", exact=False)
    length, count = struct.unpack_from("<II", data)
    _need(data, 4 + length, "DeviceNotification")
    pos = 8
    stamps: list[Stamp] = []
    for _ in range(count):
        _need(data, pos + 12, "DeviceNotification stamp", exact=False)
        ts, n = struct.unpack_from("<QI", data, pos)
        pos += 12
        samples = []
        for _ in range(n):
            _need(data, pos + 8, "DeviceNotification sample", exact=False)
            handle, size = struct.unpack_from("<II", data, pos)
            pos += 8
            _need(data, pos + size, "DeviceNotification sample data", exact=False)
            samples.append(Sample(handle, bytes(data[pos : pos + size])))
            pos += size
        stamps.append(Stamp(ts, tuple(samples)))
    if pos != len(data):
        raise PayloadError(AdsErrorCode.DEVICE_INVALIDSIZE, "DeviceNotification: trailing bytes")
    return stamps


# ---------------------------------------------------------------------- sum commands
#
# All sum commands are a ReadWrite to index group 0xF08x with index offset = n, the number
# of sub-requests (AdsDef.h comments; pyads `adsSumReadBytes`, `adsSumWriteBytes`):
#
#   0xF080 read        write n × {IG, IO, len}                -> n × result, data
#   0xF081 write       write n × {IG, IO, len} + data         -> n × result
#   0xF082 read-write  write n × {IG, IO, rlen, wlen} + data  -> n × {result, len}, data
#   0xF083 read-ex     write n × {IG, IO, len}                -> n × {result, len}, data
#                                                                (data at requested lengths)
#   0xF084 read-ex2    write n × {IG, IO, len}                -> n × {result, len}, data
#                                                                (data at returned lengths)
#
# In 0xF080/0xF083 each sub-result owns exactly its requested `len` bytes of the data
# area (pyads advances by the requested size even after an error), so a failed or shorter
# sub-read is zero-padded there. 0xF082/0xF084 concatenate only the returned data.

#: TwinCAT's documented limit is 500 sub-requests; accept more, but bound the work.
MAX_SUM_REQUESTS = 4096


@dataclass(frozen=True, slots=True)
class SubRead:
    index_group: int
    index_offset: int
    length: int


@dataclass(frozen=True, slots=True)
class SubWrite:
    index_group: int
    index_offset: int
    data: bytes


@dataclass(frozen=True, slots=True)
class SubReadWrite:
    index_group: int
    index_offset: int
    read_length: int
    data: bytes


def _check_count(count: int) -> None:
    if count > MAX_SUM_REQUESTS:
        raise PayloadError(
            AdsErrorCode.DEVICE_INVALIDSIZE,
            f"sum command with {count} sub-requests (limit {MAX_SUM_REQUESTS})",
        )


def parse_sum_read(count: int, data: bytes) -> list[SubRead]:
    _check_count(count)
    _need(data, 12 * count, "sum read")
    return [SubRead(*t) for t in _IG_IO_LEN.iter_unpack(data)] if count else []


def parse_sum_write(count: int, data: bytes) -> list[SubWrite]:
    _check_count(count)
    _need(data, 12 * count, "sum write", exact=False)
    heads = list(_IG_IO_LEN.iter_unpack(data[: 12 * count])) if count else []
    pos = 12 * count
    _need(data, pos + sum(h[2] for h in heads), "sum write")
    out = []
    for ig, io, length in heads:
        out.append(SubWrite(ig, io, bytes(data[pos : pos + length])))
        pos += length
    return out


def parse_sum_read_write(count: int, data: bytes) -> list[SubReadWrite]:
    _check_count(count)
    _need(data, 16 * count, "sum read-write", exact=False)
    heads = list(_READ_WRITE.iter_unpack(data[: 16 * count])) if count else []
    pos = 16 * count
    _need(data, pos + sum(h[3] for h in heads), "sum read-write")
    out = []
    for ig, io, rlen, wlen in heads:
        out.append(SubReadWrite(ig, io, rlen, bytes(data[pos : pos + wlen])))
        pos += wlen
    return out


def sum_read_response(results: Sequence[tuple[int, bytes]], lengths: Sequence[int]) -> bytes:
    """0xF080 read data: n × result u32, then for each sub-request exactly its requested
    length (its data, zero-padded; zeros after an error)."""
    head = b"".join(_U32.pack(code) for code, _ in results)
    body = b"".join(
        (b"" if code else data[:n]).ljust(n, b"\0")
        for (code, data), n in zip(results, lengths, strict=True)
    )
    return head + body


def sum_write_response(results: Sequence[int]) -> bytes:
    """0xF081 read data: n × result u32."""
    return b"".join(_U32.pack(code) for code in results)


def sum_read_ex_response(
    results: Sequence[tuple[int, bytes]], lengths: Sequence[int] | None = None
) -> bytes:
    """0xF082/0xF083/0xF084 read data: n × {result u32, length u32}, then the data —
    concatenated as returned, or (0xF083, `lengths` given) each in its requested length."""
    head = b"".join(struct.pack("<II", code, len(data)) for code, data in results)
    if lengths is None:
        return head + b"".join(data for _, data in results)
    return head + b"".join(
        data[:n].ljust(n, b"\0") for (_, data), n in zip(results, lengths, strict=True)
    )


def sum_read_request(items: Sequence[tuple[int, int, int]]) -> bytes:
    return b"".join(_IG_IO_LEN.pack(*it) for it in items)


def sum_write_request(items: Sequence[tuple[int, int, bytes]]) -> bytes:
    heads = b"".join(_IG_IO_LEN.pack(ig, io, len(d)) for ig, io, d in items)
    return heads + b"".join(d for _, _, d in items)


def sum_read_write_request(items: Sequence[tuple[int, int, int, bytes]]) -> bytes:
    heads = b"".join(_READ_WRITE.pack(ig, io, rl, len(d)) for ig, io, rl, d in items)
    return heads + b"".join(d for *_, d in items)


def parse_sum_read_response(data: bytes, lengths: Sequence[int]) -> list[tuple[int, bytes]]:
    n = len(lengths)
    _need(data, 4 * n + sum(lengths), "sum read response")
    codes = [c for (c,) in _U32.iter_unpack(data[: 4 * n])] if n else []
    out, pos = [], 4 * n
    for code, length in zip(codes, lengths, strict=True):
        out.append((code, bytes(data[pos : pos + length])))
        pos += length
    return out


def parse_sum_read_ex_response(data: bytes, count: int) -> list[tuple[int, bytes]]:
    _need(data, 8 * count, "sum read-ex response", exact=False)
    heads = list(struct.iter_unpack("<II", data[: 8 * count])) if count else []
    pos = 8 * count
    _need(data, pos + sum(h[1] for h in heads), "sum read-ex response")
    out = []
    for code, length in heads:
        out.append((code, bytes(data[pos : pos + length])))
        pos += length
    return out


__all__ = [
    "AMS_HEADER_SIZE",
    "AMS_TCP_HEADER_SIZE",
    "LARGEST_OBJECT",
    "MAX_FRAME",
    "MAX_REQUEST_DATA",
    "MAX_REQUEST_FRAME",
    "SUM_COMMAND_LIMIT",
    "AddNotificationRequest",
    "AdsState",
    "AmsAddr",
    "AmsHeader",
    "AmsPacket",
    "BadPacket",
    "Command",
    "DeleteNotificationRequest",
    "DeviceNotificationRequest",
    "Dropped",
    "FrameEvent",
    "Framer",
    "PayloadError",
    "ReadDeviceInfoRequest",
    "ReadRequest",
    "ReadStateRequest",
    "ReadWriteRequest",
    "Request",
    "Sample",
    "Stamp",
    "StateFlags",
    "StreamError",
    "SubRead",
    "SubReadWrite",
    "SubWrite",
    "SumGroup",
    "TransMode",
    "UnknownCommandRequest",
    "WriteControlRequest",
    "WriteRequest",
]
