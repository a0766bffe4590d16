"""Zenoh review fixes: commands off the loop, closing-loop hand-off, wildcards that match
nothing, publications on precomputed key expressions.

Real Zenoh sessions on loopback like tests/test_zenoh.py: peer mode, multicast scouting
off, explicit endpoints, a timeout on every get, sessions closed after use.
"""

from __future__ import annotations

import asyncio
import gc
import json
import queue
import struct
import threading
import time
import warnings
from pathlib import Path

import pytest
import zenoh
from conftest import free_port, run_in, wait_until_routed

import geo_server.commands.reload as reload_module
import geo_server.commands.save as save_module
import geo_server.service as service_module
from geo_server import access
from geo_server.commands.lists import CommandService
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.service import ObjectService, is_command
from geo_server.transports.zenoh.options import ZenohOptions
from geo_server.transports.zenoh.server import ZenohInterface

TIMEOUT = 5.0
JSON = zenoh.Encoding.APPLICATION_JSON
OCTET = zenoh.Encoding.APPLICATION_OCTET_STREAM
LOOP_THREAD = "test-loop"  # name of the conftest `loop_thread` thread


def session_config(connect: list[str]) -> zenoh.Config:
    c = zenoh.Config()
    c.insert_json5("mode", json.dumps("peer"))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", "[]")
    c.insert_json5("connect/endpoints", json.dumps(connect))
    return c


def get(session, key: str, payload=None, encoding=None, timeout: float = TIMEOUT):
    kwargs = {"timeout": timeout}
    if payload is not None:
        kwargs["payload"] = payload
        if encoding is not None:
            kwargs["encoding"] = encoding
    oks, errs = [], []
    for r in session.get(key, **kwargs):
        if r.ok is not None:
            oks.append((str(r.ok.key_expr), r.ok.payload.to_bytes()))
        else:
            body = r.err.payload.to_bytes()
            try:
                errs.append(json.loads(body))
            except ValueError:  # Zenoh's own errors (a get timeout) are plain text
                errs.append({"zenoh": body.decode(errors="replace")})
    return oks, errs


def get_err(session, key, payload=None, encoding=None) -> dict:
    oks, errs = get(session, key, payload, encoding)
    assert not oks, oks
    assert len(errs) == 1, errs
    return errs[0]


class Served:
    """A stepped service with its Zenoh interface and a plain client session."""

    def __init__(self, loop, service: ObjectService) -> None:
        self.loop = loop
        self.service = service
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        opts = ZenohOptions(
            machine="t", listen=[self.endpoint], publish_period=0.01, status_period=0.05
        )
        self.iface = ZenohInterface(service, opts)
        run_in(loop, self.iface.start())
        self.session = zenoh.open(session_config([self.endpoint]))

    def close(self) -> None:
        self.session.close()
        run_in(self.loop, self.iface.close())


@pytest.fixture
def served(loop_thread, service):
    s = Served(loop_thread, service)
    yield s
    s.close()


@pytest.fixture
def served_lists(loop_thread, lists_copy: Path):
    """Like `served`, on a private copy of the lists (reload/save touch the files)."""
    s = Served(loop_thread, ObjectService(Machine(load_machine(lists_copy), homed=True)))
    yield s
    s.close()


# ---------------------------------------------------------------------------- 1. commands


COMMAND_WRITES = [
    # (command, key, payload, encoding); SIM::reload = 0x12F300 ID 0x4, SIM::save = ID 0x5,
    # machine-wide (axis 0), UNS16
    ("reload", "cnc/t/sim/machine/reload", b"1", JSON),
    ("reload", "cnc/t/ads/551/0x12f300/0x4", struct.pack("<H", 1), OCTET),
    ("save", "cnc/t/sim/machine/save", b"1", JSON),
    ("save", "cnc/t/ads/551/0x12f300/0x5", struct.pack("<H", 1), OCTET),
]


