"""Fleet isolation benchmark (issue 30 item 5, docs/design.md §13.1): what one client's
load on some machines of a fleet costs every other machine.

Against a fresh `geo-server run --fleet-size N --homed` (exact engine, 1 ms cycle) in a
subprocess, three phases, each timing request round trips to machines 1, N/2 and N on
ADS (a raw AMS/TCP Read of 4 bytes, one connection per machine) and Modbus (FC 3 of 2
registers on the machine's own port), every request with a `--timeout` (a request past
it counts as timed out and the connection is opened again):

1. **quiet**: nothing else runs;
2. **notifications**: one connection registers an on-change notification (SERVERONCHA,
   cycle time 100 ns: every cycle, the pyads default) on a constant object
   (TEMPC::offset_0 of axis 1) at every machine — `--per-machine` of them each, at most
   as many as the server grants (0x716 beyond); printed: granted, refused, the slowest
   registration; then the probes, and `cnc/fleet/status` (overruns, stalled machines,
   and what the server reports about late sampling, when it does);
3. **flood on machine 1** (notifications gone): `--flood-connections` connections keep
   `--flood-depth` ADS Reads each in flight to machine 1; the probes run against the
   other machines meanwhile;
4. `--rounds` more pairs of a quiet phase and a flood, alternated (slow drifts of a
   shared host then touch both alike): the other machines' round trips pooled over the
   rounds, both interfaces and machines, and the ratio of their p99 under the flood to
   the quiet one (the issue's target: at most 2).

    python bench/fleet_isolation.py [--quick] [--machines N] [--out FILE] [--pythonpath DIR]

`--pythonpath DIR` runs the server from another source tree (e.g. the code before a
change, exported with `git archive`), for before/after figures.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing
import os
import socket
import struct
import threading
import time
from typing import Any

from common import (
    HOST,
    PYTHON,
    ServerProcess,
    address,
    emit,
    free_ports,
    free_range,
    opcua_argv,
    summary_us,
    table,
    wait_port,
    zenoh_session,
)

from geo_server.dictionary import GEO_AMS_PORT
from geo_server.fleetfile import netid_at
from geo_server.transports.ads import codec
from geo_server.transports.ads.codec import AmsAddr, AmsPacket, Command, TransMode

#: a constant object (unless written): TEMPC::offset_0 of axis 1
OBJ = address("TEMPC::offset_0", 1)
IG, IO, MB_REGISTER = OBJ.index_group, OBJ.index_offset, OBJ.register
BASE_NETID = "127.0.0.1.1.1"


class RawAds:
    """One AMS/TCP connection: synchronous requests, notification frames counted."""

    def __init__(self, port: int, source: str, timeout: float) -> None:
        self.port, self.source, self.timeout = port, source, timeout
        self.invoke = 0
        self.notifications = 0
        self._open()

    def _open(self) -> None:
        self.sock = socket.create_connection((HOST, self.port), timeout=self.timeout)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.framer = codec.Framer()
        self.pending: list[AmsPacket] = []

    def reopen(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()
        self._open()

    def send(self, netid: str, command: int, data: bytes) -> int:
        self.invoke = (self.invoke + 1) & 0xFFFF_FFFF
        frame = codec.request_frame(
            AmsAddr(netid, GEO_AMS_PORT), AmsAddr(self.source, 30000), command, data, self.invoke
        )
        self.sock.sendall(frame)
        return self.invoke

    def answer(self, invoke: int) -> AmsPacket:
        end = time.monotonic() + self.timeout
        while True:
            for p in self.pending:
                if p.header.invoke_id == invoke:
                    self.pending.remove(p)
                    return p
            left = end - time.monotonic()
            if left <= 0:
                raise TimeoutError
            self.sock.settimeout(left)
            data = self.sock.recv(1 << 16)
            if not data:
                raise ConnectionError("closed")
            for ev in self.framer.feed(data):
                if not isinstance(ev, AmsPacket):
                    continue
                if ev.header.command == Command.DEVICE_NOTIFICATION:
                    self.notifications += 1
                else:
                    self.pending.append(ev)

    def request(self, netid: str, command: int, data: bytes) -> AmsPacket:
        return self.answer(self.send(netid, command, data))

    def read(self, netid: str) -> None:
        p = self.request(netid, Command.READ, codec.read_request(IG, IO, 4))
        if struct.unpack_from("<I", p.data)[0]:
            raise RuntimeError(f"ADS error 0x{struct.unpack_from('<I', p.data)[0]:X}")

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()


class RawModbus:
    """Modbus TCP FC 3 over a plain socket."""

    def __init__(self, port: int, timeout: float) -> None:
        self.port, self.timeout, self.tid = port, timeout, 0
        self._open()

    def _open(self) -> None:
        self.sock = socket.create_connection((HOST, self.port), timeout=self.timeout)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def reopen(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()
        self._open()

    def read(self) -> None:
        self.tid = (self.tid + 1) & 0xFFFF
        self.sock.settimeout(self.timeout)
        self.sock.sendall(struct.pack(">HHHBBHH", self.tid, 0, 6, 1, 3, MB_REGISTER, 2))
        need, buf = 13, b""
        while len(buf) < need:
            chunk = self.sock.recv(need - len(buf))
            if not chunk:
                raise ConnectionError("closed")
            buf += chunk
        if buf[7] != 3:
            raise RuntimeError(f"Modbus exception {buf[8]}")

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()


def probe(
    targets: list[int],
    ads_port: int,
    mb_base: int,
    seconds: float,
    timeout: float,
    pooled: dict[int, list[float]] | None = None,
    control: int | None = None,
) -> dict[str, Any]:
    """Round trips to each target machine (1-based) on ADS and Modbus, interleaved, for
    `seconds`: per (interface, machine) the summary and the timeouts; every round trip
    (s) also appended to `pooled[machine]`. `control`: the port of a bare ADS responder
    (bench/bare.py) read in the same rounds, pooled as machine 0: what the host alone
    does to a round trip meanwhile."""
    out: dict[str, Any] = {}
    clients: list[tuple[str, int, Any, Any]] = []
    if control is not None:
        bare = RawAds(control, "10.77.0.1.1.1", timeout)
        clients.append(("bare ADS", 0, bare, lambda a=bare: a.read("127.0.0.1.1.1")))
    for m in targets:
        ads = RawAds(ads_port, f"10.77.{m % 250}.1.1.1", timeout)
        netid = netid_at(BASE_NETID, m - 1)
        clients.append(("ADS", m, ads, lambda a=ads, n=netid: a.read(n)))
        mb = RawModbus(mb_base + m - 1, timeout)
        clients.append(("Modbus", m, mb, mb.read))
    rtts: dict[tuple[str, int], list[float]] = {(k, m): [] for k, m, _c, _f in clients}
    fails: dict[tuple[str, int], int] = {(k, m): 0 for k, m, _c, _f in clients}
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for kind, m, conn, call in clients:
            t0 = time.perf_counter()
            try:
                call()
                rtts[(kind, m)].append(time.perf_counter() - t0)
            except (TimeoutError, OSError, ConnectionError, RuntimeError):
                fails[(kind, m)] += 1
                rtts[(kind, m)].append(time.perf_counter() - t0)
                with contextlib.suppress(OSError):
                    conn.reopen()
            time.sleep(0.002)
    for _k, _m, conn, _f in clients:
        conn.close()
    for key, values in rtts.items():
        if pooled is not None:
            pooled.setdefault(key[1], []).extend(values)
        us = [v * 1e6 for v in values]
        out[f"{key[0]} m{key[1]}"] = {**summary_us(us), "timeouts": fails[key]}
    return out


def fleet_status(session: Any) -> dict[str, Any]:
    for reply in session.get("cnc/fleet/status", timeout=5.0):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    return {}


def register_all(
    port: int, machines: int, per_machine: int, timeout: float, budget: float
) -> tuple[RawAds, dict[str, Any]]:
    """One connection, `per_machine` on-change notifications at every machine (for at
    most `budget` seconds: a collapsing server takes seconds per registration)."""
    conn = RawAds(port, "10.88.0.1.1.1", timeout)
    granted = refused = other = 0
    slowest = 0.0
    data = codec.add_notification_request(IG, IO, 4, TransMode.SERVERONCHA, 0, 1)
    t_end = time.monotonic() + budget
    for m in range(machines):
        netid = netid_at(BASE_NETID, m)
        if time.monotonic() > t_end:
            break
        for _ in range(per_machine):
            t0 = time.perf_counter()
            try:
                p = conn.request(netid, Command.ADD_DEVICE_NOTIFICATION, data)
            except (TimeoutError, OSError, ConnectionError):
                other += 1
                slowest = max(slowest, time.perf_counter() - t0)
                continue
            slowest = max(slowest, time.perf_counter() - t0)
            code, _h = codec.parse_add_notification_response(p.data)
            if code == 0:
                granted += 1
            elif code == 0x716:
                refused += 1
            else:
                other += 1
    return conn, {
        "machines_reached": m + 1,
        "granted": granted,
        "refused": refused,
        "failed": other,
        "slowest_ms": round(slowest * 1000, 1),
    }


def flood(
    port: int, netid: str, connections: int, depth: int, stop: Any, done: Any, nice: int = 0
) -> None:
    """Keep `depth` Reads in flight on each of `connections` connections to `netid`
    until `stop` is set; the answers counted in `done`. Runs in a process of its own:
    in the probing process its threads would hold the probe's interpreter lock for
    whole switch intervals (5 ms), which measured the client, not the server."""
    if nice:
        os.nice(nice)
    count = [0]
    lock = threading.Lock()

    def one(i: int) -> None:
        try:
            s = socket.create_connection((HOST, port), timeout=5)
        except OSError:
            return
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        framer = codec.Framer()
        src = AmsAddr(f"10.99.{i}.1.1.1", 30000)
        frame = codec.request_frame(
            AmsAddr(netid, GEO_AMS_PORT), src, Command.READ, codec.read_request(IG, IO, 4), 1
        )
        with contextlib.suppress(OSError):
            s.sendall(frame * depth)
            while not stop.is_set():
                data = s.recv(1 << 16)
                if not data:
                    break
                n = sum(isinstance(ev, AmsPacket) for ev in framer.feed(data))
                with lock:
                    count[0] += n
                if n:
                    s.sendall(frame * n)
        s.close()

    threads = [threading.Thread(target=one, args=(i,), daemon=True) for i in range(connections)]
    for t in threads:
        t.start()
    stop.wait()
    for t in threads:
        t.join(5)
    done.value = count[0]


def start_flood(args: argparse.Namespace, port: int) -> tuple[Any, Any, Any]:
    """The flooding client's process, started; (process, stop event, answers)."""
    ctx = multiprocessing.get_context("spawn")
    stop, answered = ctx.Event(), ctx.Value("q", 0)
    flooder = ctx.Process(
        target=flood,
        args=(
            port,
            BASE_NETID,
            args.flood_connections,
            args.flood_depth,
            stop,
            answered,
            args.flood_nice,
        ),
        daemon=True,
    )
    flooder.start()
    return flooder, stop, answered


