"""Rival detection without sockets (`transports/zenoh/rivals.py`): what a probe's answer
and Zenoh's hints make of the status list and the errors list."""

from __future__ import annotations

from typing import Any

from geo_server.transports.zenoh.rivals import Rivals


class Seen:
    def __init__(self) -> None:
        self.reports: list[tuple[str, str]] = []
        self.lists: list[list[dict[str, Any]]] = []

    def rivals(self) -> Rivals:
        r = Rivals("m1", "cnc/m1", lambda t, s: self.reports.append((s, t)), self.lists.append)
        r.own = "aa"
        return r


def test_a_session_answering_for_the_machine_is_reported_once_and_its_going_too() -> None:
    seen = Seen()
    r = seen.rivals()
    r.probe_done(1, frozenset({"aa", "bb"}))  # (our own answer is no rival)
    r.probe_done(2, frozenset({"aa", "bb"}))
    assert seen.lists[-1] == [{"zenoh_id": "bb", "evidence": "answered cnc/m1/status"}]
    ((severity, text),) = seen.reports
    assert severity == "error"
    assert text.startswith("another Zenoh session bb answered cnc/m1/status: it claims ")
    assert "machine 'm1'" in text and "this server's (aa)" in text
    r.probe_done(3, frozenset({"aa"}))
    assert seen.lists[-1] == []
    assert seen.reports[-1] == (
        "warning",
        "Zenoh session bb no longer claims machine 'm1' (it answered cnc/m1/status earlier)",
    )


def test_an_earlier_probes_answer_after_a_later_ones_counts_for_nothing() -> None:
    seen = Seen()
    r = seen.rivals()
    r.probe_done(5, frozenset({"aa"}))
    r.probe_done(4, frozenset({"cc"}))  # (late: the world has moved on)
    assert seen.reports == [] and seen.lists == []


def test_a_hint_without_an_id_gives_way_to_the_session_found() -> None:
    """A remote queryable on cnc/m1/** that answers no probe is a rival of unknown id;
    once a probe names the session, that entry goes without a "no longer" warning."""
    seen = Seen()
    r = seen.rivals()
    r.queryable(True)
    r.probe_done(1, frozenset())
    assert seen.lists[-1] == [
        {
            "zenoh_id": None,
            "evidence": "declared a queryable on cnc/m1/** (and did not answer cnc/m1/status)",
        }
    ]
    r.probe_done(2, frozenset({"dd"}))
    assert [z["zenoh_id"] for z in seen.lists[-1]] == ["dd"]
    assert [s for s, _ in seen.reports] == ["error", "error"]  # (no warning for the hint)
    r.queryable(False)
    r.token_gone()  # (nothing held: nothing said)
    assert [s for s, _ in seen.reports] == ["error", "error"]


def test_a_token_held_before_ours_is_a_rival_until_it_goes() -> None:
    seen = Seen()
    r = seen.rivals()
    r.token_held("cnc/m1/alive")
    assert seen.lists[-1][0]["evidence"] == "held the liveliness token cnc/m1/alive first"
    r.token_gone()
    assert seen.lists[-1] == []
    assert seen.reports[-1][0] == "warning"
