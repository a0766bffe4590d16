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
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import struct
import time
from collections import deque
from collections.abc import Awaitable, Callable, Coroutine, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, cast

import geo_server
from geo_server.dictionary import (
    ADDRESS_LOOKUP,
    AMS_PORTS,
    COM_AMS_PORT,
    GEO_AMS_PORT,
    REQUEST_PORT,
    TASK_GROUPS,
)
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.service import ObjectService, PreparedWrite
from geo_server.snapshot import Snapshot
from geo_server.transports.ads import codec, discovery, symbols
from geo_server.transports.ads.codec import (
    SYSTEM_SERVICE_PORT,
    AddNotificationRequest,
    AdsState,
    AmsHeader,
    AmsPacket,
    BadPacket,
    Command,
    DeleteNotificationRequest,
    Dropped,
    PayloadError,
    ReadDeviceInfoRequest,
    ReadRequest,
    ReadStateRequest,
    ReadWriteRequest,
    Stamp,
    StreamError,
    SumGroup,
    WriteControlRequest,
    WriteRequest,
)
from geo_server.transports.ads.notifications import (
    MAX_FLEET,
    MAX_PER_OWNER,
    MAX_TOTAL,
    Batch,
    NotificationPool,
    NotificationTable,
    SamplingPass,
)
from geo_server.transports.tcp import Listener

log = logging.getLogger(__name__)

#: Registrations sampled between two looks at the clock (keeps the budget check cheap).
_SAMPLE_STEP = 32
#: Snapshots handed from the cycle to the event loop and not sampled yet; beyond, the
#: oldest go (their samples are delayed to a later cycle, never lost). The exact engine
#: stops handing them over earlier, at `AdsOptions.sample_backlog`.
HANDOFF_MAX = 2000
#: A machine's share of one sampling round is at least this long (seconds), however many
#: machines have samples waiting: a pass makes progress in every round.
_MIN_SHARE = 0.0002


@dataclass
class AdsOptions:
    """How the ADS interface listens (docs/design.md §9)."""

    host: str = "127.0.0.1"
    port: int = 48898  # 0 = ephemeral (tests); the bound port is `AdsServer.port`
    netid: str = "127.0.0.1.1.1"  # own AMS NetId
    ams_ports: tuple[int, ...] = AMS_PORTS
    read_only: bool = False  # every write answers 0x704
    #: Reject requests addressed to another NetId with AMS error 0x7 (target machine not
    #: found). Off by default: a stand-alone server answers whatever NetId the client
    #: routed to it, and notifications echo that NetId so AdsLib dispatches them.
    strict_netid: bool = False
    #: Largest AMS/TCP length accepted: what the largest legal request needs (a sum
    #: command of 500 sub-requests each carrying the largest object, see
    #: `codec.MAX_REQUEST_FRAME`). A frame header announcing more closes the connection
    #: before its data is buffered. Answers are held to the same size.
    max_frame: int = codec.MAX_REQUEST_FRAME
    #: Largest answer payload (the client's read length bounds each one): room for the
    #: symbol upload of a machine with 128 axes (about 480 kB)
    max_answer: int = 1 << 20
    #: waiting for a write to be applied, running cycles (None: the service's
    #: `ServiceLimits.write_timeout`)
    write_timeout: float | None = None
    #: Notifications one connection may register (0x716 NOMOREHDLS beyond): half of
    #: `max_notifications_total`, so one client cannot take every handle.
    max_notifications: int = MAX_PER_OWNER
    #: Notifications all connections together may register (0x716 beyond): 550, Beckhoff's
    #: recommended maximum per ADS device. Sampling runs on the event loop that answers
    #: every transport, and this is about what it sustains at a 1 ms GEO cycle. Measured
    #: on 2 cores (bench/ads_abuse.py and a sampling micro-benchmark), with every
    #: registration due every cycle at distinct addresses: on change (the pyads default)
    #: 0.3 ms of sampling per cycle alone and about 0.5 ms inside the running server,
    #: i.e. half the loop, while Modbus, Zenoh and ADS reads stay within a few ms at p99;
    #: cyclic, every one sending every cycle, 0.65 ms alone. Twice as many (1100) took
    #: 0.45 / 0.7 ms on change and 1.2 ms cyclic: the loop no longer sampled every cycle.
    max_notifications_total: int = MAX_TOTAL
    #: Notifications the machines behind one port (a fleet) may register together (0x716
    #: beyond): 1100, twice one machine's. What a registration costs follows what it
    #: samples (an on-change check of a value that cannot change at rest costs nothing
    #: while the machine rests; docs/design.md §13), and sampling is shared fairly
    #: between machines, so a fleet of 100 holding this many still answers every machine
    #: (bench/fleet_isolation.py). Read from the server that listens.
    max_notifications_fleet: int = MAX_FLEET
    #: Snapshots waiting to be sampled at the machines behind the port together (read
    #: from the server that listens), shared evenly (at least 16 each): 2000 cycles for
    #: one machine, 20 each for 100. Beyond its share a machine's exact engine publishes
    #: no more cycles for sampling until the loop caught up — those samples come later,
    #: from a later cycle, and are counted (`status()["ads_notifications"]`) — so a loop
    #: that cannot keep up sheds sampling work instead of piling it up.
    sample_backlog: int = HANDOFF_MAX
    #: Longest stretch of notification sampling in one event-loop callback (seconds);
    #: a longer pass continues in a later loop iteration, so requests of every transport
    #: are answered in between. A late slice still sends the values and timestamp of the
    #: cycle its samples were due at.
    sample_budget: float = 0.002
    #: Simultaneous ADS connections to one machine; one beyond is closed at once
    #: (counted in `AdsStats.refused_connections`). With `max_frame` it bounds the memory
    #: clients can make the server hold for unfinished frames to about 17 MiB. Behind one
    #: port with several machines (a fleet) a connection counts at each machine it sends
    #: a request to, and a request to a machine that has this many answers 0x716: one
    #: machine's clients cannot take the port from the others'.
    max_connections: int = 128
    #: Simultaneous connections to the port when it serves several machines (a fleet;
    #: read from the server that listens): one beyond is closed at once.
    max_connections_fleet: int = 512
    #: Answers one connection may have outstanding (writes waiting for their cycle,
    #: injected delays): beyond, the server stops reading that connection until half
    #: of them are sent, so a client pipelining requests cannot queue unbounded work.
    max_pending: int = 256
    #: Requests one machine serves in one event-loop step (read from the server that
    #: listens); the rest wait for the next step, their connections' reading paused:
    #: a client flooding one machine delays that machine's answers, not the others'.
    requests_per_step: int = 16
    #: A frame still unfinished this many seconds after its first byte arrived closes the
    #: connection (counted in `AdsStats.closed_incomplete`): a client that stopped in the
    #: middle of a frame must not keep its buffer alive. 0 disables the check.
    incomplete_frame_timeout: float = 5.0
    #: Notification frames are dropped (and counted) for a client whose unsent data
    #: exceeds this: a stalled client must not make the server buffer without bound.
    notification_backlog: int = 4 * 1024 * 1024
    device_name: str = "geo-server"
    #: ReadDeviceInfo of the system service (AMS port 10000; 15 characters at most)
    system_name: str = "geo-server sys"
    #: UDP port of discovery and add-route (48899 for real tools), on `host`; None: off
    udp_port: int | None = None
    #: host name the discovery answer gives
    host_name: str = "geo-server"
    #: The credentials an add-route request on `udp_port` must carry (`geo-server run
    #: --ads-route-user/--ads-route-password`); None: every add-route is refused with
    #: 0x704, as TwinCAT refuses wrong credentials (discovery.py).
    route_user: str | None = field(default=None, repr=False)
    route_password: str | None = field(default=None, repr=False)
    #: Symbol handles one connection may hold (0x716 beyond; TwinCAT has no documented
    #: limit, but a client that never releases must not grow the server without bound).
    max_handles: int = 10_000
    #: Symbol handles all connections together may hold at one machine (0x716 beyond).
    max_handles_machine: int = 50_000
    #: Symbol handles at every machine behind one port together (a fleet; 0x716 beyond;
    #: read from the server that listens). About 60 bytes each: 12 MiB at most.
    max_handles_fleet: int = 200_000
    #: With running cycles, no notification sample earlier than this many seconds after
    #: its registration (AdsLib drops samples that overtake its own bookkeeping).
    first_sample_hold: float = 0.005

    def __post_init__(self) -> None:
        codec.netid_to_bytes(self.netid)  # ValueError early for a malformed NetId


