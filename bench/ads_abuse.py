"""ADS abuse benchmark: what hostile or careless ADS clients cost everyone else.

Two parts, each against a fresh `geo-server run --homed` (GEO cycle in real time at
1 ms) in a subprocess:

1. **Notification flood.** Read round trips on Modbus (FC 3), Zenoh (get) and ADS
   (pyads Read) are timed while the server is idle, then while a flood process holds as
   many notifications as the server grants: `--connections` connections each asking for
   `--per-connection` of them (default 40 × 1024, every registration due every cycle:
   on-change, the pyads default, or cyclic with `--cyclic`), reading every notification
   frame the server sends. Printed: registrations granted and refused (0x716), the time
   registering took, read p50/p99 idle vs flood, notification samples received, and the
   server's CPU use during the flood.
2. **Partial frames.** `--partial` connections (default 1000) each send an AMS/TCP header
   announcing `--partial-size` bytes (default 1 MiB) and then all but the last byte of
   it. Printed: the server's VmRSS (/proc/<pid>/status) before, with the connections held
   open, after the server's unfinished-frame timeout (if it has one) and after the
   client closed them; how many connections the server accepted, and how many it closed.
   The same with frames of exactly the server's request-size limit (`max_frame`).

    python bench/ads_abuse.py [--quick] [--only flood,partial] [--pythonpath DIR]

`--pythonpath DIR` runs the server from another source tree (e.g. an older checkout
exported with `git archive`), for before/after figures.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import selectors
import socket
import struct
import subprocess
import sys
import threading
import time
from typing import Any

from common import (
    HOST,
    PYTHON,
    ServerProcess,
    cpu_seconds,
    emit,
    free_ports,
    geo_server_argv,
    rss_kib,
    start_geo,
    summary_us,
    table,
    timed_loop,
    wait_port,
)

from geo_server.dictionary import GEO_AMS_PORT, load_dictionary
from geo_server.errors import AdsErrorCode
from geo_server.transports.ads import codec
from geo_server.transports.ads.codec import (
    AmsAddr,
    AmsPacket,
    Command,
    TransMode,
)

SERVER_NETID = "127.0.0.1.1.1"
FLOOD_AXES = 4  # the default machine's axes


# ---------------------------------------------------------------------- flood (child)


def flood_addresses() -> list[tuple[int, int, int]]:
    """Every readable value address of the default machine (IG, IO, length)."""
    out = []
    for obj in load_dictionary().objects:
        if not obj.readable:
            continue
        axes = range(1, FLOOD_AXES + 1) if obj.scope == "axis" else [0]
        out += [(obj.index_group, obj.index_offset(a), obj.length) for a in axes]
    return out


def flood_child(port: int, connections: int, per_connection: int, cyclic: bool) -> None:
    """Register notifications on `connections` raw AMS/TCP connections (pipelined Add
    requests), print one JSON line, then read notification frames until stdin closes
    and print the counts as a second JSON line."""
    addrs = flood_addresses()
    mode = TransMode.SERVERCYCLE if cyclic else TransMode.SERVERONCHA
    t0 = time.perf_counter()
    socks: list[socket.socket] = []
    framers: dict[socket.socket, codec.Framer] = {}
    granted = refused = other = 0
    samples = frames = 0
    for c in range(connections):
        try:
            s = socket.create_connection((HOST, port), timeout=30)
        except OSError:
            other += per_connection
            continue
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        source = AmsAddr(f"10.9.{c // 250}.{c % 250 + 1}.1.1", 30000)
        reqs = []
        for i in range(per_connection):
            ig, io, n = addrs[(c * per_connection + i) % len(addrs)]
            data = codec.add_notification_request(ig, io, n, mode, 0, 1)  # 100 ns: every cycle
            reqs.append(
                codec.request_frame(
                    AmsAddr(SERVER_NETID, GEO_AMS_PORT),
                    source,
                    Command.ADD_DEVICE_NOTIFICATION,
                    data,
                    i,
                )
            )
        framer = codec.Framer()
        answers = 0
        try:
            s.sendall(b"".join(reqs))
            while answers < per_connection:
                data = s.recv(1 << 16)
                if not data:
                    break
                for ev in framer.feed(data):
                    if not isinstance(ev, AmsPacket):
                        continue
                    if ev.header.command == Command.DEVICE_NOTIFICATION:
                        frames += 1
                        continue
                    answers += 1
                    code, _handle = codec.parse_add_notification_response(ev.data)
                    if code == 0:
                        granted += 1
                    elif code == AdsErrorCode.DEVICE_NOMOREHDLS:
                        refused += 1
                    else:
                        other += 1
        except OSError:
            pass
        other += per_connection - answers
        socks.append(s)
        framers[s] = framer
    print(
        json.dumps(
            {
                "granted": granted,
                "refused": refused,
                "other": other,
                "register_s": time.perf_counter() - t0,
            }
        ),
        flush=True,
    )
    stop = threading.Event()

    def wait_stdin() -> None:
        sys.stdin.read()
        stop.set()

    threading.Thread(target=wait_stdin, daemon=True).start()
    sel = selectors.DefaultSelector()
    for s in socks:
        s.setblocking(False)
        sel.register(s, selectors.EVENT_READ)
    t_drain = time.perf_counter()
    while not stop.is_set():
        for key, _ in sel.select(0.1):
            s = key.fileobj
            assert isinstance(s, socket.socket)
            try:
                data = s.recv(1 << 18)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                data = b""
            if not data:
                sel.unregister(s)
                continue
            for ev in framers[s].feed(data):
                if isinstance(ev, AmsPacket) and ev.header.command == Command.DEVICE_NOTIFICATION:
                    frames += 1
                    # samples in the frame: stamps x samples, counted from the headers
                    for stamp in codec.parse_device_notification(ev.data):
                        samples += len(stamp.samples)
    print(
        json.dumps(
            {"frames": frames, "samples": samples, "drain_s": time.perf_counter() - t_drain}
        ),
        flush=True,
    )
    for s in socks:
        s.close()


class Flood:
    """The flood child process: `start()` returns the registration figures once it is
    registered, `stop()` its receive counts (always reaps the process)."""

    def __init__(self, port: int, connections: int, per_connection: int, cyclic: bool) -> None:
        argv = [PYTHON, __file__, "--flood-child", str(port), str(connections)]
        argv += [str(per_connection), "1" if cyclic else "0"]
        self.proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

    def start(self, timeout: float) -> dict[str, Any]:
        assert self.proc.stdout is not None
        result: list[str] = []
        t = threading.Thread(target=lambda: result.append(self.proc.stdout.readline()))
        t.start()
        t.join(timeout)
        if not result or not result[0].strip():
            self.kill()
            raise TimeoutError(f"the flood did not register within {timeout} s")
        return json.loads(result[0])

    def stop(self) -> dict[str, Any]:
        try:
            out, _ = self.proc.communicate("", timeout=30)
            return json.loads(out.strip().splitlines()[-1])
        except (subprocess.TimeoutExpired, ValueError, IndexError):
            return {}
        finally:
            self.kill()

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


# ---------------------------------------------------------------------- flood (parent)


def readers(ports: dict[str, int]) -> dict[str, tuple[Any, Any]]:
    from transports import JSON_KEY, ads_reader, modbus_reader, zenoh_reader

    return {
        "Modbus FC 3, 4 registers": modbus_reader(ports["modbus"]),
        "Zenoh get, JSON key": zenoh_reader(ports["zenoh"], JSON_KEY),
        "ADS Read 8 bytes (pyads)": ads_reader(ports["ads"]),
    }


def latencies(clients: dict[str, tuple[Any, Any]], n: int, seconds: float) -> dict[str, Any]:
    out = {}
    for name, (read, _close) in clients.items():
        rtt, _rate = timed_loop(read, n, seconds, warmup=20)
        out[name] = summary_us(rtt)
    return out


def part_flood(args: argparse.Namespace, env: dict[str, str]) -> str:
    ports = dict(zip(("zenoh", "modbus", "ads"), free_ports(3), strict=True))
    argv = geo_server_argv(1.0, ports, pythonpath=env.get("PYTHONPATH", ""))
    with ServerProcess(argv, "abuse-flood", env=env) as server:
        session = start_geo(server, ports)
        session.close()
        clients = readers(ports)
        try:
            idle = latencies(clients, args.reads, args.seconds)
            flood = Flood(ports["ads"], args.connections, args.per_connection, args.cyclic)
            try:
                reg = flood.start(args.register_timeout)
                time.sleep(0.5)  # let the sampling settle
                cpu0, w0 = cpu_seconds(server.pid), time.monotonic()
                loaded = latencies(clients, args.reads, args.seconds)
                cpu = (cpu_seconds(server.pid) - cpu0) / (time.monotonic() - w0)
            finally:
                got = flood.stop()
        finally:
            for _read, close in clients.values():
                with contextlib.suppress(Exception):
                    close()
    mode = "cyclic" if args.cyclic else "on-change"
    head = (
        f"### Notification flood: {args.connections} connections × {args.per_connection} "
        f"{mode} notifications, due every 1 ms cycle\n\n"
        f"Granted {reg['granted']}, refused with 0x716 {reg['refused']}, other "
        f"{reg['other']}; registering took {reg['register_s']:.2f} s. During the flood the "
        f"server process used {cpu * 100:.0f} % of a core; the flood received "
        f"{got.get('samples', 0)} samples in {got.get('frames', 0)} frames in "
        f"{got.get('drain_s', float('nan')):.1f} s.\n\n"
    )
    rows = []
    for name in idle:
        a, b = idle[name], loaded[name]
        cells = [a["p50"], a["p99"], b["p50"], b["p99"], b["max"]]
        rows.append([name, *(f"{v:.0f}" for v in cells), b["n"]])
    return head + table(
        ["read", "idle p50 µs", "idle p99 µs", "flood p50 µs", "flood p99 µs", "flood max µs", "n"],
        rows,
    )


# ---------------------------------------------------------------------- partial frames


def hold_partial(
    port: int, count: int, size: int, chunk: int = 1 << 16
) -> tuple[list[socket.socket], int, int]:
    """`count` connections, each: a header announcing `size` bytes, then `size - 1` of
    them. Returns (the sockets still open, how many sent everything, how many the server
    closed or refused)."""
    socks: list[socket.socket] = []
    complete = closed = 0
    header = struct.pack("<HI", 0, size)
    body = b"\0" * chunk
    for _ in range(count):
        try:
            s = socket.create_connection((HOST, port), timeout=5)
        except OSError:
            closed += 1
            continue
        socks.append(s)
        try:
            s.sendall(header)
            left = size - 1
            while left > 0:
                n = min(left, chunk)
                s.sendall(body[:n])
                left -= n
            complete += 1
        except OSError:
            closed += 1  # the server closed it (reset / broken pipe)
    return socks, complete, closed


def still_open(socks: list[socket.socket]) -> int:
    """How many of `socks` the server has not closed (a 0-byte peek means closed)."""
    n = 0
    for s in socks:
        try:
            s.setblocking(False)
            data = s.recv(1, socket.MSG_PEEK)
            n += bool(data)  # (an answer waiting: open)
        except (BlockingIOError, InterruptedError):
            n += 1
        except OSError:
            pass
    return n


def part_partial(args: argparse.Namespace, env: dict[str, str]) -> str:
    rows = []
    for size in (args.partial_size, 0):
        port = free_ports(1)[0]
        argv = geo_server_argv(
            1.0, {"zenoh": 0, "modbus": 0, "ads": port}, pythonpath=env.get("PYTHONPATH", "")
        )
        argv = _without_options(argv, ("--zenoh-listen", "--modbus-port"))
        argv += ["--no-zenoh", "--no-modbus"]
        with ServerProcess(argv, "abuse-partial", env=env) as server:
            wait_port(port, 30.0, server.proc)
            time.sleep(1.0)
            before = rss_kib(server.pid)["VmRSS"]
            frame = size or _server_max_frame(env)
            label = f"{frame} B" + ("" if size else " (the server's max_frame)")
            t0 = time.monotonic()
            socks, complete, closed = hold_partial(port, args.partial, frame)
            time.sleep(0.5)
            held = rss_kib(server.pid)["VmRSS"]
            open_held = still_open(socks)
            # past a 5 s unfinished-frame timeout, counted from the first bytes sent
            time.sleep(max(0.0, t0 + args.wait_timeout - time.monotonic()))
            after_timeout = rss_kib(server.pid)["VmRSS"]
            open_after = still_open(socks)
            for s in socks:
                s.close()
            time.sleep(2.0)
            after_close = rss_kib(server.pid)["VmRSS"]
            peak = rss_kib(server.pid)["VmHWM"]
        rows.append(
            [
                f"{args.partial} × {label}",
                before // 1024,
                held // 1024,
                after_timeout // 1024,
                after_close // 1024,
                peak // 1024,
                complete,
                closed,
                open_held,
                open_after,
            ]
        )
    head = (
        "### Partial frames: connections holding an unfinished frame\n\n"
        "RSS of the server process in MiB (VmRSS; peak = VmHWM): before the attack, with "
        f"the frames held, {args.wait_timeout:g} s after the attack began (past a 5 s "
        "unfinished-frame timeout), and 2 s after the client closed every connection. "
        "`sendall ok` = connections whose client could hand all but the last byte to its "
        "kernel; `refused/closed` = connections the server refused or closed while the client "
        "was sending; `open` = connections the server still held after sending / after the "
        "timeout.\n\n"
    )
    return head + table(
        [
            "attack",
            "before",
            "held",
            "after timeout",
            "after close",
            "peak",
            "sendall ok",
            "refused/closed",
            "open",
            "open after timeout",
        ],
        rows,
    )


def _without_options(argv: list[str], options: tuple[str, ...]) -> list[str]:
    out: list[str] = []
    skip = False
    for a in argv:
        if skip:
            skip = False
            continue
        if a in options:
            skip = True
            continue
        out.append(a)
    return out


def _server_max_frame(env: dict[str, str]) -> int:
    """The server tree's default `AdsOptions.max_frame` (1 MiB before it had a limit of
    its own)."""
    code = "from geo_server.transports.ads.server import AdsOptions; print(AdsOptions().max_frame)"
    out = subprocess.run(
        [PYTHON, "-c", code], capture_output=True, text=True, env={**os.environ, **env}, check=True
    )
    return int(out.stdout.strip())


# ---------------------------------------------------------------------- main


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--flood-child":
        port, conns, per, cyclic = sys.argv[2:6]
        flood_child(int(port), int(conns), int(per), cyclic == "1")
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer reads, a smaller flood")
    ap.add_argument("--only", default="flood,partial")
    ap.add_argument("--pythonpath", default="", help="run the server from this source tree")
    ap.add_argument("--connections", type=int, default=40)
    ap.add_argument("--per-connection", type=int, default=1024)
    ap.add_argument("--cyclic", action="store_true", help="cyclic notifications (all sent)")
    ap.add_argument("--reads", type=int, default=2000, help="timed reads per transport")
    ap.add_argument("--seconds", type=float, default=5.0, help="at most per transport")
    ap.add_argument("--register-timeout", type=float, default=300.0)
    ap.add_argument("--partial", type=int, default=1000, help="connections of the attack")
    ap.add_argument("--partial-size", type=int, default=1 << 20)
    ap.add_argument("--wait-timeout", type=float, default=6.0)
    ap.add_argument("--out", default="")
    args = ap.parse_args()
    if args.quick:
        args.reads, args.seconds = 300, 2.0
    env = {"PYTHONPATH": args.pythonpath} if args.pythonpath else {}
    parts = set(args.only.split(","))
    text = "## ADS abuse\n\n"
    if args.pythonpath:
        text += f"Server from `{args.pythonpath}`.\n\n"
    if "flood" in parts:
        text += part_flood(args, env) + "\n"
    if "partial" in parts:
        text += part_partial(args, env) + "\n"
    emit(text, args.out or None)


if __name__ == "__main__":
    main()
