"""What an OPC UA attacker costs the other interfaces (issue 44; docs/security.md *OPC UA*).

Against a fresh `geo-server run --homed` (one machine, `--machines 1`) or a fleet of
`--machines N` (`--fleet-size N`), each attack of issue 44 runs from a process of its own
against machine 1 over OPC UA while the probes time ADS Reads (4 bytes, raw AMS/TCP) and
Modbus FC 3 reads (2 registers) — of machine 1 alone, or of machines 2 and N in a fleet —
alternated with quiet phases (`--rounds` pairs, so slow drifts of a shared host touch
both alike). Printed per attack: the probes' p50/p99 quiet and under attack, their ratio
(the issue's target: at most 2), the requests the attacker got answered, the server's RSS
before and after, and what a legitimate OPC UA client got meanwhile: it reads one value
every 0.1 s (asyncua's client, its keep-alive probe on) — its slowest Read and whether
it kept its connection.

    python bench/opcua_attacks.py [--machines N] [--seconds S] [--rounds R] [--out FILE]
        [--server-slice-us US] [--probe-slice-us US]

The server asks Linux for a short scheduler slice (`geo-server run --time-slice-us`,
geo_server/timeslice.py), and so do the probes and the bare responder here: on a host
this small the attacker's process shares the cores with them, and a probe that waits
out the attacker's turn before it reads its answer times its own wake-up, not the
server (a client on another host does not). The attacker and the legitimate client keep
the kernel's slice, each in a session of its own (`_apart_from_the_probes`).
`--server-slice-us 0 --probe-slice-us 0`: everyone the kernel's.

OPC UA is served from a process of its own (transports/opcua/apart.py); the RSS shown is
the server's, not that one's. (Until it was, `--apart` served OPC UA from a second
`geo-server run` to measure what that would give: docs/benchmarks.md.)

The attacks (each within or past the server's limits, as a hostile client would):

- `read-flood`: 4 connections keep 8 Reads each of `MaxNodesPerRead` values in flight;
- `browse-flood`: 4 connections keep 8 Browses each of `MaxNodesPerBrowse` nodes
  (the Objects folder, both directions, every field) in flight;
- `bombs`: 4 connections keep Reads of 100 000 values and TranslateBrowsePaths of
  40 000 elements in flight (refused: BadTooManyOperations);
- `unread`: a client that stops reading and sends 60 Reads of the standard's type
  dictionary (210 kB each): paused, then closed;
- `items`: one session with 1000 monitored items on a value that changes every cycle,
  published every 10 ms.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import multiprocessing
import os
import sys
import time
from pathlib import Path
from typing import Any

from common import (
    ServerProcess,
    emit,
    free_ports,
    free_range,
    geo_server_argv,
    rss_kib,
    summary_us,
    table,
    wait_port,
)
from fleet_isolation import probe

from geo_server import timeslice

ATTACKS = ("read-flood", "browse-flood", "bombs", "unread", "items")


async def _attack(kind: str, url: str, machine: str, stop: Any, done: Any) -> None:
    from asyncua import Client, ua

    from geo_server.transports.opcua.operations import OPERATION_LIMITS
    from geo_server.transports.opcua.space import NAMESPACE_URI

    def value(node: Any) -> Any:
        rv = ua.ReadValueId()
        rv.NodeId, rv.AttributeId = node, ua.AttributeIds.Value
        return rv

    # (no keep-alive probe: asyncua's client gives its connection up when its probe, queued
    # behind its own flood, waits past a second, and the flood would end after seconds)
    n = 1 if kind in ("unread", "items") else 4
    clients = [Client(url, timeout=30, watchdog_intervall=3600.0) for _ in range(n)]
    for c in clients:
        await c.connect()
    ns = await clients[0].get_namespace_index(NAMESPACE_URI)
    tempc = ua.NodeId(f"{machine}/Axes/X/TEMPC/coefficient", ns)
    count = [0]
    errors: dict[str, int] = {}

    async def keep(c: Any, make: Any, depth: int) -> None:
        async def one() -> None:
            while not stop.is_set():
                try:
                    await make(c)
                except Exception as exc:  # (refused bombs; a closed connection)
                    name = type(exc).__name__
                    errors[name] = errors.get(name, 0) + 1
                    if name not in ("BadTooManyOperations", "BadRequestTooLarge"):
                        await asyncio.sleep(0.01)
                    continue
                count[0] += 1

        await asyncio.gather(*(one() for _ in range(depth)))

    if kind == "read-flood":
        read = ua.ReadParameters(NodesToRead=[value(tempc)] * OPERATION_LIMITS["MaxNodesPerRead"])
        jobs = [keep(c, lambda c: c.uaclient.read(read), 8) for c in clients]
    elif kind == "browse-flood":
        desc = ua.BrowseDescription(
            NodeId=ua.NodeId(ua.ObjectIds.ObjectsFolder),
            BrowseDirection=ua.BrowseDirection.Both,
            ResultMask=63,
        )
        browse = ua.BrowseParameters(NodesToBrowse=[desc] * OPERATION_LIMITS["MaxNodesPerBrowse"])
        jobs = [keep(c, lambda c: c.uaclient.browse(browse), 8) for c in clients]
    elif kind == "bombs":
        clock = value(ua.NodeId(ua.ObjectIds.Server_ServerStatus_CurrentTime))
        bomb = ua.ReadParameters(NodesToRead=[clock] * 100_000)
        element = ua.RelativePathElement(
            ReferenceTypeId=ua.NodeId(33), TargetName=ua.QualifiedName("Server", 0)
        )
        path = ua.BrowsePath(
            StartingNode=ua.NodeId(84), RelativePath=ua.RelativePath(Elements=[element] * 40_000)
        )
        jobs = [keep(c, lambda c: c.uaclient.read(bomb), 2) for c in clients]
        jobs += [
            keep(c, lambda c: c.uaclient.translate_browsepaths_to_nodeids([path]), 2)
            for c in clients
        ]
    elif kind == "unread":
        c = clients[0]
        c.uaclient.protocol.transport.pause_reading()
        dictionary = value(ua.NodeId(ua.ObjectIds.OpcUa_BinarySchema))
        params = ua.ReadParameters(NodesToRead=[dictionary])
        pending = [asyncio.ensure_future(c.uaclient.read(params)) for _ in range(60)]
        while not stop.is_set():
            await asyncio.sleep(0.1)
        for p in pending:
            p.cancel()
        jobs = []
    else:  # items
        ticking = ua.NodeId(f"{machine}/SIM/cycle_count", ns)

        class Count:
            def datachange_notification(self, *_a: Any) -> None:
                count[0] += 1

        sub = await clients[0].create_subscription(10, Count())
        node = clients[0].get_node(ticking)
        per_call = OPERATION_LIMITS["MaxMonitoredItemsPerCall"]
        for _ in range(1000 // per_call):
            await sub.subscribe_data_change([node] * per_call, sampling_interval=0)
        while not stop.is_set():
            await asyncio.sleep(0.1)
        jobs = []

    async def until_stopped() -> None:
        while not stop.is_set():
            await asyncio.sleep(0.05)

    await asyncio.wait(
        [asyncio.ensure_future(j) for j in jobs] + [asyncio.ensure_future(until_stopped())],
        return_when=asyncio.FIRST_COMPLETED,
    )
    done.value = count[0]
    if errors:
        print(f"{kind}: errors {errors}", flush=True)
    for c in clients:
        with contextlib.suppress(Exception):
            c.uaclient.disconnect_socket()


async def _legit(url: str, machine: str, stop: Any, slowest: Any, lost: Any) -> None:
    from asyncua import Client, ua

    from geo_server.transports.opcua.space import NAMESPACE_URI

    async with Client(url, timeout=10) as c:  # (asyncua's defaults: it probes every second)
        ns = await c.get_namespace_index(NAMESPACE_URI)
        node = c.get_node(ua.NodeId(f"{machine}/Axes/X/TEMPC/coefficient", ns))
        while not stop.is_set():
            t0 = time.perf_counter()
            try:
                await node.read_value()
            except Exception:  # (its connection given up: what the attack cost it)
                lost.value = 1
                return
            slowest.value = max(slowest.value, time.perf_counter() - t0)
            await asyncio.sleep(0.1)


def _apart_from_the_probes() -> None:
    """A client process as one started elsewhere on the host is: at the kernel's slice
    (not the probes' it was started by) and in a session of its own (with Linux's
    autogroups, a process of the probes' session shares their group's processor share,
    and its load would delay the probes' own wake-ups as no other client's could)."""
    timeslice.request(0)
    if hasattr(os, "setsid"):
        os.setsid()


def legit(url: str, machine: str, stop: Any, slowest: Any, lost: Any) -> None:
    """A legitimate OPC UA client beside the attack, in a process of its own."""
    import logging

    _apart_from_the_probes()
    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    asyncio.run(_legit(url, machine, stop, slowest, lost))


def attack(kind: str, url: str, machine: str, stop: Any, done: Any, nice: int) -> None:
    """The attacker's process (its CPU would otherwise compete with the probes'
    interpreter lock: that measured the client, not the server)."""
    import logging

    _apart_from_the_probes()
    if nice:
        os.nice(nice)

    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    asyncio.run(_attack(kind, url, machine, stop, done))


def run_attacks(
    args: argparse.Namespace,
    url: str,
    machine: str,
    targets: list[int],
    ports: tuple[int, int, int],
    pid: int,
) -> tuple[list[list[Any]], list[str]]:
    """Each attack, alternated with quiet phases; `ports`: geo-server's ADS port, its
    first Modbus port, and the bare ADS responder's (the control)."""
    aport, mbase, control = ports
    ctx = multiprocessing.get_context("spawn")
    out: list[list[Any]] = []
    notes: list[str] = []
    for kind in args.attacks:
        quiet: dict[int, list[float]] = {}
        attacked: dict[int, list[float]] = {}
        answered = []
        rss = [rss_kib(pid)["VmRSS"]]
        slowest, lost = ctx.Value("d", 0.0), ctx.Value("i", 0)
        for _ in range(args.rounds):
            probe(targets, aport, mbase, args.seconds, args.timeout, quiet, control)
            stop, done = ctx.Event(), ctx.Value("q", 0)
            p = ctx.Process(
                target=attack, args=(kind, url, machine, stop, done, args.nice), daemon=True
            )
            client = ctx.Process(
                target=legit, args=(url, machine, stop, slowest, lost), daemon=True
            )
            client.start()
            p.start()
            time.sleep(1.5)  # (connected, attacking)
            probe(targets, aport, mbase, args.seconds, args.timeout, attacked, control)
            rss.append(rss_kib(pid)["VmRSS"])
            stop.set()
            for proc in (p, client):
                proc.join(15)
                if proc.is_alive():
                    proc.kill()
            answered.append(done.value)
            time.sleep(1.0)
        q = summary_us([x * 1e6 for m, v in quiet.items() if m for x in v])
        a = summary_us([x * 1e6 for m, v in attacked.items() if m for x in v])
        # the host's own share of the rise: a bare responder's, probed alongside
        bq, ba = (summary_us([x * 1e6 for x in d[0]])["p99"] for d in (quiet, attacked))
        out.append(
            [
                kind,
                q["n"],
                q["p50"] / 1000,
                q["p99"] / 1000,
                a["n"],
                a["p50"] / 1000,
                a["p99"] / 1000,
                round(a["p99"] / q["p99"], 2),
                f"{bq / 1000:.2f} -> {ba / 1000:.2f} ({ba / bq:.2f})",
                round((a["p99"] / q["p99"]) / (ba / bq), 2),
                answered,
                f"{slowest.value * 1000:.0f}" + (" (dropped)" if lost.value else ""),
                f"{rss[0] // 1024} -> {max(rss) // 1024}",
            ]
        )
        print(f"{kind}: p99 {q['p99'] / 1000:.2f} -> {a['p99'] / 1000:.2f} ms", flush=True)
    notes.append(f"load average after: {os.getloadavg()[0]:.1f}")
    return out, notes


