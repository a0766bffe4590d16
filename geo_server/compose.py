"""The composition root (docs/design.md §1.2): a server built from options in one place —
a machine, the engine that runs its cycles and the object service over both
(`build_machine`), and the interfaces that serve it (`Interfaces`: Zenoh, Modbus, ADS,
the web HMI, OPC UA) for one machine (`Interfaces.start_machine`), a fleet
(`Interfaces.start_fleet`) or a test (`loopback_interface`). Used by `geo-server run`
(`cli`), each fleet (`fleet`) and `GeoTestServer` (`geo_clients.testing`) alike.
Nothing else constructs a `Machine`, a scheduler and an `ObjectService` together (the
recorder's replay builds its own stepped machine), nor an interface's server
(tests/test_architecture.py). The transports are imported when built: a command that
serves nothing does not load Zenoh, aiohttp or asyncua.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import importlib
import sys
from collections.abc import Awaitable, Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from geo_server.descriptors import MIN_CAP, AcceptLog, DescriptorError, plan
from geo_server.dictionary import GEO_AMS_PORT
from geo_server.fleetfile import FLEET_STATUS_KEY, Member
from geo_server.interfaces import InterfaceStartError, start_failure
from geo_server.machine.machine import Machine
from geo_server.machine.port import CycleRunner, MachinePort
from geo_server.machine.scheduler import Scheduler
from geo_server.model import MachineConfig
from geo_server.service import ObjectService, ServiceLimits

if TYPE_CHECKING:
    from geo_server.transports.share import LoopShare


@dataclass(frozen=True)
class EngineOptions:
    """How a machine's cycles run (README *Running*, docs/design.md §5.4–§5.6, §13)."""

    cycle_ms: float = 1.0
    homed: bool = True
    #: virtual time runs this many times as fast as wall time (None: real time)
    time_scale: float | None = None
    #: "stepped" (a test steps it), "realtime" or "free"
    mode: str = "stepped"
    #: "exact" or "punctual"
    engine: str = "exact"
    #: the cycle thread ends after this many cycles (0: never)
    max_cycles: int = 0
    #: "thread" or "process" (the cycle in a child process; Linux and macOS)
    cycle_in: str = "thread"

    @classmethod
    def from_args(cls, args: argparse.Namespace, cycle_in: str = "thread") -> EngineOptions:
        """The options of `geo-server run`'s command line."""
        return cls(
            cycle_ms=args.cycle_ms,
            homed=args.homed,
            time_scale=args.time_scale,
            mode=args.mode,
            engine=args.engine,
            max_cycles=args.cycles,
            cycle_in=cycle_in,
        )


@dataclass(frozen=True)
class Built:
    """A machine with its engine and its object service (the only way in for every
    interface)."""

    machine: MachinePort
    scheduler: CycleRunner
    service: ObjectService


def build_machine(
    cfg: MachineConfig, options: EngineOptions, limits: ServiceLimits | None = None
) -> Built:
    """The machine of `cfg`, its engine and its object service, from `options`."""
    cycle_s = options.cycle_ms / 1000.0
    machine: Any
    scheduler: Any
    if options.cycle_in == "process":
        from geo_server.machine.process import ProcessScheduler, RemoteMachine

        machine = RemoteMachine(
            cfg, cycle_s=cycle_s, homed=options.homed, time_scale=options.time_scale
        )
        scheduler = ProcessScheduler(
            machine, mode=options.mode, max_cycles=options.max_cycles, engine=options.engine
        )
    else:
        machine = Machine(cfg, cycle_s=cycle_s, homed=options.homed, time_scale=options.time_scale)
        scheduler = Scheduler(
            machine, mode=options.mode, max_cycles=options.max_cycles, engine=options.engine
        )
    return Built(machine, scheduler, ObjectService(machine, scheduler, limits))


# ---------------------------------------------------------------------- interfaces

#: Connections each machine's Modbus port queues before they are accepted: a fleet has a
#: port per machine, and every queued connection may become a descriptor at once.
FLEET_BACKLOG = 16


