"""The observation-exact engine against the punctual one (SPEC §13): request latency and fleets.

Two parts, each with both engines in the same run:

1. **Added request latency from catch-up.** One default machine (`geo-server run --homed`,
   1 ms, cycle in its own process), idle and with every axis moving; requests at random
   moments (0–10 ms apart, so the exact engine has cycles to catch up on before it
   answers): an ADS read (a bare AMS/TCP client), a Modbus read (pymodbus), a Zenoh get. p50/p99 per
   engine and the difference exact − punctual.
2. **The largest fleet.** `geo-server run --fleet-size M --homed` (machines at rest, 1 ms);
   rounds in which every machine is asked once on every transport (ADS routed by NetId on
   one port and one connection, Modbus on the machine's port, Zenoh by name). A fleet
   *serves* when every request is answered and the p99 of all of them is ≤ 10 ms. M grows
   until it does not; the server's CPU share is reported alongside.

    python bench/engine.py [--quick] [--out FILE]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import random
import socket
import time
from pathlib import Path
from typing import Any

import numpy as np
from common import (
    HOST,
    ServerProcess,
    address,
    cpu_seconds,
    emit,
    free_ports,
    free_range,
    geo_server_argv,
    get_status,
    start_geo,
    summary_us,
    table,
    wait_port,
    zenoh_session,
)

MOVING = "N10 G90 G01 X200 Y150 Z-100 C90 F6000\nN20 X-200 Y-150 Z100 C-90\nN30 $GOTO N10\n"
#: the object every request reads: TEMPC::offset_0 of axis 1 ("{m}": the machine's name)
OFFSET_0 = address("TEMPC::offset_0", 1, machine="{m}")


def _children_cpu(pid: int) -> float:
    total = cpu_seconds(pid)
    try:
        kids = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    except OSError:
        kids = []
    for k in kids:
        with contextlib.suppress(OSError):
            total += cpu_seconds(int(k))
    return total


class AdsReader:
    """A bare AMS/TCP client for one target NetId (pyads' AdsLib keeps one route per
    address and process, which a benchmark of 100 NetIds behind one port outgrows)."""

    def __init__(self, port: int) -> None:
        from geo_server.transports.ads import codec

        self.codec = codec
        self.sock = socket.create_connection((HOST, port), timeout=5.0)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.source = codec.AmsAddr("10.9.9.9.1.1", 32999)
        self.framer = codec.Framer()
        self.invoke = 0

    def read(self, netid: str, ig: int, io: int, n: int) -> bytes:
        """One read at the machine with AMS NetId `netid` (one connection, every NetId:
        the server routes by target NetId)."""
        c = self.codec
        self.invoke += 1
        target = c.AmsAddr(netid, 551)
        self.sock.sendall(
            c.request_frame(
                target, self.source, c.Command.READ, c.read_request(ig, io, n), self.invoke
            )
        )
        while True:
            data = self.sock.recv(65536)
            if not data:
                raise ConnectionError("closed by the server")
            for ev in self.framer.feed(data):
                if isinstance(ev, c.AmsPacket):
                    code, value = c.parse_read_response(ev.data)
                    if code:
                        raise RuntimeError(f"ADS error {code:#x}")
                    return value

    def close(self) -> None:
        self.sock.close()


class Clients:
    """One ADS, Modbus and Zenoh client per machine (`names`, NetIds, Modbus ports)."""

    def __init__(self, ports: dict[str, int], machines: list[tuple[str, str, int]]) -> None:
        from pymodbus.client import ModbusTcpClient

        self.session = zenoh_session(f"tcp/{HOST}:{ports['zenoh']}")
        self.machines = machines
        self.ads = AdsReader(ports["ads"])
        self.mb = []
        for _name, _netid, mport in machines:
            mb = ModbusTcpClient(HOST, port=mport, timeout=2, retries=0)
            mb.connect()
            self.mb.append(mb)

    def ask(self, i: int, via: str) -> float:
        """One request to machine i over `via`: its round trip in µs (raises on failure)."""
        t0 = time.perf_counter_ns()
        if via == "ads":
            a = OFFSET_0
            self.ads.read(self.machines[i][1], a.index_group, a.index_offset, a.size)
        elif via == "modbus":
            a = OFFSET_0
            r = self.mb[i].read_holding_registers(a.register, count=a.registers, device_id=1)
            if r.isError():
                raise RuntimeError(f"modbus: {r}")
        else:
            key = OFFSET_0.named_key.format(m=self.machines[i][0])
            replies = list(self.session.get(key, timeout=5.0))
            if not any(r.ok is not None for r in replies):
                raise RuntimeError("zenoh: no reply")
        return (time.perf_counter_ns() - t0) / 1000

    def close(self) -> None:
        self.ads.close()
        for mb in self.mb:
            mb.close()
        self.session.close()


# ---------------------------------------------------------------------- 1. latency


def latency(
    engine: str, program: Path | None, seconds: float, cycle_in: str = ""
) -> dict[str, dict[str, float]]:
    zport, mport, aport = free_ports(3)
    ports = {"zenoh": zport, "modbus": mport, "ads": aport}
    extra = ["--ads-udp-port", "0"]
    if cycle_in:
        extra += ["--cycle-in", cycle_in]
    if program is not None:
        extra += ["--program", str(program)]
    argv = geo_server_argv(1.0, ports, extra=extra, engine=engine)
    out: dict[str, list[float]] = {"ads": [], "modbus": [], "zenoh": []}
    failed: list[str] = []
    with ServerProcess(argv, f"latency-{engine}") as server:
        start_geo(server, ports).close()
        clients = Clients(ports, [("local", "127.0.0.1.1.1", mport)])
        try:
            rng = random.Random(1)
            c0, t0 = _children_cpu(server.pid), time.monotonic()
            end = t0 + seconds
            while time.monotonic() < end:
                for via in ("ads", "modbus", "zenoh"):
                    time.sleep(rng.uniform(0.0, 0.010))
                    try:
                        out[via].append(clients.ask(0, via))
                    except Exception as exc:  # counted, reported with the table
                        failed.append(f"{via}: {exc}")
            cpu = 100.0 * (_children_cpu(server.pid) - c0) / (time.monotonic() - t0)
            st = get_status(clients.session)
        finally:
            clients.close()
    res = {via: summary_us(v) for via, v in out.items()}
    res["cpu"] = {"p50": cpu, "p99": cpu}  # server CPU while asked (% of one core)
    # the catch-up itself, timed in the server (exact engine on a thread)
    res["catch-up"] = {"p50": st.get("sync_p50_us", 0.0), "p99": st.get("sync_p99_us", 0.0)}
    if failed:
        print(f"  {engine}: {len(failed)} requests failed: {failed[:3]}", flush=True)
    res["failed"] = {"n": len(failed)}
    return res


# ---------------------------------------------------------------------- 2. fleets


def fleet(engine: str, size: int, seconds: float) -> dict[str, Any]:
    zport, aport = free_ports(2)
    mbase = free_range(size)
    ports = {"zenoh": zport, "ads": aport}
    argv = geo_server_argv(
        1.0,
        {"zenoh": zport, "modbus": mbase, "ads": aport},
        extra=["--fleet-size", str(size), "--cycle-in", "thread", "--ads-udp-port", "0"],
        engine=engine,
    )
    machines = [(f"local-{i + 1}", netid(i), mbase + i) for i in range(size)]
    lat: list[float] = []
    failures = 0
    with ServerProcess(argv, f"fleet-{engine}-{size}") as server:
        started = time.monotonic()
        wait_port(zport, 120.0, server.proc)
        wait_port(aport, 120.0, server.proc)
        wait_port(mbase + size - 1, 120.0, server.proc)
        ports_open = time.monotonic() - started
        opcua = "--opcua-endpoint" in argv
        opcua_ready = (wait_log(server, "opcua: ready", 900.0) if opcua else started) - started
        settle(server.pid)
        # at rest, nobody asking: the CPU, the memory and the threads of the whole fleet
        c0, t0 = _children_cpu(server.pid), time.monotonic()
        time.sleep(10.0)
        rest_cpu = 100 * (_children_cpu(server.pid) - c0) / (time.monotonic() - t0)
        rss_mib, threads = rss_threads(server.pid)
        clients = Clients(ports, machines)
        try:
            c0, t0 = _children_cpu(server.pid), time.monotonic()
            end = time.monotonic() + seconds
            rounds = 0
            while time.monotonic() < end or rounds == 0:
                for i in range(size):
                    for via in ("ads", "modbus", "zenoh"):
                        try:
                            lat.append(clients.ask(i, via))
                        except Exception:
                            failures += 1
                rounds += 1
            cpu = 100 * (_children_cpu(server.pid) - c0) / (time.monotonic() - t0)
        finally:
            clients.close()
    s = summary_us(lat)
    return {
        "size": size,
        "rounds": rounds,
        "failures": failures,
        "p50_ms": s["p50"] / 1000,
        "p99_ms": s["p99"] / 1000,
        "cpu": cpu,
        "serves": failures == 0 and s["p99"] <= 10_000,
        "ports_open_s": ports_open,
        "opcua_ready_s": opcua_ready,
        "rest_cpu": rest_cpu,
        "rss_mib": rss_mib,
        "threads": threads,
    }


def wait_log(server: ServerProcess, text: str, limit: float) -> float:
    """When `text` appeared in the server's output (monotonic seconds; the server says
    when its OPC UA address space is built, which takes minutes for hundreds of
    machines); now when it does not within `limit`."""
    end = time.monotonic() + limit
    while time.monotonic() < end and text not in server.log_text():
        time.sleep(0.5)
    return time.monotonic()


def rss_threads(pid: int) -> tuple[float, int]:
    """The server's resident memory (MiB) and its threads."""
    status = Path(f"/proc/{pid}/status").read_text().splitlines()
    fields = dict(line.split(":", 1) for line in status if ":" in line)
    return int(fields["VmRSS"].split()[0]) / 1024, int(fields["Threads"])


