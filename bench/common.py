"""Shared helpers of the benchmarks: ports, subprocess servers, statistics, tables.

Every server a benchmark starts is a `ServerProcess`: started on 127.0.0.1 with
ephemeral ports, its output sent to a log file (never an unread pipe), and always
stopped in a `finally` — SIGTERM first, SIGKILL when it does not exit in time.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import platform
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
PYTHON = sys.executable
HOST = "127.0.0.1"


# ---------------------------------------------------------------------- addresses


@dataclass(frozen=True)
class Address:
    """Where the benchmarks find one object, on every transport — from the dictionary
    (objects/), never typed a second time."""

    index_group: int
    index_offset: int
    #: first holding register of its Modbus slot, and how many carry the value
    register: int
    registers: int
    #: bytes of its ADS value
    size: int
    raw_key: str
    named_key: str


def address(name: str, axis: int = 1, machine: str = "local") -> Address:
    """The ADS, Modbus and Zenoh addresses of object `name` of `axis` on `machine`."""
    from geo_server.dictionary import load_dictionary
    from geo_server.transports.modbus.regmap import register_address, register_count
    from geo_server.transports.zenoh.keys import KeySpace

    d = load_dictionary()
    obj = d.by_name(name)
    keys = KeySpace(machine, d, (axis,))
    ig, io = obj.index_group, obj.index_offset(axis)
    return Address(
        ig,
        io,
        register_address(obj),
        register_count(obj),
        obj.length,
        keys.raw_key(ig, io),
        keys.named_key(obj, axis),
    )


# ---------------------------------------------------------------------- ports


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago, below the ephemeral range
    where there is room and never one handed out before (`geo_server.ports`)."""
    from geo_server import ports

    return ports.free_port(HOST)


def free_ports(n: int) -> list[int]:
    """`n` distinct free ports."""
    return [free_port() for _ in range(n)]


def free_range(n: int) -> int:
    """The first of `n` consecutive free ports (a fleet's Modbus ports)."""
    from geo_server import ports

    return ports.free_range(n, HOST)


