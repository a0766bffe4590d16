"""The server's time slice (geo_server/timeslice.py; docs/design.md §5): asked of Linux
by `geo-server run` for every thread of the server, given back by OPC UA's process.
Checked against the kernel's own account (/proc/PID/task/TID/sched), in processes of
their own: a slice is a property of the threads that ask for it, and the test process's
are not to change."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import free_port, geo_server_cmd, geo_server_running
from support.procfs import children, slices_ns, spawned

from geo_server import timeslice

#: What a fresh process of this machine reports, in a process of its own: its default
#: slice (ns) and whether the kernel takes a slice of 100 µs (Linux 6.12 or later).
_PROBE = """
import json, sys, threading
from pathlib import Path
from geo_server import timeslice
def kernel(tid=None):  # (the calling thread's, or thread tid's, as /proc says)
    tid = tid or threading.get_native_id()
    for line in Path(f"/proc/self/task/{tid}/sched").read_text().splitlines():
        if line.startswith("se.slice"):
            return int(line.split(":")[1])
go = threading.Event()
earlier = threading.Thread(target=go.wait)  # (started before: a library's at its import)
earlier.start()
out = {"default": kernel(), "asked": timeslice.request(int(sys.argv[1]))}
out["kernel"] = kernel()
out["earlier"] = kernel(earlier.native_id)
go.set()
earlier.join()
seen = []
t = threading.Thread(target=lambda: seen.append(kernel()))
t.start(); t.join()
out["thread"] = seen[0]
out["reset"] = timeslice.request(0)
out["kernel_after_reset"] = kernel()
print(json.dumps(out))
"""


def _probe(us: int, nice: int = 0) -> dict[str, int | None]:
    pre = (lambda: os.nice(nice)) if nice else None
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, str(us)],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
        preexec_fn=pre,
    )
    result: dict[str, int | None] = json.loads(out.stdout)
    return result


def _supported() -> bool:
    return sys.platform == "linux" and _probe(100)["asked"] == 100


needs_slices = pytest.mark.skipif(
    not _supported(), reason="Linux 6.12 or later (a slice per task) on x86-64 or arm64"
)


@needs_slices
def test_a_slice_asked_for_is_the_kernels_and_every_later_threads() -> None:
    """100 µs asked: /proc shows 100 000 ns for the thread, for one started before and
    one started after; 0 gives the kernel's default back."""
    got = _probe(100)
    assert got["kernel"] == 100_000
    assert got["earlier"] == 100_000
    assert got["thread"] == 100_000
    assert got["kernel_after_reset"] == got["default"]
    assert got["default"] != 100_000  # (else the test could not tell)


@needs_slices
def test_a_slice_keeps_the_processs_niceness() -> None:
    """A server started with `nice -n 5` stays at niceness 5 (the call sets the whole
    attribute: a zero there would raise it back to 0)."""
    script = (
        "import os; from geo_server import timeslice; "
        "print(timeslice.request(250), os.getpriority(os.PRIO_PROCESS, 0))"
    )
    out = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
        preexec_fn=lambda: os.nice(5),
    )
    assert out.stdout.split() == ["250", "5"]


@pytest.mark.parametrize("us", [1, 99, 100_001, -100])
def test_a_slice_out_of_the_kernels_range_is_refused(us: int) -> None:
    with pytest.raises(ValueError, match="100-100000"):
        timeslice.request(us)


@pytest.mark.parametrize("us", ["50", "200000"])
def test_run_refuses_a_slice_out_of_range(us: str, tmp_path: Path) -> None:
    out = subprocess.run(
        [*geo_server_cmd(), "run", "--time-slice-us", us],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2
    assert "--time-slice-us must be 0 or 100-100000" in out.stderr


@pytest.mark.slow
@needs_slices
@pytest.mark.parametrize(("us", "server_ns"), [(None, 100_000), (400, 400_000), (0, None)])
def test_run_gives_every_server_thread_the_slice_and_opcua_the_kernels(
    us: int | None, server_ns: int | None, tmp_path: Path
) -> None:
    """`geo-server run` (default 100 µs, or `--time-slice-us`): every thread of the
    server — its loop, the cycle, the interfaces' — has that slice; OPC UA's process,
    which the network drives, has the kernel's default; with 0, everyone has it."""
    default = _probe(100)["default"]
    args = ["run", "--homed", "--no-zenoh", "--status-period", "60"]
    args += ["--ads-port", str(free_port()), "--modbus-port", str(free_port())]
    args += ["--opcua-endpoint", f"opc.tcp://127.0.0.1:{free_port()}", "--opcua-no-companions"]
    args += ["--ads-udp-port", "0"]
    if us is not None:
        args += ["--time-slice-us", str(us)]
    with geo_server_running(args, tmp_path, "opcua: ready") as proc:
        server = slices_ns(proc.pid)
        (child,) = (c for c in children(proc.pid) if spawned(c))
        opcua = slices_ns(child)
    assert len(server) >= 4, server  # (the loop, the cycle, OPC UA's pipe, …)
    assert set(server.values()) == {server_ns or default}, server
    assert set(opcua.values()) == {default}, opcua