@pytest.mark.parametrize("command,key,payload,encoding", COMMAND_WRITES)
def test_command_write_runs_off_the_loop(
    served_lists, monkeypatch, command, key, payload, encoding
):
    """While reload/save is busy with the list files, the loop still answers queries."""
    srv = served_lists
    svc = srv.service
    if command == "save":  # save writes only changed parameters: change one
        access.write_name(svc, "TEMPC::coefficient", 1, 1234.5)
        access.step(svc, 1)
    # the file-touching function the command calls: blocks until the test releases it
    target = "load_machine" if command == "reload" else "rewrite_values"
    module = reload_module if command == "reload" else save_module  # (geo_server/commands)
    original = getattr(module, target)
    started, release = threading.Event(), threading.Event()
    threads: list[str] = []

    def slow(*args, **kwargs):
        threads.append(threading.current_thread().name)
        started.set()
        release.wait(10.0)
        return original(*args, **kwargs)

    monkeypatch.setattr(module, target, slow)
    result: dict = {}
    writer = threading.Thread(
        target=lambda: result.update(reply=get(srv.session, key, payload, encoding))
    )
    writer.start()
    try:
        assert started.wait(TIMEOUT), f"{command} never reached {target}"
        # A loop blocked inside the command could not answer this within the timeout.
        oks, errs = get(srv.session, "cnc/t/sim/machine/cycle_count", timeout=2.0)
        assert not errs and len(oks) == 1, (oks, errs)
    finally:
        release.set()
        writer.join(TIMEOUT + 12.0)
    oks, errs = result["reply"]
    assert not errs and len(oks) == 1, (oks, errs)
    assert oks[0] == (key, payload)
    assert threads and LOOP_THREAD not in threads, threads
    if command == "save":
        axis_list = Path(svc.info.config.axes[1].params.path)
        assert b"1234.5" in axis_list.read_bytes()


@pytest.mark.parametrize(
    "key,payload,encoding",
    [(k, p, e) for c, k, p, e in COMMAND_WRITES if c == "reload"],
)
def test_command_write_keeps_its_error_codes(served_lists, key, payload, encoding):
    """Off the loop, a rejected reload is still 0x70D and a bad value still 0x706."""
    srv = served_lists
    svc = srv.service
    axis_list = Path(svc.info.config.axes[1].params.path)
    text = axis_list.read_bytes()
    line = b"temp_comp_coefficient 4000"
    assert line in text
    axis_list.write_bytes(text.replace(line, b"temp_comp_coefficient 99999"))  # > 10000 µm/m
    assert get_err(srv.session, key, payload, encoding)["ads_error"] == 0x70D
    bad = b"2" if encoding == JSON else struct.pack("<H", 2)  # SIM::reload accepts only 1
    assert get_err(srv.session, key, bad, encoding)["ads_error"] == 0x706
    access.step(svc, 1)
    assert access.read_name(svc, "TEMPC::coefficient", 1) == 4000.0


def test_service_async_writes_run_commands_in_a_worker_thread(loop_thread, service, monkeypatch):
    """Every transport gets it: `access.write_applied`/`write_name_applied`."""
    threads: list[str] = []
    assert is_command(service.info.dictionary.by_name("SIM::reload"))
    assert is_command(service.info.dictionary.by_name("SIM::save"))
    assert not is_command(service.info.dictionary.by_name("TEMPC::coefficient"))

    def fake_save(self):
        threads.append(threading.current_thread().name)
        return service_module.CommandResult(True, "save")

    monkeypatch.setattr(CommandService, "save", fake_save)
    assert run_in(loop_thread, access.write_name_applied(service, "SIM::save", 0, 1)) == 1
    run_in(loop_thread, access.write_applied(service, 0x12F300, 0x5, struct.pack("<H", 1)))
    assert len(threads) == 2 and LOOP_THREAD not in threads, threads
    # plain values are queued (stepped: acknowledged at once) and applied at the next cycle
    run_in(loop_thread, access.write_name_applied(service, "TEMPC::coefficient", 1, 1500))
    assert access.read_name(service, "TEMPC::coefficient", 1) == 4000.0
    access.step(service, 1)
    assert access.read_name(service, "TEMPC::coefficient", 1) == 1500.0


# ---------------------------------------------------------------------------- 2. hand-off


