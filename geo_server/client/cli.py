"""`geo-client`: read, write and watch a running geo-server's CNC objects.

Address objects by name (`--axis X TEMPC::coefficient`; the axis by number or name) or
by ADS address (`0x120300 0x10043`). Values print in engineering units (positions in mm
or °, offsets in µm, velocities in mm/s) unless `--raw`; `--json` prints JSON.
`read`, `write`, `watch`, `status`, `errors`, `reload` and `save` work over all three
transports; `nc` and `reset` need Zenoh.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from geo_server import __version__
from geo_server.client import TRANSPORTS, GeoClient, open_client, resolve
from geo_server.client.base import ServerUnreachable
from geo_server.console import closes_quietly_on_broken_pipe, engine_figures
from geo_server.dictionary import ObjectDef, load_dictionary
from geo_server.errors import AdsError
from geo_server.units import LINEAR, show

#: Seconds between two polls of `watch` over Modbus (which has no notifications).
MODBUS_WATCH_PERIOD = 0.1


def _is_int(text: str) -> bool:
    try:
        int(text, 0)
    except ValueError:
        return False
    return True


def _by_address(words: list[str]) -> bool:
    return len(words) >= 2 and _is_int(words[0]) and _is_int(words[1])


class Shell:
    """One command's view of the client: targets, units and output."""

    def __init__(self, args: argparse.Namespace, client: Any) -> None:
        self.args = args
        self.client = client
        self.dictionary = load_dictionary()
        self._axis: int | None = None
        self._names: dict[int, str] | None = None

    # ------------------------------------------------------------------ targets

    @property
    def axis(self) -> int:
        if self._axis is None:
            self._axis = self.client.axis_number(self.args.axis)
        return self._axis

    def axis_label(self, axis: int) -> str:
        if self._names is None:
            try:
                self._names = {a: n for n, a in self.client.axis_names().items()}
            except AdsError:
                self._names = {}
        name = self._names.get(axis)
        return f"axis {axis} ({name})" if name else f"axis {axis}"

    def target(self, name: str) -> tuple[ObjectDef, int]:
        """The object named and its axis; a failed lookup of the axis' number is
        reported against the object asked for (issue 45 #15)."""
        obj = self.dictionary.by_name(name)
        if obj.scope == "machine":
            return obj, 0
        try:
            return obj, self.axis
        except AdsError as exc:
            raise AdsError(exc.code, f"{obj.name}: {exc.message}", obj.name) from None

    def address(self, words: list[str]) -> tuple[ObjectDef, int, int, int, str | None]:
        ig, io = int(words[0], 0), int(words[1], 0)
        obj, axis, attr = self.dictionary.resolve(ig, io, [io >> 16])
        return obj, axis, ig, io, attr

    # ------------------------------------------------------------------ output

    def shown(self, obj: ObjectDef, axis: int, value: Any) -> dict[str, Any]:
        kind = self.client.axis_type(axis) if obj.quantity and obj.scope == "axis" else LINEAR
        s = show(obj, value, kind, raw=self.args.raw)
        return {"name": obj.name, "axis": axis, "value": s.value, "unit": s.unit, "raw": value}

    def print_value(self, obj: ObjectDef, axis: int, value: Any) -> None:
        row = self.shown(obj, axis, value)
        if self.args.json:
            print(json.dumps(row, ensure_ascii=False), flush=True)
            return
        where = f"{self.axis_label(axis)} " if obj.scope == "axis" else ""
        text = json.dumps(row["value"]) if isinstance(row["value"], str) else row["value"]
        print(f"{where}{obj.name} = {text} {row['unit']}".rstrip(), flush=True)


# ---------------------------------------------------------------------- commands