@dataclass
class AdsStats:
    requests: int = 0
    errors: int = 0  # responses with a non-zero result
    dropped_frames: int = 0
    faulted: int = 0  # requests an injected fault dropped, answered, delayed or cut off
    closed_for_framing: int = 0
    notifications_sent: int = 0
    notifications_dropped: int = 0
    connections: int = 0  # accepted
    refused_connections: int = 0  # closed at once: `max_connections` were open
    closed_incomplete: int = 0  # a frame stayed unfinished past `incomplete_frame_timeout`
    router_commands: int = 0  # AMS/TCP port connect, port close, get NetId answered
    udp_answered: int = 0  # discovery and add-route datagrams answered
    udp_dropped: int = 0  # datagrams that were not ADS UDP requests
    sampling_passes: int = 0  # notification sampling passes begun
    sampling_slices: int = 0  # passes continued in a later loop iteration (over budget)
    #: cycles the engine would have published for sampling but the loop was behind
    #: (`sample_backlog` snapshots waiting): their samples come from a later cycle
    samples_refused: int = 0
    refused_requests: int = 0  # answered 0x716: `max_connections` at this machine
    deferred_requests: int = 0  # waited for a later loop step (`requests_per_step`)


def _version() -> tuple[int, int, int]:
    parts = [*geo_server.__version__.split("."), "0", "0"]
    nums = []
    for p in parts[:3]:
        digits = "".join(ch for ch in p if ch.isdigit())
        nums.append(int(digits) if digits else 0)
    return nums[0], nums[1], nums[2]


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


#: What a command handler returns: the response payload now or later.
Reply = bytes | Awaitable[bytes]
_KNOWN_COMMANDS = frozenset(int(c) for c in Command)