def test_callbacks_survive_a_loop_that_closes_during_the_hand_off(service):
    """`_on_query`/`_on_event` run on Zenoh's and the cycle's threads: a loop closing
    between their `is_closed()` check and `call_soon_threadsafe` must not raise there."""
    iface = ZenohInterface(service, ZenohOptions(machine="t", listen=[]))
    loop = asyncio.new_event_loop()
    loop.close()
    loop.is_closed = lambda: False  # the race: closed right after the check
    iface._loop = loop
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            iface._on_query(object())  # type: ignore[arg-type]  # not handed off: untouched
            iface._on_event(object())  # type: ignore[arg-type]
            gc.collect()
    finally:
        del loop.is_closed  # the real one again, so the loop's __del__ does not close twice
    # no coroutine was created for a query that could not be handed off
    assert not [w for w in caught if "never awaited" in str(w.message)], caught


# ---------------------------------------------------------------------------- 3. wildcards


@pytest.mark.parametrize(
    "key,code,words",
    [
        ("cnc/t/axis/99/**", 0x703, "axis 99"),  # unknown axis (docs/design.md §9: 0x703)
        ("cnc/t/axis/99/tempc/*", 0x703, "axis 99"),
        ("cnc/t/sim/axis/99/*", 0x703, "axis 99"),
        ("cnc/t/axis/1/nothing/*", 0x703, "no object"),  # matches no object
        ("cnc/t/*/nothing/**", 0x703, "no object"),
        ("cnc/t/ads/552/**", 0x6, "port"),  # unknown ADS port
        ("cnc/t/ads/551/0x120200/*", 0x702, "group"),  # unknown index group
        ("cnc/t/ads/551/0x120300/0x99$*", 0x703, "no object"),
    ],
)
def test_wildcard_matching_nothing_is_reply_err(served, key, code, words):
    err = get_err(served.session, key)
    assert err["ads_error"] == code, err
    assert words in err["message"], err


def test_wildcard_on_attribute_group_explains_concrete_keys(served):
    err = get_err(served.session, "cnc/t/ads/551/0x120400/*")
    assert err["ads_error"] == 0x703
    assert "concrete key" in err["message"]


def test_wildcards_that_match_still_answer_once_per_key(served):
    oks, errs = get(served.session, "cnc/t/axis/*/tempc/coefficient")
    assert not errs
    assert len(oks) == len(served.service.info.axes)


# ---------------------------------------------------------------------------- 4. publications


def test_value_status_and_error_publications(served):
    """Values, status and errors are published on the precomputed key expressions."""
    q: queue.Queue = queue.Queue()
    subs = [
        served.session.declare_subscriber(
            k, lambda s: q.put((str(s.key_expr), json.loads(s.payload.to_bytes())))
        )
        for k in ("cnc/t/axis/1/tempc/coefficient", "cnc/t/status", "cnc/t/errors")
    ]
    try:
        # published once, on change: the server must know the subscribers before
        wait_until_routed(served.session, "cnc/t/status")
        svc = served.service
        access.write_name(svc, "TEMPC::coefficient", 1, 2500)
        access.step(svc, 1)
        svc.report("test error", error_id=4242)
        seen: dict[str, object] = {}
        deadline = time.monotonic() + TIMEOUT  # status keeps coming: bound the loop itself
        while not ({"status", "errors"} <= seen.keys() and seen.get("coefficient") == 2500.0):
            assert time.monotonic() < deadline, f"publications missing: {seen}"
            key, value = q.get(timeout=TIMEOUT)
            seen[key.rsplit("/", 1)[1]] = value
        assert seen["errors"]["error_id"] == 4242
        assert seen["status"]["axes"] == list(svc.info.axes)
    finally:
        for sub in subs:
            sub.undeclare()


def test_nothing_handed_over_after_close_outlives_the_interface(loop_thread, service) -> None:
    """A query or put Zenoh hands to the loop while the interface closes starts no task:
    it would outlive the interface ("Task was destroyed but it is pending" when the loop
    ended, seen in the suite for a refused put listed after the close)."""
    s = Served(loop_thread, service)
    s.close()

    async def work() -> None:
        raise AssertionError("ran after close")

    coro = work()
    assert s.iface._spawn(coro) is None
    assert coro.cr_frame is None  # (closed: never run, no warning it was not awaited)
    assert not s.iface._tasks
