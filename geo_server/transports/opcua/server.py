"""The OPC UA interface (README *OPC UA*, docs/security.md): a thin shell of asyncua over
the object service, like the Zenoh interface (docs/design.md §7).

- **Address space**: generated from the dictionary (`space.py`); one server serves
  every machine of a fleet, each under its own name below `Objects`.
- **Reads** answer the exact-engine observation of the read's wall time
  (`ObjectService.current`, once per Read request and machine: the values of one
  request come from one cycle), stamped with the cycle's time as the source timestamp.
- **Writes** of the Value attribute go through the service's write path
  (`prepare_name` + `apply_writes`: the same range checks, applied by the next cycle);
  the writes of one request are applied in one cycle. An `AdsError` maps to a status
  code (`STATUS`, README *Errors and their codes*).
- **Monitored items** of our variables are sampled once per GEO cycle (or at the
  smallest sampling interval asked for the variable, in whole cycles) while any exists:
  each sampled cycle whose value changed is one notification with the cycle's time as
  its source timestamp, put straight into each item's queue (one DataValue shared by
  the items of a variable). Bounded per session and in total (`OpcUaOptions`).
- **Methods** Reload, Save, RunNc, Reset, InjectFault, ClearFaults: the commands of the
  other interfaces with the same results (JSON text) and errors (status codes).
- **Security**: anonymous unless `user`/`password` are given; Basic256Sha256
  SignAndEncrypt with a self-signed certificate made on first start (`certs.py`) beside
  None (or alone with `encrypt_only`); `read_only` refuses writes and methods.

asyncua is imported only when the interface starts (it takes about 0.3 s to import).
The address space (asyncua's standard nodes, then ours) is built off the loop with the
cyclic garbage collector paused, and frozen afterwards (`_collector_paused`).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import datetime as dt
import gc
import hmac
import importlib
import json
import logging
import os
import re
import socket
import threading
from collections.abc import Awaitable, Callable, Coroutine, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from geo_server import __version__
from geo_server.aio import LoopThread, nice_this_thread, on_loop
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.events import Event
from geo_server.faults import FaultError
from geo_server.seam import OpcUaService
from geo_server.service import is_command
from geo_server.snapshot import Snapshot
from geo_server.transports.opcua import cnc, companions, internals, machinetool
from geo_server.transports.opcua.cnc import Live
from geo_server.transports.opcua.endpoint import parse_endpoint
from geo_server.transports.opcua.internals import ua as _ua
from geo_server.transports.opcua.logins import LoginThrottle
from geo_server.transports.opcua.metering import RequestMeter
from geo_server.transports.opcua.monitoring import FILETIME_EPOCH, Monitoring, Var
from geo_server.transports.opcua.space import (
    APPLICATION_URI,
    AXES,
    METHODS,
    NAMESPACE_URI,
    MethodSpec,
    VariableSpec,
    machine_variables,
)
from geo_server.transports.opcua.status import ITEMS_STATUS, SHARE_STATUS
from geo_server.transports.share import LoopShare
from geo_server.units import ACHS_TYP, LINEAR, UNECE, unece_unit_id

log = logging.getLogger(__name__)
T = TypeVar("T")

#: ADS return code -> OPC UA status code name (README *Errors and their codes*).
STATUS: dict[int, str] = {
    AdsErrorCode.DEVICE_INVALIDGRP: "BadNodeIdUnknown",
    AdsErrorCode.DEVICE_INVALIDOFFSET: "BadNodeIdUnknown",
    AdsErrorCode.DEVICE_INVALIDACCESS: "BadNotWritable",
    AdsErrorCode.DEVICE_INVALIDSIZE: "BadOutOfRange",
    AdsErrorCode.DEVICE_INVALIDDATA: "BadOutOfRange",
    AdsErrorCode.DEVICE_NOTREADY: "BadResourceUnavailable",
    AdsErrorCode.DEVICE_BUSY: "BadInvalidState",
    AdsErrorCode.DEVICE_INVALIDPARM: "BadInvalidArgument",
    AdsErrorCode.DEVICE_SYNTAX: "BadSyntaxError",
    AdsErrorCode.DEVICE_ERROR: "BadInternalError",
    AdsErrorCode.DEVICE_SRVNOTSUPP: "BadNotSupported",
    AdsErrorCode.DEVICE_TIMEOUT: "BadTimeout",
}
#: The namespace of the units' common codes (OPC 10000-8 §5.6.3).
UNECE_URI = "http://www.opcfoundation.org/UA/units/un/cefact"
#: Who the server says it is (Server/ServerStatus/BuildInfo, the endpoints'
#: ApplicationDescription).
PRODUCT_URI = "urn:geo-server"
PRODUCT_NAME = MANUFACTURER = "geo-server"
#: Status of a write of a variant of the wrong type (checked before the service).
TYPE_MISMATCH = "BadTypeMismatch"
#: Status of a write or method call on a read-only interface.
READ_ONLY = "BadUserAccessDenied"


def probe_port(host: str, port: int) -> None:
    """OSError now when `host:port` cannot be listened on (taken by another server),
    before a background start (`OpcUaOptions.background`) would find out."""
    infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as sock:
        if os.name == "posix":  # as asyncio's create_server, which listens afterwards
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)


def quiet_library() -> None:
    """asyncua logs every client's mistake (a refused session, a bad request, a closed
    socket) as a warning or an error with its traceback: one misbehaving client would
    flood the console (docs/security.md). Unless logging was configured for it, only
    its critical messages are shown; the clients get status codes."""
    lib = logging.getLogger("asyncua")
    if lib.level == logging.NOTSET:
        lib.setLevel(logging.CRITICAL)


def status_name(exc: AdsError) -> str:
    """The OPC UA status code (name) of a refusal (`STATUS`; else BadInternalError)."""
    return STATUS.get(exc.code, "BadInternalError")


def source_time(snap: Snapshot) -> dt.datetime:
    """The cycle's place on the time line (`Snapshot.stamp`, FILETIME) as UTC time."""
    return FILETIME_EPOCH + dt.timedelta(microseconds=snap.stamp // 10)


@contextlib.contextmanager
def _collector_paused() -> Iterator[None]:
    """Build the address space without the cyclic garbage collector, then freeze it.

    asyncua's standard address space is about half a million objects, made at once.
    While they are made, the collector would run its oldest generation several times
    over all of them (0.1-0.3 s each, holding the GIL: every interface and the GEO cycle
    wait), about 0.5 s of a 1.3 s start, and again soon after as they age. They live as
    long as the server, so they are moved out of the collector's reach
    (`gc.freeze`, undone by `OpcUaInterface.close`): later collections skip them. The
    build makes almost no cyclic garbage (ten objects), so little is frozen with it."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        if enabled:
            gc.enable()


#: the niceness of asyncua's thread (Linux): see `start`
OPCUA_NICE = 10

#: In a fleet, the most of OPC UA's share one machine's requests may take: a client
#: flooding one machine leaves the others' clients at least the rest
MACHINE_PART = 0.5

#: The longest a request on asyncua's thread waits for the main loop to catch the
#: machine up (`_current`) before it is answered as a stall (0x707's status): the
#: service's own wait for a catch-up (`SYNC_WAIT`, 0.25 s) and as much again, well under
#: the second after which asyncua's client gives up on a keep-alive
HOST_WAIT_S = 0.5

#: `close`: the longest it waits for asyncua's server to stop, and then again for its
#: thread to end (SIGTERM ends the server within 2 s whatever its clients do: the
#: guard aborts their connections, `guard.stop`)
CLOSE_WAIT_S = 0.75


@dataclass
class OpcUaOptions:
    """The OPC UA endpoint, its security and its limits (docs/limits.md)."""

    endpoint: str = "opc.tcp://127.0.0.1:4840"
    read_only: bool = False
    #: With both set, a session needs this user name and password (anonymous refused).
    user: str | None = None
    password: str | None = None
    #: Folder of the server's certificate and key (made on first start); None: no
    #: encrypted endpoint.
    cert_dir: Path | None = None
    #: Offer only Basic256Sha256 SignAndEncrypt (no unencrypted endpoint).
    encrypt_only: bool = False
    #: The CNC (OPC 40502) and Machine Tool (OPC 40501) companion models of every
    #: machine (docs/opcua.md); loading their NodeSets takes about 3 s of the start.
    companion_models: bool = True
    #: A fleet's machines after the first of a shape are made when a request first
    #: touches one of their nodes; with `make_all`, once serving, the rest are made in
    #: the background too, one per turn of OPC UA's loop (`_make_pending`).
    make_all: bool = True
    #: TCP connections at once (asyncua's own default: 1000); more are refused.
    max_connections: int = 64
    #: Monitored items in one session (of any node); more are refused with
    #: BadTooManyMonitoredItems. 1000 is ten HMI screens of 100 values.
    max_monitored_items_per_session: int = 1000
    #: Monitored items in all sessions together, of any node (each of our variables'
    #: costs a comparison per sampled cycle on OPC UA's thread).
    max_monitored_items: int = 5000
    #: Subscriptions in all sessions together (asyncua's own default: 1000).
    max_subscriptions: int = 256
    #: A client that has not read its answers for this long (seconds) is closed; until
    #: then its requests are not read (guard.py).
    unread_close_s: float = 10.0
    #: The processor time (seconds per second) that OPC UA's requests may take on its
    #: thread, and as much again its notifications (`metering.py`; two buckets, so a
    #: flood of notifications never starves the requests, a client's keep-alive among
    #: them): asyncua's work is pure Python, and on a small host its thread competes
    #: for the cores and the interpreter lock with ADS, Modbus, the web HMI and the
    #: cycle. An HMI that reads 100 values every 100 ms takes about a thirtieth. Past
    #: it, requests wait and values are sampled less often.
    loop_share: float = 0.2
    #: The most loop time (seconds) OPC UA may take in a row after a quiet spell (a
    #: client connecting and subscribing takes a few tens of ms), one request per turn
    #: of the loop, so the others' requests are answered in between.
    loop_burst_s: float = 0.05
    #: `start` checks the port, then returns; the server (about 1.5 s of asyncua
    #: building its standard address space) comes up while the other interfaces and
    #: the GEO cycle already serve (`geo-server run`). How it ended goes to
    #: `OpcUaInterface.on_started`.
    background: bool = False

    def shrink_to(self, connections: int) -> None:
        """Fit the connection cap into `connections` descriptors (geo_server/descriptors.py)."""
        self.max_connections = max(1, min(self.max_connections, connections))

    @property
    def host_port(self) -> tuple[str, int]:
        return parse_endpoint(self.endpoint)


class OpcUaInterface:
    """Serve the objects of one machine, or of every machine of a fleet, over OPC UA."""

    def __init__(
        self,
        services: Mapping[str, OpcUaService],
        options: OpcUaOptions | None = None,
        shares: Mapping[str, LoopShare] | None = None,
        *,
        loop_share: LoopShare | None = None,
        notify_share: LoopShare | None = None,
    ) -> None:
        """`services`: machine name -> its object service; `shares` (a fleet's): machine
        name -> its share of the event loop, whose rate its share of OPC UA's thread
        takes (`machine_shares`, `metering.py`); `loop_share`, `notify_share`: OPC UA's
        own, for its requests and for its notifications (default: of the options)."""
        self.services = dict(services)
        self.options = options or OpcUaOptions()
        opts = self.options
        #: OPC UA's share of its thread for its requests (`OpcUaOptions.loop_share`)
        self.loop_share = loop_share or LoopShare(opts.loop_share, opts.loop_burst_s)
        #: each machine's share of OPC UA's thread: its fleet share's rate, at most
        #: `MACHINE_PART` of OPC UA's (so one machine's clients leave the others the
        #: rest); asyncua runs on a loop of its own (`_own`), the fleet's shares are the
        #: main loop's (ADS, Modbus)
        most = self.loop_share.rate * MACHINE_PART
        self.machine_shares = {
            m: LoopShare(min(s.rate, most), s.burst, s.clock) for m, s in (shares or {}).items()
        }
        self.meter = RequestMeter(self.loop_share, self.machine_shares)
        #: the share of its notifications, sampled and published (as much again, a
        #: bucket of its own)
        self.notify_share = notify_share or LoopShare(opts.loop_share, opts.loop_burst_s)
        self.server: Any = None
        self.port = 0
        self.ns = 0
        #: the companion models' namespace indexes (CNC, Machine Tool, Machinery)
        self.cnc_ns = self.mt_ns = self.machinery_ns = 0
        self._vars: dict[Any, Var] = {}
        #: copied machines whose nodes are still to be made: name -> (template, its
        #: service, its shape) (`_materialize`; asyncua's loop's)
        self._pending: dict[str, tuple[str, OpcUaService, Any]] = {}
        self._making: asyncio.Future[None] | None = None  # (`_make_pending`)
        #: (shape, machine): the machine whose nodes the others of its shape copy
        self._shapes: list[tuple[Any, str]] = []
        #: machine -> the node ids of its nodes, and how to copy them (`_copy_nodes`)
        self._subtrees: dict[str, list[Any]] = {}
        self._plans: dict[str, list[tuple[str, Any, list[tuple[Any, str | None]]]]] = {}
        #: template -> (a node out of it, the suffix of its node that node holds)
        self._anchors: dict[str, list[tuple[Any, str]]] = {}
        #: the NodeId attribute every copied node shares: its value made when read
        self._own_id: Any = None
        self._closing = False  # (read by a build worker between machines)
        #: each machine's event subscription's end, its events' generator and the
        #: events being sent (the loop's)
        self._unwatch: list[Callable[[], None]] = []
        self._generators: dict[str, Any] = {}
        self._sending: set[asyncio.Future[None]] = set()
        #: the monitored items of our variables and their sampling (monitoring.py)
        self.monitoring = Monitoring(
            self._vars,
            self.notify_share,
            self._datavalue,
            opts.max_monitored_items_per_session,
            opts.max_monitored_items,
        )
        self._stamped: tuple[Any, dt.datetime] = (None, FILETIME_EPOCH)
        self._frozen = False
        #: asyncua's loop and thread (`opcua`): every coroutine of this interface but
        #: `start` and `close` runs there (docs/design.md §9.1, §5.10)
        self._own = LoopThread("opcua")
        self._loop: asyncio.AbstractEventLoop | None = None
        #: the loop `start` was called on (ADS, Modbus, ...): the machine's catch-ups,
        #: writes and methods run there (`_current`, `_on_host`)
        self._host: asyncio.AbstractEventLoop | None = None
        self._start_task: asyncio.Future[None] | None = None
        #: failed logins per client address (guard.py): asyncua's loop's
        self.login_throttle = LoginThrottle()
        #: the background start (`OpcUaOptions.background`), its failure, and who is
        #: told when it is done (with the failure or None; after a failure the other
        #: interfaces keep serving)
        self.starting: asyncio.Future[None] | None = None
        self.failure: BaseException | None = None
        self.on_started: Callable[[BaseException | None], None] | None = None

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        """Serve: at once, or with `options.background` once the address space is
        built (see there); the port is checked now either way. asyncua runs on a
        thread and loop of its own, started here, niced on Linux: a request's
        milliseconds of pure Python then hold that loop, not the one of ADS, Modbus and
        the web HMI (docs/design.md §9.1)."""
        self._host = asyncio.get_running_loop()
        for machine, share in self.machine_shares.items():  # (their status: the loop's)
            self.services[machine].status_extra[SHARE_STATUS] = share.status
        for machine, service in self.services.items():  # (made before asyncua's loop runs)
            service.status_extra[ITEMS_STATUS] = self.monitoring.counts(machine)
        if not self.options.background:
            self._own.start()
            try:
                await self._own.run(self._start())
            except BaseException:
                with contextlib.suppress(Exception):  # (whatever it got to: stopped)
                    await asyncio.wait_for(self._own.run(self._close()), CLOSE_WAIT_S)
                await self._own.stop(CLOSE_WAIT_S)
                raise
            return
        host, port = self.options.host_port
        if port:
            await asyncio.to_thread(probe_port, host, port)
        self.port = port
        self._own.start()
        self.starting = asyncio.ensure_future(self._own.run(self._start()))
        self.starting.add_done_callback(self._started)

    def _started(self, task: asyncio.Future[None]) -> None:
        if task.cancelled() or self._closing:
            return
        self.failure = task.exception()
        if self.on_started is not None:
            self.on_started(self.failure)

    async def _start(self) -> None:
        self._start_task = asyncio.current_task()
        self._loop = self.monitoring.loop = asyncio.get_running_loop()
        # imported off the loop: 0.3 s the other interfaces would wait otherwise
        await asyncio.to_thread(importlib.import_module, "asyncua")
        from asyncua import Server

        quiet_library()
        opts = self.options
        users: Any = _Users(opts.user, opts.password)  # asyncua's UserManager protocol
        server = Server(user_manager=users)
        self.server = self.monitoring.server = server
        with _collector_paused():
            self._frozen = True
            await self._init_and_build(server)
        self._hook()
        from geo_server.transports.opcua import guard

        guard.guard(server, self.login_throttle, self.notify_share)  # (docs/security.md)
        await guard.advertise(
            server,
            {
                "MaxSessions": opts.max_connections,  # (one session per connection)
                "MaxSubscriptions": opts.max_subscriptions,
                "MaxMonitoredItems": opts.max_monitored_items,
            },
        )
        # served from now on: niced (built at the others' priority: a fleet's build
        # competes with its machines' start, and its workers, made meanwhile, stay so)
        nice_this_thread(OPCUA_NICE)
        await guard.start(server, opts.unread_close_s, self.meter)
        assert server.bserver is not None
        self.port = server.bserver.port
        if opts.companion_models:
            for machine, service in self.services.items():
                self._unwatch.append(service.subscribe_events(self._on_event(machine)))
        if self._pending and opts.make_all:
            self._making = asyncio.ensure_future(self._make_pending())

    async def _init_and_build(self, server: Any) -> None:
        """asyncua's standard address space (filled in a thread by asyncua), the
        endpoint and its security, then the nodes of every machine."""
        ua = _ua()
        opts = self.options
        host, port = opts.host_port
        server.product_uri = PRODUCT_URI
        server.manufacturer_name = MANUFACTURER
        await server.init()
        await server.set_build_info(
            PRODUCT_URI, MANUFACTURER, PRODUCT_NAME, __version__, __version__, _build_date()
        )
        internals.set_limits(server, opts.max_connections, opts.max_subscriptions)
        server.set_endpoint(f"opc.tcp://{host}:{port}/")
        server.set_server_name("geo-server")
        await server.set_application_uri(APPLICATION_URI)
        if opts.user is not None and opts.cert_dir is None:
            # the password travels encrypted with the server's key (guard.py)
            raise ValueError("a user and password need a certificate folder (cert_dir)")
        policies = [] if opts.encrypt_only else [ua.SecurityPolicyType.NoSecurity]
        if opts.cert_dir is not None:
            from geo_server.transports.opcua.certs import ensure_certificate

            cert, key = await asyncio.to_thread(
                ensure_certificate, opts.cert_dir, APPLICATION_URI, host
            )
            await server.load_certificate(str(cert))
            await server.load_private_key(str(key))
            policies.append(ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt)
        if not policies:
            raise ValueError("encrypt_only needs a certificate folder (cert_dir)")
        server.set_security_policy(policies)
        anonymous = opts.user is None
        server.set_identity_tokens(
            [ua.AnonymousIdentityToken] if anonymous else [ua.UserNameIdentityToken]
        )
        self.ns = await server.register_namespace(NAMESPACE_URI)
        # the CNC model's types (OPC 40502; `cnc.py`), after ours: ours stays index 2
        if opts.companion_models:
            await _off_loop(lambda: companions.add(server, lambda: self._closing))
            self.cnc_ns = await server.get_namespace_index(cnc.CNC_URI)
            self.mt_ns = await server.get_namespace_index(machinetool.MACHINE_TOOL_URI)
            self.machinery_ns = await server.get_namespace_index(machinetool.MACHINERY_URI)
        await self._build_all()
        if opts.companion_models and len(self.services) == 1:  # (a fleet's: below each)
            await self._link_cnc_from_objects(next(iter(self.services)))

    async def close(self) -> None:
        """Stop serving (within `CLOSE_WAIT_S` twice, whatever the clients do), and end
        asyncua's thread."""
        self._closing = True  # (a background start ending now tells nobody: `_started`)
        if self._own.loop is None:
            return
        try:
            # (a background start is cancelled there, not here: its coroutine may not
            # have begun yet, and `_close` comes after it on that loop)
            await asyncio.wait_for(self._own.run(self._close()), CLOSE_WAIT_S)
        except (TimeoutError, RuntimeError):  # (its loop ended already)
            pass
        finally:
            await self._own.stop(CLOSE_WAIT_S)

    async def _close(self) -> None:
        """`close` on asyncua's loop."""
        start = self._start_task
        if start is not None and not start.done():
            start.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await start
        if self._frozen:  # its address space goes back to the collector (`_collector_paused`)
            self._frozen = False  # (after the start: its freeze is behind us)
            gc.unfreeze()
        for unwatch in self._unwatch:
            unwatch()
        self._unwatch.clear()
        drain = self.monitoring.close()
        if self._making is not None:
            self._making.cancel()
        if drain is not None:
            with contextlib.suppress(asyncio.CancelledError):
                await drain
        if self.server is not None:
            from geo_server.transports.opcua import guard

            server, self.server = self.server, None
            self.monitoring.server = None
            with contextlib.suppress(Exception):
                await guard.stop(server)
        self.meter.close()  # (the requests it still held: their connections are gone)

    @property
    def endpoint(self) -> str:
        host, _ = self.options.host_port
        return f"opc.tcp://{host}:{self.port}"

    # ------------------------------------------------------------------ address space

    async def _build_all(self) -> None:
        """Every machine's object, its folders, variables (`space.machine_variables`)
        with their properties, its methods and companion models, made off the loop
        (nothing serves them yet): the first machine of a shape (its axes, their kinds,
        its dictionary) with asyncua's AddNodes (0.1-0.2 s); every other one of that
        shape is a copy of it (`_copy_nodes`) made when a request first touches one of
        its nodes (`_materialize`): only the references that lead to it from outside
        (Objects, the Machinery `Machines` folder) are made now. A copy takes 20-30 ms,
        so a fleet of 500 would wait 15 s for them, most of which nobody browses."""
        pending: dict[str, tuple[str, OpcUaService, Any]] = {}
        for machine, service in self.services.items():
            shape = _shape(service)
            template = next((m for s, m in self._shapes if s == shape), None)
            if template is None:
                await self._build_first(machine, service, shape)
                self._shapes.append((shape, machine))
                continue
            pending[machine] = (template, service, shape)
        if pending:
            await asyncio.to_thread(self._anchor_all, pending)

    def _anchor_all(self, pending: dict[str, tuple[str, OpcUaService, Any]]) -> None:
        """The references to each copied machine from outside it; its nodes are made on
        first use (`guard.lazy_nodes`)."""
        from geo_server.transports.opcua import guard

        for machine, (template, _service, _shape) in pending.items():
            if self._closing:  # (closed meanwhile: the worker is not cancelled with it)
                return
            self._anchor(template, machine)
        self._pending.update(pending)
        guard.lazy_nodes(self.server, self._materialize)
        self._vars = guard.MadeOnUse(self._vars, self._materialize)
        # (a new mapping: the items look their variables up in it too, and a copied
        # machine's variables land only there)
        self.monitoring.variables = self._vars

    def _materialize(self, node_id: Any) -> bool:
        """Make the nodes of the copied machine `node_id` belongs to, now that a request
        asks for one of them (on asyncua's loop); False: it belongs to none still to
        be made."""
        if not self._pending or not isinstance(node_id, _ua().NodeId):
            return False
        ident = node_id.Identifier
        if not isinstance(ident, str) or node_id.NamespaceIndex != self.ns:
            return False
        machine = ident.split("/", 1)[0]
        pending = self._pending.pop(machine, None)
        if pending is None:
            return False
        if self.server is None:  # (closing: nothing is made any more)
            self._pending[machine] = pending
            return False
        template, service, shape = pending
        try:
            self._copy_nodes(template, machine)
            self._serve_all(machine, service, shape)
        except BaseException:  # (made again, whole, at the next look-up)
            self._pending[machine] = pending
            raise
        if self._frozen:  # (as the build's: out of the collector's way, `_collector_paused`)
            gc.freeze()
        return True

    async def _make_pending(self) -> None:
        """Once serving, the machines no request has made yet, one per turn of the
        loop: a request that touches many of them (a Read across a fleet, a client
        browsing every machine's name) then finds them made, rather than making them
        all itself (25 ms each). A request may still make one first."""
        ua = _ua()
        while self._pending and not self._closing:
            self._materialize(ua.NodeId(next(iter(self._pending)), self.ns))
            await asyncio.sleep(0)

    async def _build_first(self, machine: str, service: OpcUaService, shape: Any) -> None:
        names, kinds, dictionary = dict(shape[0]), dict(shape[1]), shape[2]
        await asyncio.to_thread(self._add_nodes, machine, service, names, kinds)
        if self.options.companion_models:
            specs = machine_variables(machine, dictionary, names, kinds)
            await _off_loop(lambda: self._add_cnc(machine, names, kinds, specs))
            await _off_loop(lambda: self._add_machine_tool(machine))
        self._serve_all(machine, service, shape)

    def _serve_all(self, machine: str, service: OpcUaService, shape: Any) -> None:
        """Serve a machine's variables, methods and companion models."""
        names, kinds, dictionary = dict(shape[0]), dict(shape[1]), shape[2]
        self._serve(machine, service, machine_variables(machine, dictionary, names, kinds))
        if self.options.companion_models:
            axes = {axis: (names[axis], kinds[axis]) for axis in names}
            live = cnc.live_variables(dictionary, axes) + machinetool.live_variables(dictionary)
            self._serve_models(machine, service, live)

    def _add_nodes(
        self, machine: str, service: OpcUaService, names: dict[int, str], kinds: dict[int, int]
    ) -> None:
        ua = _ua()

        ns = self.ns
        objects = ua.NodeId(ua.ObjectIds.ObjectsFolder)
        root = ua.NodeId(machine, ns)
        items = [_object_item(root, objects, ua.QualifiedName(machine, ns))]
        folders: set[tuple[str, ...]] = {()}
        specs = machine_variables(machine, service.info.dictionary, names, kinds)
        for spec in specs:
            for depth in range(1, len(spec.path)):
                path = spec.path[:depth]
                if path not in folders:
                    folders.add(path)
                    parent = ua.NodeId("/".join((machine, *path[:-1])), ns)
                    node_id = ua.NodeId("/".join((machine, *path)), ns)
                    items.append(_object_item(node_id, parent, ua.QualifiedName(path[-1], ns)))
            items += self._variable_items(service, spec)
        for method in METHODS:
            items += self._method_items(root, machine, method)
        results = internals.add_nodes(self.server, items)
        for item, result in zip(items, results, strict=True):
            if not result.StatusCode.is_good():
                raise RuntimeError(f"OPC UA node {item.RequestedNewNodeId}: {result.StatusCode}")
        self._subtrees[machine] = [item.RequestedNewNodeId for item in items]

    async def _add_cnc(
        self,
        machine: str,
        names: dict[int, str],
        kinds: dict[int, int],
        specs: list[VariableSpec],
    ) -> None:
        """The machine's CncInterface (OPC 40502, `cnc.py`): the OPC Foundation's types
        instantiated with their mandatory nodes (string ids below the machine's, so a
        copy of the machine renames them), an axis per configured axis and one channel,
        every value set (live ones are served by `_serve_cnc`), and each axis linked to
        its compensation objects."""
        from asyncua.common.instantiate_util import instantiate

        ua = _ua()

        server, ns, cns = self.server, self.ns, self.cnc_ns
        root = server.get_node(ua.NodeId(machine, ns))
        top = f"{machine}/{cnc.INTERFACE}"
        await instantiate(
            root,
            server.get_node(ua.NodeId(cnc.INTERFACE_TYPE, cns)),
            nodeid=ua.NodeId(top, ns),
            bname=ua.QualifiedName(cnc.INTERFACE, cns),
            dname=ua.LocalizedText(cnc.INTERFACE),
            instantiate_optional=False,
        )
        placed = [(cnc.AXIS_LIST, name, cnc.AXIS_TYPE) for name in names.values()] + [
            (cnc.CHANNEL_LIST, cnc.CHANNEL, cnc.CHANNEL_TYPE)
        ]
        for folder, name, kind in placed:
            await instantiate(
                server.get_node(ua.NodeId(f"{top}.{folder}", ns)),
                server.get_node(ua.NodeId(kind, cns)),
                nodeid=ua.NodeId(f"{top}.{folder}.{name}", ns),
                bname=ua.QualifiedName(name, ns),
                dname=ua.LocalizedText(name),
                instantiate_optional=False,
            )
        made = self._made_below(top)
        axis_kinds = {names[axis]: kinds[axis] for axis in names}
        for node_id in made:
            self._fill_cnc(node_id, axis_kinds)
        for axis, name in names.items():
            groups = {spec.path[2] for spec in specs if spec.axis == axis and spec.path[0] == AXES}
            for group in sorted(groups):
                await server.get_node(ua.NodeId(f"{top}.{cnc.AXIS_LIST}.{name}", ns)).add_reference(
                    ua.NodeId(f"{machine}/{AXES}/{name}/{group}", ns),
                    ua.ObjectIds.Organizes,
                )
        self._subtrees[machine] += made

    async def _add_machine_tool(self, machine: str) -> None:
        """The machine's MachineTool (OPC 40501, `machinetool.py`) in the Machinery
        `Machines` folder, with its mandatory nodes (string ids below the machine's)."""
        from asyncua.common.instantiate_util import instantiate

        ua = _ua()

        server, ns = self.server, self.ns
        top = f"{machine}/{machinetool.INSTANCE}"
        await instantiate(
            server.get_node(ua.NodeId(machinetool.MACHINES_FOLDER, self.machinery_ns)),
            server.get_node(ua.NodeId(machinetool.MACHINE_TOOL_TYPE, self.mt_ns)),
            nodeid=ua.NodeId(top, ns),
            bname=ua.QualifiedName(machine, ns),
            dname=ua.LocalizedText(machine),
            instantiate_optional=False,
        )
        messages = server.get_node(ua.NodeId(f"{top}.Notification", ns))
        await instantiate(  # (optional in 40501: where the machine's messages are events)
            messages,
            server.get_node(ua.NodeId(machinetool.MESSAGES_TYPE, self.mt_ns)),
            nodeid=ua.NodeId(f"{top}.Notification.Messages", ns),
            bname=ua.QualifiedName("Messages", self.mt_ns),
            dname=ua.LocalizedText("Messages"),
            instantiate_optional=False,
        )
        await server.get_node(ua.NodeId(f"{top}.Notification.Messages", ns)).set_event_notifier(
            [ua.EventNotifier.SubscribeToEvents]
        )
        made = self._made_below(top)
        for node_id in made:
            self._set_value(node_id, None)
        self._subtrees[machine] += made

    def _made_below(self, top: str) -> list[Any]:
        """The nodes whose ids start with `top` (what an instantiation made)."""
        ns = self.ns
        return [
            node_id
            for node_id in list(internals.address_space(self.server).keys())
            if node_id.NamespaceIndex == ns
            and isinstance(node_id.Identifier, str)
            and node_id.Identifier.startswith(top)
        ]

    def _fill_cnc(self, node_id: Any, axis_kinds: dict[str, int]) -> None:
        """The value of a variable of the CncInterface that nothing live serves: a
        constant of `cnc.CONSTANTS`, the units and range of its analog parent, the
        vendor's names, else the zero of its type (a Good value, as every mandatory
        variable needs)."""
        ua = _ua()

        attrs = internals.address_space(self.server)[node_id].attributes
        if attrs[ua.AttributeIds.NodeClass].value.Value.Value != ua.NodeClass.Variable:
            return
        name = attrs[ua.AttributeIds.BrowseName].value.Value.Value.Name
        parent = node_id.Identifier.rsplit(".", 2)
        owner = parent[-2] if len(parent) >= 2 else ""
        axis = next((a for a in axis_kinds if f".{cnc.AXIS_LIST}.{a}." in node_id.Identifier), None)
        kind = axis_kinds.get(axis, LINEAR) if axis is not None else LINEAR
        value: Any
        if name == "EngineeringUnits":
            unit = cnc.UNITS.get(owner) or cnc.position_unit(kind)
            value = _eu_information(unit)
        elif name == "EURange":
            low, high = cnc.RANGES.get(cnc.UNITS.get(owner, ""), cnc.POSITION_RANGE)
            value = ua.Range(low, high)
        elif name == "IsRotational":
            value = kind != LINEAR
        elif name in ("VendorName", "VendorRevision", "Version"):
            value = {"VendorName": MANUFACTURER, "VendorRevision": __version__}.get(name, "1.00")
        elif name in cnc.CONSTANTS:
            value = cnc.CONSTANTS[name]
        else:
            value = None
        self._set_value(node_id, value)

    def _set_value(self, node_id: Any, value: Any) -> None:
        """Store `value` (None: the zero of its type, unless the type gave it one) as
        a variable's value, typed as the variable is (DataType, ValueRank), and make the
        variable read-only."""
        ua = _ua()

        attrs = internals.address_space(self.server)[node_id].attributes
        if attrs[ua.AttributeIds.NodeClass].value.Value.Value != ua.NodeClass.Variable:
            return
        # a model's variable is read-only (its values are the machine's or constants,
        # and a copy of the machine shares its constants: docs/opcua.md)
        readable = ua.DataValue(ua.Variant(ua.AccessLevel.CurrentRead.mask, ua.VariantType.Byte))
        attrs[ua.AttributeIds.AccessLevel] = internals.attribute_value(readable)
        attrs[ua.AttributeIds.UserAccessLevel] = internals.attribute_value(readable)
        current = attrs[ua.AttributeIds.Value].value
        given = current.Value if current is not None else None
        if value is None and given is not None and given.Value is not None:
            return  # (a value the type gave it)
        datatype = attrs[ua.AttributeIds.DataType].value.Value.Value
        rank = attrs[ua.AttributeIds.ValueRank].value.Value.Value
        attrs[ua.AttributeIds.Value].value = ua.DataValue(_typed(value, datatype, rank))

    def _serve_models(self, machine: str, service: OpcUaService, live: list[Live]) -> None:
        """Answer the live variables of the machine's companion models from its service,
        and give it the values that are its own (its CNC axes' ActChannel, its machine
        tool's identification): a copy's would be the first machine's."""
        ua = _ua()
        ns = self.ns
        aspace = internals.address_space(self.server)
        value = ua.AttributeIds.Value
        for spec in live:
            node_id = ua.NodeId(f"{machine}/" + ".".join(spec.path), ns)
            vtype = getattr(ua.VariantType, spec.ua_type)
            attval = aspace[node_id].attributes[value]
            var = Var(None, service, machine, node_id, vtype, attval, live=spec)
            self._vars[node_id] = var
            aspace.set_attribute_value_callback(node_id, value, self._reader(var))
            aspace.set_attribute_value_setter(node_id, value, _keep)
        top = f"{machine}/{cnc.INTERFACE}"
        channel = ua.NodeId(f"{top}.{cnc.CHANNEL_LIST}.{cnc.CHANNEL}", ns)
        own = {
            f"{machine}/{machinetool.INSTANCE}.Identification.{name}": text
            for name, text in machinetool.identification(machine, socket.gethostname()).items()
        }
        for node_id in self._subtrees[machine]:
            ident = node_id.Identifier
            if not isinstance(ident, str):
                continue
            if ident.startswith(top) and ident.endswith(".ActChannel"):
                variant = ua.Variant(channel, ua.VariantType.NodeId)
            elif ident in own:
                datatype = aspace[node_id].attributes[ua.AttributeIds.DataType].value.Value.Value
                variant = _typed(own[ident], datatype, -1)
            else:
                continue
            aspace[node_id].attributes[value] = internals.attribute_value(ua.DataValue(variant))

    async def _link_cnc_from_objects(self, machine: str) -> None:
        """With one machine, its CncInterface is also where OPC 40502 puts it: in the
        Objects folder (the same node)."""
        ua = _ua()

        await self.server.nodes.objects.add_reference(
            ua.NodeId(f"{machine}/{cnc.INTERFACE}", self.ns), ua.ObjectIds.Organizes
        )

    def _on_event(self, machine: str) -> Callable[[Event], None]:
        """The machine's warnings and errors, handed from the reporting thread (the
        cycle's) to the loop, which sends each as an event (`_send_event`)."""
        loop = self._loop
        assert loop is not None

        def on_event(event: Event) -> None:
            with contextlib.suppress(RuntimeError):  # the loop is closed: nobody listens
                loop.call_soon_threadsafe(self._post_event, machine, event)

        return on_event

    def _post_event(self, machine: str, event: Event) -> None:
        task = asyncio.ensure_future(self._send_event(machine, event))
        self._sending.add(task)
        task.add_done_callback(self._sending.discard)

    async def _send_event(self, machine: str, event: Event) -> None:
        """One warning or error as a NotificationEventType event of the machine's
        MachineTool/Notification/Messages (OPC 40501; `machinetool.notification`)."""
        ua = _ua()

        if machine in self._pending:  # (no item can be on a machine not made: nobody listens)
            return
        generator = self._generators.get(machine)
        if generator is None:
            generator = await self.server.get_event_generator(
                ua.NodeId(machinetool.NOTIFICATION_EVENT_TYPE, self.mt_ns),
                ua.NodeId(f"{machine}/{machinetool.INSTANCE}.Notification.Messages", self.ns),
            )
            self._generators[machine] = generator
        text, severity, identifier = machinetool.notification(event)
        generator.event.Severity = severity
        generator.event.SourceName = machine
        # (asyncua does not resolve the type of a model's own event field: given here)
        generator.event.add_property("Identifier", identifier, ua.VariantType.String)
        try:
            await generator.trigger(message=text)
        except Exception:  # (one event, not the others: as a broken monitored item)
            log.exception("opcua event of %s", machine)

    def _copy_nodes(self, template: str, machine: str) -> None:
        """Copy the nodes of `template` (a machine of the same shape) as `machine`'s:
        node ids, the object's name and the references within it renamed; what the
        nodes share and no client can change (the other attributes, which only an
        administrator could write, and references out of the machine) is shared."""
        ua = _ua()

        ns = self.ns
        nodes = internals.address_space(self.server)
        plan = self._plans.get(template) or self._plan(template)
        if self._own_id is None:
            self._own_id = internals.attribute_value(ua.DataValue())
            self._own_id.value_callback = _node_id_value
        ids = {suffix: ua.NodeId(machine + suffix, ns) for suffix, _, _ in plan}
        own, value = ua.AttributeIds.NodeId, ua.AttributeIds.Value
        named = _Named(ua.QualifiedName(machine, ns), ua.LocalizedText(machine))
        copied = []
        for suffix, old_id, refs in plan:
            src = nodes[old_id]
            new_id = ids[suffix]
            node = internals.node_data(new_id)
            attrs = dict(src.attributes)
            attrs[own] = self._own_id  # (made when read, from the node's id: `_own_id`)
            if old_id in self._vars:  # its value's callbacks are its own
                attrs[value] = internals.attribute_value(attrs[value].value)
            if suffix in _NAMED:
                attrs[ua.AttributeIds.BrowseName] = internals.attribute_value(
                    ua.DataValue(ua.Variant(named.browse))
                )
                attrs[ua.AttributeIds.DisplayName] = internals.attribute_value(
                    ua.DataValue(ua.Variant(named.display))
                )
            node.attributes = attrs
            node.references = [
                ref if to is None else _retargeted(ref, ids[to], named if to in _NAMED else None)
                for ref, to in refs
            ]
            nodes[new_id] = node
            copied.append(new_id)
        self._subtrees[machine] = copied

    def _anchor(self, template: str, machine: str) -> None:
        """The references to `machine`'s nodes from the nodes out of it that refer to
        `template`'s (Objects, Machines), made before its nodes (`_materialize`)."""
        ua = _ua()

        ns = self.ns
        nodes = internals.address_space(self.server)
        if template not in self._plans:
            self._plan(template)
        named = _Named(ua.QualifiedName(machine, ns), ua.LocalizedText(machine))
        for outside, suffix in self._anchors[template]:
            held = ua.NodeId(template + suffix, ns)
            here = ua.NodeId(machine + suffix, ns)
            for up in [r for r in nodes[outside].references if r.NodeId == held and r.IsForward]:
                named_here = named if suffix in _NAMED else None
                nodes[outside].references.append(_retargeted(up, here, named_here))

    def _plan(self, template: str) -> list[tuple[str, Any, list[tuple[Any, str | None]]]]:
        """How to copy `template`'s nodes: each node's id below the machine (its suffix,
        "" for the machine's object), and each of its references with the suffix of its
        target when that is in the machine (None: a reference out of it, shared)."""
        ns = self.ns
        nodes = internals.address_space(self.server)
        cut = len(template)

        def suffix(node_id: Any) -> str | None:
            ident = node_id.Identifier
            if node_id.NamespaceIndex != ns or not isinstance(ident, str):
                return None
            if ident != template and not ident.startswith(template + "/"):
                return None
            return str(ident[cut:])

        plan = []
        anchors = []
        for old_id in self._subtrees[template]:
            refs = [(ref, suffix(ref.NodeId)) for ref in nodes[old_id].references]
            here = suffix(old_id) or ""
            plan.append((here, old_id, refs))
            anchors += [(ref.NodeId, here) for ref, to in refs if to is None and not ref.IsForward]
        self._plans[template] = plan
        self._anchors[template] = anchors
        return plan

    def _serve(self, machine: str, service: OpcUaService, specs: list[VariableSpec]) -> None:
        """Answer the values and methods of a machine's nodes from its service."""
        ua = _ua()

        ns = self.ns
        aspace = internals.address_space(self.server)
        value = ua.AttributeIds.Value
        for spec in specs:
            node_id = ua.NodeId(spec.node_id, ns)
            vtype = getattr(ua.VariantType, spec.ua_type)
            attval = aspace[node_id].attributes[value]
            var = Var(spec, service, machine, node_id, vtype, attval)
            self._vars[node_id] = var
            # asyncua's own reads of the value (a new monitored item's first value);
            # a client's Read goes through `_read`
            aspace.set_attribute_value_callback(node_id, value, self._reader(var))
            # nothing is stored into the node: reads ask the service
            aspace.set_attribute_value_setter(node_id, value, _keep)
        for method in METHODS:
            node_id = ua.NodeId(f"{machine}/{method.name}", ns)
            aspace.add_method_callback(node_id, self._caller(machine, service, method))

    def _method_items(self, root: Any, machine: str, spec: MethodSpec) -> list[Any]:
        """The AddNodesItems of one method of the machine's object and of its
        InputArguments and OutputArguments (OPC 10000-3 §5.7; node ids below the
        method's, so a copy of the machine renames them too)."""
        ua = _ua()

        ns = self.ns
        node_id = ua.NodeId(f"{machine}/{spec.name}", ns)
        items = [
            ua.AddNodesItem(
                ParentNodeId=root,
                ReferenceTypeId=ua.NodeId(ua.ObjectIds.HasComponent),
                RequestedNewNodeId=node_id,
                BrowseName=ua.QualifiedName(spec.name, ns),
                NodeClass=ua.NodeClass.Method,
                NodeAttributes=ua.MethodAttributes(
                    DisplayName=ua.LocalizedText(spec.name),
                    Description=ua.LocalizedText(spec.description),
                    Executable=True,
                    # (a read-only interface: the method is there, not for this user)
                    UserExecutable=not self.options.read_only,
                ),
            )
        ]
        out = (("result", "String", "the command's result as JSON"),)
        for kind, args in (("InputArguments", spec.inputs), ("OutputArguments", out)):
            if not args:
                continue
            described = [
                ua.Argument(
                    Name=arg,
                    DataType=ua.NodeId(getattr(ua.ObjectIds, type_name)),
                    ValueRank=ua.ValueRank.Scalar,
                    Description=ua.LocalizedText(text),
                )
                for arg, type_name, text in args
            ]
            items.append(
                ua.AddNodesItem(
                    ParentNodeId=node_id,
                    ReferenceTypeId=ua.NodeId(ua.ObjectIds.HasProperty),
                    RequestedNewNodeId=ua.NodeId(f"{machine}/{spec.name}/{kind}", ns),
                    BrowseName=ua.QualifiedName(kind, 0),
                    NodeClass=ua.NodeClass.Variable,
                    NodeAttributes=ua.VariableAttributes(
                        DisplayName=ua.LocalizedText(kind),
                        Value=ua.Variant(described, ua.VariantType.ExtensionObject),
                        DataType=ua.NodeId(ua.ObjectIds.Argument),
                        ValueRank=ua.ValueRank.OneDimension,
                        ArrayDimensions=[len(described)],
                        AccessLevel=ua.AccessLevel.CurrentRead.mask,
                        UserAccessLevel=ua.AccessLevel.CurrentRead.mask,
                    ),
                    TypeDefinition=ua.NodeId(ua.ObjectIds.PropertyType),
                )
            )
        return items

    def _variable_items(self, service: OpcUaService, spec: VariableSpec) -> list[Any]:
        """The AddNodesItems of one variable and its properties (EngineeringUnits,
        EURange, AdsAddress)."""
        ua = _ua()

        ns = self.ns
        vtype = getattr(ua.VariantType, spec.ua_type)
        node_id = ua.NodeId(spec.node_id, ns)
        level = (ua.AccessLevel.CurrentRead.mask if spec.readable else 0) | (
            ua.AccessLevel.CurrentWrite.mask if spec.writable else 0
        )
        user_level = level & ~(ua.AccessLevel.CurrentWrite.mask if self.options.read_only else 0)
        attrs = ua.VariableAttributes(
            DisplayName=ua.LocalizedText(spec.path[-1]),
            Description=ua.LocalizedText(spec.description),
            Value=ua.Variant(_ZEROS[vtype.value], vtype),
            DataType=ua.NodeId(vtype.value),
            ValueRank=ua.ValueRank.Scalar,
            AccessLevel=level,
            UserAccessLevel=user_level,
            MinimumSamplingInterval=service.info.cycle_s * 1000.0,
        )
        items = [
            ua.AddNodesItem(
                ParentNodeId=ua.NodeId("/".join(spec.node_id.split("/")[:-1]), ns),
                ReferenceTypeId=ua.NodeId(ua.ObjectIds.HasComponent),
                RequestedNewNodeId=node_id,
                BrowseName=ua.QualifiedName(spec.path[-1], ns),
                NodeClass=ua.NodeClass.Variable,
                NodeAttributes=attrs,
                TypeDefinition=ua.NodeId(getattr(ua.ObjectIds, spec.type_definition)),
            )
        ]
        props: list[tuple[str, Any]] = []
        if spec.unit:
            props.append(("EngineeringUnits", ua.Variant(_eu_information(spec.unit))))
        if spec.eu_range is not None:
            props.append(("EURange", ua.Variant(ua.Range(*spec.eu_range))))
        props.append(("AdsAddress", ua.Variant(spec.ads_address, ua.VariantType.String)))
        for name, value in props:
            datatype = {
                "EngineeringUnits": ua.NodeId(ua.ObjectIds.EUInformation),
                "EURange": ua.NodeId(ua.ObjectIds.Range),
            }.get(name, ua.NodeId(ua.ObjectIds.String))
            items.append(
                ua.AddNodesItem(
                    ParentNodeId=node_id,
                    ReferenceTypeId=ua.NodeId(ua.ObjectIds.HasProperty),
                    RequestedNewNodeId=ua.NodeId(f"{spec.node_id}/{name}", ns),
                    BrowseName=ua.QualifiedName(name, 0 if name != "AdsAddress" else ns),
                    NodeClass=ua.NodeClass.Variable,
                    NodeAttributes=ua.VariableAttributes(
                        DisplayName=ua.LocalizedText(name),
                        Value=value,
                        DataType=datatype,
                        ValueRank=ua.ValueRank.Scalar,
                        AccessLevel=ua.AccessLevel.CurrentRead.mask,
                        UserAccessLevel=ua.AccessLevel.CurrentRead.mask,
                    ),
                    TypeDefinition=ua.NodeId(ua.ObjectIds.PropertyType),
                )
            )
        return items

    def _reader(self, var: Var) -> Callable[[Any, Any], Any]:
        def read(node_id: Any, attr: Any) -> Any:
            return self._read_var(var, {})

        return read

    def _read(self, params: Any) -> list[Any]:
        """asyncua's Read service (`AttributeService.read`) with the Value of our
        variables answered here: one `service.current()` per machine and request (its
        values come from one cycle, as an ADS sum read's), asyncua's address space for
        every other attribute and node."""
        ua = _ua()
        value = ua.AttributeIds.Value
        stamps = int(params.TimestampsToReturn)
        if stamps not in _STAMPS:
            from asyncua.common.utils import ServiceError

            raise ServiceError(ua.StatusCodes.BadTimestampsToReturnInvalid)
        read_attribute = internals.address_space(self.server).read_attribute_value
        snaps: dict[str, Snapshot | AdsError] = {}
        out = []
        for item in params.NodesToRead:
            var = self._vars.get(item.NodeId) if item.AttributeId == value else None
            if var is None:
                dv = read_attribute(item.NodeId, item.AttributeId)
            else:
                dv = self._read_var(var, snaps)
                if item.IndexRange:
                    dv = _ranged(dv, item.IndexRange)
            out.append(_stamped(dv, stamps))
        return out

    def _read_var(self, var: Var, snaps: dict[str, Snapshot | AdsError]) -> Any:
        """The DataValue of one variable from the machine's snapshot of this request
        (`snaps`, taken now if it has none yet)."""
        ua = _ua()

        RequestMeter.touch(var.machine)
        if not var.readable:
            return ua.DataValue(StatusCode=ua.StatusCode(ua.StatusCodes.BadNotReadable))
        snap = snaps.get(var.machine)
        if snap is None:
            try:
                snap = self._current(var.service)
            except AdsError as exc:
                snap = exc
            snaps[var.machine] = snap
        if isinstance(snap, AdsError):
            return ua.DataValue(StatusCode=_status(snap))
        return self._datavalue(var, var.value(snap), snap)

    def _current(self, service: OpcUaService) -> Snapshot:
        """The snapshot due now: here when it needs no catch-up (`current_if_due`), else
        `service.current()` run by the main loop's thread, this one waiting: the exact
        engine's catch-up holds its lock, and this thread is niced: descheduled while
        holding it, it would keep the machine's ADS and Modbus requests waiting. 0x707
        when the main loop does not answer within `HOST_WAIT_S` (or has ended)."""
        ready = service.current_if_due()
        if ready is not None:
            return ready
        host = self._host
        if host is not None and _running_loop() is host:  # (called on the main loop itself)
            return service.current()
        done: concurrent.futures.Future[Snapshot] = concurrent.futures.Future()

        def run() -> None:
            if not done.set_running_or_notify_cancel():
                return
            try:
                done.set_result(service.current())
            except BaseException as exc:  # (handed to the waiting thread)
                done.set_exception(exc)

        try:
            if host is None:
                raise RuntimeError("no main loop")
            host.call_soon_threadsafe(run)
            return done.result(HOST_WAIT_S)
        except (RuntimeError, concurrent.futures.TimeoutError):
            done.cancel()
            raise AdsError(
                AdsErrorCode.DEVICE_NOTREADY, "the server's main loop did not answer in time"
            ) from None

    async def _on_host(self, work: Coroutine[Any, Any, T]) -> T:
        """Await `work` run on the main loop (a write's or a method's: they catch the
        machine up, `_current`)."""
        host = self._host
        if host is not None and host.is_closed():  # (the main loop has ended: it stops)
            work.close()
            raise AdsError(AdsErrorCode.DEVICE_NOTREADY, "the server is stopping")
        return await on_loop(host, work)

    def _datavalue(self, var: Var, value: Any, snap: Snapshot) -> Any:
        ua = _ua()

        stamped, stamp = self._stamped
        if stamped is not snap:  # (the cycle's time once per snapshot, not per value)
            stamp = source_time(snap)
            self._stamped = (snap, stamp)
        if var.vtype == ua.VariantType.LocalizedText:
            value = ua.LocalizedText(value)
        elif var.vtype == ua.VariantType.NodeId:  # (a state of the Machine Tool model)
            value = ua.NodeId(value, self.mt_ns)
        elif var.live is not None and var.live.structure:  # (asyncua made its class from
            value = getattr(ua, var.live.structure)(*value)  # the model's NodeSet)
        return ua.DataValue(
            ua.Variant(value, var.vtype),
            SourceTimestamp=stamp,
            ServerTimestamp=dt.datetime.now(dt.UTC),
        )

    def _caller(self, machine: str, service: OpcUaService, spec: MethodSpec) -> Callable[..., Any]:
        ua = _ua()

        async def call(parent: Any, *args: Any) -> Any:
            RequestMeter.touch(machine)
            if self.options.read_only:
                return ua.StatusCode(getattr(ua.StatusCodes, READ_ONLY))
            if len(args) < len(spec.inputs):
                return ua.StatusCode(ua.StatusCodes.BadArgumentsMissing)
            if len(args) > len(spec.inputs):
                return ua.StatusCode(ua.StatusCodes.BadTooManyArguments)
            texts = []
            for arg in args:
                if not isinstance(arg, ua.Variant) or arg.VariantType != ua.VariantType.String:
                    return ua.StatusCode(ua.StatusCodes.BadTypeMismatch)
                texts.append(str(arg.Value or ""))
            try:
                body = await self._on_host(run_method(service, spec.name, texts))
            except AdsError as exc:
                log.info("opcua %s refused: %s", spec.name, exc.message)
                return _status(exc)
            return [ua.Variant(json.dumps(body), ua.VariantType.String)]

        return call

    # ------------------------------------------------------------------ hooks

    def _hook(self) -> None:
        """Route the reads, writes, monitored items and their removal of our variables
        through this interface; everything else stays asyncua's."""
        ua = _ua()
        hooked = internals.services(self.server)
        attrs = hooked.attribute
        attrs.read = self._read
        write = attrs.write

        async def hooked_write(params: Any, user: Any = None) -> list[Any]:
            return await self._write(params, user, write)

        attrs.write = hooked_write
        aspace = internals.address_space(self.server)
        add, delete = aspace.add_datachange_callback, aspace.delete_datachange_callback

        monitoring = self.monitoring

        def hooked_add(node_id: Any, attr: Any, callback: Any) -> Any:
            result = add(node_id, attr, callback)
            sampled = attr == ua.AttributeIds.Value  # (other attributes never change)
            if sampled and result[0].is_good():
                monitoring.added(node_id, result[1])
            return result

        def hooked_delete(handle: int) -> Any:
            monitoring.deleted(handle)
            return delete(handle)

        aspace.add_datachange_callback = hooked_add
        aspace.delete_datachange_callback = hooked_delete
        methods = hooked.method
        call = methods.call

        async def hooked_call(requests: list[Any]) -> list[Any]:
            return await self._call(requests, call)

        methods.call = hooked_call
        subs = hooked.subscription
        create = subs.create_monitored_items

        async def hooked_create(params: Any) -> list[Any]:
            return await monitoring.create_items(params, create)

        subs.create_monitored_items = hooked_create
        set_mode = subs.set_monitoring_mode

        async def hooked_set_mode(params: Any) -> list[Any]:
            return await monitoring.set_mode(params, set_mode)

        subs.set_monitoring_mode = hooked_set_mode
        modify = subs.modify_monitored_items

        def hooked_modify(params: Any) -> list[Any]:
            return monitoring.modify_items(params, modify)

        subs.modify_monitored_items = hooked_modify

    async def _call(self, requests: list[Any], call: Any) -> list[Any]:
        """The Call service with each method checked against its object first (OPC
        10000-4 §5.11.2): an unknown object is Bad_NodeIdUnknown, a method that is not
        a component of the object or of its type Bad_MethodInvalid; the rest is
        asyncua's."""
        ua = _ua()

        results: list[Any] = [None] * len(requests)
        passed: list[int] = []
        for i, request in enumerate(requests):
            status = self._method_refusal(request.ObjectId, request.MethodId)
            if status is None:
                passed.append(i)
            else:
                results[i] = ua.CallMethodResult(StatusCode=ua.StatusCode(status))
        done = await call([requests[i] for i in passed]) if passed else []
        for i, result in zip(passed, done, strict=True):
            results[i] = result
        return results

    def _method_refusal(self, object_id: Any, method_id: Any) -> int | None:
        """None when `method_id` is a method of `object_id`: a component of the object,
        or of its type or one of that type's supertypes."""
        ua = _ua()

        aspace = internals.address_space(self.server)
        if object_id not in aspace:
            return int(ua.StatusCodes.BadNodeIdUnknown)
        if method_id not in aspace:
            return int(ua.StatusCodes.BadMethodInvalid)
        component = ua.NodeId(ua.ObjectIds.HasComponent)
        typed = ua.NodeId(ua.ObjectIds.HasTypeDefinition)
        subtype = ua.NodeId(ua.ObjectIds.HasSubtype)
        node: Any = object_id
        for _ in range(_TYPE_DEPTH):
            refs = aspace[node].references
            has = (r.IsForward and r.ReferenceTypeId == component for r in refs)
            if any(h and r.NodeId == method_id for h, r in zip(has, refs, strict=True)):
                return None
            up = [
                r.NodeId
                for r in refs
                if (r.IsForward and r.ReferenceTypeId == typed)
                or (not r.IsForward and r.ReferenceTypeId == subtype)
            ]
            if not up or up[0] not in aspace:
                break
            node = up[0]
        return int(ua.StatusCodes.BadMethodInvalid)

    # ------------------------------------------------------------------ writes

    async def _write(self, params: Any, user: Any, write: Any) -> list[Any]:
        ua = _ua()

        from asyncua.server.user_managers import UserRole

        items = list(params.NodesToWrite)
        results: list[Any] = [None] * len(items)
        aspace = internals.address_space(self.server)
        client = user is not None and user.role != UserRole.Admin  # (not the server itself)
        for i, w in enumerate(items):
            if w.NodeId not in aspace:  # (before asyncua's access check says Denied)
                results[i] = ua.StatusCode(ua.StatusCodes.BadNodeIdUnknown)
            elif client and self.options.read_only:  # (every node: asyncua's, the models')
                results[i] = ua.StatusCode(getattr(ua.StatusCodes, READ_ONLY))
            elif client and w.NodeId not in self._vars and not _writable(aspace, w):
                results[i] = ua.StatusCode(ua.StatusCodes.BadNotWritable)
        others = [
            i for i, w in enumerate(items) if w.NodeId not in self._vars and results[i] is None
        ]
        if others:
            sub = ua.WriteParameters(NodesToWrite=[items[i] for i in others])
            done = await (write(sub, user) if user is not None else write(sub))
            for i, status in zip(others, done, strict=True):
                results[i] = status
        ours = [i for i, w in enumerate(items) if w.NodeId in self._vars and results[i] is None]
        by_service: dict[int, tuple[OpcUaService, list[tuple[int, Any]]]] = {}
        for i in ours:
            w = items[i]
            var = self._vars[w.NodeId]
            RequestMeter.touch(var.machine)
            status, prepared = self._prepare(var, w)
            if status is not None:
                results[i] = status
            else:
                by_service.setdefault(id(var.service), (var.service, []))[1].append((i, prepared))
        for service, group in by_service.values():
            for i, status in await self._apply(service, group):
                results[i] = status
        return results

    def _prepare(self, var: Var, w: Any) -> tuple[Any, Any]:
        """(a refusal's status, None) or (None, the prepared write)."""
        ua = _ua()

        if w.AttributeId != ua.AttributeIds.Value:
            return ua.StatusCode(ua.StatusCodes.BadNotWritable), None
        if self.options.read_only:
            return ua.StatusCode(getattr(ua.StatusCodes, READ_ONLY)), None
        spec = var.spec
        if spec is None or not spec.writable:
            return ua.StatusCode(ua.StatusCodes.BadNotWritable), None
        if w.IndexRange:
            return ua.StatusCode(ua.StatusCodes.BadIndexRangeInvalid), None
        variant = w.Value.Value if w.Value is not None else None
        expected = getattr(ua.VariantType, spec.ua_type)
        if variant is None or variant.VariantType != expected or variant.is_array:
            return ua.StatusCode(getattr(ua.StatusCodes, TYPE_MISMATCH)), None
        try:
            prepared = var.service.prepare_name(spec.obj.name, spec.axis, variant.Value)
        except AdsError as exc:
            return _status(exc), None
        return None, prepared

    async def _apply(
        self, service: OpcUaService, group: list[tuple[int, Any]]
    ) -> list[tuple[int, Any]]:
        """Apply the prepared writes of one machine: values in one cycle, each command
        (reload/save by object) on its own."""
        ua = _ua()

        out: list[tuple[int, Any]] = []
        values = [(i, p) for i, p in group if not is_command(p.obj)]
        commands = [(i, p) for i, p in group if is_command(p.obj)]
        batches = ([values] if values else []) + [[c] for c in commands]
        for batch in batches:
            try:
                errors = await self._on_host(service.apply_writes([p for _, p in batch]))
            except AdsError as exc:
                out += [(i, _status(exc)) for i, _ in batch]
                continue
            for (i, _), err in zip(batch, errors, strict=True):
                out.append((i, ua.StatusCode() if err is None else _status(err)))
        return out


async def run_method(service: OpcUaService, name: str, args: list[str]) -> dict[str, Any]:
    """One command by method name, as the other interfaces run it: the result as JSON,
    or the AdsError of its refusal."""
    if name in ("Reload", "Save"):
        result = await service.commands.run_applied(name.lower())
        if not result.ok:
            raise result.error()
        answer: dict[str, Any] = result.as_dict()
        return answer
    if name == "RunNc":
        cycle = await service.nc.run_applied(args[0])
        return {"ok": True, "command": "nc", "cycle": cycle}
    if name == "Reset":
        cycle = await service.nc.reset_applied()
        return {"ok": True, "command": "reset", "cycle": cycle}
    try:
        if name == "InjectFault":
            injected = await asyncio.to_thread(service.faults.inject, args[0])
            return {"ok": True, "command": "fault", "injected": injected}
        if name == "ClearFaults":
            which = args[0].strip()
            ident = None if which == "all" else _fault_id(which)
            cleared = await asyncio.to_thread(service.faults.clear, ident)
            return {"ok": True, "command": "fault", "cleared": cleared}
    except FaultError as exc:
        raise AdsError(AdsErrorCode.DEVICE_INVALIDPARM, str(exc)) from None
    raise AdsError(AdsErrorCode.DEVICE_SRVNOTSUPP, f"unknown method {name!r}")


def _fault_id(text: str) -> int:
    if not re.fullmatch(r"[0-9]{1,9}", text):
        raise FaultError(f'ClearFaults takes a fault id or "all", not {text[:40]!r}')
    return int(text)


def _status(exc: AdsError) -> Any:
    ua = _ua()

    return ua.StatusCode(getattr(ua.StatusCodes, status_name(exc)))


def _object_item(node_id: Any, parent: Any, name: Any) -> Any:
    """The AddNodesItem of a folder (a machine, `Axes`, an axis, a group)."""
    ua = _ua()

    return ua.AddNodesItem(
        ParentNodeId=parent,
        ReferenceTypeId=ua.NodeId(ua.ObjectIds.Organizes),
        RequestedNewNodeId=node_id,
        BrowseName=name,
        NodeClass=ua.NodeClass.Object,
        NodeAttributes=ua.ObjectAttributes(DisplayName=ua.LocalizedText(name.Name)),
        TypeDefinition=ua.NodeId(ua.ObjectIds.FolderType),
    )


def _running_loop() -> asyncio.AbstractEventLoop | None:
    try:
        return asyncio.get_running_loop()
    except RuntimeError:
        return None


#: TimestampsToReturn: Source, Server, Both, Neither (OPC 10000-4 §7.40)
_STAMPS = (0, 1, 2, 3)
#: how far up from an object to look for its methods (the object, its type, supertypes)
_TYPE_DEPTH = 8


def _stamped(dv: Any, stamps: int) -> Any:
    """`dv` with the timestamps a Read asked for (OPC 10000-4 §5.10.2: Source,
    Server, Both or Neither), a new DataValue when one is dropped (asyncua's own
    nodes' values are shared)."""
    if stamps == 2:
        return dv
    ua = _ua()

    return ua.DataValue(
        Value=dv.Value,
        StatusCode=dv.StatusCode,
        SourceTimestamp=dv.SourceTimestamp if stamps == 0 else None,
        ServerTimestamp=dv.ServerTimestamp if stamps == 1 else None,
    )


def _ranged(dv: Any, text: str) -> Any:
    """The part of a value an IndexRange asks for (OPC 10000-4 §7.27): our values are
    scalars, of which a String is the one with parts (its characters): a range with
    bad syntax is Bad_IndexRangeInvalid, one that finds no data Bad_IndexRangeNoData."""
    ua = _ua()

    bounds = _index_range(text)
    if bounds is None:
        return ua.DataValue(StatusCode=ua.StatusCode(ua.StatusCodes.BadIndexRangeInvalid))
    value = dv.Value.Value if dv.Value is not None else None
    if not dv.StatusCode.is_good():
        return dv
    if len(bounds) != 1 or not isinstance(value, str) or bounds[0][0] >= len(value):
        return ua.DataValue(StatusCode=ua.StatusCode(ua.StatusCodes.BadIndexRangeNoData))
    first, last = bounds[0]
    return ua.DataValue(
        ua.Variant(value[first : last + 1], ua.VariantType.String),
        SourceTimestamp=dv.SourceTimestamp,
        ServerTimestamp=dv.ServerTimestamp,
    )


#: an index of a NumericRange: ASCII digits, at most 10 (a UInt32's length)
_INDEX = re.compile(r"[0-9]{1,10}")


def _index_range(text: str) -> list[tuple[int, int]] | None:
    """A NumericRange ("2", "0:3", "1:2,0:1") as (first, last) per dimension; None
    when its syntax is bad (a bound missing, last not above first)."""
    out = []
    for part in text.split(","):
        low, colon, high = part.partition(":")
        if not _INDEX.fullmatch(low) or (colon and not _INDEX.fullmatch(high)):
            return None
        first = int(low)
        last = int(high) if colon else first
        if colon and last <= first:
            return None
        out.append((first, last))
    return out


#: the nodes of a machine whose BrowseName is the machine's name: its object, and its
#: MachineTool in the Machines folder (suffixes of their node ids)
_NAMED = ("", f"/{machinetool.INSTANCE}")


@dataclass(frozen=True)
class _Named:
    """A machine's object's BrowseName and DisplayName (a copy's: `_copy_nodes`)."""

    browse: Any
    display: Any


def _retargeted(ref: Any, target: Any, named: _Named | None) -> Any:
    """A copy of the ReferenceDescription `ref` to `target` (with the target's names
    when it is a machine's object), by its constructor (`dataclasses.replace` took
    most of a copied machine's time)."""
    return type(ref)(
        ReferenceTypeId=ref.ReferenceTypeId,
        IsForward=ref.IsForward,
        NodeId=target,
        BrowseName=ref.BrowseName if named is None else named.browse,
        DisplayName=ref.DisplayName if named is None else named.display,
        NodeClass=ref.NodeClass,
        TypeDefinition=ref.TypeDefinition,
    )


async def _off_loop(work: Callable[[], Awaitable[Any]]) -> Any:
    """Run asyncua's coroutine `work` on a loop of its own in a thread of its own
    (`opcua-build`): adding nodes before the server serves touches nothing of this
    loop, and its seconds of pure Python would hold up every interface on it.

    Not the loop's default executor: `asyncio.run` waits for its workers before it
    returns, so a SIGTERM during the companion models' import (seconds, tens of them on
    a loaded host) would wait for it. This thread is a daemon; a close cancels the
    wait for it, and the process ends without waiting (`entry.exit_now`)."""
    loop = asyncio.get_running_loop()
    done: asyncio.Future[Any] = loop.create_future()

    def settle(result: Any, exc: BaseException | None) -> None:
        if done.cancelled():
            return
        if exc is not None:
            done.set_exception(exc)
        else:
            done.set_result(result)

    def run() -> None:
        try:
            result, exc = asyncio.run(_awaited(work)), None
        except BaseException as error:  # (handed to the awaiting task)
            result, exc = None, error
        with contextlib.suppress(RuntimeError):  # (its loop closed meanwhile)
            loop.call_soon_threadsafe(settle, result, exc)

    threading.Thread(target=run, name="opcua-build", daemon=True).start()
    return await done


async def _awaited(work: Callable[[], Awaitable[Any]]) -> Any:
    return await work()


#: The zero of each built-in DataType's id (Boolean 1, UInt16 5, Int32 6, UInt32 7,
#: Double 11, String 12; NodeId 17 and LocalizedText 21 are made by `_typed`)
_ZEROS: dict[int, Any] = {1: False, 5: 0, 6: 0, 7: 0, 11: 0.0, 12: "", 17: None, 21: ""}


def _typed(value: Any, datatype: Any, rank: int) -> Any:
    """`value` (None: the type's zero) as a Variant of the variable's DataType and
    ValueRank (an array: empty); an enumeration (not a built-in type) is an Int32."""
    ua = _ua()

    builtin = datatype.NamespaceIndex == 0 and datatype.Identifier in _ZEROS
    vtype = ua.VariantType(datatype.Identifier) if builtin else ua.VariantType.Int32
    if isinstance(value, ua.EUInformation | ua.Range):
        return ua.Variant(value)
    if rank < 1 and vtype == ua.VariantType.LocalizedText:
        return ua.Variant(ua.LocalizedText(value or ""), vtype)
    if rank < 1 and vtype == ua.VariantType.NodeId:
        return ua.Variant(value if value is not None else ua.NodeId(), vtype)
    if rank >= 1:
        return ua.Variant([] if value is None else value, vtype, is_array=True)
    if value is None:
        value = _ZEROS[datatype.Identifier] if builtin else 0
    return ua.Variant(value, vtype)


def _build_date() -> dt.datetime:
    """When this copy of geo-server was built or installed: its package's time."""
    stamp = Path(__file__).resolve().parents[2].joinpath("__init__.py").stat().st_mtime
    return dt.datetime.fromtimestamp(stamp, dt.UTC)


def _shape(service: OpcUaService) -> tuple[Any, ...]:
    """What a machine's nodes depend on: (axis number, name) and (axis number, kind)
    pairs in order, and its dictionary; from its configuration (no catch-up of its
    cycles, no snapshot)."""
    info = service.info
    params = {axis: info.config.axes[axis].params for axis in info.axes}
    names = tuple((axis, p.name) for axis, p in params.items())
    kinds = tuple((axis, ACHS_TYP[p.kind]) for axis, p in params.items())
    return names, kinds, info.dictionary


def _eu_information(unit: str) -> Any:
    """The EngineeringUnits of a unit: its UN/CEFACT code as UnitId (-1 without one)
    and its name (OPC 10000-8 §5.6.3; `units.UNECE`)."""
    ua = _ua()

    return ua.EUInformation(
        NamespaceUri=UNECE_URI,
        UnitId=unece_unit_id(unit),
        DisplayName=ua.LocalizedText(unit),
        Description=ua.LocalizedText(UNECE.get(unit, ("", unit))[1]),
    )


def _node_id_value(node_id: Any, attr: Any) -> Any:
    """The value of a copied node's NodeId attribute (read rarely: made then; a
    DataValue per node would be most of a copy's objects)."""
    ua = _ua()

    return ua.DataValue(ua.Variant(node_id, ua.VariantType.NodeId))


def _writable(aspace: Any, w: Any) -> bool:
    """Whether a node of asyncua's (or a model's) lets its value be written at all
    (AccessLevel CurrentWrite; other attributes only an administrator could write)."""
    ua = _ua()

    if w.AttributeId != ua.AttributeIds.Value:
        return True  # (asyncua refuses it: BadUserAccessDenied)
    level = aspace[w.NodeId].attributes.get(ua.AttributeIds.AccessLevel)
    if level is None or level.value is None or level.value.Value is None:
        return True
    return bool(level.value.Value.Value & ua.AccessLevel.CurrentWrite.mask)


def _keep(node: Any, attr: Any, value: Any) -> None:
    """The value setter of our variables: a sample is not stored (reads ask the service)."""


class _Users:
    """asyncua's user manager: anonymous sessions when no user is configured, else only
    that user name and password (compared in constant time). Sessions get the role
    User, never Admin: the access levels of every node apply to them."""

    def __init__(self, user: str | None, password: str | None) -> None:
        self.user = user
        self.password = password

    def get_user(
        self,
        iserver: Any,
        username: str | None = None,
        password: str | None = None,
        certificate: Any = None,
    ) -> Any:
        from asyncua.server.user_managers import User, UserRole

        if self.user is None:
            return User(role=UserRole.User)
        if username is None or password is None or self.password is None:
            return None
        ok = hmac.compare_digest(username.encode(), self.user.encode())
        ok &= hmac.compare_digest(password.encode(), self.password.encode())
        return User(role=UserRole.User, name=username) if ok else None


__all__ = [
    "STATUS",
    "OpcUaInterface",
    "OpcUaOptions",
    "run_method",
    "source_time",
    "status_name",
]
