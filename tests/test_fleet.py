"""A fleet in one process (SPEC §13): `geo-server run --fleet FILE` serves several machines,
Zenoh by machine name, ADS by target AMS NetId on one port, Modbus one port per machine,
status per machine and for the fleet; `geo-client --fleet FILE --machine NAME` reaches
any of them over every transport. Real clients: a Zenoh session, pyads, geo-client (which
speaks Modbus through pymodbus)."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pyads
import pytest
import zenoh
from conftest import free_port

from geo_server.client.ads_client import close_port_first
from geo_server.dictionary import load_dictionary
from geo_server.fleet import Halted, Served, fleet_status
from geo_server.fleetfile import FleetError, Member, copies, load_fleet, member, netid_at
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.paths import default_startup_list
from geo_server.service import ObjectService

D = load_dictionary()
TIMEOUT = 5.0
#: How long a fleet's server may take to start, every interface included, counted from
#: its launch (the compiled cycle is in the cache already: conftest.pytest_configure).
#: OPC UA comes up in the background (README *OPC UA*), concurrently with the rest of
#: the start and in no fixed order with the first status line: it gets the same bound.
START = 30.0
BIN = Path(sys.executable).parent
OFFSET_0 = D.by_name("TEMPC::offset_0")
CYCLE_COUNT = D.by_name("SIM::cycle_count")


# ---------------------------------------------------------------------- the file


def test_fleet_file_defaults_and_checks(tmp_path: Path) -> None:
    f = tmp_path / "fleet.toml"
    f.write_text(
        '[[machine]]\nname = "mill-a"\n\n[[machine]]\nname = "lathe_b"\n'
        'startup = "lists/hochlauf.lis"\nnetid = "10.1.1.7.1.1"\nmodbus_port = 6000\n',
        encoding="utf-8",
    )
    a, b = load_fleet(f, "127.0.0.1.1.1", 5020)
    assert (a.name, a.startup, a.netid, a.modbus_port) == (
        "mill-a",
        default_startup_list(),
        "127.0.0.1.1.1",
        5020,
    )
    assert (b.startup, b.netid, b.modbus_port) == (
        tmp_path / "lists/hochlauf.lis",
        "10.1.1.7.1.1",
        6000,
    )
    assert [m.netid for m in copies(3, "m", a.startup, "127.0.0.1.1.1", 7000)] == [
        "127.0.0.1.1.1",
        "127.0.0.1.2.1",
        "127.0.0.1.3.1",
    ]
    assert [m.name for m in copies(2, "m", a.startup, "127.0.0.1.1.1", 7000)] == ["m-1", "m-2"]
    # past the fifth byte's 255 the count carries into the fourth, as a number would
    assert netid_at("127.0.0.1.255.1", 1) == "127.0.0.2.0.1"
    assert netid_at("127.0.0.1.1.1", 499) == "127.0.0.2.244.1"  # 1*256 + 1 + 499 = 756
    with pytest.raises(FleetError, match="cannot number 2 machines"):
        netid_at("127.0.0.255.255.1", 1)
    assert len(copies(1000, "m", a.startup, "127.0.0.1.1.1", 7000)) == 1000
    with pytest.raises(FleetError, match="between 1 and 1000, not 1001"):
        copies(1001, "m", a.startup, "127.0.0.1.1.1", 7000)
    with pytest.raises(FleetError, match="not an AMS NetId"):
        copies(2, "m", a.startup, "127.0.0.1", 7000)  # a malformed --ads-netid
    for bad in ("a/b", "fleet", "%41", ""):  # --fleet-size N --machine BAD
        with pytest.raises(FleetError, match="is not a machine name"):
            copies(2, bad, a.startup, "127.0.0.1.1.1", 7000)
    # a client counts what the file leaves out from the server's bases, as the server
    f.write_text('[[machine]]\nname = "x"\n[[machine]]\nname = "y"\n', encoding="utf-8")
    y = member(f, "y", "10.0.0.9.1.1", 6000)
    assert (y.netid, y.modbus_port) == ("10.0.0.9.2.1", 6001)
    for text, message in (
        ('[[machine]]\nname = "m"\n' * 1001, "1001 machines, at most 1000"),
        ('[[machine]]\nname = "a"\n[[machine]]\nname = "a"\n', "same name a"),
        ('[[machine]]\nname = "a/b"\n', "not a machine name"),
        ('[[machine]]\nname = "fleet"\n', "not a machine name"),
        ('[[machine]]\nname = "a"\ncolour = 1\n', "unknown keys"),
        (
            '[[machine]]\nname = "a"\n[[machine]]\nname = "b"\nnetid = "127.0.0.1.1.1"\n',
            "same netid",
        ),
        ("name = 1\n", "no \\[\\[machine\\]\\]"),
        ("[[machine]\n", "fleet.toml"),
        ('[[machine]]\nname = "a"\nnetid = "127.0.0.1.2.01x"\n', "not an AMS NetId"),
        ('[[machine]]\nname = "a"\nnetid = "mill"\n', "not an AMS NetId"),
        ('[[machine]]\nname = "a"\nnetid = 5\n', "not an AMS NetId"),
        ('[[machine]]\nname = "a"\nstartup = 3\n', "not a path"),
        ('[[machine]]\nname = "a"\nmodbus_port = true\n', "not a TCP port"),
        (
            '[[machine]]\nname = "a"\nnetid = "127.0.0.1.2.01"\n[[machine]]\nname = "b"\n'
            'netid = "127.0.0.1.2.1"\n',
            "same netid 127.0.0.1.2.1",
        ),
    ):
        f.write_text(text, encoding="utf-8")
        with pytest.raises(FleetError, match=message):
            load_fleet(f, "127.0.0.1.1.1", 5020)


# ---------------------------------------------------------------------- served


def test_a_stop_does_not_wait_for_the_fleets_status() -> None:
    """The fleet's status catches every machine up first: seconds for hundreds of
    machines just started (a SIGTERM then took 5-6 s for 500). A stop during it ends it
    before the next machine: here the stop comes while machine 1's status is made."""
    cfg = load_machine(default_startup_list())
    served = [
        Served(Member(f"m{i}", default_startup_list(), f"127.0.0.1.{i}.1", 0), s, None)
        for i, s in enumerate((ObjectService(Machine(cfg, homed=True)) for _ in range(3)), 1)
    ]
    halted = threading.Event()
    published: list[str] = []

    def publish(name: str):
        return lambda st: (published.append(name), halted.set())

    publishers = {s.member.name: publish(s.member.name) for s in served}
    with pytest.raises(Halted):
        fleet_status(served, 0.0, publishers, halted)
    assert published == ["m1"]
    halted.clear()
    assert fleet_status(served, 0.0, None, halted)["count"] == 3


