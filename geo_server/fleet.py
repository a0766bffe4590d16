"""A fleet: M machines served by one `geo-server run` process (SPEC §13, docs/design.md §13).

    geo-server run --fleet fleet.toml          # machines named in a fleet file
    geo-server run --fleet-size 50 --homed     # 50 copies of one start-up list

Each machine has its own name, start-up list, GEO cycle and object service; the exact
engines of all of them run on one thread (`scheduler.Engines`: a machine at rest costs
next to nothing). The interfaces:

- **Zenoh**: one session for the whole fleet; machine `m` answers on `cnc/m/**` as a
  single machine does, and `cnc/fleet/status` (published each status period and
  answered to a get) tells every machine's name, cycle, engine, overruns and addresses.
- **ADS**: one TCP port; requests are routed by the target AMS NetId as a TwinCAT router
  does (`AdsServer.add_device`), one NetId per machine; an unknown NetId gets 0x7.
- **Modbus**: one port per machine, `--modbus-port` + i.
- **Web HMI** (`--http`): the fleet's page at `/`, each machine's page at `/m/<name>/`.
- **OPC UA**: one server; machine `m` is `Objects/m` (README *OPC UA*).

The fleet file: `geo_server.fleetfile`; the interfaces are built by the composition root,
`geo_server.compose` (`Interfaces.start_fleet`), as a single machine's are.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import functools
import json
import signal
import sys
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from geo_server import jit
from geo_server.aio import wait_set
from geo_server.compose import EngineOptions, Interfaces, build_machine
from geo_server.fleetfile import FleetError, Member, copies, load_fleet
from geo_server.interfaces import CycleStoppedError, serve
from geo_server.machine.scheduler import Engines, Scheduler, switch_interval
from geo_server.paths import default_startup_list
from geo_server.recorder import cli as recorder_cli
from geo_server.service import ObjectService
from geo_server.transports.interface import FleetStatus, plugs
from geo_server.transports.share import STATUS_KEY

#: the interfaces' plugs (loaded once: a fleet's status asks each of them per machine)
_PLUGS = functools.cache(plugs)


def members_from_args(args: argparse.Namespace) -> list[Member]:
    if args.fleet:
        return load_fleet(Path(args.fleet), args.ads_netid, args.modbus_port)
    startup = Path(args.startup) if args.startup else default_startup_list()
    return copies(args.fleet_size, args.machine, startup, args.ads_netid, args.modbus_port)


# ---------------------------------------------------------------------- serving


@dataclass
class Served:
    member: Member
    service: ObjectService
    scheduler: Scheduler  # (a fleet's cycles run in this process: `EngineOptions`)
    late: int = 0  # samples late at the last fleet status (`starved`)
    holds: int = 0  # loop-share holds at the last fleet status (`throttled`)


def run_fleet(args: argparse.Namespace) -> int:
    """`geo-server run --fleet FILE | --fleet-size N` (exit code)."""
    from geo_server import __version__
    from geo_server.commands.faults import inject_faults
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
            print(*(f"{m.name}: {line}" for line in exc.report()), sep="\n", file=sys.stderr)
            return 2
        configs[m.startup] = cfg
        built = build_machine(cfg, EngineOptions.from_args(args))
        service = built.service
        # a folder of recordings per machine: the same name never collides (docs/recorder.md §7)
        service.recordings.record_dir = recorder_cli.record_dir(args, m.name, cfg.startup_path)
        if not inject_faults(args.fault, service.faults, f"{m.name}: "):  # every machine gets them
            return 2
        assert isinstance(built.scheduler, Scheduler)  # (cycle_in "thread", as asked)
        served.append(Served(m, service, built.scheduler))
    threads = _cycle_threads(served)
    print(
        f"geo-server {__version__}: a fleet of {len(served)} machines "
        f"({', '.join(s.member.name for s in served[:5])}{', …' if len(served) > 5 else ''}), "
        f"cycle {args.cycle_ms:g} ms ({args.mode}, {args.engine} engine, cycles on "
        f"{'one thread' if threads == 1 else f'{threads} threads'}); "
        "Ctrl-C stops",
        flush=True,
    )
    # the exact engines of every machine on one thread (started with the cycles, below)
    engines = Engines()

    def stop_cycles() -> None:
        for s in served:
            s.scheduler.stop()
        engines.stop()

    code = serve(_serve(args, served, engines), stop_cycles)
    if code == 0:
        print(f"stopped: {len(served)} machines")
    return code


def _cycle_threads(served: list[Served]) -> int:
    """The threads the machines' cycles run on: one for all the exact engines
    (`Engines`), one more per punctual or free machine."""
    exact = sum(s.scheduler.exact for s in served)
    return len(served) - exact + min(exact, 1)


class Halted(Exception):
    """A fleet's status was not computed: the fleet stops (`fleet_status`)."""


