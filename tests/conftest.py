"""Shared fixtures: the default machine in stepped mode, free ports, an asyncio loop thread."""

from __future__ import annotations

import asyncio
import contextlib
import faulthandler
import gc
import os
import shutil
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path

import pytest

from geo_server import jit, ports, timeslice
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.machine.scheduler import switch_interval
from geo_server.paths import data_dir, default_startup_list
from geo_server.service import ObjectService

#: `geo-server run` with the web HMI alone (every other interface off)
RUN_HTTP_ONLY = (
    sys.executable,
    "-m",
    "geo_server.cli",
    "run",
    "--no-zenoh",
    "--no-modbus",
    "--no-ads",
    "--no-opcua",
)


def pytest_configure(config: pytest.Config) -> None:
    """The cycle's machine code, loaded (compiled into the cache on a first run) once
    before any test: the servers the tests start in subprocesses load it from the cache
    (tests/test_jit.py checks that the interpreted laws give the same numbers)."""
    jit.load()
    # every process the tests start (servers, the clients' CLIs, pytester's runs, whose
    # HOME is a fresh folder) loads this one compile: the suite compiles once
    folder = jit.cache_dir()
    if folder is not None:
        os.environ["GEO_SERVER_JIT_CACHE"] = str(folder.parent)
    # each pytest-xdist worker draws its servers' ports from a share of its own
    # (`ports.free_port`), so that two workers never hand out the same port
    worker, count = (
        os.environ.get("PYTEST_XDIST_WORKER"),
        os.environ.get("PYTEST_XDIST_WORKER_COUNT"),
    )
    if worker and count:
        lo, hi = ports.BELOW_EPHEMERAL_FROM, ports.ephemeral_range()[0]
        width = (hi - lo) // int(count)
        # (modulo: a worker xdist starts again in place of a dead one counts on)
        first = lo + (int(worker.removeprefix("gw")) % int(count)) * width
        os.environ["GEO_SERVER_PORT_SPAN"] = f"{first}-{first + width}"
    # what `geo-server run` sets for its cycle thread (the suite is the composition root
    # of the machines its tests make: library code never changes it)
    sys.setswitchinterval(switch_interval(1))
    # and the scheduler slice it asks for (docs/design.md §5.11): set here once, so a
    # test that runs `geo_server.cli.main` in this process changes nothing for the next
    timeslice.request(timeslice.DEFAULT_US)


#: Memory blocks the allocator may gain after a test before the cyclic collector runs
#: (`_collect_big_garbage`): a closed OPC UA server leaves its address space, about half
#: a million objects in reference cycles, to the collector.
GARBAGE_SLACK_BLOCKS = 1_000_000
_blocks_after_collect = 0


@pytest.fixture(autouse=True)
def _collect_big_garbage() -> Iterator[None]:
    """After a test that left a lot behind, collect it now, between tests.

    The collector's oldest generation runs only once enough objects have aged into it, so
    garbage in cycles piles up over many tests (the OPC UA tests left 7.5 million objects)
    and is then collected in one pass, holding the interpreter lock for seconds (5.5 s
    measured next to another test run) in whatever test is running then: every server
    thread of that test stops and its clients time out (the likely cause of a CI run
    whose flood test and Modbus reader both waited 5 s). Autouse fixtures
    are set up first, so this runs after the test's own fixtures have closed its servers.
    """
    global _blocks_after_collect
    yield
    if sys.getallocatedblocks() - _blocks_after_collect > GARBAGE_SLACK_BLOCKS:
        gc.collect()
        _blocks_after_collect = sys.getallocatedblocks()


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago, for a server a test starts
    (often in another process), never one handed out before in this run."""
    return ports.free_port()


def geo_server_cmd() -> list[str]:
    """The `geo-server` console script of this environment (the module if none)."""
    exe = Path(sys.executable).parent / "geo-server"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "geo_server.cli"]


@contextlib.contextmanager
def geo_server_running(
    args: list[str], cwd: Path, ready: str, launcher: Sequence[str] = ()
) -> Iterator[subprocess.Popen[str]]:
    """`geo-server ARGS` in a subprocess (this environment's installed copy: no
    PYTHONPATH; started by `launcher`, a command that runs the rest, when given), once
    it printed a line starting with `ready`; stopped with Ctrl-C (SIGINT) after, unless
    it ended already."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.Popen(
        [*launcher, *geo_server_cmd(), *args], cwd=cwd, env=env, stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            if line.startswith(ready):
                break
        else:
            raise AssertionError(f"geo-server {args[0]} ended before printing {ready!r}")
        yield proc
    finally:
        stop_process(proc, signal.SIGINT, 30)
        if proc.stdout is not None:
            proc.stdout.close()


def stop_process(proc: subprocess.Popen, sig: int, grace: float) -> None:
    """Send `sig` to `proc` if it still runs, give it `grace` seconds to end, then kill
    it; reaped either way."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(grace)
        except subprocess.TimeoutExpired:
            proc.kill()
    proc.wait(5)


@pytest.fixture
def default_cfg():
    return load_machine(default_startup_list())


@pytest.fixture
def machine(default_cfg) -> Machine:
    """The default machine, every axis homed, stepped (nothing runs until stepped)."""
    return Machine(default_cfg, cycle_s=0.001, homed=True)


@pytest.fixture
def service(machine) -> ObjectService:
    return ObjectService(machine)


@pytest.fixture
def lists_copy(tmp_path: Path) -> Path:
    """A private copy of the default machine's lists; returns its start-up list."""
    dst = tmp_path / "lists"
    shutil.copytree(data_dir("lists"), dst, ignore=shutil.ignore_patterns("examples", "tools"))
    return dst / "hochlauf.lis"


@pytest.fixture
def loop_thread() -> Iterator[asyncio.AbstractEventLoop]:
    """An asyncio loop running in a background thread (for servers under test)."""
    loop = asyncio.new_event_loop()
    t = threading.Thread(target=loop.run_forever, name="test-loop", daemon=True)
    t.start()
    yield loop
    loop.call_soon_threadsafe(loop.stop)
    t.join(5)
    loop.close()


def run_in(loop: asyncio.AbstractEventLoop, coro, timeout: float = 10.0):
    """Run a coroutine on the loop thread and wait for its result. One that does not
    finish in time fails the test with every thread's stack on stderr (where it hung)."""
    future = asyncio.run_coroutine_threadsafe(coro, loop)
    try:
        return future.result(timeout)
    except TimeoutError:
        faulthandler.dump_traceback(sys.__stderr__, all_threads=True)
        raise


def wait_until_routed(session, status_key: str, timeout: float = 10.0) -> None:
    """Block until the server knows every subscriber `session` declared before this call.

    A subscriber declared on a client session reaches the server asynchronously; a value
    published before that is lost to it, and a value published on change only once is
    then never seen. Declarations travel in order on one Zenoh link, so once a subscriber
    declared *last* (on the server's periodic `status` key) has received a sample, the
    earlier ones are routed too.
    """
    got = threading.Event()
    sub = session.declare_subscriber(status_key, lambda _s: got.set())
    try:
        assert got.wait(timeout), f"no publication on {status_key} within {timeout} s"
    finally:
        sub.undeclare()
