"""A fleet: M machines served by one `geo-server run` process (SPEC §13, docs/design.md §13).

    geo-server run --fleet fleet.toml          # machines named in a fleet file
    geo-server run --fleet-size 50 --homed     # 50 copies of one start-up list

Each machine has its own name, start-up list, GEO cycle (the exact engine on a thread of
its own: a machine at rest costs next to nothing) and object service. The interfaces:

- **Zenoh**: one session for the whole fleet; machine `m` answers on `cnc/m/**` as a
  single machine does, and `cnc/fleet/status` (published each status period and
  answered to a get) tells every machine's name, cycle, engine, overruns and addresses.
- **ADS**: one TCP port; requests are routed by the target AMS NetId as a TwinCAT router
  does (`AdsServer.add_device`), one NetId per machine; an unknown NetId gets 0x7.
- **Modbus**: one port per machine, `--modbus-port` + i.
- **Web HMI** (`--http`): the fleet's page at `/`, each machine's page at `/m/<name>/`.
- **OPC UA**: one server; machine `m` is `Objects/m` (README *OPC UA*).

The fleet file: `geo_server.fleetfile`.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import signal
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from geo_server.descriptors import MIN_CAP, AcceptLog, DescriptorError, plan
from geo_server.fleetfile import FLEET_STATUS_KEY, FleetError, Member, copies, load_fleet
from geo_server.interfaces import CycleStoppedError, InterfaceStartError, serve, start_failure
from geo_server.paths import default_startup_list
from geo_server.recorder import cli as recorder_cli


def members_from_args(args: argparse.Namespace) -> list[Member]:
    if args.fleet:
        return load_fleet(Path(args.fleet), args.ads_netid, args.modbus_port)
    startup = Path(args.startup) if args.startup else default_startup_list()
    return copies(args.fleet_size, args.machine, startup, args.ads_netid, args.modbus_port)


# ---------------------------------------------------------------------- serving


@dataclass
class Served:
    member: Member
    service: Any
    scheduler: Any
    late: int = 0  # samples late at the last fleet status (`starved`)


def run_fleet(args: argparse.Namespace) -> int:
    """`geo-server run --fleet FILE | --fleet-size N` (exit code)."""
    from geo_server import __version__
    from geo_server.compose import EngineOptions, build_machine
    from geo_server.interfaces import inject_faults
    from geo_server.listfile import ListFileError, load_machine

    try:
        members = members_from_args(args)
    except FleetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    served: list[Served] = []
    configs: dict[Path, Any] = {}
    for m in members:
        try:
            cfg = configs.get(m.startup) or load_machine(m.startup, args.allow_dir)
        except ListFileError as exc:
            print(f"error: {m.name}: {exc}", file=sys.stderr)
            return 2
        configs[m.startup] = cfg
        built = build_machine(cfg, EngineOptions.from_args(args))  # cycles on threads
        service = built.service
        # a folder of recordings per machine: the same name never collides (docs/recorder.md §7)
        service.record_dir = recorder_cli.record_dir(args, m.name, cfg.startup_path)
        if not inject_faults(args.fault, service, f"{m.name}: "):  # every machine gets them
            return 2
        served.append(Served(m, service, built.scheduler))
    print(
        f"geo-server {__version__}: a fleet of {len(served)} machines "
        f"({', '.join(s.member.name for s in served[:5])}{', …' if len(served) > 5 else ''}), "
        f"cycle {args.cycle_ms:g} ms ({args.mode}, {args.engine} engine, cycles on threads); "
        "Ctrl-C stops",
        flush=True,
    )
    code = serve(_serve(args, served), lambda: [s.scheduler.stop() for s in served])
    if code == 0:
        print(f"stopped: {len(served)} machines")
    return code


def fleet_status(served: list[Served], loop_lag_ms: float = 0.0) -> dict[str, Any]:
    """Every machine's name, cycle, engine, overruns and addresses; the fleet's totals.

    Starvation shows too (docs/design.md §13.1): `loop_lag_ms`, how late the event loop
    that serves every machine ran a timer in the last status period, and per machine
    `samples_late`, its notification samples taken later than their cycle (the loop or
    the engine could not keep up, `ads_notifications` of its status); `starved` lists
    the machines whose count grew since the last status."""
    machines = []
    for s in served:
        st = s.service.status()
        notes = st.get("ads_notifications") or {}
        late = int(notes.get("samples_late", 0)) + int(notes.get("samples_refused", 0))
        machines.append(
            {
                "name": s.member.name,
                "cycle": st["cycle"],
                "engine": st["engine"],
                "overruns": st["overruns"],
                "stalled": st["stalled"],
                "computed_cycles": st["computed_cycles"],
                "notifications": int(notes.get("registrations", 0)),
                "samples_late": late,
                "netid": s.member.netid,
                "modbus_port": s.member.modbus_port,
            }
        )
    starved = [
        m["name"] for m, s in zip(machines, served, strict=True) if m["samples_late"] > s.late
    ]
    for m, s in zip(machines, served, strict=True):
        s.late = m["samples_late"]
    return {
        "machines": machines,
        "count": len(machines),
        "overruns": sum(m["overruns"] for m in machines),
        "stalled": [m["name"] for m in machines if m["stalled"]],
        "loop_lag_ms": round(loop_lag_ms, 1),
        "samples_late": sum(m["samples_late"] for m in machines),
        "starved": starved,
    }


#: How often the fleet's event loop checks its own lag (seconds)
LAG_TICK = 0.05


async def _watch_lag(worst: list[float]) -> None:
    """Keep `worst[0]` at the largest lateness (ms) of a `LAG_TICK` timer since it was
    last reset: a loop kept busy by one machine's clients delays every machine."""
    loop = asyncio.get_running_loop()
    while True:
        t = loop.time()
        await asyncio.sleep(LAG_TICK)
        worst[0] = max(worst[0], (loop.time() - t - LAG_TICK) * 1000)