def fleet_status(
    served: list[Served],
    loop_lag_ms: float = 0.0,
    publish: Mapping[str, Callable[[dict[str, Any]], None]] | None = None,
    halted: threading.Event | None = None,
) -> dict[str, Any]:
    """Every machine's name, cycle, engine, overruns and addresses; the fleet's totals.
    Each machine's own status is handed to `publish[name]` on the way (its Zenoh
    status: a fleet computes them here, off the event loop, not each machine on it).

    Starvation shows too (docs/design.md §13.1): `loop_lag_ms`, how late the event loop
    that serves every machine ran a timer in the last status period, and per machine
    `samples_late`, its notification samples taken later than their cycle (the loop or
    the engine could not keep up, `ads_notifications` of its status) or dropped before
    OPC UA sampled them (`opcua_items`); `starved` lists
    the machines whose count grew since the last status. Per machine `loop_share_holds`
    counts how often its ADS and Modbus requests waited for its share of the loop
    (`loop_share` of its status) and its OPC UA requests for its share of OPC UA's
    (`opcua_share`); `throttled` lists the machines held back since the last status:
    their clients ask more than their share.

    Once `halted` is set (a SIGTERM), `Halted` instead: each machine catches up first,
    seconds for hundreds of machines just started, and a stop must not wait for that."""
    machines = []
    for s in served:
        if halted is not None and halted.is_set():
            raise Halted
        st = s.service.status()
        if publish is not None and s.member.name in publish:
            publish[s.member.name](st)
        machines.append(_machine_status(s.member, st))
    starved = [
        m["name"] for m, s in zip(machines, served, strict=True) if m["samples_late"] > s.late
    ]
    throttled = [
        m["name"] for m, s in zip(machines, served, strict=True) if m["loop_share_holds"] > s.holds
    ]
    for m, s in zip(machines, served, strict=True):
        s.late = m["samples_late"]
        s.holds = m["loop_share_holds"]
    return {
        "machines": machines,
        "count": len(machines),
        "overruns": sum(m["overruns"] for m in machines),
        "stalled": [m["name"] for m in machines if m["stalled"]],
        "loop_lag_ms": round(loop_lag_ms, 1),
        "samples_late": sum(m["samples_late"] for m in machines),
        "starved": starved,
        "throttled": throttled,
    }


def _machine_status(member: Member, st: dict[str, Any]) -> dict[str, Any]:
    """A machine's entry in the fleet's status, from its own status `st`: its share of
    the loop's holds, and what each interface's entries add (`Interface.fleet_counts`)."""
    share = st.get(STATUS_KEY) or {}
    counts = [plug.fleet_counts(st) for plug in _PLUGS()]
    return {
        "name": member.name,
        "cycle": st["cycle"],
        "engine": st["engine"],
        "overruns": st["overruns"],
        "stalled": st["stalled"],
        "computed_cycles": st["computed_cycles"],
        "notifications": sum(c.notifications for c in counts),
        "samples_late": sum(c.samples_late for c in counts),
        "loop_share_holds": int(share.get("holds", 0)) + sum(c.holds for c in counts),
        "netid": member.netid,
        "modbus_port": member.modbus_port,
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


def _stop_on_signals() -> tuple[asyncio.Event, threading.Event]:
    """Ctrl-C and SIGTERM set both: the loop's event, and the same for the status's
    thread (`fleet_status`)."""
    stop, halted = asyncio.Event(), threading.Event()

    def on_signal() -> None:
        stop.set()
        halted.set()

    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, on_signal)
    return stop, halted


