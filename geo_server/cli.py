"""`geo-server`: run the emulated machine, check list files, print the object dictionary."""

from __future__ import annotations

import argparse
import csv
import io
import json
import signal
import sys
import threading
from pathlib import Path

from geo_server import __version__
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


def _check(args: argparse.Namespace) -> int:
    """Exit 0 when the machine loads, 1 when a compensation was deactivated, 2 when the
    lists cannot be read (issue 2)."""
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
    print(
        f"{path}: {len(cfg.axes)} axes ({names}), {len(cfg.diagnostics)} diagnostics, "
        f"{len(deactivated)} compensations deactivated"
    )
    return 1 if deactivated else 0


def _run(args: argparse.Namespace) -> int:
    from geo_server.listfile import ListFileError, load_machine
    from geo_server.machine.machine import Machine
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
    machine = Machine(cfg, cycle_s=args.cycle_ms / 1000.0, homed=args.homed)
    scheduler = Scheduler(machine, mode=args.mode)
    service = ObjectService(machine, scheduler)
    if args.program:
        machine.start_program(Path(args.program).read_text(encoding="utf-8"))
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    scheduler.start()
    print(
        f"geo-server {__version__}: {path} with axes {list(machine.axes)}, cycle "
        f"{args.cycle_ms} ms ({args.mode}); Ctrl-C stops"
    )
    try:
        while not stop.wait(args.status_period):
            st = service.status()
            print(
                f"cycle {st['cycle']}  lateness p50 {st['lateness_p50_us']:.0f} µs "
                f"p99 {st['lateness_p99_us']:.0f} µs max {st['lateness_max_us']:.0f} µs  "
                f"overruns {st['overruns']}  kernel p50 {st['cycle_p50_us']:.0f} µs",
                flush=True,
            )
            if args.cycles and st["cycle"] >= args.cycles:
                break
    finally:
        scheduler.stop()
    print(f"stopped after {machine.cycle} cycles")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="geo-server", description=__doc__)
    p.add_argument("--version", action="version", version=f"geo-server {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    o = sub.add_parser("objects", help="print the object dictionary")
    o.add_argument("--format", choices=("md", "csv", "json"), default="md")
    o.set_defaults(func=_objects)

    c = sub.add_parser("check", help="validate a machine's list files")
    c.add_argument("startup", nargs="?", help="start-up list (default: the default machine)")
    c.set_defaults(func=_check)

    r = sub.add_parser("run", help="run the machine in real time")
    r.add_argument("startup", nargs="?", help="start-up list (default: the default machine)")
    r.add_argument("--cycle-ms", type=float, default=1.0, help="GEO cycle length in ms (0.25 … 10)")
    r.add_argument("--program", help="NC program to run at start")
    r.add_argument("--homed", action="store_true", help="start with every axis homed")
    r.add_argument("--mode", choices=("realtime", "free"), default="realtime")
    r.add_argument("--status-period", type=float, default=1.0, help="seconds between status lines")
    r.add_argument("--cycles", type=int, default=0, help="stop after this many cycles (0: never)")
    r.set_defaults(func=_run)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "run" and not 0.25 <= args.cycle_ms <= 10:
        print("error: --cycle-ms must be between 0.25 and 10", file=sys.stderr)
        return 2
    return args.func(args)


if __name__ == "__main__":
    raise SystemExit(main())
