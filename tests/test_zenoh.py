"""The Zenoh interface (docs/design.md §7) with real Zenoh sessions on loopback.

The server runs in stepped mode; an independent plain `zenoh` session (not the project's
client) asks the questions. Peer mode, multicast scouting off, explicit endpoints, a
timeout on every get, undeclare before close.
"""

from __future__ import annotations

import json
import queue
import re
import struct
import threading
import time
from pathlib import Path

import pytest
import zenoh
from conftest import free_port, run_in, wait_until_routed
from support.fakes import VirtualClock

from geo_server import access
from geo_server.client.cli import main as client_main
from geo_server.dictionary import load_dictionary
from geo_server.faults import parse_fault
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.machine.scheduler import Scheduler
from geo_server.service import ObjectService
from geo_server.transports.zenoh.options import ZenohOptions
from geo_server.transports.zenoh.server import ZenohInterface

TIMEOUT = 5.0
D = load_dictionary()


def session_config(connect: list[str], listen: list[str] | None = None, mode: str = "peer"):
    c = zenoh.Config()
    c.insert_json5("mode", json.dumps(mode))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", json.dumps(listen or []))
    c.insert_json5("connect/endpoints", json.dumps(connect))
    return c


class Server:
    """A stepped geo-server with its Zenoh interface on an ephemeral port."""

    def __init__(
        self,
        loop,
        service: ObjectService,
        machine: str = "t",
        connect: list[str] | None = None,
        **options,
    ) -> None:
        self.loop = loop
        self.service = service
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        opts = ZenohOptions(
            machine=machine,
            listen=[self.endpoint],
            connect=connect or [],
            publish_period=0.01,
            status_period=0.05,
            **options,
        )
        self.iface = ZenohInterface(service, opts)
        run_in(loop, self.iface.start())

    def close(self) -> None:
        run_in(self.loop, self.iface.close())


@pytest.fixture
def server(loop_thread, service):
    srv = Server(loop_thread, service)
    yield srv
    srv.close()


@pytest.fixture
def zs(server):
    s = zenoh.open(session_config([server.endpoint]))
    yield s
    s.close()


def get(session, key: str, payload: bytes | None = None, encoding=None, timeout=TIMEOUT):
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
            errs.append(json.loads(r.err.payload.to_bytes()))
    return oks, errs


def get_one(session, key, payload=None, encoding=None) -> bytes:
    oks, errs = get(session, key, payload, encoding)
    assert not errs, errs
    assert len(oks) == 1, oks
    return oks[0][1]


def get_err(session, key, payload=None, encoding=None) -> dict:
    oks, errs = get(session, key, payload, encoding)
    assert not oks, oks
    assert len(errs) == 1, errs
    return errs[0]


# ---------------------------------------------------------------------------- reads


def test_raw_read_of_every_geo_object(server, zs):
    service = server.service
    for axis in service.info.axes:
        for obj in D.group_objects("geo"):
            io = (axis << 16) | obj.id
            data = get_one(zs, f"cnc/t/ads/551/0x120300/0x{io:x}")
            assert len(data) == obj.length, obj.name
            assert obj.decode(data) == access.read_name(service, obj.name, axis), (obj.name, axis)


def test_a_plain_read_is_answered_while_the_event_loop_is_busy(server, zs):
    """A get of one object's key is answered on Zenoh's own thread when the cycle due is
    there (docs/design.md §7); what needs the loop — a write, a wildcard — waits for it."""
    held, release = threading.Event(), threading.Event()

    def busy() -> None:  # a loop busy with something long (another interface's work)
        held.set()
        release.wait(2 * TIMEOUT)

    server.loop.call_soon_threadsafe(busy)
    assert held.wait(TIMEOUT)
    try:
        # the manual's example (000 p.17): offset 40 and coefficient 4000 of axis X
        assert json.loads(get_one(zs, "cnc/t/axis/1/tempc/offset_0")) == 40
        assert struct.unpack("<d", get_one(zs, "cnc/t/ads/551/0x120300/0x10043")) == (4000.0,)
        pending = zs.get("cnc/t/axis/1/tempc/*", timeout=TIMEOUT)  # a wildcard: the loop's
    finally:
        release.set()
    replies = [r for r in pending if r.ok is not None]
    assert len(replies) > 3 and "cnc/t/axis/1/tempc/offset_0" in {
        str(r.ok.key_expr) for r in replies
    }