def connection_caps(args: argparse.Namespace, machines: int | None = None) -> dict[str, int]:
    """Each interface's connection cap, fitted under the open-files limit (raised to the
    hard limit first; geo_server/descriptors.py). Zenoh's counts its sessions and the
    handshakes under way. `machines`: a fleet's size (None: one machine); a fleet's ADS
    port admits `AdsOptions.max_connections_fleet`, its Modbus ports queue
    `FLEET_BACKLOG` each and keep at least `MIN_CAP` connections each ("modbus" in the
    result is the cap of each machine's port). `BACKLOG` is held for every other
    listening queue, whatever the caps."""
    from geo_server.transports.ads.server import AdsOptions
    from geo_server.transports.modbus.server import ModbusOptions
    from geo_server.transports.tcp import BACKLOG
    from geo_server.transports.zenoh.options import ZenohOptions

    n = machines or 1
    wanted: dict[str, int] = {}
    fixed = 0
    if not args.no_zenoh:
        wanted["zenoh"] = ZenohOptions.max_sessions + ZenohOptions.accept_pending
    if not args.no_modbus:
        wanted["modbus"] = ModbusOptions.max_connections * n
        fixed += (BACKLOG if machines is None else FLEET_BACKLOG) * n
    if not args.no_ads:
        fleet_cap = AdsOptions.max_connections_fleet
        wanted["ads"] = AdsOptions.max_connections if machines is None else fleet_cap
        fixed += BACKLOG
    if args.http:  # (aiohttp is imported only for a web HMI)
        from geo_server.web.server import HmiOptions

        wanted["http"] = HmiOptions.max_connections
        fixed += BACKLOG
    if not args.no_opcua:  # one OPC UA server, for a fleet too
        from geo_server.transports.opcua.server import OpcUaOptions

        wanted["opcua"] = OpcUaOptions.max_connections
        fixed += BACKLOG
    caps, said = plan(wanted, fixed, floors={"modbus": MIN_CAP * n})
    if said:
        print(said, file=sys.stderr, flush=True)
    if "modbus" in caps:
        caps["modbus"] //= n
    return caps


@contextlib.contextmanager
def _starting(name: str) -> Iterator[None]:
    """Any failure to start interface `name` (a taken port, a bad address, Zenoh's
    config) as an `InterfaceStartError` saying why (`start_failure`)."""
    try:
        yield
    except Exception as exc:
        raise InterfaceStartError(start_failure(name, exc)) from exc


