"""Safety of exposure.

- Every interface binds to 127.0.0.1 by default: the option defaults of every transport
  and of `geo-server run`, and the sockets a real `geo-server run` (default hosts,
  ephemeral ports) actually listens on — read from /proc: every listening TCP socket of
  the process is on 127.0.0.1, and there is no UDP socket at all (Zenoh multicast
  scouting is off by default).
- `--read-only` rejects every write on every interface; `--zenoh-read-only`,
  `--modbus-read-only`, `--ads-read-only` on that one only — with the documented errors
  (Zenoh `reply_err` 0x704, Modbus exception 2, ADS 0x704), through a real
  `geo-server run` subprocess on ephemeral ports; the other interfaces keep accepting
  writes. (`tests/test_zenoh.py` covers the Zenoh ACL and the in-process read-only
  interface.)
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh
from conftest import free_port, geo_server_cmd
from pymodbus.client import ModbusTcpClient
from robust.harness import TIMEOUT, next_netid

from geo_server.cli import build_parser
from geo_server.client import DEFAULT_ENDPOINTS
from geo_server.client.ads_client import AdsClient
from geo_server.client.zenoh_client import client_config
from geo_server.errors import AdsError
from geo_server.transports.ads.server import AdsOptions
from geo_server.transports.modbus.server import ModbusOptions
from geo_server.transports.zenoh.options import ZenohOptions

BIN = Path(sys.executable).parent
LOOPBACK = "127.0.0.1"


class RunningServer:
    """`geo-server run` in a subprocess on ephemeral ports, default hosts."""

    def __init__(self, tmp: Path, startup: Path, *flags: str) -> None:
        self.zport, self.mport, self.aport = free_port(), free_port(), free_port()
        self.zenoh_endpoint = f"tcp/127.0.0.1:{self.zport}"
        env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
        args = [
            *geo_server_cmd(),
            "run",
            str(startup),
            "--homed",
            "--status-period",
            "5",
            "--zenoh-listen",
            self.zenoh_endpoint,
            "--modbus-port",
            str(self.mport),
            "--ads-port",
            str(self.aport),
            "--opcua-endpoint",
            f"opc.tcp://127.0.0.1:{free_port()}",
            "--opcua-cert-dir",
            str(tmp / "opcua"),
            "--opcua-no-companions",  # (about OPC UA's exposure, not its models: 3 s less)
            *flags,
        ]
        self.proc = subprocess.Popen(
            args, cwd=tmp, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
        )
        # the interfaces print one line each once they listen (zenoh, modbus, ads)
        deadline = time.monotonic() + 30
        seen = []
        assert self.proc.stdout is not None
        while not any(line.startswith("ads:") for line in seen):
            line = self.proc.stdout.readline()
            if not line or time.monotonic() > deadline:
                self.stop()
                raise AssertionError(f"geo-server run did not start: {seen}")
            seen.append(line)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


@pytest.fixture
def run_server(tmp_path, lists_copy):
    started: list[RunningServer] = []

    def start(*flags: str) -> RunningServer:
        srv = RunningServer(tmp_path, lists_copy, *flags)
        started.append(srv)
        return srv

    yield start
    for srv in started:
        srv.stop()


# ---------------------------------------------------------------------------- defaults


@pytest.mark.realtime
def test_option_defaults_are_loopback():
    assert ZenohOptions().listen == ["tcp/127.0.0.1:7447"]
    assert ZenohOptions().multicast_scouting is False
    assert ZenohOptions().connect == []
    assert ModbusOptions().host == LOOPBACK
    assert AdsOptions().host == LOOPBACK
    args = build_parser().parse_args(["run"])
    assert args.modbus_host == LOOPBACK and args.ads_host == LOOPBACK
    assert args.zenoh_listen is None  # -> ZenohOptions' tcp/127.0.0.1:7447 (compose._zenoh_options)
    assert args.zenoh_scouting is False and not args.zenoh_connect
    assert not (args.read_only or args.zenoh_read_only or args.modbus_read_only)
    assert not args.ads_read_only
    assert all("127.0.0.1" in ep for ep in DEFAULT_ENDPOINTS.values())


def _inet_sockets(pid: int) -> tuple[list[tuple[str, int]], list[tuple[str, int]]]:
    """(listening TCP (address, port), bound UDP (address, port)) of process `pid`."""
    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    listening: list[tuple[str, int]] = []
    udp: list[tuple[str, int]] = []
    for table in ("tcp", "tcp6", "udp", "udp6"):
        try:
            lines = Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            f = line.split()
            local, state, inode = f[1], f[3], f[9]
            if inode not in inodes:
                continue
            is_udp = table.startswith("udp")
            if not is_udp and state != "0A":  # TCP_LISTEN
                continue
            hexaddr, hexport = local.split(":")
            if table in ("tcp", "udp"):
                addr = socket.inet_ntop(socket.AF_INET, bytes.fromhex(hexaddr)[::-1])
            else:  # four little-endian 32-bit words
                raw = b"".join(bytes.fromhex(hexaddr[i : i + 8])[::-1] for i in range(0, 32, 8))
                addr = socket.inet_ntop(socket.AF_INET6, raw)
            (udp if is_udp else listening).append((addr, int(hexport, 16)))
    return listening, udp


@pytest.mark.slow
def test_running_server_listens_on_loopback_only(run_server):
    srv = run_server()
    listening, udp = _inet_sockets(srv.proc.pid)
    ports = {p for _a, p in listening}
    assert {srv.zport, srv.mport, srv.aport} <= ports, listening
    assert all(addr == LOOPBACK for addr, _p in listening), listening
    # ADS discovery (UDP 48899) on loopback only, no multicast scouting socket
    assert udp == [(LOOPBACK, 48899)] or udp == [], udp


# ---------------------------------------------------------------------------- read-only


def zenoh_write(session, m: str, key: str, payload: bytes) -> dict | None:
    """None when the write was accepted, else the JSON error body."""
    replies = list(session.get(f"cnc/{m}/{key}", payload=payload, timeout=TIMEOUT))
    assert len(replies) == 1, replies
    r = replies[0]
    return None if r.ok is not None else json.loads(r.err.payload.to_bytes())


CASES = {
    "--read-only": {"zenoh", "modbus", "ads"},
    "--zenoh-read-only": {"zenoh"},
    "--modbus-read-only": {"modbus"},
    "--ads-read-only": {"ads"},
}


@pytest.mark.slow
@pytest.mark.parametrize("flag", list(CASES))
def test_read_only_flags(run_server, flag):
    srv = run_server(flag)
    refusing = CASES[flag]
    z = zenoh.open(client_config([srv.zenoh_endpoint]))
    mb = ModbusTcpClient("127.0.0.1", port=srv.mport, timeout=TIMEOUT, retries=0)
    assert mb.connect()
    ads = AdsClient("127.0.0.1", srv.aport, netid=next_netid(), timeout=TIMEOUT)
    try:
        # reads work everywhere
        assert [
            json.loads(r.ok.payload.to_bytes())
            for r in z.get("cnc/local/axis/1/tempc/coefficient", timeout=TIMEOUT)
        ] == [4000.0]
        rr = mb.read_holding_registers(268, count=4, device_id=1)
        assert not rr.isError()
        assert ads.read("TEMPC::coefficient", 1) == 4000.0

        # Zenoh: named, raw, NC and command writes
        for key, payload in (
            ("axis/1/tempc/offset_0", b"11"),
            ("ads/551/0x120300/0x20044", (12).to_bytes(4, "little", signed=True)),
            ("cmd/save", b"{}"),
            ("nc", b"X[COMP OFF TEMP]"),
        ):
            if "zenoh" not in refusing and key in ("cmd/save", "nc"):
                continue  # would really run: not the point here
            err = zenoh_write(z, "local", key, payload)
            if "zenoh" in refusing:
                assert err is not None and err["ads_error"] == 0x704, (key, err)
            else:
                assert err is None, (key, err)

        # Modbus: FC 16, FC 6, FC 5 and SIM::save (unit 0)
        writes = [
            lambda: mb.write_registers(272, [0, 21], device_id=3),  # offset_0 = 21
            lambda: mb.write_register(0x4014, 1, device_id=0),  # SIM::save
            lambda: mb.write_coil(0x41, True, device_id=1),
        ]
        for i, w in enumerate(writes):
            if "modbus" not in refusing and i == 1:
                continue
            rr = w()
            if "modbus" in refusing:
                assert rr.isError() and rr.exception_code == 2, (i, rr)
            else:
                assert not rr.isError(), (i, rr)

        # ADS: write, write of SIM::save
        for name, axis, value in (("TEMPC::offset_0", 4, 31), ("SIM::save", 0, 1)):
            if "ads" not in refusing and name == "SIM::save":
                continue
            if "ads" in refusing:
                with pytest.raises(AdsError) as info:
                    ads.write(name, axis, value)
                assert info.value.code == 0x704
            else:
                ads.write(name, axis, value)

        # what was accepted is visible everywhere; what was refused changed nothing
        expect = {
            ("TEMPC::offset_0", 1): 40 if "zenoh" in refusing else 11,
            ("TEMPC::offset_0", 2): 0 if "zenoh" in refusing else 12,
            ("TEMPC::offset_0", 3): -20 if "modbus" in refusing else 21,
            ("TEMPC::offset_0", 4): 0 if "ads" in refusing else 31,
        }
        for (name, axis), value in expect.items():
            assert ads.read(name, axis) == value, (name, axis)
    finally:
        ads.close()
        mb.close()
        z.close()