def wait_port(port: int, timeout: float, proc: subprocess.Popen | None = None) -> None:
    """Wait until 127.0.0.1:`port` accepts a TCP connection (or raise)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"server exited with {proc.returncode} before listening")
        with contextlib.suppress(OSError), socket.create_connection((HOST, port), 0.2):
            return
        time.sleep(0.05)
    raise TimeoutError(f"nothing listens on {HOST}:{port} after {timeout} s")


# ---------------------------------------------------------------------- processes


def _die_with_parent() -> None:
    """In the server's child process (Linux): SIGKILL it when the benchmark that started
    it dies, so that a benchmark killed by a time limit leaves no server behind (a
    leftover 150-machine fleet once ran on for 40 minutes and spoiled later runs)."""
    import ctypes

    pr_set_pdeathsig = 1
    ctypes.CDLL("libc.so.6", use_errno=True).prctl(pr_set_pdeathsig, signal.SIGKILL)


class ServerProcess:
    """A server in a subprocess; use as a context manager (always stopped on exit)."""

    def __init__(self, argv: Sequence[str], name: str, env: dict[str, str] | None = None) -> None:
        self.argv = list(argv)
        self.name = name
        self.log_path = Path(tempfile.mkstemp(prefix=f"bench-{name}-", suffix=".log")[1])
        self._log = self.log_path.open("wb")
        self.proc = subprocess.Popen(
            self.argv,
            stdin=subprocess.DEVNULL,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            cwd=ROOT,
            env={**os.environ, **(env or {})},
            preexec_fn=_die_with_parent if sys.platform == "linux" else None,
        )
        self.exit_code: int | None = None
        self.stop_seconds: float | None = None

    @property
    def pid(self) -> int:
        return self.proc.pid

    def log_tail(self, lines: int = 20) -> str:
        return "\n".join(self.log_text().splitlines()[-lines:])

    def log_text(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(encoding="utf-8", errors="replace")

    def stop(self, timeout: float = 10.0) -> int:
        """SIGTERM, wait up to `timeout`, then SIGKILL. Returns the exit code."""
        if self.proc.poll() is None:
            t0 = time.monotonic()
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
            self.stop_seconds = time.monotonic() - t0
        self.exit_code = self.proc.returncode
        self._log.close()
        return self.exit_code

    def __enter__(self) -> ServerProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
        if exc[0] is None:
            with contextlib.suppress(OSError):
                self.log_path.unlink()
        else:
            print(f"[{self.name}] log kept in {self.log_path}:\n{self.log_tail()}", file=sys.stderr)


@functools.cache
def knows_option(option: str, pythonpath: str = "") -> bool:
    """Whether `geo-server run` of the tree benchmarked (this one, or `pythonpath`, an
    earlier commit's source) has `option`: a baseline may predate it."""
    env = {**os.environ, **({"PYTHONPATH": pythonpath} if pythonpath else {})}
    exe = str(Path(PYTHON).with_name("geo-server"))
    out = subprocess.run([exe, "run", "--help"], capture_output=True, text=True, env=env)
    return option in out.stdout


def opcua_argv(pythonpath: str = "") -> list[str]:
    """A free port for the OPC UA interface where the tree has one (on by default on
    4840: two servers of one benchmark would collide there)."""
    if not knows_option("--opcua-endpoint", pythonpath):
        return []
    return ["--opcua-endpoint", f"opc.tcp://{HOST}:{free_port()}"]


def geo_server_argv(
    cycle_ms: float,
    ports: dict[str, int],
    machine: str = "local",
    extra: Sequence[str] = (),
    engine: str = "punctual",
    pythonpath: str = "",
) -> list[str]:
    """`geo-server run --homed` on the given ports (zenoh, modbus, ads). The benchmarks
    of cycle lateness and request latency measure the punctual engine unless told
    otherwise (`bench/cpu.py` and `bench/engine.py` compare the two)."""
    return [
        str(Path(PYTHON).with_name("geo-server")),
        "run",
        "--homed",
        "--engine",
        engine,
        "--cycle-ms",
        str(cycle_ms),
        "--machine",
        machine,
        "--zenoh-listen",
        f"tcp/{HOST}:{ports['zenoh']}",
        "--modbus-port",
        str(ports["modbus"]),
        "--ads-port",
        str(ports["ads"]),
        "--status-period",
        "5",
        *opcua_argv(pythonpath),
        *extra,
    ]


def bench_server_argv(
    cycle_ms: float,
    ports: dict[str, int],
    demo_axes: int = 0,
    stats_size: int = 0,
    dump: Path | None = None,
    extra: Sequence[str] = (),
) -> list[str]:
    """`bench/server.py` (geo-server run + demo machines + lateness dump)."""
    argv = [
        PYTHON,
        str(BENCH / "server.py"),
        "--demo-axes",
        str(demo_axes),
        "--stats-size",
        str(stats_size),
    ]
    if dump is not None:
        argv += ["--dump", str(dump)]
    return [*argv, "--", *geo_server_argv(cycle_ms, ports, extra=extra)[2:]]


# ---------------------------------------------------------------------- zenoh


def zenoh_session(endpoint: str) -> Any:
    """A peer session connected to `endpoint`, multicast scouting off, listening nowhere."""
    import zenoh

    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("listen/endpoints", "[]")
    cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
    return zenoh.open(cfg)


def get_status(session: Any, machine: str = "local", timeout: float = 2.0) -> dict[str, Any]:
    """The server's `cnc/<m>/status` (raises TimeoutError without an answer)."""
    for reply in session.get(f"cnc/{machine}/status", timeout=timeout):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    raise TimeoutError(f"no answer on cnc/{machine}/status")


def wait_cycles(
    session: Any, n: int, timeout: float, proc: subprocess.Popen | None = None
) -> dict[str, Any]:
    """Poll the status until the server has run `n` cycles, compiled; returns the
    status."""
    end = time.monotonic() + timeout
    last: Exception | None = None
    while time.monotonic() < end:
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"server exited with {proc.returncode}")
        try:
            st = get_status(session, timeout=1.0)
            # (and its cycle compiled: a server answers while its machine code loads,
            # geo_server/jit.py; a status without the field is from before the compiler)
            if st["cycle"] >= n and st.get("compiled", True):
                return st
        except TimeoutError as exc:
            last = exc
        time.sleep(0.1)
    raise TimeoutError(f"server did not reach {n} cycles in {timeout} s ({last})")


def start_geo(server: ServerProcess, ports: dict[str, int], min_cycles: int = 200) -> Any:
    """Wait for a started geo-server (all three ports, `min_cycles` run); returns a
    Zenoh session connected to it (the caller closes it)."""
    for key in ("zenoh", "modbus", "ads"):
        wait_port(ports[key], 30.0, server.proc)
    if "--opcua-endpoint" in server.argv:
        # the OPC UA interface builds its address space on the loop after the start
        # (about 1.5 s here): measured before it is ready, the first case pays for it
        deadline = time.monotonic() + 60.0
        while "opcua: ready" not in server.log_text():
            if server.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"OPC UA did not get ready:\n{server.log_tail()}")
            time.sleep(0.05)
    session = zenoh_session(f"tcp/{HOST}:{ports['zenoh']}")
    try:
        wait_cycles(session, min_cycles, 30.0, server.proc)
    except BaseException:
        session.close()
        raise
    return session