def test_other_spellings_of_a_key_are_answered_on_the_loop_and_remembered_nowhere(server, zs):
    """A hostile peer spelling one address in endless ways (leading zeros, upper case)
    gets its answer from the loop's parser; the table of keys read on Zenoh's thread is
    the one made at start and does not grow."""
    table = dict(server.iface.reads.plain_keys)
    for zeros in (1, 100, 10_000):
        key = "cnc/t/ads/551/0x120300/0X" + "0" * zeros + "10043"
        assert struct.unpack("<d", get_one(zs, key)) == (4000.0,)  # the manual's 4000
    assert server.iface.reads.plain_keys == table


def test_named_read_of_the_manual_temperature_parameters(server, zs):
    # Default machine, axis X (1): the manual's example (000 p.17): 100 / 40 / 4000.
    assert json.loads(get_one(zs, "cnc/t/axis/1/tempc/coefficient")) == 4000.0
    assert json.loads(get_one(zs, "cnc/t/axis/1/tempc/offset_0")) == 40
    assert json.loads(get_one(zs, "cnc/t/axis/1/tempc/position_0")) == 100
    assert json.loads(get_one(zs, "cnc/t/axis/1/tempc/activated")) is True
    raw = get_one(zs, "cnc/t/ads/551/0x120300/0x10043")
    assert struct.unpack("<d", raw) == (4000.0,)


def test_wildcard_answers_once_per_object(server, zs):
    oks, errs = get(zs, "cnc/t/axis/1/tempc/*")
    assert not errs
    fields = sorted(k.rsplit("/", 1)[1] for k, _ in oks)
    assert fields == [
        "activated",
        "actual_offset",
        "coefficient",
        "f_is_active",
        "offset_0",
        "position_0",
    ]
    oks, _ = get(zs, "cnc/t/axis/*/bc/conf_backlash")
    assert len(oks) == len(server.service.info.axes)


def test_status_and_errors(server, zs):
    access.step(server.service, 3)
    status = json.loads(get_one(zs, "cnc/t/status"))
    assert status["cycle"] == 3
    assert status["axes"] == list(server.service.info.axes)
    assert isinstance(json.loads(get_one(zs, "cnc/t/errors")), list)


# ---------------------------------------------------------------------------- writes


def test_writes_of_each_tempc_object_and_their_effect(server, zs):
    svc = server.service
    # X to 100 mm: Δs = 40 + 4000e-6·(1_000_000 − 100) = 4039.6 -> 4040 (000 p.17 example).
    access.write_name(svc, "SIM::set_position", 1, 1_000_000)
    access.step(svc, 25)
    assert access.read_name(svc, "TEMPC::actual_offset", 1) == 4040
    enc = zenoh.Encoding.APPLICATION_JSON
    assert json.loads(get_one(zs, "cnc/t/axis/1/tempc/coefficient", b"2000", enc)) == 2000.0
    access.step(svc, 20)  # temp_comp_n_cycles 20: the ramp ends in the 20th cycle
    # 40 + 2000e-6·999_900 = 2039.8 -> 2040
    assert access.read_name(svc, "TEMPC::actual_offset", 1) == 2040
    get_one(zs, "cnc/t/axis/1/tempc/offset_0", b'{"value": 100}', enc)
    access.step(svc, 20)
    assert access.read_name(svc, "TEMPC::actual_offset", 1) == 2100  # 100 + 1999.8
    raw = struct.pack("<i", 0)
    get_one(zs, "cnc/t/ads/551/0x120300/0x10045", raw, zenoh.Encoding.APPLICATION_OCTET_STREAM)
    access.step(svc, 20)
    assert access.read_name(svc, "TEMPC::actual_offset", 1) == 2100  # 100 + 0.002·1_000_000
    get_one(zs, "cnc/t/axis/1/tempc/activated", b"false", enc)
    access.step(svc, 20)
    assert access.read_name(svc, "TEMPC::activated", 1) is False
    assert access.read_name(svc, "TEMPC::actual_offset", 1) == 0