def stop_during_attack(url: str, machine: str, server: ServerProcess) -> str:
    """SIGTERM while a client that does not read keeps its requests in flight (issue
    44: within 2 s): how long the server took to exit."""
    ctx = multiprocessing.get_context("spawn")
    stop, done = ctx.Event(), ctx.Value("q", 0)
    p = ctx.Process(target=attack, args=("unread", url, machine, stop, done, 0), daemon=True)
    p.start()
    time.sleep(1.5)  # (connected, its answers backed up)
    code = server.stop(timeout=30.0)
    stop.set()
    p.join(15)
    if p.is_alive():
        p.kill()
    took = server.stop_seconds or 0.0
    return f"SIGTERM during an attack by a client that does not read: exit {code}, {took:.2f} s"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--machines", type=int, default=1, help="1: one machine; N: a fleet")
    ap.add_argument("--seconds", type=float, default=5.0, help="probe time per phase")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--timeout", type=float, default=5.0)
    ap.add_argument("--attacks", nargs="+", default=list(ATTACKS), choices=ATTACKS)
    ap.add_argument(
        "--nice",
        type=int,
        default=0,
        help="run the attacker at this niceness (on a 2-core host its own CPU otherwise "
        "competes with the probes and the server: an attacker on another host does not)",
    )
    ap.add_argument(
        "--probe-slice-us",
        type=int,
        default=timeslice.DEFAULT_US,
        help="the scheduler slice the probes and the bare responder ask for, as geo-server "
        "run does (so each times the server's answer, not its own wake-up behind the "
        "attacker's turn); 0: the kernel's",
    )
    ap.add_argument(
        "--server-slice-us",
        type=int,
        default=timeslice.DEFAULT_US,
        help="geo-server run's --time-slice-us (0: the kernel's, as before it asked)",
    )
    ap.add_argument("--out", help="write the Markdown here too")
    args = ap.parse_args()
    timeslice.request(args.probe_slice_us)
    n = args.machines
    zport, aport = free_ports(2)
    mbase = free_range(n)
    ports = {"zenoh": zport, "ads": aport, "modbus": mbase}
    fleet = ["--fleet-size", str(n)] if n > 1 else []
    # the exact engine, geo-server run's default, as the figures in docs/benchmarks.md
    argv = geo_server_argv(
        1.0,
        ports,
        engine="exact",
        extra=[*fleet, "--ads-udp-port", "0", "--time-slice-us", str(args.server_slice_us)],
    )
    url = argv[argv.index("--opcua-endpoint") + 1]
    machine = "local-1" if n > 1 else "local"
    targets = [1] if n == 1 else sorted({2, n})
    (control,) = free_ports(1)
    bare = [sys.executable, str(Path(__file__).with_name("bare.py")), "ads", "--port", str(control)]
    bare += ["--time-slice-us", str(args.probe_slice_us)]
    with (
        ServerProcess(bare, "bare-ads") as responder,
        ServerProcess(argv, "opcua-attacks") as server,
    ):
        wait_port(control, 30.0, responder.proc)
        wait_port(aport, 120.0, server.proc)
        end = time.monotonic() + 180
        while "opcua: ready" not in server.log_text() and time.monotonic() < end:
            time.sleep(0.2)
        time.sleep(1.0)
        rows, notes = run_attacks(args, url, machine, targets, (aport, mbase, control), server.pid)
        notes.append(stop_during_attack(url, machine, server))
    who = "machine 1 (ADS, Modbus)" if n == 1 else f"machines {targets} of {n} (ADS, Modbus)"
    md = table(
        [
            "attack on machine 1",
            "quiet n",
            "p50 ms",
            "p99 ms",
            "attacked n",
            "p50 ms",
            "p99 ms",
            "p99 ratio",
            "bare ADS p99 ms (ratio)",
            "ratio over bare",
            "answered",
            "OPC UA client's slowest Read, ms",
            "RSS MiB",
        ],
        rows,
    )
    emit(
        f"OPC UA attacks, probes of {who}, {args.rounds} rounds of {args.seconds:g} s\n\n"
        f"{md}\n\n" + "\n".join(notes),
        args.out,
    )


if __name__ == "__main__":
    main()