class AdsServer:
    """Serve one `ObjectService` over ADS/AMS-TCP."""

    def __init__(
        self,
        service: ObjectService,
        options: AdsOptions | None = None,
        router: AdsServer | None = None,
    ) -> None:
        """`router`: the server that owns the TCP port and routes requests for this
        server's NetId to it (a fleet: one machine per NetId, `add_device`); None: this
        server listens itself."""
        self.service = service
        self.options = options or AdsOptions()
        self.router = router
        #: the devices this server routes to, by AMS NetId (itself included)
        self.devices: dict[str, AdsServer] = {self.options.netid: self}
        self.stats = AdsStats()
        cycle_s = service.cycle_s
        #: the server that listens (itself when alone): it holds the port's totals
        self.head: AdsServer = router if router is not None else self
        self.notifications: NotificationTable = NotificationTable(
            self.service.read,
            cycle_s,
            self.options.max_notifications,
            self.options.max_notifications_total,
            prepare=self._notification_getter,
            pool=(
                router.notifications.pool
                if router is not None
                else NotificationPool(self.options.max_notifications_fleet)
            ),
            steady=self._steady,
        )
        self.listener = Listener(self.options.host, self.options.port, self.options.max_connections)
        #: connections that sent this machine a request (`max_connections`)
        self._attached: set[AdsConnection] = set()
        #: symbol handles held here, by every connection (and at the head: fleet-wide)
        self.handles_held = 0
        self.fleet_handles = 0
        #: what `status()` shows of the notifications (kept current, read by status)
        self._status: dict[str, int] = {}
        #: head: the machines with snapshots to sample, served in turn (`_sample_round`)
        self._ready: deque[AdsServer] = deque()
        self._round_pending = False
        # requests served in this loop step (`take_turn`)
        self._served = 0
        self._step_reset = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._unsubscribe: Callable[[], None] | None = None
        self._notify_invoke = 0
        # Cycle thread -> loop hand-off of the cycles' snapshots (see `_on_cycle_thread`).
        self._handed: deque[Snapshot] = deque(maxlen=HANDOFF_MAX)
        self._handoff_pending = False
        # The sampling pass under way (with its FILETIME).
        self._pass: tuple[SamplingPass, int] | None = None
        # While registrations exist the cycle publishes every cycle's snapshot.
        self._every_cycle: Callable[[], None] | None = None
        self._major, self._minor, self._build = _version()
        self._symbols: symbols.SymbolTable | None = None
        self._udp: asyncio.DatagramTransport | None = None
        #: why discovery is off although a UDP port was asked for ("" when it runs)
        self.udp_error = ""
        #: AMS ports handed out by port connect (0x1000) -> their connection
        self._ams_ports: dict[int, AdsConnection] = {}
        self._next_ams_port = FIRST_CLIENT_PORT

    # ------------------------------------------------------------------ lifecycle

    def add_device(self, service: ObjectService, options: AdsOptions) -> AdsServer:
        """Serve another machine on this server's TCP port under its own AMS NetId, as a
        TwinCAT router routes by target NetId (SPEC §13: a fleet). Start and close it
        with this one (add devices before `start`)."""
        if self._loop is not None:
            raise RuntimeError("add_device() before start()")
        if options.netid in self.devices:
            raise ValueError(f"AMS NetId {options.netid} is served already")
        device = AdsServer(service, options, router=self)
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
        self._loop = asyncio.get_running_loop()
        if self.router is not None:
            self._unsubscribe = self.service.subscribe(self._on_cycle_thread)
            return
        for device in self.devices.values():
            if device is not self:
                await device.start()
        await self.listener.listen(lambda: AdsConnection(self))
        if self.options.udp_port is not None:
            # Discovery is a convenience: with its port taken (another emulator or a
            # TwinCAT router on this host) the ADS interface still starts, without it.
            try:
                transport, _ = await self._loop.create_datagram_endpoint(
                    lambda: _Discovery(self), local_addr=(self.options.host, self.options.udp_port)
                )
            except OSError as exc:
                self.udp_error = f"UDP {self.options.host}:{self.options.udp_port}: {exc.strerror}"
                log.warning("ADS discovery off: %s", self.udp_error)
            else:
                self._udp = transport
        self._unsubscribe = self.service.subscribe(self._on_cycle_thread)
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
        self._pass = None
        self._handed.clear()
        self._ready.clear()
        self._demand(False)
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
                (self._major, self._minor, self._build),
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

    def handle_packet(self, conn: AdsConnection, packet: AmsPacket) -> None:
        """Answer one request on `conn` (never raises)."""
        h = packet.header
        if h.is_response or h.command == Command.DEVICE_NOTIFICATION:
            # A response or a notification sent to us: there is nothing to answer.
            self.stats.dropped_frames += 1
            return
        device = self.devices.get(h.target.netid, self)
        if device is not self:
            device.handle_packet(conn, packet)
            return
        self.stats.requests += 1
        if self.service.faults.active and self._faulted(conn, packet):
            return
        self.serve_packet(conn, packet)

    def serve_packet(self, conn: AdsConnection, packet: AmsPacket) -> None:
        """Answer one request addressed to this device (no fault decided any more)."""
        h = packet.header
        if self.options.strict_netid and h.target.netid != self.options.netid:
            self.stats.errors += 1
            conn.send(codec.response_frame(h, b"", AdsErrorCode.TARGET_MACHINE_NOT_FOUND))
            return
        if conn not in self._attached and not self._attach(conn):
            self._respond(conn, h, error_payload(h.command, AdsErrorCode.DEVICE_NOMOREHDLS))
            return
        if h.target.port == SYSTEM_SERVICE_PORT:
            self._answer(conn, h, lambda: self._system_service(conn, packet))
            return
        if h.target.port not in self.options.ams_ports:
            self.stats.errors += 1
            conn.send(codec.response_frame(h, b"", AdsErrorCode.TARGET_PORT_NOT_FOUND))
            return
        token = REQUEST_PORT.set(h.target.port)  # resolves only this task's groups
        try:
            self._answer(conn, h, lambda: self._dispatch(conn, packet))
        finally:
            REQUEST_PORT.reset(token)

    # ------------------------------------------------------------------ injected faults

    def _faulted(self, conn: AdsConnection, packet: AmsPacket) -> bool:
        """Carry out the injected fault that hits this request, if any (docs/faults.md):
        True when the request is dealt with (dropped, answered with the error, its
        connection closed, or delayed to be served later)."""
        op, name = self._fault_target(conn, packet)
        fault = self.service.faults.decide("ads", op, name)
        if fault is None:
            return False
        h = packet.header
        self.stats.faulted += 1
        if fault.kind == "drop":
            return True
        if fault.kind == "disconnect":
            conn.abort()
            return True
        if fault.kind == "error":
            self._respond(conn, h, error_payload(h.command, int(fault.value)))
            return True

        async def later() -> None:
            await fault.delay()  # cut short when the fault is cleared
            if conn.transport is not None and not conn.transport.is_closing():
                self.serve_packet(conn, packet)

        conn.spawn(later())
        return True

    def _fault_target(self, conn: AdsConnection, packet: AmsPacket) -> tuple[str, str]:
        """("read" | "write", object name or "") of a request, for the faults' filters:
        a write is a Write (also by handle) or a sum write; a ReadWrite otherwise reads
        (by name, handles, sum reads)."""
        write = packet.header.command == Command.WRITE
        name = ""
        with contextlib.suppress(Exception):  # an unparsable request has no name
            req = codec.parse_request(packet)
            if isinstance(req, ReadWriteRequest):
                write = req.index_group in (SumGroup.WRITE, SumGroup.READ_WRITE)
            elif isinstance(req, ReadRequest | WriteRequest):
                ig, io = self._address(conn, req.index_group, req.index_offset)
                name = self.service.resolve(ig, io)[0].name
        return ("write" if write else "read"), name

    def _answer(self, conn: AdsConnection, h: AmsHeader, handler: Callable[[], Reply]) -> None:
        """Run `handler`, turning its exceptions into the command's error payload."""
        try:
            reply = handler()
        except AdsError as exc:
            reply = error_payload(h.command, exc.code)
        except PayloadError as exc:
            reply = error_payload(h.command, exc.code)
        except Exception:
            log.exception("ADS %s request failed", h.command)
            reply = error_payload(h.command, AdsErrorCode.DEVICE_ERROR)
        if isinstance(reply, bytes):
            self._respond(conn, h, reply)
        else:
            conn.spawn(self._respond_later(conn, h, reply))

    def _respond(self, conn: AdsConnection, h: AmsHeader, payload: bytes) -> None:
        if payload[:4] != b"\0\0\0\0":
            self.stats.errors += 1
        # An unknown command id also carries 0x701 in the AMS header: a client cannot
        # know the layout of a response to a command it should not have sent.
        error = 0 if h.command in _KNOWN_COMMANDS else AdsErrorCode.DEVICE_SRVNOTSUPP
        conn.send(codec.response_frame(h, payload, error))

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
        self._respond(conn, h, payload)

    def _dispatch(self, conn: AdsConnection, packet: AmsPacket) -> Reply:
        req = codec.parse_request(packet)
        if isinstance(req, ReadRequest):
            fixed = self._service_read(req.index_group, req.index_offset, req.length)
            if fixed is not None:
                return codec.read_response(0, fixed)
            ig, io = self._address(conn, req.index_group, req.index_offset)
            return codec.read_response(0, self.service.read(ig, io, req.length))
        if isinstance(req, ReadWriteRequest):
            if req.index_group in _NAME_SERVICES:
                return self._by_name(conn, req)
            return self._read_write(conn, req)
        if isinstance(req, WriteRequest):
            if req.index_group == symbols.SYM_RELEASEHND:
                return self._release_handle(conn, req.data)
            ig, io = self._address(conn, req.index_group, req.index_offset)
            return self._write_reply(ig, io, req.data)
        if isinstance(req, AddNotificationRequest):
            return self._add_notification(conn, packet.header, req)
        if isinstance(req, DeleteNotificationRequest):
            self.notifications.delete(conn, req.handle)
            self._demand(len(self.notifications) > 0)
            self._update_status()
            return codec.result_response(0)
        if isinstance(req, ReadStateRequest):
            return codec.read_state_response(0, AdsState.RUN, 0)
        if isinstance(req, ReadDeviceInfoRequest):
            return codec.read_device_info_response(
                0, self._major, self._minor, self._build, self.options.device_name
            )
        # WriteControl and anything else: the CNC object interface offers Read, Write and
        # ReadWrite only (TF5200)
        return codec.result_response(AdsErrorCode.DEVICE_SRVNOTSUPP)

    # ------------------------------------------------------------------ the AMS router

    def handle_router(self, conn: AdsConnection, cmd: codec.RouterCommand) -> None:
        """AMS/TCP router commands (jisotalo/ads-client `registerAdsPort`): a client
        without a router of its own asks ours for an AMS port (0x1000) and gets our NetId
        with a port of its own; 0x0001 gives the port back (the connection closes, as
        TwinCAT's router does); 0x1002 asks for the NetId. Anything else is dropped."""
        try:
            if cmd.command == codec.AMS_TCP_PORT_CONNECT:
                port = self._assign_port(conn, codec.parse_router_port(cmd))
                conn.send(codec.port_connect_response(self.options.netid, port))
            elif cmd.command == codec.AMS_TCP_PORT_CLOSE:
                codec.parse_router_port(cmd)
                if conn.ams_port is not None:
                    self._ams_ports.pop(conn.ams_port, None)
                    conn.ams_port = None
                conn.close()
            elif cmd.command == codec.AMS_TCP_GET_LOCAL_NETID:
                conn.send(codec.local_netid_response(self.options.netid))
            else:
                raise PayloadError(AdsErrorCode.DEVICE_SRVNOTSUPP, "router note from a client")
        except PayloadError as exc:
            self.stats.dropped_frames += 1
            log.debug("ADS router command 0x%04X from %s dropped: %s", cmd.command, conn.peer, exc)
            return
        self.stats.router_commands += 1

    def _assign_port(self, conn: AdsConnection, wanted: int) -> int:
        """The port a client asked for when it is free, else the next free one."""
        if conn.ams_port is not None:
            return conn.ams_port  # asked twice: the same answer
        port = wanted
        taken = self._ams_ports
        reserved = _RESERVED_PORTS | set(self.options.ams_ports)
        if not port or port in taken or port in reserved:
            # at most max_connections ports are taken: a free one is found within that many
            port = self._next_ams_port
            while port in taken or port in reserved:
                port = port + 1 if port < LAST_CLIENT_PORT else FIRST_CLIENT_PORT
            self._next_ams_port = port + 1 if port < LAST_CLIENT_PORT else FIRST_CLIENT_PORT
        self._ams_ports[port] = conn
        conn.ams_port = port
        return port

    # ------------------------------------------------------------------ system service

    def _system_service(self, conn: AdsConnection, packet: AmsPacket) -> Reply:
        """AMS port 10000, the TwinCAT system service: ReadState (always RUN: the
        emulator has no config mode), ReadDeviceInfo, WriteControl to RUN (anything else
        0x712), the ADS state at 0xF100 (read and notification)."""
        req = codec.parse_request(packet)
        if isinstance(req, ReadStateRequest):
            return codec.read_state_response(0, AdsState.RUN, 0)
        if isinstance(req, ReadDeviceInfoRequest):
            return codec.read_device_info_response(
                0, self._major, self._minor, self._build, self.options.system_name
            )
        if isinstance(req, WriteControlRequest):
            if req.ads_state != AdsState.RUN:
                raise AdsError(
                    AdsErrorCode.DEVICE_INVALIDSTATE,
                    f"ADS state {req.ads_state}: the emulator only runs",
                )
            return codec.result_response(0)
        if isinstance(req, ReadRequest) and req.index_group == symbols.DEVICE_DATA:
            return codec.read_response(0, self._device_data(req.length))
        if isinstance(req, ReadRequest) and req.index_group == symbols.SYSTEM_STATE_EXTENDED:
            state = symbols.system_state_extended((self._major, self._minor, self._build))
            return codec.read_response(0, _fixed(state, req.length, "the system state"))
        if isinstance(req, AddNotificationRequest) and req.index_group == symbols.DEVICE_DATA:
            return self._add_notification(conn, packet.header, req)
        if isinstance(req, DeleteNotificationRequest):
            self.notifications.delete(conn, req.handle)
            self._demand(len(self.notifications) > 0)
            return codec.result_response(0)
        if isinstance(req, ReadRequest | AddNotificationRequest):
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDGRP,
                f"index group 0x{req.index_group:X} is not served on the system port",
            )
        # (raised, so that the error payload has the layout of the command's response)
        raise AdsError(AdsErrorCode.DEVICE_SRVNOTSUPP, "not served on the system port")

    def _device_data(self, length: int) -> bytes:
        """0xF100: ADS state RUN, device state 0 (u16 each)."""
        return _fixed(struct.pack("<HH", AdsState.RUN, 0), length, "the ADS state")

    # ------------------------------------------------------------------ symbols

    @property
    def symbols(self) -> symbols.SymbolTable:
        """The machine's symbol table (built on first use: the axes are fixed)."""
        if self._symbols is None:
            m = self.service.machine
            names = {m.axes[slot]: name for name, slot in sorted(m.names.items(), key=_by_slot)}
            self._symbols = symbols.SymbolTable(self.service.dictionary, names)
        return self._symbols

    def _service_read(self, ig: int, io: int, length: int) -> bytes | None:
        """Reads of the symbol and state services on the GEO port, None for the rest."""
        if ig in _GEO_SERVICES:
            _geo_port_only(ig)
        if ig == symbols.DEVICE_DATA:
            return self._device_data(length)
        if ig == symbols.SYM_VERSION:
            return _fixed(bytes([symbols.SYMBOL_VERSION]), length, "the symbol version")
        if ig not in _UPLOADS:
            return None
        table = self.symbols
        if ig == symbols.SYM_UPLOAD or ig == symbols.SYM_DT_UPLOAD:
            blob = table.upload if ig == symbols.SYM_UPLOAD else table.datatype_upload
            self._fit_size(len(blob), length)  # all of it or 0x705
            return blob
        info = table.upload_info() if ig == symbols.SYM_UPLOADINFO else table.upload_info2()
        self._fit_size(len(info), length)  # never cut: clients tell its version by length
        return info

    def _address(self, conn: AdsConnection, ig: int, io: int) -> tuple[int, int]:
        """The object address behind a symbol handle (0xF005, offset = handle)."""
        if ig != symbols.SYM_VALBYHND:
            return ig, io
        _geo_port_only(ig)
        sym = conn.table(self).handles.get(io)
        if sym is None:
            raise AdsError(AdsErrorCode.DEVICE_SYMBOLNOTFOUND, f"no symbol handle 0x{io:X}")
        return sym.index_group, sym.index_offset

    def _sub_read(
        self, conn: AdsConnection, ig: int, io: int, length: int, snap: Snapshot
    ) -> tuple[int, bytes]:
        """One sub-request of a sum read, as a plain Read would answer it."""
        try:
            fixed = self._service_read(ig, io, length)
            if fixed is not None:
                return 0, fixed
            ig, io = self._address(conn, ig, io)
            return 0, self.service.read(ig, io, length, snap)
        except AdsError as exc:
            return exc.code, b""

    def _sub_write(self, conn: AdsConnection, ig: int, io: int, data: bytes) -> WriteItem:
        """One sub-request of a sum write: the object address to write, or the code it
        earned already (a handle released here, an unknown handle)."""
        try:
            if ig == symbols.SYM_RELEASEHND:
                return codec.parse_result(self._release_handle(conn, data))
            ig, io = self._address(conn, ig, io)
        except AdsError as exc:
            return int(exc.code)
        return ig, io, data

    def _by_name(self, conn: AdsConnection, req: ReadWriteRequest) -> Reply:
        return codec.read_response(
            0, self._name_service(conn, req.index_group, req.data, req.read_length)
        )

    def _name_service(self, conn: AdsConnection, ig: int, data: bytes, read_length: int) -> bytes:
        """Handle by name (0xF003), value by name (0xF004), symbol info (0xF009) and
        data type info (0xF011) by name: the write data is the name. A handle asked for
        with more than 4 bytes of read length comes with size, type decoration and type
        name (as ads-client's `createVariableHandle` reads it)."""
        _geo_port_only(ig)
        name = symbols.decode_name(data)
        if ig == symbols.SYM_DT_INFOBYNAMEEX:
            entry = symbols.datatype_entry(self.symbols.datatype(name))
            self._fit_size(len(entry), read_length)
            return entry
        sym = self.symbols.lookup(name)
        if ig == symbols.SYM_INFOBYNAMEEX:
            entry = symbols.symbol_entry(sym)
            self._fit_size(len(entry), read_length)
            return entry
        if ig == symbols.SYM_VALBYNAME:
            return self.service.read(sym.index_group, sym.index_offset, read_length)
        # SYM_HNDBYNAME
        table = conn.table(self)
        answer = symbols.handle_answer(table.next_handle + 1, sym, extended=read_length > 4)
        self._fit_size(len(answer), read_length)
        self._check_handles(table)
        table.next_handle += 1
        table.handles[table.next_handle] = sym
        self.handles_held += 1
        self.head.fleet_handles += 1
        return answer

    def _check_handles(self, table: HandleTable) -> None:
        """0x716 when one more symbol handle would pass a cap: the connection's at this
        machine, this machine's, or (at the head) every machine's behind the port."""
        head = self.head
        for held, cap, where in (
            (len(table.handles), self.options.max_handles, "on this connection"),
            (self.handles_held, self.options.max_handles_machine, "at this machine"),
            (head.fleet_handles, head.options.max_handles_fleet, "at the machines of this port"),
        ):
            if held >= cap:
                raise AdsError(
                    AdsErrorCode.DEVICE_NOMOREHDLS, f"{held} symbol handles are open {where}"
                )

    def _lookup_address(self, req: ReadWriteRequest) -> bytes:
        """Group + 0x600: in (channel, axis) as two UNS32 (or two UNS16), the element in
        the index offset's low word; out (IndexGroup, IndexOffset), (0, 0) for none."""
        _geo_port_only(req.index_group)
        if len(req.data) == 8:
            channel, axis = struct.unpack("<II", req.data)
        elif len(req.data) == 4:
            channel, axis = struct.unpack("<HH", req.data)
        else:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDSIZE,
                f"address lookup: (channel, axis) has 8 bytes, not {len(req.data)}",
            )
        self._fit_size(8, req.read_length)
        ig, io = self.service.dictionary.lookup_address(
            req.index_group, req.index_offset & 0xFFFF, channel, axis, self.service.axes
        )
        return codec.read_response(0, struct.pack("<II", ig, io))

    def _release_handle(self, conn: AdsConnection, data: bytes) -> bytes:
        """0xF006: give a handle back (unknown -> 0x710). A notification registered on
        it keeps its object address: it stays until it is deleted itself."""
        if len(data) != 4:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDSIZE, f"a handle has 4 bytes, not {len(data)}"
            )
        handle = struct.unpack("<I", data)[0]
        if conn.table(self).handles.pop(handle, None) is None:
            raise AdsError(AdsErrorCode.DEVICE_SYMBOLNOTFOUND, f"no symbol handle 0x{handle:X}")
        self.handles_held -= 1
        self.head.fleet_handles -= 1
        return codec.result_response(0)

    # ------------------------------------------------------------------ reads

    def _read_write(self, conn: AdsConnection, req: ReadWriteRequest) -> Reply:
        ig, io = req.index_group, req.index_offset
        if ig in _SUM_GROUPS:
            return self._sum(conn, req)
        if ig in _LOOKUPS:
            return self._lookup_address(req)
        ig, io = self._address(conn, ig, io)
        if not req.data:
            return codec.read_response(0, self.service.read(ig, io, req.read_length))
        # Write, then read the object back once the write is applied (stepped mode: the
        # value read back is still the one of the current snapshot).
        write = self._write_reply(ig, io, req.data)

        async def read_back() -> bytes:
            result = codec.parse_result(await write)
            if result:
                return codec.read_response(result)
            return codec.read_response(0, self.service.read(ig, io, req.read_length))

        return read_back()

    def _sum(self, conn: AdsConnection, req: ReadWriteRequest) -> Reply:
        group, count, data = req.index_group, req.index_offset, req.data
        if group in (SumGroup.READ, SumGroup.READ_EX, SumGroup.READ_EX2):
            subs = codec.parse_sum_read(count, data)
            if group != SumGroup.READ_EX2:
                # The answer holds every requested length: check it fits the read buffer
                # before building it (a sub-request may ask for gigabytes).
                head = 4 if group == SumGroup.READ else 8
                self._fit_size(head * len(subs) + sum(s.length for s in subs), req.read_length)
            snap = self.service.current()
            results = [
                self._sub_read(conn, s.index_group, s.index_offset, s.length, snap) for s in subs
            ]
            if group == SumGroup.READ_EX2:
                out = codec.sum_read_ex_response(results)
            elif group == SumGroup.READ_EX:
                out = codec.sum_read_ex_response(results, [s.length for s in subs])
            else:
                out = codec.sum_read_response(results, [s.length for s in subs])
            return self._fit(out, req.read_length)
        if group == SumGroup.WRITE:
            writes = codec.parse_sum_write(count, data)
            pending = self._write_many(
                [self._sub_write(conn, w.index_group, w.index_offset, w.data) for w in writes]
            )

            async def written() -> bytes:
                return self._fit(codec.sum_write_response(await pending), req.read_length)

            return written()
        if group == SumGroup.READ_WRITE:
            subs_rw = codec.parse_sum_read_write(count, data)
            # name services (handles by name: ads-client's createVariableHandleMulti) are
            # answered at once; the others write, then read back
            named: dict[int, tuple[int, bytes]] = {}
            for i, s in enumerate(subs_rw):
                if s.index_group in _NAME_SERVICES:
                    try:
                        named[i] = (
                            0,
                            self._name_service(conn, s.index_group, s.data, s.read_length),
                        )
                    except AdsError as exc:
                        named[i] = (int(exc.code), b"")
            pending = self._write_many(
                [
                    None
                    if i in named or not s.data
                    else self._sub_write(conn, s.index_group, s.index_offset, s.data)
                    for i, s in enumerate(subs_rw)
                ]
            )

            async def written_then_read() -> bytes:
                write_codes = await pending
                snap = self.service.current()
                results: list[tuple[int, bytes]] = []
                for i, (s, code) in enumerate(zip(subs_rw, write_codes, strict=True)):
                    if i in named:
                        results.append(named[i])
                    elif code:
                        results.append((code, b""))
                    else:
                        results.append(
                            self._sub_read(conn, s.index_group, s.index_offset, s.read_length, snap)
                        )
                return self._fit(codec.sum_read_ex_response(results), req.read_length)

            return written_then_read()
        raise AdsError(AdsErrorCode.DEVICE_SRVNOTSUPP, f"sum command 0x{group:X} is not supported")

    def _fit_size(self, size: int, read_length: int) -> None:
        """Never more bytes than requested: a too small read buffer is 0x705; so is an
        answer that would not fit one frame of `max_frame` bytes."""
        limit = min(read_length, self.options.max_answer)
        if size > limit:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDSIZE,
                f"the answer has {size} bytes, the read length is {read_length}",
            )

    def _fit(self, out: bytes, read_length: int) -> bytes:
        self._fit_size(len(out), read_length)
        return codec.read_response(0, out)

    # ------------------------------------------------------------------ writes

    def _check_writes_allowed(self) -> None:
        if self.options.read_only:
            raise AdsError(AdsErrorCode.DEVICE_INVALIDACCESS, "the ADS interface is read-only")

    def _write_reply(self, ig: int, io: int, data: bytes) -> Awaitable[bytes]:
        """Validate now (an invalid write raises at once), answer once applied."""
        self._check_writes_allowed()
        prepared = self.service.prepare(ig, io, data)

        async def applied() -> bytes:
            (error,) = await self.service.apply_writes([prepared], self.options.write_timeout)
            return codec.result_response(error.code if error is not None else 0)

        return applied()

    def _write_many(self, items: Sequence[WriteItem | None]) -> Awaitable[list[int]]:
        """Sum write: validate each item (its own code), apply the valid ones together
        in one cycle; per item 0 or the ADS code it earned. A command object (reload,
        save) must be written on its own, not inside a sum command (0x704)."""
        codes: list[int] = []
        valid: list[tuple[int, PreparedWrite]] = []
        for i, item in enumerate(items):
            codes.append(0)
            if item is None:
                continue
            if isinstance(item, int):  # the item's code is known already
                codes[i] = item
                continue
            try:
                self._check_writes_allowed()
                w = self.service.prepare(*item)
                if w.obj.command:
                    raise AdsError(
                        AdsErrorCode.DEVICE_INVALIDACCESS,
                        f"{w.obj.name} cannot be written inside a sum command",
                    )
                valid.append((i, w))
            except AdsError as exc:
                codes[i] = exc.code

        async def applied() -> list[int]:
            if not valid:
                return codes
            try:
                errors = await self.service.apply_writes(
                    [w for _, w in valid], self.options.write_timeout
                )
            except AdsError as exc:  # the whole batch: stalled (0x707), withdrawn (0x719)
                errors = [exc] * len(valid)
            for (i, _w), err in zip(valid, errors, strict=True):
                codes[i] = err.code if err is not None else 0
            return codes

        return applied()

    # ------------------------------------------------------------------ notifications

    def _add_notification(
        self, conn: AdsConnection, h: AmsHeader, req: AddNotificationRequest
    ) -> bytes:
        hold = 0.0
        if self.service.running:
            hold = time.monotonic() + self.options.first_sample_hold
        if req.index_group == symbols.SYM_VALBYHND:
            ig, io = self._address(conn, req.index_group, req.index_offset)
            req = replace(req, index_group=ig, index_offset=io)
        # the cycles the registrations want from now on, before the first one's cycle
        self._demand(True)
        try:
            reg = self.notifications.add(
                conn, h.source, h.target, req, self.service.fresh(), hold_until=hold
            )
        finally:
            self._demand(len(self.notifications) > 0)
            self._update_status()
        return codec.add_notification_response(0, reg.handle)

    def _demand(self, on: bool) -> None:
        """Ask the engine for the snapshots the registrations want while any exist (the
        exact engine publishes only the cycles someone looks at, docs/design.md §13):
        this server is the `CycleDemand` (`wants`). An engine without that (the cycle
        process) is asked for every cycle's snapshot."""
        if on and self._every_cycle is None:
            sched = self.service.scheduler
            demand_cycles = getattr(sched, "demand_cycles", None)
            if demand_cycles is not None:
                self._every_cycle = demand_cycles(self)
            else:
                self._every_cycle = sched.demand_every_cycle()
        elif not on and self._every_cycle is not None:
            self._every_cycle()
            self._every_cycle = None

    def wants(self, cycle: int, quiescent: bool) -> bool:
        """`CycleDemand` (engine thread): the registrations want `cycle` published,
        unless `sample_backlog` snapshots already wait for the loop — then the engine
        goes on without it (counted; those samples come from a later cycle)."""
        if not self.notifications.wants(cycle, quiescent):
            return False
        if len(self._handed) >= self._backlog:
            self.stats.samples_refused += 1
            return False
        return True

    @property
    def _backlog(self) -> int:
        """This machine's share of the port's `sample_backlog`."""
        head = self.head
        return max(16, head.options.sample_backlog // len(head.devices))

    def next_wanted(self, cycle: int, quiescent: bool) -> int | None:
        """`CycleDemand` (engine thread): the next cycle the registrations want."""
        return self.notifications.next_wanted(cycle, quiescent)

    def _steady(self, ig: int, io: int) -> bool:
        """The value a notification watches cannot change while the machine is at rest
        (a constant service, an attribute, or an object `varies_at_rest` is False for)."""
        if ig in _NOTIFIABLE_SERVICES:
            return True
        try:
            obj, _axis, attr = self.service.resolve(ig, io)
        except AdsError:
            return False
        return attr is not None or not self.service.varies_at_rest(obj)

    def _update_status(self) -> None:
        """What `status()["ads_notifications"]` shows (a dict the status reads)."""
        st = self._status
        st["registrations"] = len(self.notifications)
        st["samples_late"] = self.notifications.late
        st["samples_refused"] = self.stats.samples_refused
        st["waiting_snapshots"] = len(self._handed)
        self.service.status_extra["ads_notifications"] = st

    def _notification_getter(
        self, ig: int, io: int, length: int, snap: Snapshot
    ) -> Callable[[Snapshot], bytes]:
        """Check a notification's address by reading it (0x702…0x705 as a Read answers)
        and resolve it once: sampling then only encodes the value of each snapshot (an
        attribute is a constant)."""
        fixed = self._service_read(ig, io, length)
        if fixed is not None and ig in _NOTIFIABLE_SERVICES:
            return lambda _snap: fixed
        data = self.service.read(ig, io, length, snap)
        obj, axis, attr = self.service.resolve(ig, io)
        if attr is not None:
            return lambda _snap: data
        return lambda later: later.encode(obj, axis)

    def _on_cycle_thread(self, snap: Snapshot) -> None:
        """GEO cycle thread: hand the cycle's snapshot to the loop, when someone listens.

        Every snapshot is handed over, in cycle order (the exact engine publishes a
        batch of cycles at once, each with its own time stamp, and the samples due in
        each must be taken from it), but at most one hand-off callback is queued at a
        time: one `call_soon_threadsafe` per cycle (each also waking the loop through its
        self-pipe) piles up callbacks whenever the loop is busy. `_on_cycle` works
        through all snapshots handed over, in the head's rounds (`_sample_round`:
        machines in turn). When the loop falls `HANDOFF_MAX` cycles
        behind the oldest ones go: sampling counts intervals in cycles
        (`NotificationTable.begin`), so a snapshot the loop never saw delays a sample,
        it does not lose one.
        """
        if not len(self.notifications):
            return
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        # Append first, then test the flag (`_on_cycle` clears it, then reads): a
        # snapshot appended after `_on_cycle` looked finds the flag cleared and queues a
        # new hand-off, so no snapshot is left unsampled. deque.append and popleft are
        # atomic; no lock on the cycle thread.
        self._handed.append(snap)
        if self._handoff_pending:
            return
        self._handoff_pending = True
        try:
            loop.call_soon_threadsafe(self._on_cycle)
        except RuntimeError:  # the loop closed in between: nobody to notify any more
            self._handoff_pending = False

    def _on_cycle(self) -> None:
        """Event loop: this machine has snapshots to sample; it joins the head's round."""
        self._handoff_pending = False
        head = self.head
        if self not in head._ready:
            head._ready.append(self)
        head._again()

    def _sample_round(self) -> None:
        """Event loop (head): sample for at most `sample_budget` seconds, the machines
        with snapshots waiting in turn (docs/design.md §13.1).

        Each machine of the round gets an equal share of the budget (at least
        `_MIN_SHARE`) before the next one's turn; one with work left goes to the back of
        the queue. What the budget leaves waits for a later loop iteration
        (`call_soon`): the loop first answers the requests of every transport that
        arrived meanwhile. So one machine's many registrations delay its own samples,
        not the other machines' — nor anyone's requests by more than one budget.
        """
        self._round_pending = False
        ready = self._ready
        now = time.perf_counter()
        deadline = now + self.options.sample_budget
        for turn in range(len(ready)):
            if not ready or (turn and now >= deadline):  # (the first turn always runs)
                break
            device = ready.popleft()
            share = max(_MIN_SHARE, (deadline - now) / (len(ready) + 1))
            if device._sample(min(deadline, now + share)):
                ready.append(device)
            now = time.perf_counter()
        self._again()

    def _sample(self, deadline: float) -> bool:
        """Work on this machine's sampling passes until `deadline`; True when work is
        left (a pass under way or snapshots waiting).

        A pass covers the registrations due at one snapshot; it is begun from the oldest
        snapshot handed over when none is under way. A pass cut short by the deadline
        (thousands of due registrations) goes on in a later turn, still sampling its
        own snapshot and carrying its timestamp — values the client sees are those of
        the cycle they were due at, only later. Passes follow each other in cycle order.
        """
        while True:
            if self._pass is None:
                try:
                    snap = self._handed.popleft()
                except IndexError:
                    break  # every snapshot handed over is sampled
                self._pass = (self.notifications.begin(snap, time.monotonic()), snap.stamp)
                self.stats.sampling_passes += 1
            samples, filetime = self._pass
            while not samples.done:
                samples.step(_SAMPLE_STEP)
                if time.perf_counter() >= deadline:
                    break
            for batch in samples.take():
                self._send_batch(batch, filetime)
            if samples.done:
                self._pass = None
            else:
                self.stats.sampling_slices += 1
            if time.perf_counter() >= deadline:
                break
        self._update_status()
        return self._pass is not None or bool(self._handed)

    def _again(self) -> None:
        """Head: another sampling round in a later loop iteration (other requests
        first), while machines wait."""
        if self._ready and not self._round_pending:
            loop = self._loop
            if loop is not None and not loop.is_closed():
                self._round_pending = True
                loop.call_soon(self._sample_round)

    def _send_batch(self, batch: Batch, filetime: int) -> None:
        conn = batch.owner
        assert isinstance(conn, AdsConnection)
        if conn.backlog > self.options.notification_backlog:
            self.stats.notifications_dropped += len(batch.samples)
            return
        self._notify_invoke = (self._notify_invoke + 1) & 0xFFFF_FFFF
        payload = codec.device_notification([Stamp(filetime, tuple(batch.samples))])
        conn.send(
            codec.notification_frame(batch.server, batch.client, payload, self._notify_invoke)
        )
        self.stats.notifications_sent += len(batch.samples)

    # ------------------------------------------------------------------ connections

    def _connected(self, conn: AdsConnection) -> bool:
        """Admit `conn` unless `max_connections` are open already (then False: the
        connection closes at once, before it can make the server buffer anything)."""
        if not self.listener.admit(conn):
            self.stats.refused_connections = self.listener.refused
            return False
        self.stats.connections += 1
        return True

    def take_turn(self, packet: AmsPacket) -> bool:
        """Head: may `packet` be served in this loop step? Each machine serves at most
        `requests_per_step` requests per step (counted at the machine the request
        targets); the counts start again in the next step."""
        device = self.devices.get(packet.header.target.netid, self)
        if device._served >= self.options.requests_per_step:
            device.stats.deferred_requests += 1
            return False
        device._served += 1
        if not device._step_reset and self._loop is not None:
            device._step_reset = True
            self._loop.call_soon(device._new_step)
        return True

    def _new_step(self) -> None:
        self._served = 0
        self._step_reset = False

    def _attach(self, conn: AdsConnection) -> bool:
        """`conn` sends this machine its first request: it counts towards this machine's
        `max_connections` — False (the request is answered 0x716) when it is full."""
        if len(self._attached) >= self.options.max_connections:
            self.stats.refused_requests += 1
            _log_rarely(
                self.stats.refused_requests,
                "ADS %s: refusing a request of %s: %d connections use this machine",
                self.options.netid,
                conn.peer,
                len(self._attached),
            )
            return False
        self._attached.add(conn)
        return True

    def _disconnected(self, conn: AdsConnection) -> None:
        if self.router is None:
            self.listener.forget(conn)
            if conn.ams_port is not None:
                self._ams_ports.pop(conn.ams_port, None)
            for device in self.devices.values():
                if device is not self:
                    device._disconnected(conn)
        self._attached.discard(conn)
        table = conn.tables.pop(id(self), None)
        if table is not None:
            self.handles_held -= len(table.handles)
            self.head.fleet_handles -= len(table.handles)
        n = self.notifications.drop_owner(conn)
        if n:
            log.debug("dropped %d notifications of %s", n, conn.peer)
            self._update_status()
        if not len(self.notifications):
            self._demand(False)


#: A sum write item: the object address and data, or the ADS code it earned already.
WriteItem = tuple[int, int, bytes] | int
#: AMS ports the router hands to clients (TwinCAT's ADS clients get 30000 and up).
FIRST_CLIENT_PORT, LAST_CLIENT_PORT = 32768, 65535
_RESERVED_PORTS = frozenset({*AMS_PORTS, SYSTEM_SERVICE_PORT})
_NAME_SERVICES = frozenset(
    {
        symbols.SYM_HNDBYNAME,
        symbols.SYM_VALBYNAME,
        symbols.SYM_INFOBYNAMEEX,
        symbols.SYM_DT_INFOBYNAMEEX,
    }
)
_LOOKUPS = frozenset(ig + ADDRESS_LOOKUP for ig in TASK_GROUPS.values())


def _geo_port_only(ig: int) -> None:
    """The symbol, name and lookup services are the GEO task's: on the COM task's port
    (553, the volumetric objects) they answer 0x702, as a group that port does not know."""
    if REQUEST_PORT.get() == COM_AMS_PORT:
        raise AdsError(
            AdsErrorCode.DEVICE_INVALIDGRP,
            f"index group 0x{ig:X} is a service of the GEO task (AMS port 551), not 553",
        )


_UPLOADS = frozenset(
    {symbols.SYM_UPLOAD, symbols.SYM_UPLOADINFO, symbols.SYM_UPLOADINFO2, symbols.SYM_DT_UPLOAD}
)
#: The GEO task's symbol services (reads)
_GEO_SERVICES = _UPLOADS | {symbols.SYM_VERSION}
#: Services a notification may watch besides the objects (constant values: one sample)
_NOTIFIABLE_SERVICES = frozenset({symbols.DEVICE_DATA, symbols.SYM_VERSION})


def _fixed(value: bytes, length: int, what: str) -> bytes:
    """A short fixed value: at most `length` bytes of it; 0 bytes asked is 0x705."""
    if length <= 0:
        raise AdsError(AdsErrorCode.DEVICE_INVALIDSIZE, f"read of {length} bytes of {what}")
    return value[:length]


def _by_slot(item: tuple[str, int]) -> int:
    return item[1]


_SUM_GROUPS = frozenset(int(g) for g in SumGroup) - {
    SumGroup.ADD_DEVICE_NOTIFICATION,
    SumGroup.DELETE_DEVICE_NOTIFICATION,
}


def _log_rarely(count: int, msg: str, *args: object) -> None:
    """A warning for the 1st, 2nd, 4th, 8th… occurrence, debug otherwise: a flood of
    hostile connections must not turn into a flood of log lines."""
    log.log(logging.WARNING if count & (count - 1) == 0 else logging.DEBUG, msg, *args)


class _Discovery(asyncio.DatagramProtocol):
    """UDP 48899: one answer per request datagram, to its sender."""

    def __init__(self, server: AdsServer) -> None:
        self.server = server
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # (the selector loop's datagram transport is not an asyncio.DatagramTransport
        # subclass on every Python: no isinstance check)
        self.transport = cast(asyncio.DatagramTransport, transport)

    def datagram_received(self, data: bytes, addr: Any) -> None:
        reply = self.server.answer_datagram(data)
        if reply is not None and self.transport is not None:
            self.transport.sendto(reply, addr)


@dataclass
class HandleTable:
    """The symbol handles one connection holds at one device (0xF003 -> symbol)."""

    handles: dict[int, symbols.Symbol] = field(default_factory=dict)
    next_handle: int = 0


class AdsConnection(asyncio.Protocol):
    """One TCP client: framing in, responses and notifications out.

    A frame that stays unfinished for `incomplete_frame_timeout` seconds after its first
    byte (the framer's `incomplete_since`, on the loop's clock) closes the connection:
    one timer per connection, armed when an unfinished frame begins and cancelled when
    it completes.
    """

    def __init__(self, server: AdsServer) -> None:
        self.server = server
        self.framer = codec.Framer(server.options.max_frame)
        self.transport: asyncio.Transport | None = None
        self.peer: Any = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._admitted = False
        self._frame_timer: asyncio.TimerHandle | None = None
        self._frame_timer_since: float | None = None
        #: AMS port the router gave this client (port connect), None without
        self.ams_port: int | None = None
        #: symbol handles of this connection (0xF003), per device (AMS NetId) it
        #: talks to: one TCP connection may address every machine of a fleet
        self.tables: dict[int, HandleTable] = {}
        # reading paused: the client does not read its answers / too many outstanding
        self._paused_writing = False
        self._paused_work = False
        #: events read but not served yet: their machine had served its turn
        self._queued: deque[codec.FrameEvent] = deque()

    def table(self, device: AdsServer) -> HandleTable:
        """This connection's symbol handles at `device`."""
        t = self.tables.get(id(device))
        if t is None:
            t = self.tables[id(device)] = HandleTable()
        return t

    # (Equality and hash are object identity, the C defaults: a connection is a key of
    # the notification table and of every sampled route, looked up per sample.)

    # asyncio callbacks

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        self.peer = transport.get_extra_info("peername")
        self._admitted = self.server._connected(self)
        if not self._admitted:
            refused = self.server.stats.refused_connections
            _log_rarely(
                refused,
                "ADS refusing %s: %d connections open (%d refused so far)",
                self.peer,
                self.server.connection_count,
                refused,
            )
            self.framer.close()
            transport.abort()  # nothing was sent to it; free the socket at once

    def connection_lost(self, exc: Exception | None) -> None:
        if self._admitted:
            self.server._disconnected(self)
        for t in list(self._tasks):
            t.cancel()
        self._cancel_frame_timer()
        self.framer.close()  # release an unfinished frame's buffer now
        self.transport = None

    def data_received(self, data: bytes) -> None:
        loop = self.server._loop
        now = loop.time() if loop is not None else 0.0
        events = self.framer.feed(data, now)
        if self._queued:  # (reading is paused; what was read already waits its turn)
            self._queued.extend(events)
        else:
            self._handle(events)
        self._arm_frame_timer()

    def _handle(self, events: Sequence[codec.FrameEvent]) -> None:
        """Serve `events` in order. A request for a machine that has served its
        `requests_per_step` in this loop step waits, with the rest, for the next step
        (reading paused meanwhile): a client pipelining requests to one machine takes
        that machine's turn, not the other machines' (docs/design.md §13.1)."""
        for i, ev in enumerate(events):
            if isinstance(ev, AmsPacket):
                if not self.server.take_turn(ev):
                    self._queued.extend(events[i:])
                    if self.transport is not None and not self.transport.is_closing():
                        self.transport.pause_reading()
                    loop = self.server._loop
                    if loop is not None:
                        loop.call_soon(self._drain)
                    return
                self.server.handle_packet(self, ev)
            elif isinstance(ev, codec.RouterCommand):
                self.server.handle_router(self, ev)
            elif isinstance(ev, BadPacket):
                self.server.stats.dropped_frames += 1
                log.debug("ADS bad packet from %s: %s", self.peer, ev.reason)
                if not ev.header.is_response and ev.header.command != Command.DEVICE_NOTIFICATION:
                    self.send(codec.response_frame(ev.header, b"", ev.error_code))
            elif isinstance(ev, Dropped):
                self.server.stats.dropped_frames += 1
                log.debug("ADS frame dropped from %s: %s", self.peer, ev.reason)
            elif isinstance(ev, StreamError):
                self.server.stats.closed_for_framing += 1
                log.warning("ADS closing %s: %s", self.peer, ev.reason)
                self._cancel_frame_timer()
                if self.transport is not None:
                    self.transport.close()  # flushes the answers already queued
                return

    def _drain(self) -> None:
        """A later loop step: serve the requests that waited for their machine's turn."""
        if self.transport is None:
            self._queued.clear()
            return
        events, self._queued = list(self._queued), deque()
        self._handle(events)
        if not self._queued:
            self._resume_reading()

    def _arm_frame_timer(self) -> None:
        """Keep the timer in step with the unfinished frame (if any) after a feed."""
        since = self.framer.incomplete_since
        timeout = self.server.options.incomplete_frame_timeout
        if since is None or timeout <= 0:
            self._cancel_frame_timer()
            return
        if self._frame_timer is not None and self._frame_timer_since == since:
            return  # the same frame is still arriving: its deadline stands
        self._cancel_frame_timer()
        loop = self.server._loop
        if loop is None:
            return
        self._frame_timer = loop.call_at(since + timeout, self._frame_timed_out)
        self._frame_timer_since = since

    def _cancel_frame_timer(self) -> None:
        if self._frame_timer is not None:
            self._frame_timer.cancel()
        self._frame_timer = None
        self._frame_timer_since = None

    def _frame_timed_out(self) -> None:
        self._frame_timer = None
        if self.transport is None or self.framer.incomplete_since is None:
            return
        self.server.stats.closed_incomplete += 1
        _log_rarely(
            self.server.stats.closed_incomplete,
            "ADS closing %s: a frame stayed unfinished for %g s (%d bytes buffered)",
            self.peer,
            self.server.options.incomplete_frame_timeout,
            self.framer.buffered,
        )
        self.framer.close()
        # abort, not close: a client that stalls mid-frame may not read either, and a
        # graceful close would wait for its unread answers.
        self.transport.abort()

    def pause_writing(self) -> None:
        # The client does not read its answers: stop reading its requests meanwhile.
        self._paused_writing = True
        if self.transport is not None:
            self.transport.pause_reading()

    def resume_writing(self) -> None:
        self._paused_writing = False
        self._resume_reading()

    def _resume_reading(self) -> None:
        if self._paused_writing or self._paused_work or self._queued:
            return
        if self.transport is not None and not self.transport.is_closing():
            self.transport.resume_reading()

    # used by the server

    @property
    def backlog(self) -> int:
        return self.transport.get_write_buffer_size() if self.transport is not None else 0

    def send(self, frame: bytes) -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.write(frame)

    def spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        """Run an answer that comes later. With `max_pending` of them outstanding the
        connection stops reading requests until half are answered: the work one client
        can queue is bounded, whatever it pipelines."""
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._done)
        if len(self._tasks) >= self.server.options.max_pending and not self._paused_work:
            self._paused_work = True
            if self.transport is not None and not self.transport.is_closing():
                self.transport.pause_reading()

    def _done(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        if self._paused_work and len(self._tasks) <= self.server.options.max_pending // 2:
            self._paused_work = False
            self._resume_reading()

    def abort(self) -> None:
        if self.transport is not None:
            self.transport.abort()

    def close(self) -> None:
        """Close after the answers already queued."""
        if self.transport is not None:
            self.transport.close()


__all__ = ["GEO_AMS_PORT", "AdsConnection", "AdsOptions", "AdsServer", "AdsStats", "error_payload"]
