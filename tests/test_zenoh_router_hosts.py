"""Machines on several hosts meet through a Zenoh router (docs/deployment.md).

Two `geo-server run` processes stand for two hosts: each listens on its own loopback
address (127.0.0.2, 127.0.0.3), knows only the router (`--zenoh-connect`), and serves its
own machine name. The router is Zenoh's own router (a Zenoh session in router mode, as
`zenohd` runs it), not a broker of ours. A client on a third address that knows only the
router sees both machines' keys and liveliness tokens, reads and writes either, and sees
a machine's token disappear when that host stops.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh
from conftest import free_port, stop_process

TIMEOUT = 5.0
BIN = Path(sys.executable).parent


def config(connect: list[str], listen: list[str], mode: str) -> zenoh.Config:
    c = zenoh.Config()
    c.insert_json5("mode", json.dumps(mode))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", json.dumps(listen))
    c.insert_json5("connect/endpoints", json.dumps(connect))
    return c


def start_host(address: str, machine: str, router: str, tmp: Path) -> subprocess.Popen:
    args = [
        str(BIN / "geo-server"),
        "run",
        "--homed",
        "--machine",
        machine,
        "--zenoh-listen",
        f"tcp/{address}:{free_port()}",
        "--zenoh-connect",
        router,
        "--no-modbus",
        "--no-ads",
        "--no-opcua",
        "--status-period",
        "60",
    ]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    # output to files: an unread pipe would block the server once it is full
    with open(tmp / f"{machine}.out", "wb") as out, open(tmp / f"{machine}.err", "wb") as err:
        return subprocess.Popen(args, cwd=tmp, env=env, stdout=out, stderr=err)


def get_json(session: zenoh.Session, key: str) -> list[tuple[str, object]]:
    out = []
    for r in session.get(key, timeout=TIMEOUT):
        if r.ok is not None:
            out.append((str(r.ok.key_expr), json.loads(r.ok.payload.to_bytes())))
    return out


def alive(session: zenoh.Session) -> list[str]:
    replies = session.liveliness().get("cnc/*/alive", timeout=TIMEOUT)
    return sorted(str(r.ok.key_expr) for r in replies if r.ok is not None)


def wait_for(predicate, timeout: float = 30.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.2)
    return False


@pytest.mark.slow
def test_two_hosts_and_a_client_through_a_router(tmp_path) -> None:
    router_ep = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(config([], [router_ep], "router"))
    hosts = [
        start_host("127.0.0.2", "mill", router_ep, tmp_path),
        start_host("127.0.0.3", "lathe", router_ep, tmp_path),
    ]
    client = zenoh.open(config([router_ep], [f"tcp/127.0.0.4:{free_port()}"], "client"))
    try:
        assert wait_for(lambda: alive(client) == ["cnc/lathe/alive", "cnc/mill/alive"]), alive(
            client
        )
        # every machine's keys, through the router only
        counts = dict(get_json(client, "cnc/*/sim/machine/cycle_count"))
        assert set(counts) == {
            "cnc/lathe/sim/machine/cycle_count",
            "cnc/mill/sim/machine/cycle_count",
        }
        assert all(isinstance(v, int) and v > 0 for v in counts.values())
        # a write to one machine reaches that machine only
        key = "cnc/{}/axis/1/tempc/coefficient"
        replies = list(client.get(key.format("mill"), payload=b"3500", timeout=TIMEOUT))
        assert [r.ok is not None for r in replies] == [True]
        assert get_json(client, key.format("mill")) == [(key.format("mill"), 3500.0)]
        assert get_json(client, key.format("lathe")) == [(key.format("lathe"), 4000.0)]
        # a host that stops: its token goes, the other machine stays
        hosts[1].send_signal(signal.SIGTERM)
        assert hosts[1].wait(20) == 0
        assert wait_for(lambda: alive(client) == ["cnc/mill/alive"]), alive(client)
        assert [k for k, _ in get_json(client, "cnc/*/status")] == ["cnc/mill/status"]
    finally:
        client.close()
        for p in hosts:
            stop_process(p, signal.SIGTERM, 20)
        router.close()
    for name in ("mill", "lathe"):
        err = (tmp_path / f"{name}.err").read_text(errors="replace")
        assert "Traceback" not in err, err


@pytest.fixture(autouse=True)
def _need_loopback_addresses() -> None:
    """127.0.0.2 … 4 are loopback on Linux; elsewhere (macOS) they need an alias."""
    import socket

    with socket.socket() as s:
        try:
            s.bind(("127.0.0.3", 0))
        except OSError:
            pytest.skip("127.0.0.3 is not a local address here")