async def _serve(args: argparse.Namespace, served: list[Served], engines: Engines) -> None:
    stop, halted = _stop_on_signals()
    # as for one machine (geo_server/descriptors.py): the soft open-files limit raised to
    # the hard one, every interface's connections fitted under it, and accept failures
    # said once per period, not once per retry
    interfaces = Interfaces.plan(args, len(served))
    machines = [(s.member, s.service) for s in served]
    current: list[dict[str, Any]] = [{}]  # the latest status (the web HMI's page)
    latest: list[bytes | None] = [None]  # ... as JSON (Zenoh's `cnc/fleet/status`)
    status = FleetStatus(lambda: current[0], lambda: latest[0])
    try:
        await interfaces.start_fleet(args, machines, status)
        # A fleet's cycles start compiled: a hundred machines interpreted would take the
        # cores the compiler needs (one machine starts interpreted: cli._serve). The
        # interfaces answer meanwhile, with each machine at its cycle 0.
        await _load_compiled()
        # the switch interval for the cycle threads there are: one for every exact
        # engine, one more per punctual or free machine (docs/design.md §13.1); set
        # here, the fleet process's composition root
        sys.setswitchinterval(switch_interval(_cycle_threads(served)))
        engines.start()
        for s in served:
            s.scheduler.start(engines)  # (a punctual or free one: a thread of its own)
        lag = [0.0]
        watch = asyncio.ensure_future(_watch_lag(lag))
        interfaces.closes("the loop lag watch", lambda: _cancel(watch))
        # the fleet's status, computed off the loop once per status period (each machine
        # catches up first: a few hundred machines take tens of milliseconds)
        publish = status.publishers

        def says(st: dict[str, Any]) -> None:
            """One status computation said everywhere, its status line first, then the
            same dict to the HMI's page and as JSON to the interfaces that serve it:
            whoever reads a status anywhere finds its line printed already (the line and
            `cnc/fleet/status` never disagree on `throttled`, `starved`, ...)."""
            print(status_line(st), flush=True)
            current[0] = st
            said = latest[0] = json.dumps(st).encode()
            for put in status.said:
                put(said)

        try:
            says(await asyncio.to_thread(fleet_status, served, 0.0, publish, halted))
        except Halted:
            return
        # those that show the fleet's status (its web HMI): once the cycles run
        await interfaces.start_fleet_late(args, status)
        while not stop.is_set():
            await wait_set(stop, args.status_period)
            if stop.is_set():  # (no last status: see `fleet_status`)
                break
            worst, lag[0] = lag[0], 0.0
            try:
                says(await asyncio.to_thread(fleet_status, served, worst, publish, halted))
            except Halted:
                break
            if _done(args, served):
                break
    finally:
        await interfaces.close()


def status_line(st: dict[str, Any]) -> str:
    """The fleet's status line of status `st` (`fleet_status`)."""
    cycles = [m["cycle"] for m in st["machines"]]
    return (
        f"fleet: {st['count']} machines, cycles {min(cycles)}…{max(cycles)}, "
        f"overruns {st['overruns']}, stalled {len(st['stalled'])}, "
        f"loop lag {st['loop_lag_ms']:g} ms, starved {len(st['starved'])}, "
        f"throttled {len(st['throttled'])}"
    )


def _done(args: argparse.Namespace, served: list[Served]) -> bool:
    """True when `--cycles` are done. A machine whose cycle ended by itself otherwise:
    CycleStoppedError (serving a frozen machine would look alive)."""
    if args.cycles and all(not s.scheduler.running for s in served):
        return True
    dead = [s.member.name for s in served if not s.scheduler.running]
    if dead and not args.cycles:
        raise CycleStoppedError(f"the GEO cycle of {', '.join(dead)} ended unexpectedly")
    return False


async def _load_compiled() -> None:
    """`jit.load` off the loop; says so when it takes long: compiling (a cold cache) or
    only loading the machine code from the cache (a warm one, on a busy host)."""
    warm = await asyncio.to_thread(jit.cache_is_warm)
    loading = asyncio.ensure_future(asyncio.to_thread(jit.load))
    try:
        await asyncio.wait_for(asyncio.shield(loading), 2.0)
    except TimeoutError:
        print(
            "loading the compiled GEO cycle from its cache (the machines' cycles start after it)"
            if warm
            else "compiling the GEO cycle (the first start after an installation or an "
            "update: up to a minute; the machines' cycles start after it)",
            flush=True,
        )
        await loading


async def _cancel(task: asyncio.Future[None]) -> None:
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task
