"""Which other Zenoh sessions claim this machine (docs/design.md §7, Rivals), without I/O.

The Zenoh interface feeds it what Zenoh tells: our liveliness token held by someone else
at start, another session's token gone, a remote queryable matching our keys or no
longer, and each probe's answer (the ids of the sessions that answered
`cnc/<m>/status`). It keeps the list the status JSON shows (`zenoh_rivals`) and says,
once per rival, what goes in the machine's errors list: an error when one appears, a
warning when it goes. Tested without sockets (tests/test_zenoh_rivals.py).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

#: a report in the machine's errors list: (text, severity)
Report = Callable[[str, str], object]
#: the status JSON's `zenoh_rivals`: one entry per rival, a new list each time
Publish = Callable[[list[dict[str, Any]]], None]


class Rivals:
    """The rivals of one machine's Zenoh interface; all of it on the event loop."""

    def __init__(self, machine: str, prefix: str, report: Report, publish: Publish) -> None:
        self.machine = machine
        self.status_key = f"{prefix}/status"
        self.queryables = f"{prefix}/**"
        #: our own session's id (set once the session is open)
        self.own = ""
        self._report = report
        self._publish = publish
        #: key (a session id, or "token" / "queryable" for hints without one) ->
        #: (the session's id if known, what it did)
        self._found: dict[str, tuple[str | None, str]] = {}
        self._applied = 0  # the latest probe whose answer counts
        self.matching = False  # a remote queryable covers all of cnc/<m>/**

    def publish(self) -> None:
        self._publish([{"zenoh_id": zid, "evidence": ev} for zid, ev in self._found.values()])

    def token_held(self, alive_key: str) -> None:
        """At start: another session held our liveliness token first."""
        self._add("token", None, f"held the liveliness token {alive_key} first")

    def token_gone(self) -> None:
        """Our own token lives as long as the interface: a DELETE while it runs is
        another session's token going away."""
        self._drop("token")

    def queryable(self, matching: bool) -> None:
        """Zenoh says whether a remote queryable matches our keys."""
        self.matching = matching
        if not matching:
            self._drop("queryable")

    def probe_done(self, number: int, found: frozenset[str]) -> None:
        """Probe `number` ended: the sessions in `found` answered. A later probe's
        answer, once applied, makes an earlier one's void."""
        if number < self._applied:
            return
        self._applied = number
        others = {zid for zid in found if zid != self.own}
        for zid in sorted(others):
            self._add(zid, zid, f"answered {self.status_key}")
        for key, (rival, _) in list(self._found.items()):
            if rival is not None and rival not in others:
                self._drop(key)
        if others:
            # the id-less hints (a token, a queryable) most likely came from the sessions
            # now known by id: keep the identified entries only
            self._drop("token", explained=True)
            self._drop("queryable", explained=True)
        elif self.matching:
            self._add(
                "queryable",
                None,
                f"declared a queryable on {self.queryables} (and did not answer {self.status_key})",
            )

    def _add(self, key: str, zid: str | None, evidence: str) -> None:
        """Record a rival; the first time, report it in the errors list."""
        if key in self._found:
            return
        self._found[key] = (zid, evidence)
        self.publish()
        who = f"Zenoh session {zid}" if zid else "Zenoh session (id unknown)"
        self._report(
            f"another {who} {evidence}: it claims machine {self.machine!r}, so clients "
            f"may get its answers instead of this server's ({self.own}). Stop it or give "
            "each server its own machine name (--machine); on a shared network, admit only "
            "known sessions (Zenoh access control, TLS, user/password authentication)",
            "error",
        )

    def _drop(self, key: str, *, explained: bool = False) -> None:
        """Forget a rival: reported as gone, unless `explained` by an entry with an id."""
        entry = self._found.pop(key, None)
        if entry is None:
            return
        self.publish()
        if explained:
            return
        who = f"Zenoh session {entry[0]}" if entry[0] else "the other Zenoh session"
        self._report(
            f"{who} no longer claims machine {self.machine!r} (it {entry[1]} earlier)",
            "warning",
        )
