"""Starting a server's interfaces: why one did not start, and what to do about it."""

from __future__ import annotations

import asyncio
import re
import sys
from collections.abc import Callable, Coroutine
from typing import Any, Protocol

from geo_server.errors import GeoError
from geo_server.faults import FaultError


class InterfaceStartError(GeoError):
    """An interface could not start (port in use, bad address or Zenoh config)."""


#: What to change when an interface's port is taken (`start_failure`).
_PORT_OPTION = {
    "zenoh": "--zenoh-listen tcp/127.0.0.1:PORT",
    "modbus": "--modbus-port PORT",
    "ads": "--ads-port PORT",
    "http": "--http HOST:PORT",
    "opcua": "--opcua-endpoint opc.tcp://127.0.0.1:PORT (or --no-opcua)",
}


def start_failure(name: str, exc: BaseException) -> str:
    """One line saying why an interface did not start and what to do about it.

    Zenoh's errors carry the Rust source location of every layer (`… at
    /root/.cargo/…/tcp.rs:61.]`); that is left out, the reason stays."""
    text = re.sub(r"\s+at /\S+\.rs:\d+\.?\]?", "", str(exc)).strip().rstrip(".")
    if "in use" in text.lower() or getattr(exc, "errno", None) in (48, 98, 10048):
        where = text.split("bound to ", 1)[1].split(":", 2) if "bound to " in text else []
        endpoint = ":".join(where[:2]) if where else "its address"
        return (
            f"{name} interface did not start: {endpoint} is in use (another geo-server?); "
            f"choose another port with {_PORT_OPTION[name]} or stop the other server"
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


class _Injecting(Protocol):
    def inject(self, fault: str) -> dict[str, Any]: ...


class _Faulted(Protocol):
    """What `inject_faults` uses of the object service (this layer is below it)."""

    @property
    def faults(self) -> _Injecting: ...


def inject_faults(specs: list[str] | None, service: _Faulted, label: str = "") -> bool:
    """`run --fault`: inject each fault before the first cycle (docs/faults.md);
    False (after saying why) when one cannot be."""
    for spec in specs or ():
        try:
            fault = service.faults.inject(spec)
        except FaultError as exc:
            print(f"error: {label}{exc}", file=sys.stderr)
            return False
        print(f"{label}fault {fault['id']} injected: {fault['fault']}", file=sys.stderr)
    return True
