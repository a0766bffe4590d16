"""`geo-server`: run the emulated machine, check list files, print the object dictionary."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import csv
import io
import json
import os
import secrets
import shutil
import signal
import sys
from pathlib import Path
from typing import Any

from geo_server import __version__
from geo_server.console import closes_quietly_on_broken_pipe
from geo_server.dictionary import COLUMNS, dictionary_markdown, load_dictionary
from geo_server.paths import default_startup_list


def _objects(args: argparse.Namespace) -> int:
    d = load_dictionary()
    if args.format == "md":
        sys.stdout.write(dictionary_markdown(d))
    elif args.format == "json":
        json.dump([o.as_row() for o in d.objects], sys.stdout, indent=2, ensure_ascii=False)
        sys.stdout.write("\n")
    else:
        buf = io.StringIO()
        w = csv.DictWriter(
            buf,
            fieldnames=[*COLUMNS, "min", "max", "description"],
            extrasaction="ignore",
            lineterminator="\n",
        )
        w.writeheader()
        for o in d.objects:
            w.writerow(o.as_row())
        sys.stdout.write(buf.getvalue())
    return 0


def _modbus_map(args: argparse.Namespace) -> int:
    from geo_server.modbus.regmap import modbus_map

    sys.stdout.write(modbus_map(args.format))
    return 0


def _init(args: argparse.Namespace) -> int:
    """Copy the default machine's lists into a folder of the user's (to edit and save).

    All or nothing: every file is copied to a temporary name first and renamed once all
    are complete; on any OSError (disk full, no permission, read-only folder) the
    temporary files and the folders this command created are removed again, and one
    line says why (exit 2).
    """
    from geo_server.listfile.writer import TEMP_SUFFIX, temp_prefix

    src = default_startup_list().parent
    dest = Path(args.directory)
    files = sorted(p for p in src.iterdir() if p.is_file() and p.suffix in (".lis", ".nc"))
    clash = [p.name for p in files if (dest / p.name).exists()]
    if clash and not args.force:
        print(f"error: {dest} already has {', '.join(clash)} (--force overwrites)", file=sys.stderr)
        return 2
    created = [d for d in (dest, *dest.parents) if not d.exists()]
    temps: list[Path] = []
    try:
        dest.mkdir(parents=True, exist_ok=True)
        for p in files:
            # named like save's temporaries (`remove_orphan_temps` knows them); created by
            # copyfile, so the copy gets the mode a new file gets, as the list itself
            tmp = dest / f"{temp_prefix(dest / p.name)}{secrets.token_hex(4)}{TEMP_SUFFIX}"
            temps.append(tmp)
            shutil.copyfile(p, tmp)
        for p, tmp in zip(files, temps, strict=True):
            os.replace(tmp, dest / p.name)
    except OSError as exc:
        for tmp in temps:
            with contextlib.suppress(OSError):
                tmp.unlink()
        for folder in created:  # deepest first
            with contextlib.suppress(OSError):
                folder.rmdir()
        reason = exc.strerror or (os.strerror(exc.errno) if exc.errno else str(exc))
        print(f"error: cannot copy the default machine to {dest}: {reason}", file=sys.stderr)
        return 2
    print(f"default machine copied to {dest} ({len(files)} files); run it with:")
    print(f"  geo-server run {dest / 'hochlauf.lis'}")
    return 0


def _check(args: argparse.Namespace) -> int:
    """Exit 0 when the machine loads, 1 when a compensation was deactivated or a list had
    to be skipped (any error: the same that makes a reload fail), 2 when the lists cannot
    be read (issue 2)."""
    from geo_server.listfile import ListFileError, load_machine

    path = Path(args.startup) if args.startup else default_startup_list()
    try:
        cfg = load_machine(path)
    except ListFileError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for d in cfg.diagnostics:
        print(d)
    names = ", ".join(f"{a}={cfg.axes[a].params.name or '?'}" for a in sorted(cfg.axes))
    deactivated = cfg.deactivated
    errors = [d for d in cfg.diagnostics if d.severity == "error"]
    print(
        f"{path}: {len(cfg.axes)} axes ({names}), {len(cfg.diagnostics)} diagnostics, "
        f"{len(deactivated)} compensations deactivated, {len(errors)} errors"
    )
    return 1 if deactivated or errors else 0


def _run(args: argparse.Namespace) -> int:
    from geo_server.listfile import ListFileError, load_machine
    from geo_server.machine.machine import Machine
    from geo_server.machine.nc import NcError
    from geo_server.machine.scheduler import Scheduler
    from geo_server.service import ObjectService

    path = Path(args.startup) if args.startup else default_startup_list()
    try:
        cfg = load_machine(path)
    except ListFileError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for d in cfg.diagnostics:
        print(d, file=sys.stderr)
    _remove_orphans(cfg)
    machine: Any
    scheduler: Any
    if args.cycle_in == "process":
        from geo_server.machine.process import ProcessScheduler, RemoteMachine

        machine = RemoteMachine(cfg, cycle_s=args.cycle_ms / 1000.0, homed=args.homed)
        scheduler = ProcessScheduler(machine, mode=args.mode, max_cycles=args.cycles)
    else:
        machine = Machine(cfg, cycle_s=args.cycle_ms / 1000.0, homed=args.homed)
        scheduler = Scheduler(machine, mode=args.mode, max_cycles=args.cycles)
    service = ObjectService(machine, scheduler)
    if args.program:
        try:
            machine.start_program(Path(args.program).read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, NcError) as exc:
            print(f"error: NC program {args.program}: {exc}", file=sys.stderr)
            return 2
    print(
        f"geo-server {__version__}: {path} with axes {list(machine.axes)}, cycle "
        f"{args.cycle_ms:g} ms ({args.mode}, cycle in its own {args.cycle_in}); Ctrl-C stops",
        flush=True,
    )
    try:
        asyncio.run(_serve(args, service, scheduler))
    except InterfaceStartError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except CycleStoppedError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    finally:
        scheduler.stop()
    print(f"stopped after {machine.cycle} cycles")
    return 0


def _remove_orphans(cfg: Any) -> None:
    """A save killed half-way (power loss, SIGKILL) can leave its temporary file next
    to a list: remove those at start, before anything could be saving."""
    from geo_server.listfile import remove_orphan_temps

    lists = [cfg.startup_path]
    for ax in cfg.axes.values():
        lists += [p for p in (ax.params.path, ax.comp.path if ax.comp else "") if p]
    for tmp in remove_orphan_temps(lists):
        print(f"removed {tmp}: left over from an interrupted save", file=sys.stderr)


def _zenoh(args: argparse.Namespace, service: Any) -> tuple[Any, Any]:
    from geo_server.transports.zenoh_server import ZenohInterface, ZenohOptions

    opts = ZenohOptions(
        machine=args.machine,
        mode=args.zenoh_mode,
        listen=args.zenoh_listen or ["tcp/127.0.0.1:7447"],
        connect=args.zenoh_connect or [],
        config_file=args.zenoh_config,
        multicast_scouting=args.zenoh_scouting,
        read_only=args.read_only or args.zenoh_read_only,
    )
    return (
        ZenohInterface(service, opts),
        lambda: (
            f"zenoh: machine {args.machine!r} on {', '.join(opts.listen)} "
            f"(keys cnc/{args.machine}/**)"
        ),
    )


def _modbus(args: argparse.Namespace, service: Any) -> tuple[Any, Any]:
    from geo_server.modbus.server import ModbusInterface, ModbusOptions

    read_only = args.read_only or args.modbus_read_only
    mb = ModbusInterface(
        service, ModbusOptions(host=args.modbus_host, port=args.modbus_port, read_only=read_only)
    )
    return mb, lambda: f"modbus: tcp://{mb.endpoint} (unit id = axis number, unit 0 = machine)"


def _ads(args: argparse.Namespace, service: Any) -> tuple[Any, Any]:
    from geo_server.ads.server import AdsOptions, AdsServer

    read_only = args.read_only or args.ads_read_only
    opts = AdsOptions(
        host=args.ads_host, port=args.ads_port, netid=args.ads_netid, read_only=read_only
    )
    ads = AdsServer(service, opts)
    return ads, lambda: f"ads: tcp://{ads.address} AMS NetId {args.ads_netid} port 551"


async def _serve(args: argparse.Namespace, service: Any, scheduler: Any) -> None:
    """Run the transports on the asyncio loop until Ctrl-C / SIGTERM."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    interfaces: list[Any] = []
    try:
        for name, disabled, build in (
            ("zenoh", args.no_zenoh, _zenoh),
            ("modbus", args.no_modbus, _modbus),
            ("ads", args.no_ads, _ads),
        ):
            if disabled:
                continue
            iface, describe = build(args, service)
            # Registered before start() so a half-started interface is closed too.
            interfaces.append(iface)
            try:
                await iface.start()
            except Exception as exc:  # OSError (port busy), zenoh.ZError, bad config
                raise InterfaceStartError(f"{name} interface did not start: {exc}") from exc
            print(describe(), flush=True)
        # The cycle starts once every interface is up, so start-up work does not show as
        # lateness of the first cycles.
        scheduler.start()
        next_status = loop.time() + args.status_period
        while not stop.is_set():
            # With --cycles, look often whether the cycle thread has finished its cycles.
            wait = min(args.status_period, 0.02) if args.cycles else args.status_period
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), wait)
            finished = bool(args.cycles) and not scheduler.running
            if not scheduler.running and not finished and not stop.is_set():
                # Serving the last snapshot forever would look alive but be wrong.
                raise CycleStoppedError(
                    f"the GEO cycle ended unexpectedly after cycle {scheduler.machine.cycle}"
                )
            if loop.time() < next_status and not finished:
                continue
            next_status = loop.time() + args.status_period
            st = service.status()
            if st.get("stalled"):
                print(
                    f"cycle {st['cycle']}  STALLED: no GEO cycle for {st['stalled_for_s']:.1f} s"
                    " (reads answer 'not ready', writes are refused)",
                    flush=True,
                )
                continue
            print(
                f"cycle {st['cycle']}  lateness p50 {st['lateness_p50_us']:.0f} µs "
                f"p99 {st['lateness_p99_us']:.0f} µs max {st['lateness_max_us']:.0f} µs  "
                f"overruns {st['overruns']}  cycle p50 {st['cycle_p50_us']:.0f} µs "
                f"(kernel {st['kernel_p50_us']:.0f} µs)",
                flush=True,
            )
            if finished:
                break
    finally:
        # Reverse order of start; one interface failing to close must not keep the
        # others (and their ports) open.
        for iface in reversed(interfaces):
            try:
                await iface.close()
            except Exception as exc:  # report and go on closing the others
                print(f"warning: closing {type(iface).__name__}: {exc}", file=sys.stderr)