def _read(sh: Shell) -> int:
    words = sh.args.target
    if _by_address(words):
        # By address the request goes out as that address, so attribute groups
        # (0x120400 … 0x120800: name, type, length, unit, writable) read what they are.
        obj, axis, ig, io, attr = sh.address(words)
        if attr is None:
            sh.print_value(obj, axis, obj.decode(sh.client.read_raw(ig, io, obj.length)))
            return 0
        length = len(obj.attribute(attr))  # what the server answers for this attribute
        value = obj.decode_attribute(attr, sh.client.read_raw(ig, io, length))
        if sh.args.json:
            print(json.dumps({"name": obj.name, "axis": axis, "attribute": attr, "value": value}))
        else:
            where = f"{sh.axis_label(axis)} " if obj.scope == "axis" else ""
            print(f"{where}{obj.name} {attr} = {value}")
        return 0
    for name in words:
        try:  # the axis' number may need a read of its own (SIM::axis_names)
            obj, axis = sh.target(name)
            value = sh.client.read(obj.name, axis)
        except AdsError as exc:
            if name.lower() in exc.message.lower():  # it names the object already
                raise
            raise AdsError(exc.code, f"{name}: {exc.message}", exc.name or name) from None
        sh.print_value(obj, axis, value)
    return 0


def _write(sh: Shell) -> int:
    words = sh.args.target
    by_address = _by_address(words)
    if len(words) != (3 if by_address else 2):
        print("error: write takes NAME VALUE or GROUP OFFSET VALUE", file=sys.stderr)
        return 2
    raw = words[-1]
    try:
        value: Any = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    if not by_address:
        obj, axis = sh.target(words[0])
        sh.print_value(obj, axis, sh.client.write(obj.name, axis, value))
        return 0
    # The write goes to the address given, so the server judges it (an attribute group
    # is read-only: ADS 0x704), not a by-name write to the object behind it.
    obj, axis, ig, io, _attr = sh.address(words)
    sh.client.write_raw(ig, io, obj.encode(value))
    sh.print_value(obj, axis, obj.coerce(value))
    return 0


def _watch(sh: Shell) -> int:
    words = sh.args.target
    if sh.args.via == "zenoh" and "/" in words[0]:
        return _print_updates(sh, None, 0, sh.client.watch(words[0]))
    obj, axis = sh.target(words[0])
    updates: Iterator[Any]
    if sh.args.via == "zenoh":
        updates = (v for _k, v in sh.client.watch(sh.client.keyspace().named_key(obj, axis)))
    elif sh.args.via == "ads":
        updates = _ads_updates(sh.client, obj, axis)
    else:
        updates = _polled(sh.client, obj, axis)
    return _print_updates(sh, obj, axis, updates)


def _print_updates(sh: Shell, obj: ObjectDef | None, axis: int, updates: Iterator[Any]) -> int:
    seen = 0
    try:
        for update in updates:
            if obj is None:  # a Zenoh key expression: (key, value)
                key, value = update
                print(
                    json.dumps({"key": key, "value": value}) if sh.args.json else f"{key} = {value}"
                )
            else:
                sh.print_value(obj, axis, update)
            sys.stdout.flush()
            seen += 1
            if sh.args.count and seen >= sh.args.count:
                break
    except KeyboardInterrupt:
        pass
    return 0


def _ads_updates(client: Any, obj: ObjectDef, axis: int) -> Iterator[Any]:
    """Values from an on-change ADS notification (the first one at once)."""
    import queue

    q: queue.SimpleQueue[Any] = queue.SimpleQueue()
    handle = client.subscribe(obj.name, axis, lambda value, _ft: q.put(value))
    try:
        while True:
            yield q.get()
    finally:
        client.unsubscribe(handle)


def _polled(client: Any, obj: ObjectDef, axis: int) -> Iterator[Any]:
    """Modbus has no notifications: poll, and yield the value whenever it changed."""
    last: Any = object()
    while True:
        value = client.read(obj.name, axis)
        if value != last:
            last = value
            yield value
        time.sleep(MODBUS_WATCH_PERIOD)


def _nc(sh: Shell) -> int:
    args = sh.args
    text = Path(args.file).read_text(encoding="utf-8") if args.file else "\n".join(args.lines)
    result = sh.client.nc(text)
    if args.json:
        print(json.dumps(result))
    else:
        print(f"NC started at cycle {result.get('cycle')} ({result.get('lines')} lines)")
    return 0