@pytest.mark.parametrize(
    "key,payload,code",
    [
        ("cnc/t/ads/551/0x120200/0x10043", None, 0x702),  # unknown index group
        ("cnc/t/ads/551/0x120300/0x10099", None, 0x703),  # unknown offset
        ("cnc/t/ads/551/0x120300/0x90043", None, 0x703),  # unknown axis (raw)
        ("cnc/t/axis/9/tempc/coefficient", None, 0x703),  # unknown axis (named)
        ("cnc/t/axis/1/tempc/nonsense", None, 0x703),  # unknown field
        ("cnc/t/ads/552/0x120300/0x10043", None, 0x6),  # unknown ADS port
        ("cnc/t/axis/1/bc/actual_backlash", b"5", 0x704),  # read-only
        ("cnc/t/ads/551/0x120300/0x10043", b"\0\0\0\0", 0x705),  # REAL64 needs 8 bytes
        ("cnc/t/axis/1/tempc/coefficient", b"20000", 0x706),  # > 10000 µm/m
        ("cnc/t/axis/1/tempc/coefficient", b"{not json", 0x706),  # garbage JSON
        ("cnc/t/axis/1/tempc/activated", b"[1, 2]", 0x706),  # not a scalar
        ("cnc/t/axis/1/tempc/coefficient", b"1" * 70_000, 0x705),  # huge payload
    ],
)
def test_errors_are_reply_err_with_the_ads_code(server, zs, key, payload, code):
    err = get_err(zs, key, payload, zenoh.Encoding.APPLICATION_JSON if payload else None)
    assert err["ads_error"] == code
    assert err["message"]
    access.step(server.service, 1)  # the cycle keeps running
    assert server.service.current(stale_ok=True).cycle == 1


def test_garbage_leaves_values_untouched(server, zs):
    before = access.read_axis(server.service, 1)
    for payload in (b"\xff\xfe", b"nan", b"1e999", b'"text"'):
        oks, errs = get(
            zs, "cnc/t/axis/1/tempc/coefficient", payload, zenoh.Encoding.APPLICATION_JSON
        )
        assert errs and not oks
    access.step(server.service, 2)
    assert access.read_axis(server.service, 1)["TEMPC::coefficient"] == before["TEMPC::coefficient"]


# ---------------------------------------------------------------------------- publications


def test_publications_arrive_on_a_subscriber(server, zs):
    q: queue.Queue = queue.Queue()
    sub = zs.declare_subscriber(
        "cnc/t/axis/1/tempc/actual_offset",
        lambda s: q.put((str(s.key_expr), json.loads(s.payload.to_bytes()))),
    )
    try:
        # published on change only: the server must know the subscriber before it changes
        wait_until_routed(zs, "cnc/t/status")
        access.write_name(server.service, "SIM::set_position", 1, 1_000_000)
        access.step(server.service, 25)
        values = []
        while 4040 not in values:  # the manual's example value, after the ramp
            key, value = q.get(timeout=TIMEOUT)  # at most 25 distinct values: bounded
            assert key == "cnc/t/axis/1/tempc/actual_offset"
            values.append(value)
    finally:
        sub.undeclare()


@pytest.mark.realtime
def test_nothing_is_computed_for_publication_while_nobody_subscribes(loop_thread, default_cfg):
    """The publish loop asks Zenoh whether any subscriber matches `cnc/<m>/**`: without
    one the exact engine is never made to catch up for a publication; with one, the
    changed values flow (and each publication is a catch-up)."""
    machine = Machine(default_cfg, cycle_s=0.001, homed=True)
    sched = Scheduler(machine, mode="realtime", engine="exact")
    srv = Server(loop_thread, ObjectService(machine, sched))
    sched.start()
    s = zenoh.open(session_config([srv.endpoint]))
    try:
        time.sleep(0.3)  # 30 publish periods of 10 ms
        assert sched.status()["syncs"] == 0
        q: queue.Queue = queue.Queue()
        sub = s.declare_subscriber("cnc/t/sim/machine/twin_time", lambda smp: q.put(smp))
        try:
            first = json.loads(q.get(timeout=TIMEOUT).payload.to_bytes())
            second = json.loads(q.get(timeout=TIMEOUT).payload.to_bytes())
            assert second > first > 0  # the twin's clock, published as it runs
            assert sched.status()["syncs"] >= 2
        finally:
            sub.undeclare()
    finally:
        s.close()
        sched.stop()
        srv.close()


# ---------------------------------------------------------------------------- nc, commands


def test_nc_switches_temperature_compensation_off(server, zs):
    svc = server.service
    access.step(svc, 1)
    assert access.read_name(svc, "TEMPC::activated", 1) is True
    reply = json.loads(get_one(zs, "cnc/t/nc", b"X[COMP OFF TEMP]", zenoh.Encoding.TEXT_PLAIN))
    assert reply["ok"] is True
    access.step(svc, 3)
    assert access.read_name(svc, "TEMPC::activated", 1) is False


