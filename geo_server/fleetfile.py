"""Fleet files (SPEC §13): which machines one `geo-server run --fleet` serves, and where.

A fleet file (TOML), paths relative to the file:

    [[machine]]
    name = "mill-1"
    startup = "mill1/hochlauf.lis"   # default: the default machine's start-up list
    netid = "127.0.0.1.2.1"          # default: --ads-netid with its 5th byte + i
    modbus_port = 5021               # default: --modbus-port + i

The server (`geo_server.fleet`) and the clients (`geo-client --fleet FILE --machine NAME`,
which find a machine's NetId and Modbus port here) read the same file.
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from geo_server.errors import GeoError
from geo_server.paths import default_startup_list

#: The defaults of `geo-server run --ads-netid` and `--modbus-port`.
DEFAULT_NETID = "127.0.0.1.1.1"
DEFAULT_MODBUS_PORT = 5020
#: A machine name is one Zenoh key chunk, without wildcards or a leading `@`.
NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")
#: A name no machine may have: Zenoh serves the fleet's status at `cnc/fleet/status`
#: (`geo_server.transports.zenoh.plug.FLEET_STATUS_KEY`).
RESERVED_NAME = "fleet"


class FleetError(GeoError, ValueError):
    """A fleet file or fleet option that cannot be served (file and what is wrong)."""


@dataclass(frozen=True)
class Member:
    """One machine of a fleet: its name, lists and addresses."""

    name: str
    startup: Path
    netid: str
    modbus_port: int


#: the most machines of one fleet, `--fleet-size` or a fleet file (docs/limits.md;
#: bench/engine.py measures how many a 2-core machine serves)
MAX_FLEET_SIZE = 1000


def parse_netid(text: object) -> list[int]:
    """The six bytes of an AMS NetId written `a.b.c.d.e.f` (FleetError otherwise)."""
    parts = str(text).strip().split(".") if isinstance(text, str) else []
    if len(parts) != 6 or not all(p.isdigit() and int(p) <= 255 for p in parts):
        raise FleetError(f"{text!r} is not an AMS NetId (six numbers 0…255, a.b.c.d.e.f)")
    return [int(p) for p in parts]


def netid_at(base: str, i: int) -> str:
    """The i-th machine's AMS NetId: `base` with its fifth byte raised by i, carrying
    into the fourth (127.0.0.1.255.1 is followed by 127.0.0.2.0.1; canonical spelling, as
    routing compares it)."""
    parts = parse_netid(base)
    number = parts[3] * 256 + parts[4] + i
    if number > 0xFFFF:
        raise FleetError(f"cannot number {i + 1} machines from AMS NetId {base}")
    parts[3], parts[4] = divmod(number, 256)
    return ".".join(str(x) for x in parts)


def copies(n: int, name: str, startup: Path, base_netid: str, base_port: int) -> list[Member]:
    """`--fleet-size n`: n machines from one start-up list, named `<name>-1` … `<name>-n`."""
    if not 1 <= n <= MAX_FLEET_SIZE:
        raise FleetError(f"--fleet-size must be between 1 and {MAX_FLEET_SIZE}, not {n}")
    if not NAME.fullmatch(name) or name == RESERVED_NAME:
        raise FleetError(
            f"--machine {name!r} is not a machine name (letters, digits, _.-): "
            "the copies are named <machine>-1 …"
        )
    return [
        Member(f"{name}-{i + 1}", startup, netid_at(base_netid, i), base_port + i) for i in range(n)
    ]


def load_fleet(path: Path, base_netid: str, base_port: int) -> list[Member]:
    """The machines of a fleet file, checked: names, NetIds and ports distinct."""
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise FleetError(f"{path}: {exc}") from None
    entries = data.get("machine")
    if not isinstance(entries, list) or not entries:
        raise FleetError(f"{path}: no [[machine]] tables")
    if len(entries) > MAX_FLEET_SIZE:
        raise FleetError(f"{path}: {len(entries)} machines, at most {MAX_FLEET_SIZE}")
    members: list[Member] = []
    for i, entry in enumerate(entries):
        where = f"{path}: machine {i + 1}"
        unknown = set(entry) - {"name", "startup", "netid", "modbus_port"}
        if unknown:
            raise FleetError(f"{where}: unknown keys {sorted(unknown)}")
        name = entry.get("name")
        if not isinstance(name, str) or not NAME.fullmatch(name) or name == RESERVED_NAME:
            raise FleetError(f"{where}: name {name!r} is not a machine name (letters, digits, _.-)")
        raw = entry.get("startup")
        if raw is not None and not isinstance(raw, str):
            raise FleetError(f"{where}: startup {raw!r} is not a path")
        startup = Path(raw) if raw is not None else default_startup_list()
        if not startup.is_absolute():
            startup = path.parent / startup
        try:
            netid = netid_at(
                str(entry["netid"]) if "netid" in entry else base_netid,
                0 if "netid" in entry else i,
            )
        except FleetError as exc:
            raise FleetError(f"{where}: netid {exc}") from None
        port = entry.get("modbus_port", base_port + i)
        if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
            raise FleetError(f"{where}: modbus_port {port!r} is not a TCP port")
        members.append(Member(name, startup, netid, port))
    for attr in ("name", "netid", "modbus_port"):
        seen: dict[Any, str] = {}
        for m in members:
            key = getattr(m, attr)
            if key in seen and not (attr == "modbus_port" and key == 0):
                raise FleetError(f"{path}: {m.name} and {seen[key]} have the same {attr} {key}")
            seen[key] = m.name
    return members


def member(
    path: Path, name: str, base_netid: str = DEFAULT_NETID, base_port: int = DEFAULT_MODBUS_PORT
) -> Member:
    """The machine `name` of a fleet file (clients: its NetId and Modbus port). Where the
    file leaves them out they count from `base_netid` / `base_port`, which must be the
    server's `--ads-netid` / `--modbus-port`."""
    members = load_fleet(path, base_netid, base_port)
    for m in members:
        if m.name == name:
            return m
    names = ", ".join(m.name for m in members[:20]) + (", …" if len(members) > 20 else "")
    raise FleetError(
        f"{path}: no machine named {name!r} (machines: {names}; choose with --machine)"
    )
