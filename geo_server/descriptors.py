"""The process's file descriptors, shared by every interface (docs/security.md, *One
client cannot starve the others*).

Every socket of every interface — ADS, Modbus, HTTP, Zenoh — is a descriptor of this one
process. Without a plan, 1100 slow HTTP connections used up the 1024 of a default Linux
soft limit and every interface stopped accepting. So, at start:

1. `raise_soft_limit`: the soft `RLIMIT_NOFILE` is raised to the hard limit (nothing to do
   on Windows, which has no such limit for sockets).
2. `fit`: every interface's connection cap, plus what its listening socket may hold in
   its accept backlog (`geo_server.transports.tcp.BACKLOG` each; Zenoh: its sessions and
   the handshakes under way), plus the descriptors already open and `RESERVE` for files
   and the runtime, must fit under that limit. When they do not, the caps are shrunk in
   proportion (none below `MIN_CAP`); when even that does not fit, the server refuses
   to start and says how many descriptors it needs. A flood on one interface then meets
   that interface's cap, and the others keep descriptors for their new clients.
3. `AcceptLog`: should accepting still fail for want of descriptors (another process of
   the user, a flood faster than connections are closed), asyncio reports it once per
   accept attempt and retries — 414 000 tracebacks in 38 s were seen. The loop's
   exception handler says it once per `AcceptLog.every` seconds per message instead,
   with the number left unsaid.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import sys
import time
from collections.abc import Callable
from typing import Any

from geo_server.errors import GeoError

log = logging.getLogger(__name__)

#: Descriptors kept for everything that is not a client connection: list files and
#: recordings being read or written, the event loop's own, Zenoh's runtime, a margin.
RESERVE = 64
#: Smallest connection cap `fit` shrinks an interface to.
MIN_CAP = 4


class DescriptorError(GeoError):
    """The open-files limit is too low for the interfaces to start (the message says
    how many descriptors they need)."""


def raise_soft_limit() -> tuple[int, int] | None:
    """Raise the soft open-files limit to the hard one; (soft, hard) after, None where
    there is no such limit (Windows). An unlimited hard limit (macOS) is met with the
    largest value the system takes."""
    try:
        import resource
    except ImportError:  # Windows
        return None
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != hard:
        # macOS refuses an unlimited soft limit (OPEN_MAX, 10240, is the most it takes)
        for value in (hard, 10240) if hard == resource.RLIM_INFINITY else (hard,):
            try:
                resource.setrlimit(resource.RLIMIT_NOFILE, (value, hard))
                break
            except (ValueError, OSError):
                continue
    return resource.getrlimit(resource.RLIMIT_NOFILE)


def open_descriptors() -> int:
    """Descriptors this process has open now (0 where that cannot be counted)."""
    for folder in ("/proc/self/fd", "/dev/fd"):
        try:
            return max(0, len(os.listdir(folder)) - 1)  # minus the one listdir opened
        except OSError:
            continue
    return 0


def fit(
    caps: dict[str, int],
    limit: int,
    in_use: int,
    fixed: int,
    reserve: int = RESERVE,
    floors: dict[str, int] | None = None,
) -> dict[str, int]:
    """Connection caps (interface -> connections) that fit under `limit` descriptors
    with `in_use` open already, `fixed` held whatever the caps (the listeners' backlogs)
    and `reserve` kept: `caps` itself when it fits, else each shrunk in proportion
    (at least its floor: `MIN_CAP`, or `floors[name]` for a cap shared by several
    listeners). `DescriptorError` when not even that fits."""
    room = limit - in_use - fixed - reserve
    total = sum(caps.values())
    if total <= room:
        return dict(caps)
    floor = {k: min((floors or {}).get(k, MIN_CAP), c) for k, c in caps.items()}
    least = sum(floor.values())
    if least > room:
        need = in_use + fixed + reserve + least
        raise DescriptorError(
            f"the open-files limit ({limit}) is too low: the interfaces need at least "
            f"{need} descriptors ({fixed} for their listening queues, {reserve} kept for "
            f"files, {in_use} open already, {least} for {MIN_CAP} connections each); raise "
            f"it (ulimit -n {max(need, 1024)}) or start fewer interfaces"
        )
    scale = room / total
    out = {k: max(floor[k], math.floor(c * scale)) for k, c in caps.items()}
    while sum(out.values()) > room:  # the minimums took more than their share
        k = max((n for n in out if out[n] > floor[n]), key=lambda n: out[n] - floor[n])
        out[k] -= 1
    return out


def plan(
    wanted: dict[str, int], fixed: int, floors: dict[str, int] | None = None
) -> tuple[dict[str, int], str]:
    """At start: raise the soft limit (`raise_soft_limit`), then `fit` the connection
    caps `wanted` (interface -> connections) with `fixed` descriptors for the listening
    queues. The caps to use, and a line saying what was shrunk ("" when nothing was).
    `DescriptorError` when they cannot fit."""
    limits = raise_soft_limit()
    if limits is None:  # Windows: no per-process limit on sockets to plan for
        return dict(wanted), ""
    soft, hard = limits
    caps = fit(wanted, soft, open_descriptors(), fixed, floors=floors)
    if caps == wanted:
        return caps, ""
    shrunk = ", ".join(f"{k} {wanted[k]} -> {caps[k]}" for k in caps if caps[k] != wanted[k])
    return caps, (
        f"descriptors: the open-files limit is {soft} (hard {hard}); connection caps "
        f"shrunk to fit under it: {shrunk} (raise it with ulimit -n; docs/security.md)"
    )


class AcceptLog:
    """An event-loop exception handler that says each kind of "out of descriptors"
    failure at most once per `every` seconds (with how many went unsaid) and hands
    everything else to the loop's default handler."""

    #: messages asyncio reports for accept failures and for the retries it schedules
    MESSAGES = ("socket.accept() out of system resource",)

    def __init__(self, every: float = 10.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.every = every
        self._clock = clock
        self._last: dict[str, float] = {}
        self.suppressed: dict[str, int] = {}
        self.reported = 0

    def install(self, loop: asyncio.AbstractEventLoop) -> None:
        loop.set_exception_handler(self)

    def __call__(self, loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        key = self._key(context)
        if key is None:
            loop.default_exception_handler(context)
            return
        now = self._clock()
        last = self._last.get(key)
        if last is not None and now - last < self.every:
            self.suppressed[key] = self.suppressed.get(key, 0) + 1
            return
        self._last[key] = now
        unsaid = self.suppressed.pop(key, 0)
        self.reported += 1
        exc = context.get("exception")
        more = f" ({unsaid} more since the last report)" if unsaid else ""
        print(
            f"warning: {key}: {exc}{more}; new connections wait until descriptors are "
            f"free (said at most every {self.every:g} s; docs/security.md)",
            file=sys.stderr,
            flush=True,
        )

    def _key(self, context: dict[str, Any]) -> str | None:
        message = str(context.get("message", ""))
        if message in self.MESSAGES:
            return message
        exc = context.get("exception")
        # a retry of a listener closed meanwhile (asyncio's `_start_serving` on fd -1)
        handle = repr(context.get("handle", ""))
        if isinstance(exc, ValueError) and "_start_serving" in handle:
            return "accept retry on a closed listener"
        if isinstance(exc, OSError) and exc.errno in _OUT_OF_DESCRIPTORS:
            return message or "out of descriptors"
        return None


def _errnos() -> tuple[int, ...]:
    import errno

    return (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM)


_OUT_OF_DESCRIPTORS = _errnos()

__all__ = [
    "MIN_CAP",
    "RESERVE",
    "AcceptLog",
    "DescriptorError",
    "fit",
    "open_descriptors",
    "plan",
    "raise_soft_limit",
]