#: Connections each machine's Modbus port queues before they are accepted: a fleet has a
#: port per machine, and every queued connection may become a descriptor at once.
FLEET_BACKLOG = 16


def connection_caps(args: argparse.Namespace, machines: int) -> dict[str, int]:
    """The fleet's connection caps fitted under the open-files limit, as for one machine
    (geo_server/descriptors.py): Zenoh's sessions and handshakes on the one session, ADS
    connections of the one port (`AdsOptions.max_connections_fleet`), the web HMI's, and
    Modbus per machine ("modbus" in the result is the cap of each machine's port). The
    listening queues are held whatever the caps: `FLEET_BACKLOG` per Modbus port,
    `BACKLOG` for ADS and HTTP."""
    from geo_server.transports.ads.server import AdsOptions
    from geo_server.transports.modbus.server import ModbusOptions
    from geo_server.transports.tcp import BACKLOG
    from geo_server.transports.zenoh.server import ZenohOptions
    from geo_server.web.server import HmiOptions

    wanted: dict[str, int] = {}
    fixed = 0
    if not args.no_zenoh:
        wanted["zenoh"] = ZenohOptions.max_sessions + ZenohOptions.accept_pending
    if not args.no_modbus:
        wanted["modbus"] = ModbusOptions.max_connections * machines
        fixed += FLEET_BACKLOG * machines
    if not args.no_ads:
        wanted["ads"] = AdsOptions.max_connections_fleet
        fixed += BACKLOG
    if args.http:
        wanted["http"] = HmiOptions.max_connections
        fixed += BACKLOG
    if not args.no_opcua:  # one OPC UA server for the fleet
        from geo_server.transports.opcua.server import OpcUaOptions

        wanted["opcua"] = OpcUaOptions.max_connections
        fixed += BACKLOG
    # every machine's port keeps at least MIN_CAP connections
    caps, said = plan(wanted, fixed, floors={"modbus": MIN_CAP * machines})
    if said:
        print(said, file=sys.stderr, flush=True)
    if "modbus" in caps:
        caps["modbus"] //= machines
    return caps