def test_save_and_reload(loop_thread, lists_copy: Path):
    service = ObjectService(Machine(load_machine(lists_copy), homed=True))
    srv = Server(loop_thread, service)
    s = zenoh.open(session_config([srv.endpoint]))
    try:
        axis_list = Path(service.info.config.axes[1].params.path)
        before = axis_list.read_bytes()
        get_one(s, "cnc/t/axis/1/tempc/coefficient", b"1234.5", zenoh.Encoding.APPLICATION_JSON)
        access.step(service, 1)
        result = json.loads(get_one(s, "cnc/t/cmd/save", b"{}"))
        assert result["ok"] and str(axis_list) in result["files"]
        after = axis_list.read_bytes()
        assert after != before
        assert after.replace(b"1234.5", b"4000", 1) == before
        # a valid reload keeps the saved value
        result = json.loads(get_one(s, "cnc/t/cmd/reload", b"{}"))
        assert result["ok"], result
        access.step(service, 1)
        assert access.read_name(service, "TEMPC::coefficient", 1) == 1234.5
        # a broken list: the reload is rejected as a whole, nothing changes
        values = access.read_axis(service, 1)
        axis_list.write_bytes(after.replace(b"1234.5", b"99999", 1))  # out of range
        err = get_err(s, "cnc/t/cmd/reload", b"{}")
        assert err["ads_error"] == 0x70D
        assert "99999" in err["message"] or "coefficient" in err["message"]
        access.step(service, 1)
        assert access.read_axis(service, 1)["TEMPC::coefficient"] == values["TEMPC::coefficient"]
    finally:
        s.close()
        srv.close()


# ---------------------------------------------------------------------------- topology


def test_two_servers_through_a_router(loop_thread, default_cfg):
    router_ep = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(session_config([], [router_ep], mode="router"))
    a = ObjectService(Machine(default_cfg, homed=True))
    b = ObjectService(Machine(default_cfg, homed=True))
    sa = Server(loop_thread, a, machine="mill", connect=[router_ep])
    sb = Server(loop_thread, b, machine="lathe", connect=[router_ep])
    client = zenoh.open(session_config([router_ep], mode="client"))
    try:
        access.step(a, 7)
        access.step(b, 3)
        assert json.loads(get_one(client, "cnc/mill/sim/machine/cycle_count")) == 7
        assert json.loads(get_one(client, "cnc/lathe/sim/machine/cycle_count")) == 3
        oks, _ = get(client, "cnc/*/sim/machine/cycle_count")
        assert sorted(k for k, _ in oks) == [
            "cnc/lathe/sim/machine/cycle_count",
            "cnc/mill/sim/machine/cycle_count",
        ]
    finally:
        client.close()
        sa.close()
        sb.close()
        router.close()


def test_liveliness_token(server, zs):
    replies = list(zs.liveliness().get("cnc/t/alive", timeout=TIMEOUT))
    assert [str(r.ok.key_expr) for r in replies if r.ok is not None] == ["cnc/t/alive"]


# ---------------------------------------------------------------------------- geo-client


def test_geo_client_read_write(server, capsys):
    base = ["--machine", "t", "--connect", server.endpoint, "--timeout", "5"]
    assert client_main([*base, "read", "--axis", "1", "TEMPC::coefficient"]) == 0
    assert capsys.readouterr().out.strip() == "axis 1 (X) TEMPC::coefficient = 4000.0 µm/m"
    assert client_main([*base, "--json", "read", "0x120300", "0x10044"]) == 0
    out = json.loads(capsys.readouterr().out)  # 40 increments of 0.1 µm = 4.0 µm
    assert out == {"name": "TEMPC::offset_0", "axis": 1, "value": 4.0, "unit": "µm", "raw": 40}
    assert client_main([*base, "write", "--axis", "1", "TEMPC::coefficient", "3000"]) == 0
    capsys.readouterr()
    access.step(server.service, 1)
    assert access.read_name(server.service, "TEMPC::coefficient", 1) == 3000.0
    assert client_main([*base, "write", "--axis", "1", "BC::actual backlash", "1"]) == 1
    assert "ADS 0x704" in capsys.readouterr().err