def _reset(sh: Shell) -> int:
    result = sh.client.reset()
    print(json.dumps(result) if sh.args.json else f"reset at cycle {result.get('cycle')}")
    return 0


def _status(sh: Shell) -> int:
    st = sh.client.status()
    if sh.args.json:
        print(json.dumps(st))
        return 0
    for line in status_lines(st):
        print(line)
    return 0


def status_lines(st: dict[str, Any]) -> list[str]:
    """The status as a few readable lines (the JSON has every field)."""
    head = f"cycle {st.get('cycle')}  {st.get('cycle_time_us')} µs"
    if "mode" in st:
        where = f", cycle in its own {st['cycle_in']}" if st.get("cycle_in") else ""
        head += f"  {st['mode']}{where}"
    lines = [head]
    if st.get("stalled"):
        lines.append(
            f"STALLED: no GEO cycle for {st.get('stalled_for_s')} s (reads answer 'not "
            "ready', writes are refused)"
        )
    if "engine" in st or "lateness_p50_us" in st:  # the server's own status (Zenoh)
        lines.append(engine_figures(st))
    else:
        lines.append(f"overruns {st.get('overruns')}")
    if "program_running" in st:
        prog = f"running, line {st['program_line']}" if st["program_running"] else "not running"
        lines.append(f"NC program {prog}")
    axes = st.get("axes")
    names = st.get("axis_names")
    if isinstance(names, dict) and names:
        lines.append("axes " + ", ".join(f"{a} {n}" for a, n in names.items()))
    elif isinstance(axes, dict):
        lines.append("axes " + ", ".join(f"{a} {n}" for a, n in axes.items()))
    elif axes:
        lines.append("axes " + ", ".join(str(a) for a in axes))
    faults = fault_lines(st.get("faults") or [])
    if faults:
        lines.append("FAULTS injected:\n" + faults)
    for rival in st.get("zenoh_rivals") or ():
        lines.append(f"WARNING: another server answers for this machine: {rival}")
    return lines


def _errors(sh: Shell) -> int:
    errors = sh.client.errors()
    if sh.args.json:
        print(json.dumps(errors))
        return 0
    if not errors:
        print("no warnings or errors")
    for e in errors:
        cycle = f"cycle {e['cycle']}  " if "cycle" in e else ""
        severity = f"{e['severity']}  " if "severity" in e else ""
        where = f"{e['file']}:{e['line']}: " if e.get("file") and e.get("line") else ""
        ident = f"[{e['error_id']}] " if e.get("error_id") else ""
        print(f"{cycle}{severity}{ident}{where}{e['message']}")
    return 0


def _fault(sh: Shell) -> int:
    args = sh.args
    if args.action == "inject" and not args.spec:
        print("error: fault inject needs a fault, e.g. ads:error=0x707,count=2", file=sys.stderr)
        return 2
    if args.action == "clear":
        which: int | str = "all"
        if args.spec and args.spec[0] != "all":
            if not _is_int(args.spec[0]):
                print(
                    f"error: fault clear takes an id or 'all', not {args.spec[0]!r}",
                    file=sys.stderr,
                )
                return 2
            which = int(args.spec[0], 0)
        result = sh.client.fault(clear=which)
    elif args.action == "inject":
        result = {"faults": []}
        for spec in args.spec:
            result = sh.client.fault(inject=spec)
    else:
        result = sh.client.fault()
    if args.json:
        print(json.dumps(result))
        return 0
    for f in result.get("cleared") or ():
        print(f"cleared fault {f['id']}: {f['fault']} ({f['hits']} hits)")
    print(fault_lines(result.get("faults") or []) or "no active faults")
    return 0


def fault_lines(faults: list[dict[str, Any]]) -> str:
    """Active faults, one line each: id, text, hits, what is left."""
    return "\n".join(
        f"fault {f['id']}: {f['fault']}  hits {f['hits']}"
        + (f", {f['left']} left" if "left" in f else "")
        for f in faults
    )


