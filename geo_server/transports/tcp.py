"""What the TCP interfaces (Modbus, ADS) share: one listening socket and the connections
it admitted, capped.

A connection beyond `max_connections` is closed at once, before it can make the server
buffer anything, and counted in `refused`; `close()` stops listening and drops every
connection. The protocol classes call `admit` from `connection_made` and `forget` from
`connection_lost`.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Protocol


class Connection(Protocol):
    def abort(self) -> None: ...


class Listener:
    """A listening TCP socket and the connections it admitted."""

    def __init__(self, host: str, port: int, max_connections: int) -> None:
        self.host = host
        self.requested_port = port
        self.max_connections = max_connections
        self.connections: set[Connection] = set()
        self.refused = 0
        self._server: asyncio.Server | None = None

    async def listen(self, factory: Callable[[], asyncio.Protocol]) -> None:
        loop = asyncio.get_running_loop()
        self._server = await loop.create_server(factory, self.host, self.requested_port)

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


__all__ = ["Connection", "Listener"]