async def _serve(args: argparse.Namespace, served: list[Served]) -> None:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)
    # as for one machine (geo_server/descriptors.py): the soft open-files limit raised to
    # the hard one, every interface's connections fitted under it, and accept failures
    # said once per period, not once per retry
    AcceptLog().install(loop)
    try:
        args.caps = connection_caps(args, len(served))
    except DescriptorError as exc:
        raise InterfaceStartError(str(exc)) from None
    closers: list[Any] = []
    try:
        session = await _start_interfaces(args, served, closers)
        for s in served:
            s.scheduler.start()
        lag = [0.0]
        watch = asyncio.ensure_future(_watch_lag(lag))
        closers.append(lambda: _cancel(watch))
        # the fleet's status, computed off the loop once per status period (each machine
        # catches up first: a few hundred machines take tens of milliseconds)
        current = [await asyncio.to_thread(fleet_status, served)]
        latest = [json.dumps(current[0]).encode()]
        if args.http:
            await _start_http(args, served, closers, lambda: current[0])
        if session is not None:
            # Zenoh thread: answer with the latest status, computed on the loop
            queryable = session.declare_queryable(
                FLEET_STATUS_KEY, lambda q: q.reply(FLEET_STATUS_KEY, latest[0])
            )

            async def undeclare() -> None:
                await loop.run_in_executor(None, queryable.undeclare)

            closers.append(undeclare)
        while not stop.is_set():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), args.status_period)
            worst, lag[0] = lag[0], 0.0
            st = current[0] = await asyncio.to_thread(fleet_status, served, worst)
            latest[0] = json.dumps(st).encode()
            if session is not None:
                session.put(FLEET_STATUS_KEY, latest[0])
            if _report(args, served, st):
                break
    finally:
        for close in reversed(closers):
            try:
                await close()
            except Exception as exc:  # report and go on closing the others
                print(f"warning: closing: {exc}", file=sys.stderr)


async def _start_interfaces(
    args: argparse.Namespace, served: list[Served], closers: list[Any]
) -> Any:
    """Start the fleet's interfaces (each one's closer appended to `closers` as it
    starts); the Zenoh session, None without Zenoh."""
    session = None
    if not args.no_zenoh:
        session = await _start_zenoh(args, served, closers)
    if not args.no_modbus:
        try:
            await _start_modbus(args, served, closers)
        except OSError as exc:
            raise InterfaceStartError(start_failure("modbus", exc)) from exc
    if not args.no_ads:
        await _start_ads(args, served, closers)
    if not args.no_opcua:
        await _start_opcua(args, served, closers)
    return session


def _report(args: argparse.Namespace, served: list[Served], st: dict[str, Any]) -> bool:
    """Print the fleet's status line; True when `--cycles` are done. A machine whose
    cycle ended by itself otherwise: CycleStoppedError (serving a frozen machine would
    look alive)."""
    cycles = [m["cycle"] for m in st["machines"]]
    print(
        f"fleet: {st['count']} machines, cycles {min(cycles)}…{max(cycles)}, "
        f"overruns {st['overruns']}, stalled {len(st['stalled'])}, "
        f"loop lag {st['loop_lag_ms']:g} ms, starved {len(st['starved'])}",
        flush=True,
    )
    if args.cycles and all(not s.scheduler.running for s in served):
        return True
    dead = [s.member.name for s in served if not s.scheduler.running]
    if dead and not args.cycles:
        raise CycleStoppedError(f"the GEO cycle of {', '.join(dead)} ended unexpectedly")
    return False


async def _cancel(task: asyncio.Future[None]) -> None:
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task


async def _start_zenoh(args: argparse.Namespace, served: list[Served], closers: list[Any]) -> Any:
    import zenoh

    from geo_server.transports.zenoh.server import ZenohInterface, ZenohOptions

    base = ZenohOptions(
        mode=args.zenoh_mode,
        listen=args.zenoh_listen or ["tcp/127.0.0.1:7447"],
        connect=args.zenoh_connect or [],
        config_file=args.zenoh_config,
        multicast_scouting=args.zenoh_scouting,
        read_only=args.read_only or args.zenoh_read_only,
    )
    base.shrink_to(args.caps["zenoh"])
    loop = asyncio.get_running_loop()
    try:
        session = await loop.run_in_executor(None, zenoh.open, base.zenoh_config())
    except Exception as exc:
        raise InterfaceStartError(start_failure("zenoh", exc)) from exc

    async def close_session() -> None:
        await loop.run_in_executor(None, session.close)

    closers.append(close_session)
    ifaces = []
    for s in served:
        opts = ZenohOptions(**{**base.__dict__, "machine": s.member.name})
        iface = ZenohInterface(s.service, opts, session=session)
        closers.append(iface.close)
        ifaces.append(iface)
    # together: each start looks for a rival's liveliness token (up to a second)
    await asyncio.gather(*(iface.start() for iface in ifaces))
    print(
        f"zenoh: {len(served)} machines on {', '.join(base.listen)} (keys cnc/<name>/**, "
        f"{FLEET_STATUS_KEY})",
        flush=True,
    )
    return session


