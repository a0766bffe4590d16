"""What the TCP interfaces (Modbus, ADS) share: one listening socket and the connections
it admitted, capped.

A connection beyond `max_connections` is closed at once, before it can make the server
buffer anything, and counted in `refused`; `close()` stops listening and drops every
connection. The protocol classes call `admit` from `connection_made` and `forget` from
`connection_lost`; `Gate` does it for a protocol that knows nothing of the cap (the web
HMI's aiohttp handlers).

Every listener of the server listens with `BACKLOG`: with the caps it bounds the
descriptors one interface can take (geo_server/descriptors.py).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any, Protocol

log = logging.getLogger(__name__)

#: Connections a listening socket may have accepted and not yet closed or admitted:
#: the `backlog` of `loop.create_server` (asyncio accepts up to that many in one event
#: loop step). Counted in the descriptor budget beside each interface's cap.
BACKLOG = 100


class Connection(Protocol):
    def abort(self) -> None: ...


class Listener:
    """A listening TCP socket and the connections it admitted."""

    def __init__(self, host: str, port: int, max_connections: int, backlog: int = BACKLOG) -> None:
        self.host = host
        self.requested_port = port
        self.max_connections = max_connections
        self.backlog = backlog
        self.connections: set[Connection] = set()
        self.refused = 0
        self._server: asyncio.Server | None = None

    async def listen(self, factory: Callable[[], asyncio.Protocol]) -> None:
        loop = asyncio.get_running_loop()
        self._server = await loop.create_server(
            factory, self.host, self.requested_port, backlog=self.backlog
        )

    async def close(self) -> None:
        """Stop listening and drop every connection."""
        if self._server is None:
            return
        server, self._server = self._server, None
        server.close()
        for conn in list(self.connections):
            conn.abort()
        await server.wait_closed()

    @property
    def listening(self) -> bool:
        return self._server is not None

    @property
    def port(self) -> int:
        """The bound TCP port (useful with port 0: an ephemeral one)."""
        if self._server is None or not self._server.sockets:
            return self.requested_port
        return int(self._server.sockets[0].getsockname()[1])

    @property
    def endpoint(self) -> str:
        return f"{self.host}:{self.port}"

    def admit(self, conn: Connection) -> bool:
        """True: `conn` is registered. False: `max_connections` are open (the caller
        closes it at once)."""
        if len(self.connections) >= self.max_connections:
            self.refused += 1
            return False
        self.connections.add(conn)
        return True

    def forget(self, conn: Connection) -> None:
        self.connections.discard(conn)

    def say_refused(self, label: str, peer: object) -> None:
        """Log a refused connection: a warning for the 1st, 2nd, 4th, 8th… refusal,
        debug otherwise — a flood of connections must not become a flood of log lines."""
        n = self.refused
        level = logging.WARNING if n & (n - 1) == 0 else logging.DEBUG
        log.log(
            level,
            "%s: refusing %s: %d connections open (%d refused so far)",
            label,
            peer,
            len(self.connections),
            n,
        )


class Gate(asyncio.Protocol):
    """The protocol of one accepted connection, made by `factory` only once `listener`
    admits the connection: past its cap the connection is aborted before the protocol
    exists (so before it can start a task or buffer a byte). Every other event is passed
    on as it comes."""

    def __init__(
        self, listener: Listener, factory: Callable[[], asyncio.Protocol], label: str = "http"
    ) -> None:
        self._listener = listener
        self._label = label
        self._factory = factory
        self._inner: asyncio.Protocol | None = None
        self._transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        tcp: Any = transport
        if not self._listener.admit(tcp):
            self._listener.say_refused(self._label, tcp.get_extra_info("peername"))
            tcp.abort()
            return
        self._transport = tcp
        self._inner = self._factory()
        self._inner.connection_made(transport)

    def connection_lost(self, exc: Exception | None) -> None:
        if self._inner is None or self._transport is None:
            return
        self._listener.forget(self._transport)
        self._inner.connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self._inner is not None:
            self._inner.data_received(data)

    def eof_received(self) -> bool | None:
        return self._inner.eof_received() if self._inner is not None else None

    def pause_writing(self) -> None:
        if self._inner is not None:
            self._inner.pause_writing()

    def resume_writing(self) -> None:
        if self._inner is not None:
            self._inner.resume_writing()


__all__ = ["BACKLOG", "Connection", "Gate", "Listener"]