class Interfaces:
    """A server's interfaces, started in order and closed in the reverse order.

    `plan` fits their connection caps under the open-files limit; `start_machine`
    starts those of one machine, `start_fleet` (and `start_fleet_hmi`) those of a fleet,
    each printing its start-up line. Whatever starts is registered before its start, so
    a half-started interface is closed too (`close`)."""

    def __init__(self, caps: dict[str, int]) -> None:
        #: connection caps by interface (`connection_caps`)
        self.caps = caps
        self._closers: list[tuple[str, Callable[[], Awaitable[Any]]]] = []
        #: a fleet's machines by name -> publish its status on Zenoh (from any thread)
        self.status_publishers: dict[str, Callable[[dict[str, Any]], None]] = {}

    @classmethod
    def plan(cls, args: argparse.Namespace, machines: int | None = None) -> Interfaces:
        """On the running loop, before anything starts: accept failures for want of
        descriptors said once per period (`AcceptLog`), not once per retry; the caps
        fitted under the open-files limit (`connection_caps`), an `InterfaceStartError`
        when they cannot be."""
        AcceptLog().install(asyncio.get_running_loop())
        try:
            return cls(connection_caps(args, machines))
        except DescriptorError as exc:
            raise InterfaceStartError(str(exc)) from None

    def closes(self, what: str, close: Callable[[], Awaitable[Any]]) -> None:
        """Have `close` (of `what`) called by `close`, before what was registered earlier."""
        self._closers.append((what, close))

    async def start(self, name: str, server: Any, line: Callable[[], str] | None = None) -> None:
        """Start `server`, of interface `name`, and print its start-up `line`."""
        self.closes(type(server).__name__, server.close)
        with _starting(name):
            await server.start()
        if line is not None:
            print(line(), flush=True)

    async def close(self) -> None:
        """Close everything in the reverse order of start; one failing to close must not
        keep the others (and their ports) open."""
        while self._closers:
            what, close = self._closers.pop()
            try:
                await close()
            except Exception as exc:  # report and go on closing the others
                print(f"warning: closing {what}: {exc}", file=sys.stderr)

    async def start_machine(self, args: argparse.Namespace, service: ObjectService) -> None:
        """`geo-server run`'s interfaces of one machine, those not turned off, each up
        before the next starts: Zenoh, Modbus, ADS, the web HMI, OPC UA."""
        for name, off, build in (
            ("zenoh", args.no_zenoh, _zenoh),
            ("modbus", args.no_modbus, _modbus),
            ("ads", args.no_ads, _ads),
            ("http", not args.http, _http),
            ("opcua", args.no_opcua, _opcua),
        ):
            if not off:
                if name == "opcua":  # asyncua takes most of a second to import: not on
                    await _import_off_loop(_OPCUA_MODULE)  # the loop the others answer on
                await self.start(name, *build(args, service, self.caps))

    async def start_fleet(
        self, args: argparse.Namespace, machines: Sequence[tuple[Member, ObjectService]]
    ) -> Any:
        """A fleet's interfaces (fleet.py), those not turned off: one Zenoh session with a
        machine's keys per machine, a Modbus port per machine, one ADS port routing by
        AMS NetId, one OPC UA server. The Zenoh session (None without Zenoh), for the
        fleet's status. Each machine's Modbus, ADS and OPC UA requests draw on one share of
        the event loop (`transports.share`, docs/design.md §13.1)."""
        from geo_server.transports.share import LoopShare, fleet_rate

        rate = fleet_rate(len(machines))
        shares = [LoopShare(rate) if len(machines) > 1 else None for _ in machines]
        session = None
        if not args.no_zenoh:
            session = await self._fleet_zenoh(args, machines)
        if not args.no_modbus:
            await self._fleet_modbus(args, machines, shares)
        if not args.no_ads:
            await self._fleet_ads(args, machines, shares)
        if not args.no_opcua:
            await _import_off_loop(_OPCUA_MODULE)
            services = {m.name: service for m, service in machines}
            where = args.fleet or args.startup  # the certificate beside the fleet file
            said = f"{len(services)} machines: Objects/<name>"
            by_name = {
                m.name: share for (m, _), share in zip(machines, shares, strict=True) if share
            }
            built = _opcua_server(args, services, where, self.caps, said, by_name)
            await self.start("opcua", *built)
        return session

    async def start_fleet_hmi(
        self,
        args: argparse.Namespace,
        machines: Sequence[tuple[Member, ObjectService]],
        status: Callable[[], dict[str, Any]],
    ) -> None:
        """The fleet's web HMI (`--http`): the fleet's page (its `status`) at `/`, each
        machine's at `/m/<name>/`."""
        from geo_server.web.server import FleetHmi, access_note, http_options

        options = http_options(args, max_connections=self.caps["http"])
        hmi = FleetHmi({m.name: service for m, service in machines}, status, options)
        await self.start(
            "http",
            hmi,
            lambda: (
                f"http: web HMI on {hmi.url} (the fleet; a machine at /m/<name>/; "
                f"{access_note(hmi.options)})"
            ),
        )

    async def _fleet_zenoh(
        self, args: argparse.Namespace, machines: Sequence[tuple[Member, ObjectService]]
    ) -> Any:
        import zenoh

        from geo_server.transports.zenoh.server import ZenohInterface

        base = _zenoh_options(args, self.caps)
        loop = asyncio.get_running_loop()
        with _starting("zenoh"):
            session = await loop.run_in_executor(None, zenoh.open, base.zenoh_config())

        async def close_session() -> None:
            await loop.run_in_executor(None, session.close)

        self.closes("the Zenoh session", close_session)
        ifaces = []
        for i, (m, service) in enumerate(machines):
            # No status loop per machine (the fleet publishes every machine's status,
            # computed off the loop); the rival probes and the looks for subscribers
            # spread over their periods, the looks ten a second for the whole fleet: a
            # hundred catch-ups, probes or looks at once kept the loop every machine
            # shares busy for milliseconds to tens of milliseconds (docs/design.md §13.1).
            # The periodic probes are twenty a second for the whole fleet at most (each
            # starts a thread for its replies; Zenoh's reports of a new queryable or
            # token still start one at once).
            options = replace(
                base,
                machine=m.name,
                status_period=0.0,
                watch_recheck=max(base.watch_recheck, len(machines) / 10),
                rival_check_period=max(base.rival_check_period, len(machines) / 20),
                spread=i / len(machines),
            )
            iface = ZenohInterface(service, options, session=session)
            self.closes(type(iface).__name__, iface.close)
            ifaces.append(iface)
            self.status_publishers[m.name] = iface.publish_status
        with _starting("zenoh"):  # together: each looks for a rival's token (up to 1 s)
            await asyncio.gather(*(iface.start() for iface in ifaces))
        print(
            f"zenoh: {len(ifaces)} machines on {', '.join(base.listen)} (keys cnc/<name>/**, "
            f"{FLEET_STATUS_KEY})",
            flush=True,
        )
        return session

    async def _fleet_modbus(
        self,
        args: argparse.Namespace,
        machines: Sequence[tuple[Member, ObjectService]],
        shares: Sequence[LoopShare | None],
    ) -> None:
        from geo_server.transports.modbus.server import ModbusInterface

        for (m, service), share in zip(machines, shares, strict=True):
            options = _modbus_options(
                args, m.modbus_port, max_connections=self.caps["modbus"], backlog=FLEET_BACKLOG
            )
            await self.start("modbus", ModbusInterface(service, options, share))
        first, last = machines[0][0].modbus_port, machines[-1][0].modbus_port
        print(f"modbus: tcp://{args.modbus_host}:{first}…{last}, one port per machine", flush=True)

    async def _fleet_ads(
        self,
        args: argparse.Namespace,
        machines: Sequence[tuple[Member, ObjectService]],
        shares: Sequence[LoopShare | None],
    ) -> None:
        from geo_server.transports.ads.server import AdsServer

        (head, service), last = machines[0], machines[-1][0]
        ads = AdsServer(
            service,
            _ads_options(args, head.netid, listener=True, max_connections_fleet=self.caps["ads"]),
            share=shares[0],
        )
        for (m, other), share in zip(machines[1:], shares[1:], strict=True):
            ads.add_device(other, _ads_options(args, m.netid), share)
        await self.start(
            "ads",
            ads,
            lambda: (
                f"ads: tcp://{ads.address}, AMS NetIds {head.netid}…{last.netid} "
                "(routed by target NetId)"
            ),
        )


