"""geo-server's interfaces: the registry of them, and why one did not start.

`REGISTRY` is the one table of interfaces (docs/design.md §1.3), in the manner of
python-can's backend table: each line names an interface, the module holding its plug
(a `geo_server.transports.interface.Interface`, imported only when it is wanted) and the
transport faults it carries out (docs/faults.md). Adding an interface is its module and
one line here."""

from __future__ import annotations

import asyncio
import re
import sys
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from typing import Any

from geo_server.errors import GeoError

#: What a transport fault can do to a request it hits (docs/faults.md).
FAULT_KINDS = ("delay", "drop", "error", "disconnect")


@dataclass(frozen=True)
class Registered:
    """One line of the registry."""

    #: the module whose `INTERFACE` is the interface's plug
    plug: str
    #: the transport faults it carries out (`FAULT_KINDS`; none: no fault targets it)
    faults: tuple[str, ...] = ()
    #: (what it calls them, codes) of its own an error fault aimed at it alone may
    #: answer, below 0x100; every other code is an ADS return code
    codes: tuple[str, tuple[int, ...]] | None = None


#: Every interface, in the order they start (and the reverse of the order they close).
REGISTRY: dict[str, Registered] = {
    # a query is answered on the session: no connection of its own to drop
    "zenoh": Registered("geo_server.transports.zenoh.plug", ("delay", "drop", "error")),
    "modbus": Registered(
        "geo_server.transports.modbus.plug",
        FAULT_KINDS,
        ("Modbus exception", (1, 2, 3, 4, 6, 0x0A, 0x0B)),  # (6 busy, 0x0A/0x0B gateway)
    ),
    "ads": Registered("geo_server.transports.ads.plug", FAULT_KINDS),
    "http": Registered("geo_server.web.plug"),
    "opcua": Registered("geo_server.transports.opcua.plug"),
}


class InterfaceStartError(GeoError):
    """An interface could not start (port in use, bad address or Zenoh config)."""


def start_failure(name: str, exc: BaseException, port_option: str) -> str:
    """One line saying why interface `name` did not start and what to do about it (when
    its port is taken: change `port_option`).

    Zenoh's errors carry the Rust source location of every layer (`… at
    /root/.cargo/…/tcp.rs:61.]`); that is left out, the reason stays."""
    text = re.sub(r"\s+at /\S+\.rs:\d+\.?\]?", "", str(exc)).strip().rstrip(".")
    if "in use" in text.lower() or getattr(exc, "errno", None) in (48, 98, 10048):
        where = text.split("bound to ", 1)[1].split(":", 2) if "bound to " in text else []
        endpoint = ":".join(where[:2]) if where else "its address"
        return (
            f"{name} interface did not start: {endpoint} is in use (another geo-server?); "
            f"choose another port with {port_option} or stop the other server"
        )
    return f"{name} interface did not start: {text}"


class CycleStoppedError(GeoError):
    """The GEO cycle thread died (a defect; its traceback is on stderr)."""


def serve(main: Coroutine[Any, Any, None], stop: Callable[[], object]) -> int:
    """Run a server's interfaces until Ctrl-C / SIGTERM, then `stop` its cycles: the
    exit code of `geo-server run` (0; 2 an interface did not start; 1 a cycle died)."""
    try:
        asyncio.run(main)
    except KeyboardInterrupt:  # where signal handlers cannot be installed (Windows)
        pass
    except InterfaceStartError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except CycleStoppedError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    finally:
        stop()
    return 0