class InterfaceStartError(RuntimeError):
    """An interface could not start (port in use, bad address or Zenoh config)."""


class CycleStoppedError(RuntimeError):
    """The GEO cycle thread died (a defect; its traceback is on stderr)."""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="geo-server", description=__doc__)
    p.add_argument("--version", action="version", version=f"geo-server {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    o = sub.add_parser("objects", help="print the object dictionary")
    o.add_argument("--format", choices=("md", "csv", "json"), default="md")
    o.set_defaults(func=_objects)

    i = sub.add_parser("init", help="copy the default machine's list files into DIRECTORY")
    i.add_argument("directory", help="folder for the lists (created if missing)")
    i.add_argument("--force", action="store_true", help="overwrite existing files")
    i.set_defaults(func=_init)

    c = sub.add_parser("check", help="validate a machine's list files")
    c.add_argument("startup", nargs="?", help="start-up list (default: the default machine)")
    c.set_defaults(func=_check)

    r = sub.add_parser("run", help="run the machine in real time")
    r.add_argument("startup", nargs="?", help="start-up list (default: the default machine)")
    r.add_argument("--cycle-ms", type=float, default=1.0, help="GEO cycle length in ms (0.25 … 10)")
    r.add_argument("--program", help="NC program to run at start")
    r.add_argument("--homed", action="store_true", help="start with every axis homed")
    r.add_argument("--mode", choices=("realtime", "free"), default="realtime")
    r.add_argument(
        "--cycle-in",
        choices=("process", "thread"),
        default="process",
        help="run the GEO cycle in its own process (default: no interpreter lock shared "
        "with the transports, punctual under load) or in a thread of the server",
    )
    r.add_argument("--status-period", type=float, default=1.0, help="seconds between status lines")
    r.add_argument("--cycles", type=int, default=0, help="stop after this many cycles (0: never)")
    r.add_argument("--machine", default="local", help="machine name (Zenoh key prefix)")
    r.add_argument("--read-only", action="store_true", help="reject every write")
    z = r.add_argument_group("zenoh")
    z.add_argument("--no-zenoh", action="store_true", help="do not start the Zenoh interface")
    z.add_argument(
        "--zenoh-listen",
        action="append",
        metavar="ENDPOINT",
        help="listen endpoint (default tcp/127.0.0.1:7447; repeatable)",
    )
    z.add_argument(
        "--zenoh-connect",
        action="append",
        metavar="ENDPOINT",
        help="router or peer to connect to (repeatable)",
    )
    z.add_argument("--zenoh-mode", choices=("peer", "client"), default="peer")
    z.add_argument(
        "--zenoh-config", metavar="FILE", help="Zenoh JSON5 config file (TLS, access control, …)"
    )
    z.add_argument("--zenoh-scouting", action="store_true", help="enable multicast scouting")
    m = r.add_argument_group("modbus")
    m.add_argument("--no-modbus", action="store_true", help="do not start Modbus TCP")
    m.add_argument("--modbus-host", default="127.0.0.1", help="listen address (default 127.0.0.1)")
    m.add_argument("--modbus-port", type=int, default=5020, help="listen port (default 5020)")
    m.add_argument("--modbus-read-only", action="store_true", help="reject Modbus writes")
    z.add_argument("--zenoh-read-only", action="store_true", help="reject Zenoh writes")
    a = r.add_argument_group("ads")
    a.add_argument("--no-ads", action="store_true", help="do not start ADS/AMS over TCP")
    a.add_argument("--ads-host", default="127.0.0.1", help="listen address (default 127.0.0.1)")
    a.add_argument("--ads-port", type=int, default=48898, help="listen port (default 48898)")
    a.add_argument("--ads-netid", default="127.0.0.1.1.1", help="own AMS NetId")
    a.add_argument("--ads-read-only", action="store_true", help="reject ADS writes (0x704)")
    r.set_defaults(func=_run)

    mm = sub.add_parser("modbus-map", help="print the Modbus register map")
    mm.add_argument("--format", choices=("md", "csv"), default="md")
    mm.set_defaults(func=_modbus_map)
    return p


@closes_quietly_on_broken_pipe
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "run" and not 0.25 <= args.cycle_ms <= 10:
        print("error: --cycle-ms must be between 0.25 and 10", file=sys.stderr)
        return 2
    return args.func(args)


if __name__ == "__main__":
    raise SystemExit(main())