def alternate(
    args: argparse.Namespace, others: list[int], aport: int, mbase: int
) -> tuple[list[list[Any]], list[str]]:
    """`--rounds` pairs of a quiet phase and a flood on machine 1, each other machine's
    round trips (ADS and Modbus) pooled over the rounds: the summary rows and a line with
    each machine's p99 ratio, flood to quiet."""
    quiet: dict[int, list[float]] = {}
    flooded: dict[int, list[float]] = {}
    answers = []
    for _ in range(args.rounds):
        probe(others, aport, mbase, args.seconds, args.timeout, quiet)
        flooder, stop, answered = start_flood(args, aport)
        time.sleep(1.0)
        probe(others, aport, mbase, args.seconds, args.timeout, flooded)
        stop.set()
        flooder.join(10)
        answers.append(answered.value)
        time.sleep(1.0)
    out = []
    ratios = []
    for m in others:
        p99 = []
        for phase, values in (("quiet", quiet[m]), ("flood on m1", flooded[m])):
            v = summary_us([x * 1e6 for x in values])
            p99.append(v["p99"] / 1000)
            out.append(
                [
                    f"{args.rounds} rounds: {phase}",
                    f"m{m}, ADS and Modbus",
                    v["n"],
                    v["p50"] / 1000,
                    v["p99"] / 1000,
                    v["max"] / 1000,
                    "",
                ]
            )
        ratios.append(f"m{m} {p99[0]:.1f} -> {p99[1]:.1f} ms ({p99[1] / p99[0]:.2f}x)")
    line = (
        f"alternating quiet and flood, {args.rounds} rounds, p99 of the other machines: "
        f"{', '.join(ratios)}; reads answered on machine 1 per flood: {answers}; "
        f"load average {os.getloadavg()[0]:.1f}"
    )
    return out, [line]