#: An interface's server and its start-up line.
_Server = tuple[Any, Callable[[], str]]


def _zenoh_options(args: argparse.Namespace, caps: dict[str, int], **more: Any) -> Any:
    from geo_server.transports.zenoh.options import ZenohOptions

    options = ZenohOptions(
        mode=args.zenoh_mode,
        listen=args.zenoh_listen or ["tcp/127.0.0.1:7447"],
        connect=args.zenoh_connect or [],
        config_file=args.zenoh_config,
        multicast_scouting=args.zenoh_scouting,
        read_only=args.read_only or args.zenoh_read_only,
        **more,
    )
    if "zenoh" in caps:  # sessions and handshakes shrunk alike (`connection_caps`)
        options.shrink_to(caps["zenoh"])
    return options


def _zenoh(args: argparse.Namespace, service: ObjectService, caps: dict[str, int]) -> _Server:
    from geo_server.transports.zenoh.server import ZenohInterface

    options = _zenoh_options(args, caps, machine=args.machine)
    return (
        ZenohInterface(service, options),
        lambda: (
            f"zenoh: machine {args.machine!r} on {', '.join(options.listen)} "
            f"(keys cnc/{args.machine}/**)"
        ),
    )


def _modbus_options(args: argparse.Namespace, port: int, **more: Any) -> Any:
    """One machine's Modbus options from `geo-server run`'s command line (one machine or
    a fleet's member, on its own port)."""
    from geo_server.transports.modbus.server import ModbusOptions

    return ModbusOptions(
        host=args.modbus_host,
        port=port,
        read_only=args.read_only or args.modbus_read_only,
        **more,
    )


def _ads_options(
    args: argparse.Namespace, netid: str, *, listener: bool = False, **more: Any
) -> Any:
    """One machine's ADS options from the command line; `listener`: the machine that owns
    the TCP and UDP ports (the only one of a single run, a fleet's first)."""
    from geo_server.transports.ads.server import AdsOptions

    if listener:
        more.update(
            port=args.ads_port,
            udp_port=args.ads_udp_port or None,
            route_user=args.ads_route_user,
            route_password=args.ads_route_password,
        )
    return AdsOptions(
        host=args.ads_host, netid=netid, read_only=args.read_only or args.ads_read_only, **more
    )