@pytest.fixture
def fleet(tmp_path: Path):
    with served_fleet(tmp_path, [("mill-a", None), ("lathe-b", "127.0.0.1.9.1")]) as f:
        yield f


@contextlib.contextmanager
def served_fleet(tmp_path: Path, machines: list[tuple[str, str | None]]) -> Iterator[dict]:
    """`geo-server run --fleet` of `machines` (name, NetId or None for the default),
    each with a Modbus port of its own; what a test needs to reach it."""
    zport, aport, oport = free_port(), free_port(), free_port()
    mports = tuple(free_port() for _ in machines)
    f = tmp_path / "fleet.toml"
    f.write_text(
        "\n".join(
            f'[[machine]]\nname = "{name}"\n'
            + (f'netid = "{netid}"\n' if netid else "")
            + f"modbus_port = {port}\n"
            for (name, netid), port in zip(machines, mports, strict=True)
        ),
        encoding="utf-8",
    )
    args = [
        str(BIN / "geo-server"),
        "run",
        "--fleet",
        str(f),
        "--homed",
        "--zenoh-listen",
        f"tcp/127.0.0.1:{zport}",
        "--ads-port",
        str(aport),
        "--ads-udp-port",
        "0",
        "--opcua-endpoint",
        f"opc.tcp://127.0.0.1:{oport}",
        "--status-period",
        "0.2",
    ]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    out = tmp_path / "out.txt"
    with open(out, "wb") as o, open(tmp_path / "err.txt", "wb") as e:
        proc = subprocess.Popen(args, cwd=tmp_path, env=env, stdout=o, stderr=e)
    started = time.monotonic() + START  # the start's deadline, for every interface
    wait_started(out, tmp_path / "err.txt", proc, f"fleet: {len(machines)} machines", started)
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("listen/endpoints", "[]")
    cfg.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{zport}"]))
    session = zenoh.open(cfg)
    try:
        yield {
            "file": f,
            "zenoh": session,
            "zport": zport,
            "ads": f"127.0.0.1:{aport}",
            "aport": aport,
            "modbus": mports,
            "opcua": f"opc.tcp://127.0.0.1:{oport}",
            "out": out,
            "err": tmp_path / "err.txt",
            "proc": proc,
            "started": started,
        }
    finally:
        session.close()
        proc.terminate()
        proc.wait(10)
    assert proc.returncode == 0, (tmp_path / "err.txt").read_text()
    assert f"stopped: {len(machines)} machines" in out.read_text()


