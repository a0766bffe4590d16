"""ADS discovery and add-route over UDP port 48899 (sans-I/O).

What TwinCAT's system service answers on UDP 48899 and what pyads'
`adsGetNetIdForPLC` / `add_route_to_plc` and TwinCAT's "Search (Ethernet)" send. Every
datagram is

    magic u32 0x71146603 | invoke id u32 | service u32 | AMS NetId (6) | AMS port u16 |
    tag count u32 | tags: id u16, length u16, data

(little-endian; a response has bit 31 of the service set). Services: 1 discovery, 6 add
route. Tags answered: 1 status (u32 ADS error code), 3 TwinCAT version (major u8, minor u8,
build u16), 5 host name (tag 4, Windows' OS version structure, is left out). The
request's tags are read generously (a bad one ends the list); nothing but `UdpError` is
raised on garbage.

Add-route carries the target's user name (tag 13) and password (tag 2), NUL-terminated
(pyads' `adsAddRouteToPLC`). It is accepted only when both equal the credentials given at
start (`geo-server run --ads-route-user/--ads-route-password`, compared in constant time);
without those, every add-route is refused. The refusal is status 0x704
(ADSERR_DEVICE_INVALIDACCESS, 1796): what a TwinCAT 3 router answers to a wrong user name
or password — captured as `04 07 00 00` in the status tag (stlehmann/pyads issue #460; the
ADS library's `AddRemoteRoute` reads that status the same way). pyads' own
`add_route_to_plc` expects the failure one byte off and raises "Unexpected response from
PLC" for it, as it does against a real router.
"""

from __future__ import annotations

import hmac
import struct
from dataclasses import dataclass, field

from geo_server.errors import GeoError
from geo_server.transports.ads.codec import SYSTEM_SERVICE_PORT, netid_from_bytes, netid_to_bytes

MAGIC = 0x71146603
SERVICE_DISCOVERY = 1
SERVICE_ADD_ROUTE = 6
RESPONSE = 0x8000_0000
TAG_STATUS = 1
TAG_PASSWORD = 2
TAG_USER = 13
#: The status of a refused add-route: what TwinCAT answers to wrong credentials
#: (ADSERR_DEVICE_INVALIDACCESS; module docstring).
ROUTE_REFUSED = 0x704
TAG_TC_VERSION = 3
TAG_HOST_NAME = 5
#: Largest datagram looked at (an add-route request is about 100 bytes).
MAX_DATAGRAM = 2048

_HEAD = struct.Struct("<III6sH")


class UdpError(GeoError, ValueError):
    """A datagram that is not an ADS UDP request (dropped, nothing is answered)."""


@dataclass(frozen=True)
class UdpRequest:
    invoke_id: int
    service: int
    sender: str  # AMS NetId of the sender
    tags: dict[int, bytes] = field(default_factory=dict)


def parse(datagram: bytes) -> UdpRequest:
    """Header and tags of a request; `UdpError` for anything else (responses included)."""
    if len(datagram) > MAX_DATAGRAM:
        raise UdpError(f"{len(datagram)} bytes: larger than any ADS UDP request")
    if len(datagram) < _HEAD.size:
        raise UdpError(f"{len(datagram)} bytes: shorter than the ADS UDP header")
    magic, invoke, service, netid, _port = _HEAD.unpack_from(datagram)
    if magic != MAGIC:
        raise UdpError(f"magic 0x{magic:08X} is not ADS UDP")
    if service & RESPONSE:
        raise UdpError("a response, not a request")
    return UdpRequest(invoke, service, netid_from_bytes(netid), _tags(datagram[_HEAD.size :]))


def _tags(rest: bytes) -> dict[int, bytes]:
    """Tag id -> data, read as far as the bytes are consistent (the count is advisory:
    pyads' add-route request does not carry one)."""
    tags: dict[int, bytes] = {}
    pos = 4 if len(rest) >= 4 else len(rest)  # skip the tag count
    while pos + 4 <= len(rest):
        tag, length = struct.unpack_from("<HH", rest, pos)
        if pos + 4 + length > len(rest):
            break
        tags.setdefault(tag, rest[pos + 4 : pos + 4 + length])
        pos += 4 + length
    return tags


def _tag(tag: int, data: bytes) -> bytes:
    return struct.pack("<HH", tag, len(data)) + data


def _response(req: UdpRequest, netid: str, tags: list[bytes]) -> bytes:
    head = _HEAD.pack(
        MAGIC, req.invoke_id, req.service | RESPONSE, netid_to_bytes(netid), SYSTEM_SERVICE_PORT
    )
    return head + struct.pack("<I", len(tags)) + b"".join(tags)


def discovery_response(
    req: UdpRequest, netid: str, host_name: str, version: tuple[int, int, int]
) -> bytes:
    """Who we are: NetId in the header, host name and version as tags (real captures,
    e.g. nmap's twincat-scan: tag 3 `03 01 b8 0f` = 3.1.4024)."""
    major, minor, build = version
    return _response(
        req,
        netid,
        [
            _tag(TAG_HOST_NAME, host_name.encode("utf-8")[:255] + b"\0"),
            _tag(TAG_TC_VERSION, struct.pack("<BBH", major & 0xFF, minor & 0xFF, build & 0xFFFF)),
        ],
    )


def add_route_response(req: UdpRequest, netid: str, error: int = 0) -> bytes:
    """The route is taken (status 0) or refused (`error`, an ADS code)."""
    return _response(req, netid, [_tag(TAG_STATUS, struct.pack("<I", error))])


def _text(tags: dict[int, bytes], tag: int) -> bytes:
    return tags.get(tag, b"").split(b"\0", 1)[0]


def route_allowed(req: UdpRequest, user: str | None, password: str | None) -> bool:
    """Does add-route `req` carry exactly the credentials configured at start? Never
    without them (None). Both are compared whatever the first gives, in constant time."""
    if user is None or password is None:
        return False
    user_ok = hmac.compare_digest(_text(req.tags, TAG_USER), user.encode("utf-8"))
    password_ok = hmac.compare_digest(_text(req.tags, TAG_PASSWORD), password.encode("utf-8"))
    return user_ok and password_ok


def answer(
    datagram: bytes,
    netid: str,
    host_name: str,
    version: tuple[int, int, int],
    route_user: str | None = None,
    route_password: str | None = None,
) -> bytes:
    """The response to one datagram; `UdpError` when there is nothing to answer.

    An add-route request is accepted (status 0) only with the credentials given at start
    (`route_allowed`), else refused with `ROUTE_REFUSED`. Nothing else changes either
    way: geo-server answers every NetId on its TCP port."""
    req = parse(datagram)
    if req.service == SERVICE_DISCOVERY:
        return discovery_response(req, netid, host_name, version)
    if req.service == SERVICE_ADD_ROUTE:
        ok = route_allowed(req, route_user, route_password)
        return add_route_response(req, netid, 0 if ok else ROUTE_REFUSED)
    raise UdpError(f"service {req.service} is not answered")
