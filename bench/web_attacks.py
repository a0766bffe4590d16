"""What a hostile web client costs the other interfaces (issue 30 items 2 and 4;
docs/security.md): ADS, Modbus and Zenoh round trips while an attacker works on the HMI.

One `geo-server run --homed --http … --http-token …` (exact engine, machine at rest).
Rounds alternate *quiet* and *attack*; each attack runs in a process of its own (threads
in the probing process would hold its interpreter lock and measure the client):

- **long name**: POST `/api/write` with a 1 MiB object name, back to back (with the
  run's token: the worst case, a client that may write);
- **ws frames**: a WebSocket client sending 4 MiB frames, reconnecting after each close;
- **500 pages**: 500 WebSockets opened and held (the server keeps `ws_max_clients`);
- **slow clients**: 1100 connections sending a request head a byte at a time.

Per round and reader: closed-loop round trips for `--seconds`; the table gives p50/p99
of quiet and attack rounds pooled, and their ratio, plus the server's descriptors.

    python bench/web_attacks.py [--rounds 2] [--seconds 3] [--out FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing
import os
import socket
import time
from typing import Any

import numpy as np
from common import (
    HOST,
    ServerProcess,
    address,
    emit,
    free_ports,
    geo_server_argv,
    start_geo,
    table,
    timed_loop,
    wait_port,
)
from transports import ads_reader, modbus_reader, zenoh_reader

TOKEN = "bench-web-attacks"
COEFF = address("TEMPC::coefficient")
READERS = {
    "ADS read": lambda p: ads_reader(p["ads"]),
    "Modbus read": lambda p: modbus_reader(p["modbus"]),
    "Zenoh get": lambda p: zenoh_reader(p["zenoh"], COEFF.raw_key),
}


async def _long_names(port: int, stop: Any, done: Any) -> None:
    import aiohttp

    body = b'{"name": "' + b"A" * (1 << 20) + b'", "axis": 1, "value": 1}'
    headers = {"Content-Type": "application/json", "X-Geo-Token": TOKEN}
    async with aiohttp.ClientSession() as s:
        while not stop.is_set():
            try:
                async with s.post(
                    f"http://{HOST}:{port}/api/write", data=body, headers=headers
                ) as r:
                    await r.read()
            except aiohttp.ClientError:
                await asyncio.sleep(0.01)
            done.value += 1


async def _ws_frames(port: int, stop: Any, done: Any) -> None:
    import aiohttp

    frame = "x" * (4 << 20)
    async with aiohttp.ClientSession() as s:
        while not stop.is_set():
            try:
                async with s.ws_connect(f"http://{HOST}:{port}/ws") as ws:
                    await ws.send_str(frame)
                    await asyncio.wait_for(ws.receive(), 5)
            except (aiohttp.ClientError, TimeoutError, ConnectionError):
                await asyncio.sleep(0.01)
            done.value += 1


async def _pages(port: int, stop: Any, done: Any) -> None:
    import aiohttp

    async with aiohttp.ClientSession(connector=aiohttp.TCPConnector(limit=0)) as s:

        async def one() -> Any:
            try:
                return await s.ws_connect(f"http://{HOST}:{port}/ws", heartbeat=None)
            except (aiohttp.ClientError, ConnectionError):
                return None

        sockets = await asyncio.gather(*(one() for _ in range(500)))
        done.value = sum(ws is not None for ws in sockets)
        while not stop.is_set():
            for ws in sockets:  # take what is pushed, as an open page does
                if ws is not None and not ws.closed:
                    with _quiet():
                        await asyncio.wait_for(ws.receive(), 0.001)
            await asyncio.sleep(0.05)
        for ws in sockets:
            if ws is not None:
                await ws.close()


def _slow(port: int, stop: Any, done: Any) -> None:
    conns = []
    for _ in range(1100):
        try:
            c = socket.create_connection((HOST, port), timeout=2)
        except OSError:
            break
        c.setblocking(False)
        conns.append(c)
    done.value = len(conns)
    head = b"GET /api/state HTTP/1.1\r\nHost: x\r\n"
    i = 0
    while not stop.is_set():
        byte = head[i % len(head) : i % len(head) + 1]
        for c in conns:
            with _quiet():
                c.send(byte)
        i += 1
        stop.wait(0.5)
    for c in conns:
        c.close()


class _quiet:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: object) -> bool:
        return True


def attacker(kind: str, port: int, stop: Any, done: Any) -> None:
    """The attack `kind` until `stop` is set (runs in its own process)."""
    if kind == "slow clients":
        _slow(port, stop, done)
        return
    coro = {"long name": _long_names, "ws frames": _ws_frames, "500 pages": _pages}[kind]

    async def main() -> None:
        task = asyncio.ensure_future(coro(port, stop, done))
        while not stop.is_set():
            await asyncio.sleep(0.05)
        task.cancel()
        with _quiet():
            await task

    asyncio.run(main())


def descriptors(pid: int) -> int:
    try:
        return len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return -1


def run(rounds: int, seconds: float, attacks: list[str]) -> dict[str, Any]:
    zp, mp, ap, hp = free_ports(4)
    ports = {"zenoh": zp, "modbus": mp, "ads": ap}
    extra = ["--http", f"{HOST}:{hp}", "--http-token", TOKEN]
    argv = geo_server_argv(1.0, ports, extra=extra, engine="exact")
    ctx = multiprocessing.get_context("spawn")
    samples: dict[tuple[str, str], list[np.ndarray]] = {}
    notes: dict[str, str] = {}
    with ServerProcess(argv, "web-attacks") as srv:
        session = start_geo(srv, ports, min_cycles=300)
        wait_port(hp, 20.0, srv.proc)
        try:
            for _ in range(rounds):
                for kind in ["quiet", *attacks]:
                    stop, done = ctx.Event(), ctx.Value("q", 0)
                    proc = None
                    if kind != "quiet":
                        proc = ctx.Process(target=attacker, args=(kind, hp, stop, done))
                        proc.start()
                        time.sleep(2.0)
                    fds = descriptors(srv.pid)
                    for label, factory in READERS.items():
                        read, close = factory(ports)
                        try:
                            rtt, _ = timed_loop(read, 100_000, seconds)
                        finally:
                            close()
                        samples.setdefault((kind, label), []).append(rtt)
                    if proc is not None:
                        stop.set()
                        proc.join(15)
                        if proc.is_alive():
                            proc.kill()
                        notes[kind] = f"{done.value} (server descriptors {fds})"
                    print(f"  {kind}: done", flush=True)
        finally:
            session.close()
    return {"samples": samples, "notes": notes}


def report(res: dict[str, Any], attacks: list[str], seconds: float) -> str:
    s = res["samples"]
    rows = []
    for kind in attacks:
        for label in READERS:
            q = np.concatenate(s[("quiet", label)])
            a = np.concatenate(s[(kind, label)])
            q50, q99 = np.median(q), np.percentile(q, 99)
            a50, a99 = np.median(a), np.percentile(a, 99)
            rows.append(
                [
                    kind,
                    label,
                    f"{q50:.0f} / {q99:.0f}",
                    f"{a50:.0f} / {a99:.0f}",
                    f"{a50 / q50:.2f} / {a99 / q99:.2f}",
                ]
            )
    what = {
        "long name": "1 MiB names posted",
        "ws frames": "4 MiB frames sent",
        "500 pages": "WebSockets opened",
        "slow clients": "slow connections opened",
    }
    notes = "".join(f"- {k}: {what[k]} {v}\n" for k, v in res["notes"].items())
    return (
        f"## Web attacks: the other interfaces' round trips ({seconds:g} s per reader "
        "and round; µs, p50 / p99)\n\n"
        + table(["attack", "reader", "quiet", "attack", "ratio"], rows, "llrrr")
        + "\n"
        + notes
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--seconds", type=float, default=3.0)
    p.add_argument("--attacks", default="long name,ws frames,500 pages,slow clients")
    p.add_argument("--out")
    args = p.parse_args()
    attacks = [a.strip() for a in args.attacks.split(",") if a.strip()]
    res = run(args.rounds, args.seconds, attacks)
    emit(report(res, attacks, args.seconds), args.out)


if __name__ == "__main__":
    main()
