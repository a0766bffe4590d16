"""What the service modules of the ADS interface see of the server (docs/design.md §9):
`Device`, one machine behind the port, and `Port`, what a connection sees of the server
that listens. Typing only — the service modules never import `server`, which imports
them.
"""

from __future__ import annotations

import asyncio
from collections.abc import Sized
from typing import Any, Protocol

from geo_server.service import ObjectService
from geo_server.transports.ads.codec import AmsHeader, AmsPacket, RouterCommand
from geo_server.transports.ads.notifications import NotificationTable
from geo_server.transports.ads.options import AdsOptions, AdsStats
from geo_server.transports.ads.symbols import SymbolTable
from geo_server.transports.share import LoopShare


class Device(Protocol):
    """One machine served under its AMS NetId (`server.AdsServer`)."""

    service: ObjectService
    options: AdsOptions
    stats: AdsStats
    notifications: NotificationTable
    #: symbol handles held at this machine; at the head: at every machine of the port
    handles_held: int
    fleet_handles: int
    version: tuple[int, int, int]
    loop: asyncio.AbstractEventLoop | None
    #: notification sampling (`sampling.Sampler`)
    sampler: Any
    #: the machine's share of the loop in a fleet (None: no limit)
    share: LoopShare | None

    @property
    def head(self) -> Device:
        """The server that listens (the device itself when alone)."""

    @property
    def devices(self) -> Sized:
        """The machines behind the port (at the head)."""

    @property
    def symbols(self) -> SymbolTable: ...

    def respond(self, conn: Any, h: AmsHeader, payload: bytes) -> None: ...

    def serve_packet(self, conn: Any, packet: AmsPacket) -> None: ...


class Port(Protocol):
    """What a connection sees of the server that listens (`server.AdsServer`)."""

    options: AdsOptions
    stats: AdsStats
    loop: asyncio.AbstractEventLoop | None
    #: some machine behind the port has a share of the loop (a fleet)
    shared: bool

    @property
    def connection_count(self) -> int: ...

    def connected(self, conn: Any) -> bool: ...

    def disconnected(self, conn: Any) -> None: ...

    def take_turn(self, packet: AmsPacket, shares: list[LoopShare]) -> float | None: ...
    def repeat(self, conn: Any, frame: bytes) -> bool: ...

    def handle_packet(self, conn: Any, packet: AmsPacket) -> None: ...

    def handle_router(self, conn: Any, cmd: RouterCommand) -> None: ...

    def answer_datagram(self, data: bytes) -> bytes | None: ...