def test_geo_client_by_address_reads_attribute_groups(server, capsys):
    """`GROUP OFFSET` goes out as that address: attribute groups answer their attribute
    (docs/design.md §2: +0x100 name … +0x500 writable), writes to them are refused by the server."""
    base = ["--machine", "t", "--connect", server.endpoint, "--timeout", "5"]
    expected = {
        "0x120400": "axis 1 (X) TEMPC::coefficient name = TEMPC::coefficient",
        "0x120500": "axis 1 (X) TEMPC::coefficient type = REAL64",
        "0x120600": "axis 1 (X) TEMPC::coefficient length = 8",
        "0x120700": "axis 1 (X) TEMPC::coefficient unit = [um/m]",
        "0x120800": "axis 1 (X) TEMPC::coefficient writable = True",
    }
    for group, line in expected.items():
        assert client_main([*base, "read", group, "0x10043"]) == 0
        assert capsys.readouterr().out.strip() == line
    assert client_main([*base, "write", "0x120400", "0x10043", "3000"]) == 1
    assert "ADS 0x704" in capsys.readouterr().err
    assert client_main([*base, "write", "0x120300", "0x10043", "3000"]) == 0
    assert capsys.readouterr().out.strip() == "axis 1 (X) TEMPC::coefficient = 3000.0 µm/m"
    access.step(server.service, 1)
    assert access.read_name(server.service, "TEMPC::coefficient", 1) == 3000.0


