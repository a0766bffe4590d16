"""What keeps the web HMI safe in a browser (docs/web.md §4): one aiohttp middleware in
front of every route of the page, its API, its WebSocket and, in a fleet, every
machine's sub-application.

A browser lets any page the user visits send requests to the HMI's port: plain GETs,
and POSTs with a `text/plain` or form body that need no CORS preflight. A DNS-rebinding
page even reads the answers, under a name of its own that resolves to 127.0.0.1. So:

- `Host` must be an address of this server (`Guard.host_ok`): the bound `host:port`,
  its loopback equivalents when bound to loopback, any IP literal at the bound port when
  bound to every address, and the names given with `--http-allowed-hosts`. A rebinding
  page sends its own name: refused (421) before anything is read or written.
- With `--http-user/--http-password`, HTTP Basic authentication on every request (401).
- A POST or WebSocket upgrade whose `Origin` is present and not the page's own
  (`scheme://Host`): 403.
- A POST must be `application/json` (415): a cross-origin page cannot send that type
  without a preflight, which is never granted.
- A POST must carry the run's secret token in `X-Geo-Token` (403): the page takes it
  from the URL printed at start. Compared in constant time.
"""

from __future__ import annotations

import base64
import binascii
import hmac
import ipaddress
from collections.abc import Awaitable, Callable, Iterable
from urllib.parse import urlsplit

from aiohttp import hdrs, web

#: The request header that carries the write token.
TOKEN_HEADER = "X-Geo-Token"
#: Methods that change nothing (no token, no Origin check).
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
_LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


def refusal(status: int, message: str, **headers: str) -> web.Response:
    """A refusal of the guard: HTTP `status` with `{"ok": false, "status", "message"}`
    (the page shows the message)."""
    return web.json_response(
        {"ok": False, "status": status, "message": message}, status=status, headers=headers
    )


def _split(hostport: str) -> tuple[str, str]:
    """`host:port` (`[v6]:port`) -> (host, port); no port -> (host, "")."""
    if hostport.startswith("["):
        host, _, rest = hostport.partition("]")
        return host + "]", rest[1:] if rest.startswith(":") else ""
    host, sep, port = hostport.rpartition(":")
    return (host, port) if sep and port.isdigit() else (hostport, "")


def _netloc(origin: str) -> str:
    """`host:port` of an Origin header ("" for `null` or nonsense)."""
    try:
        return urlsplit(origin).netloc.lower()
    except ValueError:
        return ""


def _ip(host: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address | None:
    try:
        return ipaddress.ip_address(host.strip("[]"))
    except ValueError:
        return None


class Guard:
    """The checks of this module for one server; `bind_to` once the port is bound."""

    def __init__(
        self,
        token: str,
        allowed_hosts: Iterable[str] = (),
        user: str = "",
        password: str = "",
        max_body: int = 0,
    ) -> None:
        self.token = token.encode()
        #: a body announced larger than this is refused before a byte of it is read
        #: (0: no bound here; aiohttp's `client_max_size` still stops the reading)
        self.max_body = max_body
        self._extra = [h.strip().lower() for h in allowed_hosts if h.strip()]
        self._auth = (user.encode(), password.encode()) if user else None
        self.hosts: frozenset[str] = frozenset()
        self._any_ip_port = ""  # bound to every address: any IP literal at this port

    def bind_to(self, address: str) -> None:
        """The Host values accepted for a server bound at `address` (`host:port`)."""
        host, port = _split(address.lower())
        names = {host}
        ip = _ip(host)
        if (ip is not None and ip.is_loopback) or host == "localhost":
            names.update(_LOOPBACK_NAMES)
        hosts = {f"{n}:{port}" for n in names}
        if port == "80":  # a browser leaves the default port out of Host
            hosts |= names
        for entry in self._extra:
            name, entry_port = _split(entry)
            # a name without a port: at the bound port, or as a proxy forwards it (none)
            hosts |= {entry} if entry_port else {name, f"{name}:{port}"}
        self.hosts = frozenset(hosts)
        self._any_ip_port = port if ip is not None and ip.is_unspecified else ""

    def host_ok(self, host: str) -> bool:
        """Is `host` (a Host header, lowercase) an address of this server?"""
        if host in self.hosts:
            return True
        if self._any_ip_port:
            name, port = _split(host)
            return port == self._any_ip_port and _ip(name) is not None
        return False

    def _user_ok(self, request: web.Request) -> bool:
        assert self._auth is not None
        scheme, _, encoded = request.headers.get(hdrs.AUTHORIZATION, "").partition(" ")
        try:
            given = base64.b64decode(encoded.strip(), validate=True)
        except (binascii.Error, ValueError):
            return False
        login, _, password = given.partition(b":")
        user, secret = self._auth
        # both compared, always: the time taken says nothing about which one is wrong
        ok_user = hmac.compare_digest(login, user)
        ok_password = hmac.compare_digest(password, secret)
        return scheme.lower() == "basic" and ok_user and ok_password

    @web.middleware
    async def middleware(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        """The checks, in order, before any handler (and before a body is read)."""
        host = request.headers.get(hdrs.HOST, "").lower()
        if not self.host_ok(host):
            return refusal(
                421,
                f"Host {host[:100]!r} is not an address of this server; open it by the "
                "address it printed, or name this one with --http-allowed-hosts",
            )
        if self._auth is not None and not self._user_ok(request):
            return refusal(
                401,
                "user name and password needed (--http-user)",
                **{hdrs.WWW_AUTHENTICATE: 'Basic realm="geo-server", charset="UTF-8"'},
            )
        writes = request.method not in SAFE_METHODS
        upgrade = request.headers.get(hdrs.UPGRADE, "").lower() == "websocket"
        origin = request.headers.get(hdrs.ORIGIN)
        # the page's own origin is this Host: compared by host and port, the scheme left
        # aside (a proxy in front may terminate TLS)
        if (writes or upgrade) and origin is not None and _netloc(origin) != host:
            return refusal(403, f"requests from {origin[:100]!r} are not accepted")
        if writes:
            size = request.content_length
            if self.max_body and size is not None and size > self.max_body:
                # refused on its Content-Length, the connection closed: reading (and
                # discarding) a megabyte per request would be the attacker's lever
                response = refusal(
                    413, f"a body of {size} bytes; at most {self.max_body} are accepted"
                )
                response.force_close()
                return response
            if request.content_type != "application/json":
                return refusal(
                    415, f"the body must be application/json, not {request.content_type!r}"
                )
            given = request.headers.get(TOKEN_HEADER, "").encode("utf-8", "surrogateescape")
            if not hmac.compare_digest(given, self.token):
                return refusal(
                    403,
                    "this needs the token of the URL the server printed at start "
                    "(open the page by that URL: …/?token=…)",
                )
        return await handler(request)