async def _start_modbus(args: argparse.Namespace, served: list[Served], closers: list[Any]) -> None:
    from geo_server.transports.modbus.server import ModbusInterface, ModbusOptions

    read_only = args.read_only or args.modbus_read_only
    caps = args.caps["modbus"]
    for s in served:
        mb = ModbusInterface(
            s.service,
            ModbusOptions(
                host=args.modbus_host,
                port=s.member.modbus_port,
                read_only=read_only,
                max_connections=caps,
                backlog=FLEET_BACKLOG,
            ),
        )
        closers.append(mb.close)
        await mb.start()
    first, last = served[0].member.modbus_port, served[-1].member.modbus_port
    print(f"modbus: tcp://{args.modbus_host}:{first}…{last}, one port per machine", flush=True)


async def _start_opcua(args: argparse.Namespace, served: list[Served], closers: list[Any]) -> None:
    """One OPC UA server for the fleet, each machine under its own name (its
    certificate beside the fleet file, or as for the start-up list of --fleet-size)."""
    from geo_server.opcua_run import announce, options_from_args
    from geo_server.transports.opcua.server import OpcUaInterface

    where = args.fleet or args.startup
    options = options_from_args(args, Path(where) if where else None, args.caps)
    ua = OpcUaInterface({s.member.name: s.service for s in served}, options)
    announce(ua, f"{len(served)} machines: Objects/<name>")
    closers.append(ua.close)
    try:
        await ua.start()
    except Exception as exc:  # a taken port
        raise InterfaceStartError(start_failure("opcua", exc)) from exc
    print(f"opcua: {ua.endpoint} starting (README *OPC UA*)", flush=True)


async def _start_http(
    args: argparse.Namespace,
    served: list[Served],
    closers: list[Any],
    status: Callable[[], dict[str, Any]],
) -> None:
    from geo_server.web.server import FleetHmi, access_note, http_options

    options = http_options(args, max_connections=args.caps["http"])
    hmi = FleetHmi({s.member.name: s.service for s in served}, status, options)
    closers.append(hmi.close)
    try:
        await hmi.start()
    except Exception as exc:  # a taken port
        raise InterfaceStartError(start_failure("http", exc)) from exc
    print(
        f"http: web HMI on {hmi.url} (the fleet; a machine at /m/<name>/; "
        f"{access_note(hmi.options)})",
        flush=True,
    )


async def _start_ads(args: argparse.Namespace, served: list[Served], closers: list[Any]) -> None:
    from geo_server.transports.ads.server import AdsOptions, AdsServer

    read_only = args.read_only or args.ads_read_only

    def options(m: Member, **kw: Any) -> AdsOptions:
        return AdsOptions(host=args.ads_host, netid=m.netid, read_only=read_only, **kw)

    head = served[0]
    ads = AdsServer(
        head.service,
        options(
            head.member,
            port=args.ads_port,
            udp_port=args.ads_udp_port or None,
            route_user=args.ads_route_user,
            route_password=args.ads_route_password,
            max_connections_fleet=args.caps["ads"],
        ),
    )
    for s in served[1:]:
        ads.add_device(s.service, options(s.member))
    closers.append(ads.close)
    try:
        await ads.start()
    except OSError as exc:
        raise InterfaceStartError(start_failure("ads", exc)) from exc
    print(
        f"ads: tcp://{ads.address}, AMS NetIds {head.member.netid}…{served[-1].member.netid} "
        "(routed by target NetId)",
        flush=True,
    )
