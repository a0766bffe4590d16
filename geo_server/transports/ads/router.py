"""The AMS router's part of the port (docs/design.md §9): AMS/TCP router commands
(jisotalo/ads-client `registerAdsPort`). A client without a router of its own asks ours
for an AMS port (0x1000) and gets our NetId with a port of its own; 0x0001 gives the
port back (the connection closes, as TwinCAT's router does); 0x1002 asks for the NetId.
Anything else is dropped. Sans-I/O: `answer` returns the frame to send, or None.
"""

from __future__ import annotations

from geo_server.dictionary import AMS_PORTS
from geo_server.errors import AdsErrorCode
from geo_server.transports.ads import codec
from geo_server.transports.ads.codec import SYSTEM_SERVICE_PORT, PayloadError
from geo_server.transports.ads.connection import Connection

#: AMS ports the router hands to clients (TwinCAT's ADS clients get 30000 and up).
FIRST_CLIENT_PORT, LAST_CLIENT_PORT = 32768, 65535
_RESERVED_PORTS = frozenset({*AMS_PORTS, SYSTEM_SERVICE_PORT})

#: What a router command asks of the connection besides its answer.
CLOSE = "close"


class Router:
    """The AMS ports handed out by port connect (0x1000), and their connections."""

    def __init__(self, netid: str, ams_ports: tuple[int, ...]) -> None:
        self.netid = netid
        self._reserved = _RESERVED_PORTS | set(ams_ports)
        self._ports: dict[int, Connection] = {}
        self._next = FIRST_CLIENT_PORT

    def answer(self, conn: Connection, cmd: codec.RouterCommand) -> bytes | str:
        """The answer frame to `cmd`, or `CLOSE` (port close). PayloadError for a
        command the router does not take (the caller drops and counts it)."""
        if cmd.command == codec.AMS_TCP_PORT_CONNECT:
            port = self._assign(conn, codec.parse_router_port(cmd))
            return codec.port_connect_response(self.netid, port)
        if cmd.command == codec.AMS_TCP_PORT_CLOSE:
            codec.parse_router_port(cmd)
            self.release(conn)
            return CLOSE
        if cmd.command == codec.AMS_TCP_GET_LOCAL_NETID:
            return codec.local_netid_response(self.netid)
        raise PayloadError(AdsErrorCode.DEVICE_SRVNOTSUPP, "router note from a client")

    def release(self, conn: Connection) -> None:
        """`conn` gave its port back or closed."""
        if conn.ams_port is not None:
            self._ports.pop(conn.ams_port, None)
            conn.ams_port = None

    def _assign(self, conn: Connection, wanted: int) -> int:
        """The port a client asked for when it is free, else the next free one."""
        if conn.ams_port is not None:
            return conn.ams_port  # asked twice: the same answer
        port = wanted
        taken = self._ports
        reserved = self._reserved
        if not port or port in taken or port in reserved:
            # at most max_connections ports are taken: a free one is found within that many
            port = self._next
            while port in taken or port in reserved:
                port = port + 1 if port < LAST_CLIENT_PORT else FIRST_CLIENT_PORT
            self._next = port + 1 if port < LAST_CLIENT_PORT else FIRST_CLIENT_PORT
        self._ports[port] = conn
        conn.ams_port = port
        return port