def _command(name: str) -> Callable[[Shell], int]:
    def run(sh: Shell) -> int:
        result = getattr(sh.client, name)()
        if sh.args.json:
            print(json.dumps(result))
            return 0
        files = result.get("files") or []
        done = {"reload": "reloaded", "save": "saved"}[name]
        if files:
            print(f"{done}: {', '.join(files)}")
        elif name == "save" and "files" in result:
            print("saved: nothing had changed")
        else:
            print(f"{done} (cycle {result.get('cycle')})")
        for w in result.get("warnings") or ():
            print(f"  {w}")
        return 0

    return run


# ---------------------------------------------------------------------- parser

_TARGET_HELP = (
    "object name (TEMPC::coefficient, also in the Zenoh spelling tempc::coefficient; "
    "several for read) or an ADS address GROUP OFFSET (0x120300 0x10043)"
)
#: Commands only the Zenoh interface offers.
ZENOH_ONLY = frozenset({"nc", "reset", "fault"})


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="geo-client", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--version", action="version", version=f"geo-client {__version__}")
    p.add_argument("--via", choices=TRANSPORTS, default="zenoh", help="transport (default zenoh)")
    p.add_argument("--machine", default="local", help="machine name (Zenoh key prefix)")
    p.add_argument(
        "--connect",
        metavar="ENDPOINT",
        help="server endpoint: zenoh tcp/127.0.0.1:7447 (default), modbus 127.0.0.1:5020, "
        "ads 127.0.0.1:48898; without it the environment variable GEO_CLIENT_ZENOH, "
        "GEO_CLIENT_MODBUS or GEO_CLIENT_ADS, else the default",
    )
    p.add_argument("--netid", default="127.0.0.1.1.1", help="AMS NetId of the server (ADS)")
    p.add_argument(
        "--fleet",
        metavar="FILE",
        help="a fleet file: address --machine by name over every transport (its AMS "
        "NetId for ADS, its port for Modbus; what the file leaves out counts from --netid "
        "and the --connect port, as the server's from --ads-netid and --modbus-port)",
    )
    p.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for a reply")
    p.add_argument(
        "--wait",
        type=float,
        default=0.0,
        metavar="S",
        help="wait up to S seconds for the server to answer (a server just started) "
        "before the command",
    )
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument(
        "--raw", action="store_true", help="internal units (increments, µm/s) instead of mm, µm"
    )
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, func, help_ in (
        ("read", _read, "read objects: NAME [NAME …] or GROUP OFFSET"),
        ("write", _write, "write an object: NAME VALUE or GROUP OFFSET VALUE"),
        ("watch", _watch, "print a value whenever it changes (Zenoh: also a key expression)"),
    ):
        s = sub.add_parser(name, help=help_, description=help_)
        s.add_argument(
            "--axis", default="1", help="logical axis number or name, e.g. 1 or X (default 1)"
        )
        s.add_argument("target", nargs="+", metavar="TARGET", help=_TARGET_HELP)
        if name == "watch":
            s.add_argument("--count", type=int, default=0, help="stop after N updates")
        s.set_defaults(func=func)
    s = sub.add_parser("nc", help="execute NC lines (Zenoh)")
    s.add_argument("lines", nargs="*", help="NC lines, e.g. 'G01 X10 F6000'")
    s.add_argument("-f", "--file", help="NC program file")
    s.set_defaults(func=_nc)
    sub.add_parser("status", help="cycle status").set_defaults(func=_status)
    sub.add_parser("errors", help="latest warnings and errors").set_defaults(func=_errors)
    sub.add_parser("reload", help="reload the list files").set_defaults(func=_command("reload"))
    sub.add_parser("save", help="save live TEMPC parameters").set_defaults(func=_command("save"))
    sub.add_parser("reset", help="CNC reset: stop the NC program and the axes (Zenoh)")
    sub.choices["reset"].set_defaults(func=_reset)
    s = sub.add_parser(
        "fault",
        help="inject, clear or list faults (Zenoh; docs/faults.md)",
        description="fault inject SPEC [SPEC …] | fault clear [ID|all] | fault list — e.g. "
        "`fault inject ads:error=0x707,count=2`, `fault inject sensor@X:stuck`",
    )
    s.add_argument("action", choices=("inject", "clear", "list"))
    s.add_argument("spec", nargs="*", help="faults to inject, or the id to clear")
    s.set_defaults(func=_fault)
    sub.add_parser("objects", help="print the object dictionary").set_defaults(func=None)
    return p


