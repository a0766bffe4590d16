"""Failed OPC UA logins per client address (docs/security.md, *OPC UA*): what
`guard.py` asks before it lets a session be activated. No asyncua here, so the interface
can hold one before asyncua is imported."""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from collections.abc import Callable

log = logging.getLogger("geo_server.opcua")

#: the wait after a failed login from one address, doubled per further failure
LOGIN_BACKOFF_FIRST_S = 0.05
LOGIN_BACKOFF_MAX_S = 2.0
#: addresses whose failed logins are remembered at once (the oldest forgotten first)
LOGIN_ADDRESSES = 1024
#: a failed login is logged at most this often per address, with the count since
LOGIN_LOG_EVERY_S = 10.0


class LoginThrottle:
    """Failed logins per client address: after the n-th failure in a row, the next
    attempt from that address is refused unchecked until `LOGIN_BACKOFF_FIRST_S · 2^(n-1)`
    (at most `LOGIN_BACKOFF_MAX_S`) has passed, so guessing is slow whichever session or
    connection it comes from; logged at most every `LOGIN_LOG_EVERY_S` per address. Owned
    by the event loop (every login is checked there)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        #: address -> [failures in a row, not before, last logged, failures unlogged]
        self._seen: OrderedDict[str, list[float]] = OrderedDict()

    def allowed(self, address: str) -> bool:
        entry = self._seen.get(address)
        return entry is None or self._clock() >= entry[1]

    def failed(self, address: str) -> None:
        now = self._clock()
        entry = self._seen.pop(address, None) or [0.0, 0.0, -LOGIN_LOG_EVERY_S, 0.0]
        entry[0] += 1
        entry[1] = now + min(LOGIN_BACKOFF_FIRST_S * 2 ** (entry[0] - 1), LOGIN_BACKOFF_MAX_S)
        entry[3] += 1
        if now - entry[2] >= LOGIN_LOG_EVERY_S:
            log.warning(
                "opcua: %d failed login(s) from %s (%d in a row); the next waits %.2f s",
                entry[3],
                address,
                entry[0],
                entry[1] - now,
            )
            entry[2], entry[3] = now, 0.0
        self._seen[address] = entry
        while len(self._seen) > LOGIN_ADDRESSES:
            self._seen.popitem(last=False)

    def succeeded(self, address: str) -> None:
        self._seen.pop(address, None)


__all__ = ["LoginThrottle"]
