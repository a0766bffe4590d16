"""Starting a server's interfaces: why one did not start, and what to do about it."""

from __future__ import annotations

import re

from geo_server.errors import GeoError


class InterfaceStartError(GeoError):
    """An interface could not start (port in use, bad address or Zenoh config)."""


#: What to change when an interface's port is taken (`start_failure`).
_PORT_OPTION = {
    "zenoh": "--zenoh-listen tcp/127.0.0.1:PORT",
    "modbus": "--modbus-port PORT",
    "ads": "--ads-port PORT",
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
