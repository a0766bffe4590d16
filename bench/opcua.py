"""OPC UA benchmark (README *OPC UA*): geo-server's OPC UA interface beside a bare
asyncua server of the same version, side by side in one run, alternating.

Each server runs in a subprocess of its own (this file with `--serve`), the clients
(asyncua) in this process:

- **geo**: the default machine, homed, exact engine, 1 ms cycle, `OpcUaInterface`;
- **bare**: `asyncua.Server` with one Double variable in its own namespace, static; for
  the notification rate it writes a new value into it every millisecond (the GEO cycle).

Figures, per round and server:

1. **read round trip**: `--reads` single reads of one variable (TEMPC::coefficient of X;
   the bare server's variable), p50 and p99. Both servers run at once and the reads
   alternate between them in blocks of `--block`, so that the load of a shared machine
   (which drifts by tens of percent within seconds) weighs on both alike;
2. **notification rate**: one subscription (publishing every 10 ms) with 100 monitored
   items at the smallest sampling interval on a value that changes every cycle
   (SIM::cycle_count; the bare server's ticking variable), notifications per second
   received over `--window` seconds (the most a server could send: 100 000/s);
3. **idle CPU**: 10 sessions with 100 monitored items each on values that do not change
   (geo: TEMPC/CROSSC/LSEC objects of the 4 axes; bare: its variable, not ticking), the
   server process's CPU time over `--window` seconds, in % of one core.

    python bench/opcua.py [--rounds 3] [--reads 1000] [--block 100] [--window 3]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve()
NAMESPACE = "urn:geo-server:cnc"
BARE_NAMESPACE = "urn:bench:bare"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# ---------------------------------------------------------------------- servers


async def serve_geo(port: int) -> None:
    from geo_server import jit
    from geo_server.listfile import load_machine
    from geo_server.machine.machine import Machine
    from geo_server.machine.scheduler import Scheduler
    from geo_server.paths import default_startup_list
    from geo_server.service import ObjectService
    from geo_server.transports.opcua.server import OpcUaInterface, OpcUaOptions

    jit.load()  # the cycle's machine code before anything is timed (geo_server/jit.py)
    machine = Machine(load_machine(default_startup_list()), cycle_s=0.001, homed=True)
    scheduler = Scheduler(machine, mode="realtime")
    service = ObjectService(machine, scheduler)
    iface = OpcUaInterface({"local": service}, OpcUaOptions(endpoint=f"opc.tcp://127.0.0.1:{port}"))
    await iface.start()
    scheduler.start()
    print("ready", flush=True)
    await asyncio.Event().wait()


async def serve_bare(port: int, tick: bool) -> None:
    import logging

    from asyncua import Server, ua

    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    server = Server()
    await server.init()
    server.set_endpoint(f"opc.tcp://127.0.0.1:{port}/")
    server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
    ns = await server.register_namespace(BARE_NAMESPACE)
    var = await server.nodes.objects.add_variable(ua.NodeId("value", ns), f"{ns}:value", 0.0)
    await var.set_writable()
    await server.start()
    print("ready", flush=True)
    n = 0.0
    while True:
        await asyncio.sleep(0.001 if tick else 3600)
        n += 1
        await server.write_attribute_value(var.nodeid, ua.DataValue(ua.Variant(n)))


class Proc:
    def __init__(self, kind: str, tick: bool = False) -> None:
        self.port = free_port()
        args = [sys.executable, str(HERE), "--serve", kind, "--port", str(self.port)]
        self.proc = subprocess.Popen(
            args + (["--tick"] if tick else []),
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        assert line.strip() == "ready", line
        self.url = f"opc.tcp://127.0.0.1:{self.port}"
        self.kind = kind

    def cpu(self) -> float:
        """CPU seconds of the server process so far (Linux /proc)."""
        fields = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def close(self) -> None:
        self.proc.terminate()
        self.proc.wait(10)


# ---------------------------------------------------------------------- clients


async def node_ids(c: Any, kind: str) -> tuple[Any, Any, list[Any]]:
    """(the read's node, the ticking node, 100 nodes at rest)."""
    from asyncua import ua

    if kind == "bare":
        ns = await c.get_namespace_index(BARE_NAMESPACE)
        one = ua.NodeId("value", ns)
        return one, one, [one] * 100
    ns = await c.get_namespace_index(NAMESPACE)
    rest = [
        ua.NodeId(f"local/Axes/{a}/{g}", ns)
        for a in "XYZC"
        for g in (
            "TEMPC/activated",
            "TEMPC/coefficient",
            "TEMPC/offset_0",
            "TEMPC/position_0",
            "CROSSC/activated",
            "CC2/activated",
            "LSEC/active",
            "BC/conf_backlash",
            "CROSSTALK/activated",
            "TEMPC/f_is_active",
        )
    ]
    rest = (rest * 3)[:100]
    return (
        ua.NodeId("local/Axes/X/TEMPC/coefficient", ns),
        ua.NodeId("local/SIM/cycle_count", ns),
        rest,
    )


async def reads(procs: list[Proc], n: int, block: int) -> dict[str, list[float]]:
    """Round trips of `n` single reads per server, `block` reads at a time on each in
    turn (each server's connection open throughout)."""
    from asyncua import Client

    clients = {p.kind: Client(p.url, timeout=10) for p in procs}
    nodes = {}
    times: dict[str, list[float]] = {k: [] for k in clients}
    try:
        for kind, c in clients.items():
            await c.connect()
            one, _, _ = await node_ids(c, kind)
            nodes[kind] = c.get_node(one)
            for _ in range(20):  # (first reads: connections and caches warm)
                await nodes[kind].read_value()
        for _ in range(max(1, n // block)):
            for kind, node in nodes.items():
                for _ in range(block):
                    t = time.perf_counter()
                    await node.read_value()
                    times[kind].append(time.perf_counter() - t)
    finally:
        for c in clients.values():
            await c.disconnect()
    return times


class Count:
    def __init__(self) -> None:
        self.n = 0

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        self.n += 1


async def rate(url: str, kind: str, window: float) -> float:
    from asyncua import Client

    async with Client(url, timeout=10) as c:
        _, ticking, _ = await node_ids(c, kind)
        handler = Count()
        sub = await c.create_subscription(10, handler)
        await sub.subscribe_data_change([c.get_node(ticking)] * 100, sampling_interval=0)
        await asyncio.sleep(0.5)
        start = handler.n
        await asyncio.sleep(window)
        got = handler.n - start
        await sub.delete()
    return got / window


async def idle_cpu(proc: Proc, window: float) -> float:
    from asyncua import Client

    clients = [Client(proc.url, timeout=10) for _ in range(10)]
    for c in clients:
        await c.connect()
    try:
        for c in clients:
            _, _, rest = await node_ids(c, proc.kind)
            sub = await c.create_subscription(100, Count())
            await sub.subscribe_data_change([c.get_node(n) for n in rest], sampling_interval=0)
        await asyncio.sleep(0.5)
        t0, c0 = time.monotonic(), proc.cpu()
        await asyncio.sleep(window)
        return 100.0 * (proc.cpu() - c0) / (time.monotonic() - t0)
    finally:
        for c in clients:
            await c.disconnect()


def pct(values: list[float], q: float) -> float:
    values = sorted(values)
    return values[min(len(values) - 1, int(q * len(values)))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--serve", choices=("geo", "bare"))
    ap.add_argument("--port", type=int, default=0)
    ap.add_argument("--tick", action="store_true")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--reads", type=int, default=1000)
    ap.add_argument("--block", type=int, default=100)
    ap.add_argument("--window", type=float, default=3.0)
    a = ap.parse_args()
    if a.serve == "geo":
        asyncio.run(serve_geo(a.port))
        return
    if a.serve == "bare":
        asyncio.run(serve_bare(a.port, a.tick))
        return
    import logging

    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    figures: dict[str, dict[str, list[float]]] = {
        k: {"p50": [], "p99": [], "rate": [], "cpu": []} for k in ("geo", "bare")
    }
    for r in range(a.rounds):
        order = ("bare", "geo") if r % 2 else ("geo", "bare")
        procs = []
        try:
            procs = [Proc(kind) for kind in order]
            t = asyncio.run(reads(procs, a.reads, a.block))
        finally:
            for proc in procs:
                proc.close()
        for kind in order:
            figures[kind]["p50"].append(pct(t[kind], 0.5) * 1e3)
            figures[kind]["p99"].append(pct(t[kind], 0.99) * 1e3)
            proc = Proc(kind, tick=kind == "bare")
            try:
                figures[kind]["rate"].append(asyncio.run(rate(proc.url, kind, a.window)))
            finally:
                proc.close()
            proc = Proc(kind)  # the bare one not ticking: idle
            try:
                figures[kind]["cpu"].append(asyncio.run(idle_cpu(proc, a.window)))
            finally:
                proc.close()
        print(f"round {r + 1}: " + ", ".join(
            f"{k} p50 {f['p50'][-1]:.3f} ms p99 {f['p99'][-1]:.3f} ms "
            f"{f['rate'][-1]:.0f}/s cpu {f['cpu'][-1]:.1f} %"
            for k, f in figures.items()
        ), flush=True)  # fmt: skip
    med = {k: {m: statistics.median(v) for m, v in f.items()} for k, f in figures.items()}
    g, b = med["geo"], med["bare"]
    print()
    print("| figure (median of rounds) | geo-server | bare asyncua | ratio |")
    print("|---|---|---|---|")
    rows = [
        ("read round trip p50", "p50", "{:.3f} ms"),
        ("read round trip p99", "p99", "{:.3f} ms"),
        ("notifications/s, 100 items, 1 ms", "rate", "{:.0f}"),
    ]
    for label, key, form in rows:
        ratio = g[key] / b[key]
        print(f"| {label} | {form.format(g[key])} | {form.format(b[key])} | {ratio:.2f}× |")
    print(f"| CPU, 10 idle sessions × 100 items | {g['cpu']:.1f} % | {b['cpu']:.1f} % | — |")
    for key in ("p50", "rate"):
        ratios = [x / y for x, y in zip(figures["geo"][key], figures["bare"][key], strict=True)]
        print(f"{key} ratio per round: {min(ratios):.2f}-{max(ratios):.2f}")


if __name__ == "__main__":
    main()
