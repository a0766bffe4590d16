"""Free TCP ports for servers started on 127.0.0.1 by tests and benchmarks.

A port `bind(0)` returns is an ephemeral one: until the server that was given it binds
it, any outgoing connection of any process (a client of an earlier test, a Zenoh
session) may take it as its own local port, and the server then fails with "address in
use" (seen in CI, twice). So a port is taken below the system's ephemeral range where
there is room, and never handed out twice by one process.
"""

from __future__ import annotations

import os
import random
import socket
import threading
from pathlib import Path

#: Ports `free_port` handed out in this process (never twice), under `_lock`: the one
#: piece of state here, a memo any thread may add to.
_handed: set[int] = set()
_lock = threading.Lock()
#: The lowest port handed out (below the ephemeral range, where there is room).
BELOW_EPHEMERAL_FROM = 20_000


def ephemeral_range() -> tuple[int, int]:
    """The ports the system takes for outgoing connections and bind(0) (Linux: from
    /proc; elsewhere the IANA range)."""
    try:
        lo, hi = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(lo), int(hi)
    except (OSError, ValueError):
        return 49152, 65535


def _span() -> tuple[int, int]:
    """Where to look: `GEO_SERVER_PORT_SPAN` (`first-end`), a share of the ports that no
    other process draws from (each test worker's: tests/conftest.py), else every port
    from `BELOW_EPHEMERAL_FROM` up to the ephemeral range."""
    text = os.environ.get("GEO_SERVER_PORT_SPAN", "")
    first, _, end = text.partition("-")
    if first.isdigit() and end.isdigit() and 1024 <= int(first) < int(end) <= 65_536:
        return int(first), int(end)
    return BELOW_EPHEMERAL_FROM, ephemeral_range()[0]


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port on `host` that was free a moment ago, for a server about to start
    (often in another process), never one this process handed out before."""
    first, end = _span()
    rng = random.Random()
    with _lock:
        if end - first > 1_000:
            for _ in range(200):
                port = rng.randrange(first, end)
                if port not in _handed and _bindable(host, port):
                    _handed.add(port)
                    return port
        while True:  # (no room below the ephemeral range)
            with socket.socket() as s:
                s.bind((host, 0))
                port = int(s.getsockname()[1])
            if port not in _handed:
                _handed.add(port)
                return port


def free_range(n: int, host: str = "127.0.0.1") -> int:
    """The first of `n` consecutive ports that were free a moment ago (a fleet's
    Modbus ports, one per machine), below the ephemeral range where there is room;
    none of them handed out before, and all of them handed out now."""
    lo, _hi = ephemeral_range()
    top = lo if lo > 10_000 + 2 * n else 65_536
    rng = random.Random()
    with _lock:
        for _ in range(200):
            base = rng.randrange(10_000, top - n)
            span = range(base, base + n)
            if all(p not in _handed and _bindable(host, p) for p in span):
                _handed.update(span)
                return base
    raise OSError(f"no {n} consecutive free ports on {host}")


def _bindable(host: str, port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True