@pytest.mark.slow
def test_geo_client_commands(server, capsys):
    base = ["--machine", "t", "--connect", server.endpoint, "--timeout", "5"]
    svc = server.service
    access.step(svc, 4)
    assert client_main([*base, "--json", "status"]) == 0
    assert json.loads(capsys.readouterr().out)["cycle"] == 4
    assert client_main([*base, "--json", "nc", "X[COMP OFF TEMP]"]) == 0
    assert json.loads(capsys.readouterr().out)["ok"] is True
    access.step(svc, 2)
    assert access.read_name(svc, "TEMPC::activated", 1) is False
    assert client_main([*base, "nc", "G05 X1"]) == 1  # not in the supported subset
    assert "ADS 0x70D" in capsys.readouterr().err
    assert client_main([*base, "--json", "errors"]) == 0
    assert isinstance(json.loads(capsys.readouterr().out), list)
    # watch: the first publication of the value, then stop
    assert (
        client_main([*base, "--json", "watch", "--count", "1", "--axis", "1", "TEMPC::coefficient"])
        == 0
    )
    out = json.loads(capsys.readouterr().out)
    assert out == {
        "name": "TEMPC::coefficient",
        "axis": 1,
        "value": 4000.0,
        "unit": "µm/m",
        "raw": 4000.0,
    }
    # a raw ADS key: its current bytes, as hex (4000.0 as little-endian REAL64)
    raw = "cnc/t/ads/551/0x120300/0x10043"
    assert client_main([*base, "--json", "watch", "--count", "1", raw]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out == {"key": raw, "value": "000000000040af40"}


# ---------------------------------------------------------------------------- exposure

ACL = """{
  access_control: {
    enabled: true,
    default_permission: "allow",
    rules: [
      { id: "no-commands", permission: "deny", flows: ["ingress", "egress"],
        messages: ["query", "reply"],
        key_exprs: ["cnc/acl/cmd/**", "cnc/acl/axis/*/tempc/coefficient"] },
    ],
    subjects: [ { id: "loopback", interfaces: ["lo"] } ],
    policies: [ { rules: ["no-commands"], subjects: ["loopback"] } ],
  },
}
"""


def test_access_control_config_refuses_a_denied_key(loop_thread, service, tmp_path):
    acl = tmp_path / "acl.json5"
    acl.write_text(ACL, encoding="utf-8")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    opts = ZenohOptions(machine="acl", listen=[endpoint], config_file=str(acl))
    iface = ZenohInterface(service, opts)
    run_in(loop_thread, iface.start())
    s = zenoh.open(session_config([endpoint]))
    try:
        # allowed keys work: a read, and a write that the next cycle applies
        assert json.loads(get_one(s, "cnc/acl/axis/1/tempc/offset_0")) == 40
        assert json.loads(get_one(s, "cnc/acl/axis/1/tempc/offset_0", b"55")) is not None
        # denied keys: the query never reaches the server (no reply at all, not even an
        # error), so the write has no effect
        for key, payload in [
            ("cnc/acl/axis/1/tempc/coefficient", b"1234"),
            ("cnc/acl/axis/1/tempc/coefficient", None),
            ("cnc/acl/cmd/reload", b"{}"),
        ]:
            oks, errs = get(s, key, payload, timeout=1.0)
            assert oks == [] and errs == [], key
        access.step(service, 25)
        assert access.read_name(service, "TEMPC::offset_0", 1) == 55
        assert access.read_name(service, "TEMPC::coefficient", 1) == 4000.0
    finally:
        s.close()
        run_in(loop_thread, iface.close())


def test_read_only_interface_rejects_writes(loop_thread, service):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    iface = ZenohInterface(service, ZenohOptions(machine="ro", listen=[endpoint], read_only=True))
    run_in(loop_thread, iface.start())
    s = zenoh.open(session_config([endpoint]))
    try:
        assert json.loads(get_one(s, "cnc/ro/axis/1/tempc/coefficient")) == 4000.0
        for key, payload in [
            ("cnc/ro/axis/1/tempc/coefficient", b"1"),
            ("cnc/ro/ads/551/0x120300/0x10044", b"\0\0\0\0"),
            ("cnc/ro/nc", b"X[COMP OFF TEMP]"),
            ("cnc/ro/cmd/save", b"{}"),
        ]:
            assert get_err(s, key, payload)["ads_error"] == 0x704
        access.step(service, 2)
        assert access.read_name(service, "TEMPC::coefficient", 1) == 4000.0
        assert access.read_name(service, "TEMPC::activated", 1) is True
    finally:
        s.close()
        run_in(loop_thread, iface.close())


# ---------------------------------------------------------------------------- put, delete


def _until(predicate, timeout: float = TIMEOUT) -> None:
    """Wait for something another session's put sets off (it has no reply to wait for)."""
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "the server never took the put"
        time.sleep(0.005)


def test_a_put_is_a_write_and_a_refused_one_is_reported(server, zs):
    """A plain Zenoh `put` (what the REST and MQTT bridges send) writes the object of its
    key like a get with payload; a refused put or a delete has no one to answer, so the
    errors list says why, naming the key."""
    svc = server.service
    access.write_name(svc, "SIM::set_position", 1, 1_000_000)  # X at 100 mm
    access.step(svc, 25)
    zs.put("cnc/t/axis/1/tempc/coefficient", b"2000")
    _until(lambda: server.iface.puts == 1)
    access.step(svc, 20)  # the ramp of temp_comp_n_cycles = 20
    # 40 + 2000e-6·(1_000_000 − 100) = 2039.8 -> 2040 (000 p.15)
    assert access.read_name(svc, "TEMPC::coefficient", 1) == 2000.0
    assert access.read_name(svc, "TEMPC::actual_offset", 1) == 2040
    zs.put("cnc/t/ads/551/0x120300/0x10044", struct.pack("<i", 100))  # offset_0, raw
    _until(lambda: server.iface.puts == 2)
    access.step(svc, 20)
    assert access.read_name(svc, "TEMPC::actual_offset", 1) == 2100  # 100 + 1999.8
    # refused: out of range, read-only, a command, a delete — the value stays
    zs.put("cnc/t/axis/1/tempc/coefficient", b"20000")
    zs.put("cnc/t/axis/1/bc/actual_backlash", b"5")
    zs.put("cnc/t/cmd/save", b"")
    zs.delete("cnc/t/axis/1/tempc/coefficient")
    _until(lambda: server.iface.refused_puts == 4)
    access.step(svc, 1)
    assert access.read_name(svc, "TEMPC::coefficient", 1) == 2000.0
    messages = [e["message"] for e in svc.errors()[-4:]]
    assert messages[0].startswith("zenoh put cnc/t/axis/1/tempc/coefficient: ")
    assert messages[0].endswith("(ADS 0x706)")
    assert messages[1].startswith("zenoh put cnc/t/axis/1/bc/actual_backlash: ")
    assert messages[1].endswith("(ADS 0x704)")
    assert "commands and NC text take a get with payload" in messages[2]
    assert messages[3] == (
        "zenoh delete cnc/t/axis/1/tempc/coefficient: an object cannot be deleted "
        "(put a value to write it) (ADS 0x704)"
    )


def test_refused_puts_are_reported_in_the_order_they_arrived(server, zs, monkeypatch):
    """One session's puts arrive in order (Zenoh keeps a publisher's order on a reliable
    link); their refusals are listed in that order too, each one in the list by the time
    `refused_puts` counts it — a burst must not come out shuffled by the threads that
    record it. Every other report takes 20 ms (as one that waits for a catch-up does)."""
    svc = server.service
    report = svc.report
    calls = []

    def slow_every_other(message, **kwargs):
        calls.append(message)
        if len(calls) % 2:
            time.sleep(0.02)
        return report(message, **kwargs)

    monkeypatch.setattr(svc, "report", slow_every_other)
    keys = [
        f"cnc/t/axis/{axis}/{obj}"
        for _ in range(4)
        for obj in ("bc/actual_backlash", "tempc/actual_offset", "tempc/coefficient")
        for axis in (1, 2, 3)
    ]
    for n, key in enumerate(keys):
        if key.endswith("coefficient"):
            zs.delete(key)
        else:
            zs.put(key, str(n).encode())
    _until(lambda: server.iface.refused_puts == len(keys))
    listed = [e["message"].split(":")[0] for e in svc.errors()[-len(keys) :]]
    assert listed == [
        f"zenoh {'delete' if key.endswith('coefficient') else 'put'} {key}" for key in keys
    ]
    # writes are queued in that order too: the last put of a key is the value that stays
    for value in range(100, 3100, 100):
        zs.put("cnc/t/axis/2/tempc/coefficient", str(value).encode())
    _until(lambda: server.iface.puts == len(keys) + 30)
    access.step(svc, 1)
    assert access.read_name(svc, "TEMPC::coefficient", 2) == 3000.0


def test_a_burst_of_refused_puts_is_listed_up_to_a_bound_and_then_counted(server, zs, monkeypatch):
    """Refusals wait to be listed one by one; with MAX_REFUSALS_WAITING (64) waiting, the
    next are counted and listed as one line: a session's bad puts cannot flood the errors
    list or make the server hold a report each. The first report is held until all 80
    deletes have been refused."""
    svc = server.service
    report = svc.report
    first = threading.Event()

    def held_first(message, **kwargs):
        if not first.is_set():
            assert first.wait(TIMEOUT)
        return report(message, **kwargs)

    monkeypatch.setattr(svc, "report", held_first)
    for axis in range(80):
        zs.delete(f"cnc/t/axis/{axis}/tempc/coefficient")
    _until(lambda: server.iface.puts == 80)
    first.set()
    _until(lambda: server.iface.refused_puts == 80)
    messages = [e["message"] for e in svc.errors()]
    # the first refusal is listed (or waits to be) while the others arrive: 64 more
    # wait, or 63 when they came before the listing task took the first one
    m = re.fullmatch(
        r"zenoh: (\d+) more puts refused and not listed \(more than 64 refusals waited "
        r"to be listed\)",
        messages[-1],
    )
    assert m is not None, messages[-1]
    listed = 80 - int(m.group(1))
    assert listed in (64, 65), listed
    lines = [text.split(":")[0] for text in messages[-1 - listed : -1]]
    assert lines[:64] == [f"zenoh delete cnc/t/axis/{axis}/tempc/coefficient" for axis in range(64)]
    # the 65th: the first put refused after the listing task took the first one off the
    # waiting line — axis 64 when it did so early, a later axis when the line was full
    # by then (the ones between were counted)
    if listed == 65:
        last = re.fullmatch(r"zenoh delete cnc/t/axis/(\d+)/tempc/coefficient", lines[64])
        assert last is not None and 64 <= int(last.group(1)) < 80, lines[64]


def test_work_in_flight_is_capped_however_fast_a_session_sends(loop_thread, service):
    """At most `max_pending` gets and puts wait on the loop at once; beyond, a get is
    answered 0x716 at once and a put is dropped (counted in the status): a session that
    sends faster than the machine answers cannot make the server hold unbounded work.
    An injected delay holds the first gets; the status and the fault command are
    answered all the same, so the fault is cleared over Zenoh itself."""
    srv = Server(loop_thread, service, max_pending=8)
    zs = zenoh.open(session_config([srv.endpoint]))
    key = "cnc/t/axis/1/tempc/coefficient"
    try:
        service.faults.add(parse_fault("zenoh:delay=60000"))
        held = [zs.get(key, timeout=30.0) for _ in range(8)]
        _until(lambda: srv.iface.queries == 8)
        err = get_err(zs, key)
        assert err["ads_error"] == 0x716
        assert "more than 8 requests in flight" in err["message"]
        for value in (1000, 2000, 3000):
            zs.put(key, str(value).encode())
        _until(lambda: srv.iface.busy["puts_dropped"] == 3)
        status = json.loads(get_one(zs, "cnc/t/status"))
        assert status["zenoh_busy"] == {"gets_refused": 1, "puts_dropped": 3}
        assert srv.iface.puts == 0
        get_one(zs, "cnc/t/cmd/fault", json.dumps({"clear": "all"}).encode())
        for replies in held:  # they go on, each answered with the value
            (reply,) = list(replies)
            # the default machine's X: 4000 µm/m (000 p.17), none of the puts taken
            assert reply.ok is not None and reply.ok.payload.to_bytes() == b"4000.0"
        # nothing is in flight any more: gets (a wildcard goes to the loop) and puts
        # are taken again
        oks, errs = get(zs, "cnc/t/axis/1/tempc/*")
        assert not errs and ("cnc/t/axis/1/tempc/coefficient", b"4000.0") in oks
        zs.put(key, b"3500")
        _until(lambda: srv.iface.puts == 1)
        access.step(service, 1)
        assert access.read_name(service, "TEMPC::coefficient", 1) == 3500.0
        assert srv.iface.busy == {"gets_refused": 1, "puts_dropped": 3}
    finally:
        zs.close()
        srv.close()


def test_the_servers_own_publications_are_not_puts(server, zs):
    """The server publishes values on the object keys; they never come back as writes
    (its put subscriber takes remote samples only), and that subscriber of its own does
    not count as a listener (the publish loop sleeps while no other session listens)."""
    from geo_server.transports.zenoh.server import _matching

    assert not _matching(server.iface._watch)
    got = queue.Queue()
    sub = zs.declare_subscriber("cnc/t/axis/1/tempc/coefficient", got.put)
    try:
        wait_until_routed(zs, "cnc/t/status")
        access.step(server.service, 3)
        got.get(timeout=TIMEOUT)  # a publication came
    finally:
        sub.undeclare()
    assert server.iface.puts == 0


@pytest.mark.realtime
def test_a_get_sent_again_at_rest_is_answered_from_what_the_last_one_kept(loop_thread):
    """docs/design.md §13, *Repeated reads*: the exact engine on a virtual clock, the
    machine at rest with TEMPC::offset_0 of axis 1 written to -250. A get of its raw or
    named key keeps its reply with the snapshot it came from; the next get is answered
    from it while the machine still shows that rest, 5 s later too. A write applied in
    a later cycle is seen in that cycle, not hidden by what was kept. The cycle counter
    varies at rest: it is never kept, each get catches up (5000 cycles in 5 s)."""
    from geo_server.machine.port import WriteObjects
    from geo_server.paths import default_startup_list
    from geo_server.service import ServiceLimits

    P = 1_000_000
    vc = VirtualClock()
    m = Machine(load_machine(default_startup_list()), homed=True)
    sched = Scheduler(m, mode="realtime", engine="exact", clock=vc.clock, sleep=vc.sleep)
    service = ObjectService(m, sched, ServiceLimits(stall_after=60.0))
    sched.drive()
    m.submit(WriteObjects((("TEMPC::offset_0", 1, -250),)))
    vc.t += 100 * P
    assert service.current().cycle == m.cycle and sched.shows_rest()
    srv = Server(loop_thread, service)
    zs = zenoh.open(session_config([srv.endpoint]))
    try:
        keys = srv.iface.keys
        offset = D.by_name("TEMPC::offset_0")
        raw = keys.raw_key(offset.index_group, offset.index_offset(1))
        named = keys.named_key(offset, 1)
        count = keys.named_key(D.by_name("SIM::cycle_count"), 0)
        for _ in range(2):
            assert get_one(zs, raw) == struct.pack("<i", -250)
            assert json.loads(get_one(zs, named)) == -250
        assert {raw, named} <= set(srv.iface.reads.kept)
        cycle, computed = m.cycle, sched.computed
        vc.t += 5000 * P
        assert get_one(zs, raw) == struct.pack("<i", -250)
        assert (m.cycle, sched.computed) == (cycle, computed)  # nothing caught up
        first = json.loads(get_one(zs, count))
        vc.t += 5000 * P
        assert json.loads(get_one(zs, count)) == first + 5000
        assert count not in srv.iface.reads.kept
        sched.submit(WriteObjects((("TEMPC::offset_0", 1, 125),)))
        vc.t += P
        assert get_one(zs, raw) == struct.pack("<i", 125)
        assert json.loads(get_one(zs, named)) == 125
    finally:
        zs.close()
        srv.close()