def _modbus(args: argparse.Namespace, service: ObjectService, caps: dict[str, int]) -> _Server:
    from geo_server.transports.modbus.server import ModbusInterface

    more = {"max_connections": caps["modbus"]} if "modbus" in caps else {}
    mb = ModbusInterface(service, _modbus_options(args, args.modbus_port, **more))
    return mb, lambda: f"modbus: tcp://{mb.endpoint} (unit id = axis number, unit 0 = machine)"


def _ads(args: argparse.Namespace, service: ObjectService, caps: dict[str, int]) -> _Server:
    from geo_server.transports.ads.server import AdsServer

    more = {"max_connections": caps["ads"]} if "ads" in caps else {}
    ads = AdsServer(service, _ads_options(args, args.ads_netid, listener=True, **more))

    def line() -> str:
        said = f"ads: tcp://{ads.address} AMS NetId {args.ads_netid} port {GEO_AMS_PORT}"
        if ads.udp_port is not None:
            return said + f", discovery udp://{args.ads_host}:{ads.udp_port}"
        return said + (f" (discovery off: {ads.udp_error})" if ads.udp_error else "")

    return ads, line


def _http(args: argparse.Namespace, service: ObjectService, caps: dict[str, int]) -> _Server:
    from geo_server.web.server import HmiServer, access_note, http_options

    more = {"max_connections": caps["http"]} if "http" in caps else {}
    hmi = HmiServer(service, http_options(args, machine=args.machine, **more))
    return hmi, lambda: f"http: web HMI on {hmi.url} ({access_note(hmi.options)})"


def _opcua(args: argparse.Namespace, service: ObjectService, caps: dict[str, int]) -> _Server:
    return _opcua_server(
        args, {args.machine: service}, args.startup, caps, f"Objects/{args.machine}"
    )


_OPCUA_MODULE = "geo_server.transports.opcua.server"


async def _import_off_loop(module: str) -> None:
    """Import `module` in a worker thread: the event loop keeps answering meanwhile."""
    await asyncio.to_thread(importlib.import_module, module)


def _opcua_server(
    args: argparse.Namespace,
    services: dict[str, ObjectService],
    where: str | None,
    caps: dict[str, int],
    said: str,
    shares: Mapping[str, LoopShare] | None = None,
) -> _Server:
    """One OPC UA server, each machine of `services` under its own name, its
    certificate beside `where` (the start-up list or the fleet file; README *OPC UA*);
    it starts in the background, and says so with `said` when ready (`announce`). In a
    fleet, each machine's requests draw on its share of the loop (`shares`)."""
    from geo_server.opcua_run import announce, options_from_args
    from geo_server.transports.opcua.server import OpcUaInterface

    options = options_from_args(args, Path(where) if where else None, caps)
    ua = OpcUaInterface(services, options, shares)
    announce(ua, said)
    return ua, lambda: f"opcua: {ua.endpoint} starting (README *OPC UA*)"


def loopback_interface(
    via: str,
    service: ObjectService,
    *,
    machine: str,
    netid: str,
    publish_period: float,
    status_period: float,
) -> Any:
    """`GeoTestServer`'s interface `via` (`zenoh`, `modbus` or `ads`; docs/design.md
    §10), not started: on a free port of 127.0.0.1, Zenoh in peer mode with multicast
    scouting off and an explicit listen endpoint (it needs its port number up front;
    Modbus and ADS bind port 0 and report theirs)."""
    if via == "zenoh":
        from geo_server.ports import free_port
        from geo_server.transports.zenoh.options import ZenohOptions
        from geo_server.transports.zenoh.server import ZenohInterface

        port = free_port()  # (free a moment ago, never one handed out before)
        options = ZenohOptions(
            machine=machine,
            listen=[f"tcp/127.0.0.1:{port}"],
            publish_period=publish_period,
            status_period=status_period,
        )
        return ZenohInterface(service, options)
    if via == "modbus":
        from geo_server.transports.modbus.server import ModbusInterface, ModbusOptions

        return ModbusInterface(service, ModbusOptions(port=0))
    if via == "ads":
        from geo_server.transports.ads.server import AdsOptions, AdsServer

        return AdsServer(service, AdsOptions(port=0, netid=netid))
    raise ValueError(f"no loopback interface {via!r} (zenoh, modbus or ads)")