# ---------------------------------------------------------------------- /proc


def rss_kib(pid: int) -> dict[str, int]:
    """VmRSS and VmHWM (peak) of a process in KiB, from /proc/<pid>/status."""
    out: dict[str, int] = {}
    text = Path(f"/proc/{pid}/status").read_text()
    for key in ("VmRSS", "VmHWM"):
        m = re.search(rf"^{key}:\s+(\d+) kB", text, re.M)
        if m:
            out[key] = int(m.group(1))
    return out


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process so far (/proc/<pid>/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


# ---------------------------------------------------------------------- statistics


def pct(values: np.ndarray | Sequence[float], q: float) -> float:
    a = np.asarray(values, dtype=float)
    return float(np.percentile(a, q)) if a.size else float("nan")


def summary_us(values: np.ndarray | Sequence[float]) -> dict[str, float]:
    """count, p50, p99, max of a sample in µs."""
    a = np.asarray(values, dtype=float)
    if not a.size:
        return {"n": 0, "p50": float("nan"), "p99": float("nan"), "max": float("nan")}
    p50, p99 = np.percentile(a, (50, 99))
    return {"n": int(a.size), "p50": float(p50), "p99": float(p99), "max": float(a.max())}


class Reservoir:
    """Bounded latency store: keeps the first `size` samples, counts all of them."""

    def __init__(self, size: int = 200_000) -> None:
        self.data = np.empty(size)
        self.n = 0

    def add(self, value: float) -> None:
        if self.n < len(self.data):
            self.data[self.n] = value
        self.n += 1

    def values(self) -> np.ndarray:
        return self.data[: min(self.n, len(self.data))]


def timed_loop(
    call: Callable[[], Any],
    max_requests: int,
    max_seconds: float,
    warmup: int = 200,
    gap_ms: float = 0.0,
) -> tuple[np.ndarray, float]:
    """Run `call` back to back (closed loop), bounded in count and time; with `gap_ms`,
    a pause drawn uniformly from 0 to `gap_ms` before each call (not timed: open loop at
    random moments, so a server's cycles run on between requests).

    Returns the round-trip times in µs (after `warmup` untimed calls) and requests/s.
    """
    for _ in range(warmup):
        call()
    res = Reservoir(max_requests)
    clock = time.perf_counter_ns
    gaps = np.random.default_rng(7).uniform(0.0, gap_ms / 1000, 1 << 16)
    start = clock()
    end = start + int(max_seconds * 1e9)
    while res.n < max_requests:
        if gap_ms:
            time.sleep(gaps[res.n & 0xFFFF])
        t0 = clock()
        call()
        t1 = clock()
        res.add((t1 - t0) / 1000)
        if t1 > end:
            break
    elapsed = (clock() - start) / 1e9
    return res.values(), res.n / elapsed


# ---------------------------------------------------------------------- output


def table(header: Sequence[str], rows: Sequence[Sequence[Any]], align: str = "") -> str:
    """A Markdown table; numbers right-aligned unless `align` says otherwise."""
    align = align or "".join("l" if i == 0 else "r" for i in range(len(header)))
    sep = ["---:" if a == "r" else ":---" for a in align]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(sep) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(_cell(c) for c in r) + " |")
    return "\n".join(lines) + "\n"


def _cell(v: Any) -> str:
    if isinstance(v, float):
        if v != v:
            return "–"
        if abs(v) >= 100:
            return f"{v:.0f}"
        if abs(v) >= 10:
            return f"{v:.1f}"
        return f"{v:.2f}"
    return str(v)


def machine_info() -> dict[str, str]:
    """Date, host, CPU, cores and the versions of the libraries that matter."""
    import importlib.metadata as md

    cpu = "?"
    with contextlib.suppress(OSError):
        m = re.search(r"^model name\s*:\s*(.+)$", Path("/proc/cpuinfo").read_text(), re.M)
        cpu = m.group(1).strip() if m else "?"
    versions = {}
    for dist in ("geo-server", "numpy", "eclipse-zenoh", "pymodbus", "pyads"):
        try:
            versions[dist] = md.version(dist)
        except md.PackageNotFoundError:
            versions[dist] = "not installed"
    return {
        "date": time.strftime("%Y-%m-%d %H:%M:%S %z"),
        "uname": subprocess.run(["uname", "-a"], capture_output=True, text=True).stdout.strip(),
        "cpu": cpu,
        "cores": str(os.cpu_count()),
        "python": platform.python_version(),
        **versions,
    }


def emit(markdown: str, out: str | None) -> None:
    """Print a part's Markdown and also write it to `out` (for run_all)."""
    sys.stdout.write(markdown)
    sys.stdout.flush()
    if out:
        Path(out).write_text(markdown, encoding="utf-8")
