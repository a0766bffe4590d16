"""`geo-client`: read, write and watch a running geo-server's CNC objects.

Address an object by name (`--axis 1 TEMPC::coefficient`) or by ADS address
(`0x120300 0x10043`). Values print decoded, with their unit; `--json` prints JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from geo_server.client import TRANSPORTS, open_client, resolve
from geo_server.console import closes_quietly_on_broken_pipe
from geo_server.dictionary import STRING_LENGTH, ObjectDef, load_dictionary
from geo_server.errors import AdsError


def _target(args: argparse.Namespace) -> tuple[ObjectDef, int]:
    """(object, axis) from `NAME` + --axis or from `GROUP OFFSET`."""
    words = args.target
    if _by_address(args):
        ig, io = int(words[0], 0), int(words[1], 0)
        return resolve(ig, io), io >> 16
    obj = load_dictionary().by_name(words[0])
    return obj, (0 if obj.scope == "machine" else args.axis)


def _by_address(args: argparse.Namespace) -> bool:
    return len(args.target) >= 2 and all(_is_int(w) for w in args.target[:2])


def _address(args: argparse.Namespace) -> tuple[int, int, str | None]:
    """(index group, index offset, attribute kind or None) of `GROUP OFFSET`."""
    ig, io = int(args.target[0], 0), int(args.target[1], 0)
    _obj, _axis, attr = load_dictionary().resolve(ig, io, [io >> 16])
    return ig, io, attr


def _attribute_length(kind: str) -> int:
    return {"length": 4, "writable": 1}.get(kind, STRING_LENGTH)


def _is_int(text: str) -> bool:
    try:
        int(text, 0)
    except ValueError:
        return False
    return True


def _show(args: argparse.Namespace, obj: ObjectDef, axis: int, value: Any) -> None:
    if args.json:
        print(json.dumps({"name": obj.name, "axis": axis, "value": value, "unit": obj.unit}))
    else:
        where = f"axis {axis} " if obj.scope == "axis" else ""
        print(f"{where}{obj.name} = {value} {obj.unit}")


def _read(args: argparse.Namespace, client: Any) -> int:
    obj, axis = _target(args)
    if not _by_address(args):
        _show(args, obj, axis, client.read(obj.name, axis))
        return 0
    # By address the request goes out as that address, so attribute groups
    # (0x120400 … 0x120800: name, type, length, unit, writable) read what they are.
    ig, io, attr = _address(args)
    if attr is None:
        _show(args, obj, axis, obj.decode(client.read_raw(ig, io, obj.length)))
        return 0
    value = obj.decode_attribute(attr, client.read_raw(ig, io, _attribute_length(attr)))
    if args.json:
        print(json.dumps({"name": obj.name, "axis": axis, "attribute": attr, "value": value}))
    else:
        where = f"axis {axis} " if obj.scope == "axis" else ""
        print(f"{where}{obj.name} {attr} = {value}")
    return 0


def _write(args: argparse.Namespace, client: Any) -> int:
    obj, axis = _target(args)
    by_address = _by_address(args)
    if len(args.target) < (3 if by_address else 2):
        print("error: write needs a value", file=sys.stderr)
        return 2
    raw = args.target[-1]
    try:
        value: Any = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    if not by_address:
        _show(args, obj, axis, client.write(obj.name, axis, value))
        return 0
    # The write goes to the address given, so the server judges it (an attribute
    # group is read-only: ADS 0x704), not a by-name write to the object behind it.
    ig, io, _attr = _address(args)
    client.write_raw(ig, io, obj.encode(value))
    _show(args, obj, axis, value)
    return 0


def _watch(args: argparse.Namespace, client: Any) -> int:
    if args.target and "/" in args.target[0]:
        key = args.target[0]
    else:
        obj, axis = _target(args)
        key = client.keyspace().named_key(obj, axis)
    seen = 0
    try:
        for k, v in client.watch(key):
            print(json.dumps({"key": k, "value": v}) if args.json else f"{k} = {v}", flush=True)
            seen += 1
            if args.count and seen >= args.count:
                break
    except KeyboardInterrupt:
        pass
    return 0


def _nc(args: argparse.Namespace, client: Any) -> int:
    text = Path(args.file).read_text(encoding="utf-8") if args.file else "\n".join(args.lines)
    print(json.dumps(client.nc(text)))
    return 0


def _status(args: argparse.Namespace, client: Any) -> int:
    print(json.dumps(client.status(), indent=None if args.json else 2))
    return 0


def _command(name: str):
    def run(args: argparse.Namespace, client: Any) -> int:
        result = getattr(client, name)()
        print(
            json.dumps(
                result if result is not None else {"ok": True}, indent=None if args.json else 2
            )
        )
        return 0

    return run


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="geo-client", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--via", choices=TRANSPORTS, default="zenoh", help="transport")
    p.add_argument("--machine", default="local", help="machine name (Zenoh key prefix)")
    p.add_argument(
        "--connect",
        metavar="ENDPOINT",
        help="server endpoint: zenoh tcp/127.0.0.1:7447 (default), modbus 127.0.0.1:5020, "
        "ads 127.0.0.1:48898",
    )
    p.add_argument("--netid", default="127.0.0.1.1.1", help="AMS NetId of the server (ADS)")
    p.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for a reply")
    p.add_argument("--json", action="store_true", help="print JSON")
    sub = p.add_subparsers(dest="command", required=True)
    for name, func, help_ in (
        ("read", _read, "read an object: NAME or GROUP OFFSET"),
        ("write", _write, "write an object: NAME VALUE or GROUP OFFSET VALUE"),
        ("watch", _watch, "print changes of an object or a key expression"),
    ):
        s = sub.add_parser(name, help=help_)
        s.add_argument("--axis", type=int, default=1, help="logical axis number (default 1)")
        s.add_argument("target", nargs="+")
        if name == "watch":
            s.add_argument("--count", type=int, default=0, help="stop after N updates")
        s.set_defaults(func=func)
    s = sub.add_parser("nc", help="execute NC lines")
    s.add_argument("lines", nargs="*")
    s.add_argument("-f", "--file", help="NC program file")
    s.set_defaults(func=_nc)
    sub.add_parser("status", help="cycle status").set_defaults(func=_status)
    sub.add_parser("errors", help="latest warnings and errors").set_defaults(
        func=_command("errors")
    )
    sub.add_parser("reload", help="reload the list files").set_defaults(func=_command("reload"))
    sub.add_parser("save", help="save live TEMPC parameters").set_defaults(func=_command("save"))
    sub.add_parser("reset", help="CNC reset: stop the NC program and the axes").set_defaults(
        func=_command("reset")
    )
    sub.add_parser("objects", help="print the object dictionary").set_defaults(func=None)
    return p


@closes_quietly_on_broken_pipe
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "objects":
        from geo_server.dictionary import dictionary_markdown

        sys.stdout.write(dictionary_markdown())
        return 0
    try:
        client = open_client(
            args.via, args.connect, machine=args.machine, timeout=args.timeout, netid=args.netid
        )
    except Exception as exc:
        print(f"error: cannot open {args.via} client: {exc}", file=sys.stderr)
        return 2
    needs = {
        "watch": "watch",
        "nc": "nc",
        "status": "status",
        "errors": "errors",
        "reload": "reload",
        "save": "save",
        "reset": "reset",
    }.get(args.command)
    if needs and not hasattr(client, needs):
        client.close()
        print(
            f"error: `{args.command}` is not available over {args.via}; use --via zenoh",
            file=sys.stderr,
        )
        return 2
    try:
        return args.func(args, client)
    except AdsError as exc:
        print(f"error: ADS 0x{exc.code:X}: {exc.message}", file=sys.stderr)
        return 1
    except TimeoutError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    finally:
        client.close()


if __name__ == "__main__":
    raise SystemExit(main())
