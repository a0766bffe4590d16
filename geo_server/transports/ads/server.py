"""ADS over AMS/TCP (docs/design.md §9): a thin asyncio shell over the codec and the object service.

One `asyncio.Protocol` per TCP connection feeds received bytes into a `codec.Framer`,
dispatches each complete request to `AdsServer.handle_packet`, and writes the response
frames. Reads are answered synchronously from the published snapshot; writes are
validated at once (0x702…0x706) and applied by the GEO cycle at the next boundary — with
running cycles the response waits until the write was applied, in stepped mode it is
acknowledged as soon as it is queued (nobody runs the cycle until the test steps).

Served (Beckhoff "ADS commands"): ReadDeviceInfo, Read, Write, ReadState,
ReadWrite (incl. sum commands 0xF080 read, 0xF081 write, 0xF082 read-write, 0xF083
read-ex, 0xF084 read-ex2), AddDeviceNotification, DeleteDeviceNotification and
server-sent DeviceNotification. WriteControl and unknown commands answer 0x701. A request
for another AMS port than 551 gets AMS error 0x6 (target port not found) in the AMS
header with an empty payload — AdsLib returns a non-zero AMS header error code as is.

Robustness: partial and coalesced TCP segments are reassembled; a frame that is too short
or inconsistent is answered (0xE invalid AMS length) or skipped; only an AMS/TCP length
beyond `max_frame` (the largest legal request) or an unknown AMS/TCP header kind closes
that connection. A failing handler answers 0x700 and is logged; other connections are
never affected. What clients can make the server hold is bounded: `max_connections`
(one more is closed at once), `max_frame` per unfinished frame, which must complete within
`incomplete_frame_timeout`, and `max_notifications` per connection / in total; notification
sampling yields the event loop after `sample_budget` seconds.

The pieces beside it (docs/design.md §1.2): `connection` (sans-I/O: bytes in, typed
events out, replies to bytes), `protocol` (the asyncio connection), one module per AMS
service — `router` (AMS/TCP port connect), `system` (port 10000), `tasks` (the GEO task
551 and the COM task 553), `handles` (symbols and handles), `sums` (sum commands),
`writes`, `sampling` (notifications on the loop over `notifications`' table) — and
`faulting` (injected faults). This module admits connections and routes each request
to its machine and service.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable
from dataclasses import replace
from typing import cast

from geo_server.dictionary import GEO_AMS_PORT
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.service import ObjectService
from geo_server.transports.ads import discovery, repeats, symbols
from geo_server.transports.ads.codec import (
    SYSTEM_SERVICE_PORT,
    AmsHeader,
    AmsPacket,
    Command,
    PayloadError,
    RouterCommand,
)
from geo_server.transports.ads.connection import Reply, error_payload
from geo_server.transports.ads.faulting import faulted
from geo_server.transports.ads.notifications import NotificationPool, NotificationTable
from geo_server.transports.ads.options import HANDOFF_MAX, AdsOptions, AdsStats, server_version
from geo_server.transports.ads.protocol import AdsConnection, DiscoveryProtocol, log_rarely
from geo_server.transports.ads.router import CLOSE, Router
from geo_server.transports.ads.sampling import Sampler
from geo_server.transports.ads.system import serve_system
from geo_server.transports.ads.tasks import serve_task
from geo_server.transports.share import STATUS_KEY, LoopShare
from geo_server.transports.tcp import Listener

log = logging.getLogger(__name__)
#: (a module int: an IntEnum member costs a class attribute lookup per request)
_NOTIFICATION = int(Command.DEVICE_NOTIFICATION)


class AdsServer:
    """Serve one `ObjectService` over ADS/AMS-TCP."""

    def __init__(
        self,
        service: ObjectService,
        options: AdsOptions | None = None,
        router: AdsServer | None = None,
        share: LoopShare | None = None,
    ) -> None:
        """`router`: the server that owns the TCP port and routes requests for this
        server's NetId to it (a fleet: one machine per NetId, `add_device`); None: this
        server listens itself. `share`: the machine's share of the event loop in a fleet
        (`transports.share`; its Modbus interface charges the same one), None: no
        limit."""
        self.service = service
        self.share = share
        #: some machine behind the port has a loop share (at the head: time the batches)
        self.shared = share is not None
        if share is not None:
            service.status_extra[STATUS_KEY] = share.status
        self.options = options or AdsOptions()
        self.router = router
        #: the devices this server routes to, by AMS NetId (itself included)
        self.devices: dict[str, AdsServer] = {self.options.netid: self}
        self.stats = AdsStats()
        #: the server that listens (itself when alone): it holds the port's totals
        self.head: AdsServer = router if router is not None else self
        self.notifications: NotificationTable = NotificationTable(
            self.service.read,
            service.info.cycle_s,
            self.options.max_notifications,
            self.options.max_notifications_total,
            pool=(
                router.notifications.pool
                if router is not None
                else NotificationPool(self.options.max_notifications_fleet)
            ),
        )
        self.sampler = Sampler(self)
        self.listener = Listener(self.options.host, self.options.port, self.options.max_connections)
        #: the AMS router of the port (port connect; the head's serves)
        self.ams_router = Router(self.options.netid, self.options.ams_ports)
        #: connections that sent this machine a request (`max_connections`)
        self._attached: set[AdsConnection] = set()
        #: symbol handles held here, by every connection (and at the head: fleet-wide)
        self.handles_held = 0
        self.fleet_handles = 0
        # requests served in this loop step (`take_turn`)
        self._served = 0
        self._step_reset = False
        self.loop: asyncio.AbstractEventLoop | None = None
        self._unsubscribe: Callable[[], None] | None = None
        #: (major, minor, build) of ReadDeviceInfo
        self.version = server_version()
        self._symbols: symbols.SymbolTable | None = None
        self._udp: asyncio.DatagramTransport | None = None
        #: why discovery is off although a UDP port was asked for ("" when it runs)
        self.udp_error: str = ""

    # ------------------------------------------------------------------ lifecycle

    def add_device(
        self, service: ObjectService, options: AdsOptions, share: LoopShare | None = None
    ) -> AdsServer:
        """Serve another machine on this server's TCP port under its own AMS NetId, as a
        TwinCAT router routes by target NetId (SPEC §13: a fleet), with its own share of
        the loop (`share`, None: no limit). Start and close it with this one (add
        devices before `start`)."""
        if self.loop is not None:
            raise RuntimeError("add_device() before start()")
        if options.netid in self.devices:
            raise ValueError(f"AMS NetId {options.netid} is served already")
        device = AdsServer(service, options, router=self, share=share)
        self.shared = self.shared or share is not None
        self.devices[options.netid] = device
        # several NetIds behind one port: requests for any other get 0x7, and the port
        # admits the fleet's connections (each machine still at most `max_connections`)
        self.options = replace(self.options, strict_netid=True)
        self.listener.max_connections = max(
            self.options.max_connections, self.options.max_connections_fleet
        )
        return device

    async def start(self) -> None:
        """Listen and subscribe to the GEO cycle (for notifications); a routed device
        only subscribes (its router listens)."""
        self.loop = asyncio.get_running_loop()
        if self.router is not None:
            self._unsubscribe = self.service.subscribe(self.sampler.on_cycle_thread)
            return
        for device in self.devices.values():
            if device is not self:
                await device.start()
        await self.listener.listen(lambda: AdsConnection(self))
        if self.options.udp_port is not None:
            # Discovery is a convenience: with its port taken (another emulator or a
            # TwinCAT router on this host) the ADS interface still starts, without it.
            try:
                transport, _ = await self.loop.create_datagram_endpoint(
                    lambda: DiscoveryProtocol(self),
                    local_addr=(self.options.host, self.options.udp_port),
                )
            except OSError as exc:
                self.udp_error = f"UDP {self.options.host}:{self.options.udp_port}: {exc.strerror}"
                log.warning("ADS discovery off: %s", self.udp_error)
            else:
                self._udp = transport
        self._unsubscribe = self.service.subscribe(self.sampler.on_cycle_thread)
        log.info("ADS listening on %s:%d as %s", self.options.host, self.port, self.options.netid)

    async def close(self) -> None:
        """Stop listening, drop every connection and notification."""
        for device in self.devices.values():
            if device is not self:
                await device.close()
        if self._unsubscribe is not None:
            with contextlib.suppress(ValueError):
                self._unsubscribe()
            self._unsubscribe = None
        self.sampler.stop()
        if self._udp is not None:
            self._udp.close()
            self._udp = None
        if self.router is None:
            await self.listener.close()

    async def __aenter__(self) -> AdsServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    @property
    def port(self) -> int:
        """The bound TCP port (useful with `port=0`)."""
        return self.listener.port

    @property
    def address(self) -> str:
        """`host:port` as pyads' `Connection(netid, 551, address)` wants it."""
        return self.listener.endpoint

    @property
    def udp_port(self) -> int | None:
        """The bound UDP port of discovery (None when off)."""
        if self._udp is None:
            return None
        return int(self._udp.get_extra_info("sockname")[1])

    def answer_datagram(self, data: bytes) -> bytes | None:
        """The answer to one UDP datagram (discovery, add route), None to stay silent."""
        try:
            reply = discovery.answer(
                data,
                self.options.netid,
                self.options.host_name,
                self.version,
                self.options.route_user,
                self.options.route_password,
            )
        except discovery.UdpError as exc:
            self.stats.udp_dropped += 1
            log.debug("ADS UDP datagram dropped: %s", exc)
            return None
        self.stats.udp_answered += 1
        return reply

    @property
    def connection_count(self) -> int:
        return len(self.listener.connections)

    # ------------------------------------------------------------------ dispatch

    @property
    def symbols(self) -> symbols.SymbolTable:
        """The machine's symbol table (built on first use: the axes are fixed)."""
        if self._symbols is None:
            self._symbols = symbols.SymbolTable(
                self.service.info.dictionary, self.service.info.axis_names()
            )
        return self._symbols

    # ------------------------------------------------------------------ dispatch

    def handle_packet(self, conn: AdsConnection, packet: AmsPacket) -> None:
        """Answer one request on `conn` (never raises)."""
        h = packet.header
        if h.is_response or h.command == _NOTIFICATION:
            # A response or a notification sent to us: there is nothing to answer.
            self.stats.dropped_frames += 1
            return
        device = self.devices.get(h.target.netid, self)
        if device is not self:
            device.handle_packet(conn, packet)
            return
        self.stats.requests += 1
        if self.service.faults.active and faulted(self, conn, packet):
            return
        self.serve_packet(conn, packet)

    def serve_packet(self, conn: AdsConnection, packet: AmsPacket) -> None:
        """Answer one request addressed to this device (no fault decided any more): the
        service of its AMS port answers, the port passed along explicitly."""
        h = packet.header
        if self.options.strict_netid and h.target.netid != self.options.netid:
            self.stats.errors += 1
            conn.send(conn.refusal(h, AdsErrorCode.TARGET_MACHINE_NOT_FOUND))
            return
        if conn not in self._attached and not self._attach(conn):
            self.respond(conn, h, error_payload(h.command, AdsErrorCode.DEVICE_NOMOREHDLS))
            return
        port = h.target.port
        if port == SYSTEM_SERVICE_PORT:
            self._answer(conn, h, lambda: serve_system(self, conn, packet))
            return
        if port not in self.options.ams_ports:
            self.stats.errors += 1
            conn.send(conn.refusal(h, AdsErrorCode.TARGET_PORT_NOT_FOUND))
            return
        self._answer(conn, h, lambda: serve_task(self, conn, packet, port))

    def _answer(self, conn: AdsConnection, h: AmsHeader, handler: Callable[[], Reply]) -> None:
        """Run `handler`, turning its exceptions into the command's error payload."""
        try:
            reply = handler()
        except (AdsError, PayloadError) as exc:
            reply = error_payload(h.command, exc.code)
        except Exception:
            log.exception("ADS %s request failed", h.command)
            reply = error_payload(h.command, AdsErrorCode.DEVICE_ERROR)
        if isinstance(reply, bytes):
            self.respond(conn, h, reply)
        else:
            conn.spawn(self._respond_later(conn, h, reply))

    def respond(self, conn: AdsConnection, h: AmsHeader, payload: bytes) -> None:
        if payload[:4] != b"\0\0\0\0":
            self.stats.errors += 1
        conn.send(conn.response(h, payload))

    async def _respond_later(
        self, conn: AdsConnection, h: AmsHeader, reply: Awaitable[bytes]
    ) -> None:
        try:
            payload = await reply
        except AdsError as exc:
            payload = error_payload(h.command, exc.code)
        except Exception:
            log.exception("ADS %s request failed", h.command)
            payload = error_payload(h.command, AdsErrorCode.DEVICE_ERROR)
        self.respond(conn, h, payload)

    def handle_router(self, conn: AdsConnection, cmd: RouterCommand) -> None:
        """An AMS/TCP router command (`router.Router`): answered, or dropped and counted."""
        try:
            answer = self.ams_router.answer(conn, cmd)
        except PayloadError as exc:
            self.stats.dropped_frames += 1
            log.debug("ADS router command 0x%04X from %s dropped: %s", cmd.command, conn.peer, exc)
            return
        if answer == CLOSE:
            conn.close()
        else:
            conn.send(cast(bytes, answer))
        self.stats.router_commands += 1

    # ------------------------------------------------------------------ connections

    # ------------------------------------------------------------------ connections

    def connected(self, conn: AdsConnection) -> bool:
        """Admit `conn` unless `max_connections` are open already (then False: the
        connection closes at once, before it can make the server buffer anything)."""
        if not self.listener.admit(conn):
            self.stats.refused_connections = self.listener.refused
            return False
        self.stats.connections += 1
        return True

    def take_turn(self, packet: AmsPacket, shares: list[LoopShare]) -> float | None:
        """Head: may `packet` be served now (None; its machine's loop share, if it has
        one, is appended to `shares`: the batch's loop time is charged to it)? Or must it
        wait, with the rest of its connection's requests: for the next loop step (0.0),
        when its machine has served `requests_per_step` in this one (counted at the
        machine the request targets), or that many seconds, when its machine's loop
        share is used up (a fleet; docs/design.md §13.1). A machine's count starts again
        in the step after it reached half the limit, not after every step: a reset
        scheduled for every request was a tenth of a read's cost in the server, and a
        count carried over from earlier steps only lowers what this one may serve."""
        device = self.devices.get(packet.header.target.netid, self)
        share = device.share
        if share is not None:
            wait = share.wait()
            if wait:
                device.stats.held_requests += 1
                return wait
        if device._served >= self.options.requests_per_step:
            device.stats.deferred_requests += 1
            return 0.0
        self._count_turn(device)
        if share is not None:
            shares.append(share)
        return None

    def _count_turn(self, device: AdsServer) -> None:
        """One more request served by `device` in this loop step (`take_turn`)."""
        device._served += 1
        if (
            device._served * 2 >= self.options.requests_per_step
            and not device._step_reset
            and self.loop is not None
        ):
            device._step_reset = True
            self.loop.call_soon(device._new_step)

    def repeat(self, conn: AdsConnection, frame: bytes) -> bool:
        """Answer `frame`, one whole frame, from what `conn` kept for it if it is a Read
        sent before that this still answers (`repeats`; docs/design.md §13, *Repeated
        reads*); False: it is served the whole way. It counts as a request of its
        machine in this loop step (`take_turn`: none when the turn is used up)."""
        kept = repeats.still(conn.repeats, frame)
        if kept is None:
            return False
        device = cast(AdsServer, kept.device)
        if device._served >= self.options.requests_per_step:
            return False
        self._count_turn(device)
        device.stats.requests += 1
        device.stats.repeated_reads += 1
        conn.send(repeats.answer(kept, frame))
        return True

    def _new_step(self) -> None:
        self._served = 0
        self._step_reset = False

    def _attach(self, conn: AdsConnection) -> bool:
        """`conn` sends this machine its first request: it counts towards this machine's
        `max_connections` — False (the request is answered 0x716) when it is full."""
        if len(self._attached) >= self.options.max_connections:
            self.stats.refused_requests += 1
            log_rarely(
                self.stats.refused_requests,
                "ADS %s: refusing a request of %s: %d connections use this machine",
                self.options.netid,
                conn.peer,
                len(self._attached),
            )
            return False
        self._attached.add(conn)
        return True

    def disconnected(self, conn: AdsConnection) -> None:
        if self.router is None:
            self.listener.forget(conn)
            self.ams_router.release(conn)
            for device in self.devices.values():
                if device is not self:
                    device.disconnected(conn)
        self._attached.discard(conn)
        table = conn.tables.pop(id(self), None)
        if table is not None:
            self.handles_held -= len(table.handles)
            self.head.fleet_handles -= len(table.handles)
        n = self.notifications.drop_owner(conn)
        if n:
            log.debug("dropped %d notifications of %s", n, conn.peer)
            self.sampler.update_status()
        if not len(self.notifications):
            self.sampler.demand(False)


__all__ = ["GEO_AMS_PORT", "HANDOFF_MAX", "AdsOptions", "AdsServer", "AdsStats", "Command"]