def netid(i: int) -> str:
    """The i-th fleet machine's AMS NetId from the default 127.0.0.1.1.1: the fifth byte
    raised by i, carrying into the fourth (README *Fleets*)."""
    high, low = divmod(256 + 1 + i, 256)
    return f"127.0.0.{high}.{low}.1"


def settle(pid: int, limit: float = 60.0) -> None:
    """Wait until a starting fleet has settled: the ports are open before every machine's
    interfaces have finished starting (a large fleet takes seconds more), so wait for a
    second in which the server used less than half a core (at most `limit` seconds)."""
    end = time.monotonic() + limit
    while time.monotonic() < end:
        c0, t0 = _children_cpu(pid), time.monotonic()
        time.sleep(1.0)
        if (_children_cpu(pid) - c0) / (time.monotonic() - t0) < 0.5:
            return


def largest(engine: str, sizes: list[int], seconds: float) -> list[dict[str, Any]]:
    rows = []
    for n in sizes:
        r = fleet(engine, n, seconds)
        rows.append(r)
        print(f"  {engine} fleet of {n}: {r}", flush=True)
        if not r["serves"]:
            break
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short windows, fewer fleet sizes")
    ap.add_argument("--sizes", help="fleet sizes of the exact engine, comma-separated")
    ap.add_argument("--fleets-only", action="store_true", help="skip the latency part")
    ap.add_argument("--out", help="also write the Markdown here")
    args = ap.parse_args()
    seconds = 4.0 if args.quick else 15.0
    prog = Path(os.environ.get("TMPDIR", "/tmp")) / f"geo-bench-engine-{os.getpid()}.nc"
    prog.write_text(MOVING, encoding="utf-8")
    md = "### Added request latency from catch-up (one default machine, 1 ms)\n\n"
    rows = []
    failures = 0
    try:
        cases = [] if args.fleets_only else [("idle", None), ("all axes moving", prog)]
        for case, program in cases:
            res = {e: latency(e, program, seconds) for e in ("exact", "punctual")}
            failures += sum(int(res[e]["failed"]["n"]) for e in res)
            cu = res["exact"]["catch-up"]
            rows.append(
                [f"{case}, catch-up in the server", f"{cu['p50']:.0f} / {cu['p99']:.0f}", "", ""]
            )
            rows.append(
                [
                    f"{case}, server CPU while asked (% of one core)",
                    f"{res['exact']['cpu']['p50']:.1f}",
                    f"{res['punctual']['cpu']['p50']:.1f}",
                    "",
                ]
            )
            for via in ("ads", "modbus", "zenoh"):
                ex, pu = res["exact"][via], res["punctual"][via]
                rows.append(
                    [
                        f"{case}, {via}",
                        f"{ex['p50']:.0f} / {ex['p99']:.0f}",
                        f"{pu['p50']:.0f} / {pu['p99']:.0f}",
                        f"{ex['p50'] - pu['p50']:+.0f} / {ex['p99'] - pu['p99']:+.0f}",
                    ]
                )
    finally:
        prog.unlink(missing_ok=True)
    md += table(
        ["case, transport", "exact p50 / p99 µs", "punctual p50 / p99 µs", "added p50 / p99 µs"],
        rows,
    )
    md += f"\nUnanswered requests: {failures}.\n"
    md += (
        "\nRequests 0–10 ms apart (the exact engine catches up before each answer); the "
        "exact engine's cycle runs on a thread, the punctual engine's in its own process "
        "(each engine's default). *Catch-up in the server*: the time `sync()` took before "
        "an answer, timed in the server (its `sync_p50_us` / `sync_p99_us` status).\n\n"
    )
    sizes = [1, 10, 50, 100, 200, 300, 500] if not args.quick else [1, 10, 50]
    if args.sizes:
        sizes = [int(x) for x in args.sizes.split(",")]
    window = 5.0 if args.quick else 8.0
    fleets = {"exact": largest("exact", sizes, window)}
    if not args.sizes:
        fleets["punctual"] = largest("punctual", [1, 2, 4, 8], window)
    md += "### Fleets of default machines at rest (1 ms, one process)\n\n"
    frows = [
        [
            engine,
            r["size"],
            r["rounds"],
            r["failures"],
            f"{r['p50_ms']:.2f}",
            f"{r['p99_ms']:.2f}",
            f"{r['cpu']:.0f}",
            "yes" if r["serves"] else "no",
            f"{r['rest_cpu']:.1f}",
            f"{r['rss_mib']:.0f}",
            r["threads"],
            f"{r['ports_open_s']:.0f} / {r['opcua_ready_s']:.0f}",
        ]
        for engine, rs in fleets.items()
        for r in rs
    ]
    md += table(
        [
            "engine",
            "machines",
            "rounds",
            "unanswered",
            "p50 ms",
            "p99 ms",
            "server CPU %",
            "every machine, every transport, p99 ≤ 10 ms",
            "at rest, nobody asking: CPU %",
            "RSS MiB",
            "threads",
            "ports open / OPC UA ready, s",
        ],
        frows,
    )
    best = {e: max((r["size"] for r in rs if r["serves"]), default=0) for e, rs in fleets.items()}
    md += "\nLargest fleet served: " + ", ".join(f"{e} engine {n}" for e, n in best.items())
    md += ".\n"
    emit(md, args.out)


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