def _open_ready(args: argparse.Namespace, endpoint: str | None) -> GeoClient:
    """The client; with `--wait S`, once the server answers a read of its cycle count,
    tried every 0.2 s for up to S seconds (not listening yet, not answering yet), the
    last failure raised when S has passed."""
    deadline = time.monotonic() + max(0.0, args.wait)
    while True:
        client = None
        try:
            client = open_client(
                args.via, endpoint, machine=args.machine, timeout=args.timeout, netid=args.netid
            )
            if args.wait > 0:
                client.read("SIM::cycle_count")
            return client
        except (ServerUnreachable, TimeoutError, AdsError, OSError):
            if client is not None:
                client.close()
            if time.monotonic() >= deadline:
                raise
            time.sleep(0.2)


def _opened(args: argparse.Namespace, endpoint: str | None) -> GeoClient:
    """`_open_ready` on a thread of its own, waited for here in short steps: Ctrl-C
    interrupts the wait at once. (Called here, zenoh.open held the main thread inside
    Rust until its session was open or its 10 s open timeout had passed — against an
    endpoint that accepts and says nothing, Ctrl-C took effect 10 s late.) The process
    ends with `entry.exit_now`, so an opening left behind holds nothing up."""
    done = threading.Event()
    got: list[GeoClient] = []
    failed: list[BaseException] = []

    def opening() -> None:
        try:
            got.append(_open_ready(args, endpoint))
        except BaseException as exc:  # (raised again on the main thread)
            failed.append(exc)
        finally:
            done.set()

    threading.Thread(target=opening, name="geo-client-open", daemon=True).start()
    while not done.wait(0.1):  # (a step: a wait without one is not interrupted on Windows)
        pass
    if failed:
        raise failed[0]
    return got[0]


@closes_quietly_on_broken_pipe
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "objects":
        from geo_server.dictionary import dictionary_markdown

        sys.stdout.write(dictionary_markdown())
        return 0
    if args.command in ZENOH_ONLY and args.via != "zenoh":
        print(
            f"error: `{args.command}` is available over Zenoh only (--via zenoh)", file=sys.stderr
        )
        return 2
    endpoint = args.connect or os.environ.get(f"GEO_CLIENT_{args.via.upper()}")
    if args.fleet:  # the machine's NetId and Modbus port from the fleet file
        from geo_server.fleetfile import FleetError, member

        # what the file leaves out counts from the server's defaults, or from the
        # --netid / Modbus --connect port given here (the server's --ads-netid and
        # --modbus-port)
        base_port = 5020
        if args.via == "modbus" and endpoint and endpoint.rsplit(":", 1)[-1].isdigit():
            base_port = int(endpoint.rsplit(":", 1)[-1])
        try:
            found = member(Path(args.fleet), args.machine, args.netid, base_port)
        except FleetError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        args.netid = found.netid
        if args.via == "modbus":
            host = (endpoint or "127.0.0.1:5020").rsplit(":", 1)[0]
            endpoint = f"{host}:{found.modbus_port}"
    try:
        client = _opened(args, endpoint)
    except ServerUnreachable as exc:  # one line, the same on every transport
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:
        print(f"error: cannot reach the server over {args.via}: {exc}", file=sys.stderr)
        return 2
    try:
        return int(args.func(Shell(args, client)))
    except AdsError as exc:
        if args.via == "zenoh":
            from geo_server.client.zenoh_client import ServerConflictError

            if isinstance(exc, ServerConflictError):  # not an ADS answer: no code to show
                print(f"error: {exc.message}", file=sys.stderr)
                return 1
        print(f"error: {exc.message} (ADS 0x{exc.code:X})", file=sys.stderr)
        return 1
    except TimeoutError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    finally:
        client.close()


__all__ = ["build_parser", "main", "resolve", "status_lines"]


if __name__ == "__main__":
    raise SystemExit(main())