def rows(phase: str, result: dict[str, Any]) -> list[list[Any]]:
    return [
        [phase, key, v["n"], v["p50"] / 1000, v["p99"] / 1000, v["max"] / 1000, v["timeouts"]]
        for key, v in result.items()
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="3 machines, short phases")
    ap.add_argument("--machines", type=int, default=100)
    ap.add_argument("--per-machine", type=int, default=1)
    ap.add_argument("--seconds", type=float, default=6.0, help="probe time per phase")
    ap.add_argument("--timeout", type=float, default=5.0, help="per request (s)")
    ap.add_argument("--flood-connections", type=int, default=4)
    ap.add_argument("--flood-depth", type=int, default=64)
    ap.add_argument(
        "--flood-nice",
        type=int,
        default=0,
        help="run the flooding client at this niceness (on a 2-core host the client's own "
        "CPU otherwise competes with the probes: an attacker on another host does not)",
    )
    ap.add_argument("--register-seconds", type=float, default=120.0)
    ap.add_argument(
        "--rounds",
        type=int,
        default=2,
        help="pairs of a quiet phase and a flood after the phases above (0: none)",
    )
    ap.add_argument("--pythonpath", help="run the server from this source tree")
    ap.add_argument("--out", help="write the Markdown here too")
    args = ap.parse_args()
    if args.quick:
        args.machines, args.seconds, args.rounds = 3, 1.0, min(args.rounds, 1)
    n = args.machines
    zport, aport = free_ports(2)
    mbase = free_range(n)
    env = {"PYTHONPATH": args.pythonpath} if args.pythonpath else {}
    argv = [
        str(os.path.join(os.path.dirname(PYTHON), "geo-server")),
        "run",
        "--fleet-size",
        str(n),
        "--homed",
        "--zenoh-listen",
        f"tcp/{HOST}:{zport}",
        "--ads-port",
        str(aport),
        "--ads-udp-port",
        "0",
        "--modbus-port",
        str(mbase),
        "--status-period",
        "1",
        *opcua_argv(args.pythonpath or ""),
    ]
    targets = sorted({1, max(1, n // 2), n})
    out_rows: list[list[Any]] = []
    notes: list[str] = []
    with ServerProcess(argv, "fleet-isolation", env=env) as server:
        wait_port(aport, 120.0, server.proc)
        wait_port(mbase + n - 1, 120.0, server.proc)
        session = zenoh_session(f"tcp/{HOST}:{zport}")
        try:
            end = time.monotonic() + 120
            while time.monotonic() < end and "fleet:" not in server.log_text():
                time.sleep(0.2)
            # the OPC UA address space of every machine is built in the background after
            # the start (seconds for a hundred): "quiet" measured that build before
            while "--opcua-endpoint" in argv and time.monotonic() < end:
                if "opcua: ready" in server.log_text():
                    break
                time.sleep(0.2)
            time.sleep(1.0)
            quiet = probe(targets, aport, mbase, args.seconds, args.timeout)
            out_rows += rows("quiet", quiet)
            print("quiet done", flush=True)
            t_reg = time.monotonic()
            conn, reg = register_all(
                aport, n, args.per_machine, args.timeout, args.register_seconds
            )
            reg["took_s"] = round(time.monotonic() - t_reg, 1)
            notes.append(f"registrations: {json.dumps(reg)}")
            print(notes[-1], flush=True)
            try:
                time.sleep(1.0)
                loaded = probe(targets, aport, mbase, args.seconds, args.timeout)
                out_rows += rows("notifications", loaded)
                st = fleet_status(session)
                extra = {
                    k: st.get(k) for k in ("overruns", "stalled", "loop_lag_ms", "samples_late")
                }
                notes.append(f"fleet status with notifications: {json.dumps(extra)}")
                print(notes[-1], flush=True)
            finally:
                conn.close()
            time.sleep(1.0)
            after = probe(targets, aport, mbase, args.seconds, args.timeout)
            out_rows += rows("client gone", after)
            print("after done", flush=True)
            flooder, stop, answered = start_flood(args, aport)
            time.sleep(1.0)
            others = [m for m in targets if m != 1] or [1]
            flooded = probe(others, aport, mbase, args.seconds, args.timeout)
            st = fleet_status(session)
            stop.set()
            flooder.join(10)
            out_rows += rows("flood on m1", flooded)
            notes.append(f"flood: {answered.value} reads answered on machine 1")
            extra = {k: st.get(k) for k in ("loop_lag_ms", "throttled", "starved")}
            notes.append(f"fleet status during the flood: {json.dumps(extra)}")
            time.sleep(1.0)
            if args.rounds:
                more, lines = alternate(args, others, aport, mbase)
                out_rows += more
                notes += lines
                print(lines[-1], flush=True)
        finally:
            session.close()
    md = (
        f"### Fleet isolation (`bench/fleet_isolation.py`), {n} machines\n\n"
        + table(
            ["phase", "interface, machine", "n", "p50 ms", "p99 ms", "max ms", "timeouts"],
            out_rows,
            "llrrrrr",
        )
        + "\n"
        + "".join(f"- {line}\n" for line in notes)
    )
    emit(md, args.out)


if __name__ == "__main__":
    main()