def wait_started(
    out: Path, err: Path, proc: subprocess.Popen, line: str, deadline: float, failed: str = ""
) -> None:
    """Wait until the server printed `line` (its start is done that far): at once an
    error when it ended, or said `failed` on stderr, first; by `deadline` at the latest."""
    while line not in out.read_text(errors="replace"):
        assert proc.poll() is None, err.read_text()
        assert not failed or failed not in err.read_text(errors="replace"), err.read_text()
        assert time.monotonic() < deadline, out.read_text()
        time.sleep(0.1)


def zget(session: zenoh.Session, key: str) -> list[tuple[str, object]]:
    got = []
    for r in session.get(key, timeout=TIMEOUT):
        if r.ok is not None:
            got.append((str(r.ok.key_expr), json.loads(r.ok.payload.to_bytes())))
    return got


def client(fleet, *args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["GEO_CLIENT_ZENOH"] = f"tcp/127.0.0.1:{fleet['zport']}"
    env["GEO_CLIENT_ADS"] = fleet["ads"]
    return subprocess.run(
        [str(BIN / "geo-client"), "--fleet", str(fleet["file"]), "--json", *args],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
    )


@pytest.mark.slow
def test_every_machine_on_every_transport_by_name(fleet) -> None:
    s = fleet["zenoh"]
    # Zenoh: one liveliness token and key space per machine name, and the fleet status
    tokens = sorted(
        str(r.ok.key_expr)
        for r in s.liveliness().get("cnc/*/alive", timeout=TIMEOUT)
        if r.ok is not None
    )
    assert tokens == ["cnc/lathe-b/alive", "cnc/mill-a/alive"]
    deadline = time.monotonic() + TIMEOUT
    status: dict = {}
    while time.monotonic() < deadline:
        got = zget(s, "cnc/fleet/status")
        if got:
            status = got[0][1]  # type: ignore[assignment]
            break
        time.sleep(0.1)
    assert status["count"] == 2 and status["overruns"] == 0
    assert [m["name"] for m in status["machines"]] == ["mill-a", "lathe-b"]
    assert [m["netid"] for m in status["machines"]] == ["127.0.0.1.1.1", "127.0.0.1.9.1"]
    assert all(m["engine"] == "exact" for m in status["machines"])
    ((_, st_b),) = zget(s, "cnc/lathe-b/status")
    assert st_b["axis_names"]["1"] == "X"  # type: ignore[index]

    # ADS: one port, routed by the target NetId; a write reaches only its machine
    a = pyads.Connection("127.0.0.1.1.1", 551, fleet["ads"])
    b = pyads.Connection("127.0.0.1.9.1", 551, fleet["ads"])
    ghost = pyads.Connection("127.0.0.1.77.1", 551, fleet["ads"])
    for c in (a, b, ghost):
        c.open()
        c.set_timeout(int(TIMEOUT * 1000))
    try:
        before = a.read(OFFSET_0.index_group, OFFSET_0.index_offset(1), pyads.PLCTYPE_DINT)
        b.write(OFFSET_0.index_group, OFFSET_0.index_offset(1), before + 77, pyads.PLCTYPE_DINT)
        assert (
            b.read(OFFSET_0.index_group, OFFSET_0.index_offset(1), pyads.PLCTYPE_DINT)
            == before + 77
        )
        assert a.read(OFFSET_0.index_group, OFFSET_0.index_offset(1), pyads.PLCTYPE_DINT) == before
        assert b.read_by_name("GEO.X.TEMPC.offset_0", pyads.PLCTYPE_DINT) == before + 77
        assert a.read_by_name("GEO.X.TEMPC.offset_0", pyads.PLCTYPE_DINT) == before
        assert a.read_device_info()[0] == "geo-server"
        with pytest.raises(pyads.ADSError) as err:
            ghost.read(CYCLE_COUNT.index_group, CYCLE_COUNT.index_offset(0), pyads.PLCTYPE_UDINT)
        assert err.value.err_code == 0x7  # target machine not found
    finally:
        for c in (a, b, ghost):
            close_port_first(c)
    # Zenoh sees the same: the write went to lathe-b only
    ((_, vb),) = zget(s, "cnc/lathe-b/axis/1/tempc/offset_0")
    ((_, va),) = zget(s, "cnc/mill-a/axis/1/tempc/offset_0")
    assert (va, vb) == (before, before + 77)

    # geo-client by machine name over every transport (Modbus: one port per machine)
    for via in ("zenoh", "ads", "modbus"):
        for name, value in (("mill-a", before), ("lathe-b", before + 77)):
            r = client(fleet, "--via", via, "--machine", name, "--raw", "read", "TEMPC::offset_0")
            assert r.returncode == 0, (via, name, r.stderr)
            assert json.loads(r.stdout)["value"] == value, (via, name, r.stdout)
    # the HMI by machine name (over Zenoh)
    r = subprocess.run(
        [
            str(BIN / "geo-hmi"),
            "--connect",
            f"tcp/127.0.0.1:{fleet['zport']}",
            "--machine",
            "lathe-b",
            "--once",
            "--format",
            "json",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    assert "lathe-b" in r.stdout and str(before + 77) in r.stdout
    r = client(fleet, "--via", "ads", "--machine", "drill-c", "read", "TEMPC::offset_0")
    assert r.returncode == 2 and "no machine named 'drill-c'" in r.stderr
    # issue 45 #16: a client that names no machine is told the fleet's names, the same
    # on every transport (before: Modbus and ADS answered for the first machine)
    for via in ("zenoh", "ads", "modbus"):
        r = client(fleet, "--via", via, "read", "TEMPC::offset_0")
        told = "no machine named 'local' (machines: mill-a, lathe-b; choose with --machine)"
        assert r.returncode == 2 and told in r.stderr, (via, r.stderr)
    # ... and over Zenoh without the fleet file, the machines alive on the network
    r = subprocess.run(
        [
            str(BIN / "geo-client"),
            *("--connect", f"tcp/127.0.0.1:{fleet['zport']}", "--timeout", "1"),
            *("read", "TEMPC::offset_0"),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode != 0
    assert "no machine named 'local'; machines alive: lathe-b, mill-a" in r.stderr, r.stderr
    assert "fleet: 2 machines, cycles" in fleet["out"].read_text()


@pytest.mark.slow
def test_one_opcua_server_serves_every_machine_under_its_name(fleet) -> None:
    """README *OPC UA*: a fleet's machines are Objects/<name> of one server."""
    import asyncio

    from asyncua import Client, ua

    # ready in the background, in no order with the status line the fixture waited for:
    # within the start's bound from launch, or its failure on stderr at once
    wait_started(
        fleet["out"], fleet["err"], fleet["proc"], "opcua: ready", fleet["started"], "error: opcua"
    )

    async def scenario() -> tuple[float, float]:
        async with Client(fleet["opcua"], timeout=10) as c:
            ns = await c.get_namespace_index("urn:geo-server:cnc")
            lathe = c.get_node(ua.NodeId("lathe-b/Axes/X/TEMPC/coefficient", ns))
            mill = c.get_node(ua.NodeId("mill-a/Axes/X/TEMPC/coefficient", ns))
            await lathe.write_value(ua.Variant(21.5, ua.VariantType.Double))  # applied
            return await lathe.read_value(), await mill.read_value()

    lathe, mill = asyncio.run(asyncio.wait_for(scenario(), TIMEOUT))
    assert (lathe, mill) == (21.5, 4000.0)
