"""The server's time slice (geo_server/timeslice.py; docs/design.md §5.11): asked of
Linux by `geo-server run` for every thread of the server, given back by OPC UA's
process. Checked against the kernel's own account (/proc/PID/task/TID/sched), in
processes of their own: a slice belongs to the threads that ask for it, and the test
process's are not to change."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import free_port, geo_server_cmd, geo_server_running
from support.procfs import children, slices_ns, spawned

from geo_server import timeslice

#: A process of its own: its threads' slices as /proc says (None where it says nothing)
#: at the kernel's default (the suite runs at the server's slice) and after
#: `request(argv[1])`, a thread started before it (at a niceness of its own, two above
#: the process's) and one after, and the slice once given back.
_PROBE = """
import json, os, sys, threading
from pathlib import Path
from geo_server import timeslice
def kernel(tid=None):
    tid = tid or threading.get_native_id()
    try:
        lines = Path(f"/proc/self/task/{tid}/sched").read_text().splitlines()
    except OSError:
        return None
    return next((int(l.split(":")[1]) for l in lines if l.startswith("se.slice")), None)
timeslice.request(0)  # (the kernel's default, whatever this process inherited)
go, ready = threading.Event(), threading.Event()
BASE = os.getpriority(os.PRIO_PROCESS, 0)  # (the suite's; raised is always allowed)
def earlier_thread():
    os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), min(BASE + 2, 19))
    ready.set()
    go.wait()
earlier = threading.Thread(target=earlier_thread)
earlier.start()
ready.wait()
out = {"default": kernel(), "asked": timeslice.request(int(sys.argv[1]))}
out["kernel"] = kernel()
out["earlier"] = kernel(earlier.native_id)
out["earlier_nice"] = os.getpriority(os.PRIO_PROCESS, earlier.native_id) - BASE
out["nice"] = os.getpriority(os.PRIO_PROCESS, 0) - BASE
go.set()
earlier.join()
seen = []
later = threading.Thread(target=lambda: seen.append(kernel()))
later.start()
later.join()
out["later"] = seen[0]
out["reset"] = timeslice.request(0)
out["kernel_after_reset"] = kernel()
print(json.dumps(out))
"""


def _probe(us: int) -> dict[str, int | None]:
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, str(us)],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    )
    result: dict[str, int | None] = json.loads(out.stdout)
    return result


def _supported() -> bool:
    """Linux 6.12 or later, on a 64-bit x86 or Arm, with /proc's scheduling files."""
    if sys.platform != "linux":
        return False
    got = _probe(100)
    return got["asked"] == 100 and got["kernel"] is not None


needs_slices = pytest.mark.skipif(
    not _supported(), reason="Linux 6.12 or later (a slice per task) on x86-64 or arm64"
)


@needs_slices
def test_a_slice_asked_for_is_every_threads_and_keeps_their_niceness() -> None:
    """100 µs asked: /proc shows 100 000 ns for the thread, for one started before (its
    niceness, two above the process's, its own still) and one started after; 0 gives
    the default back."""
    got = _probe(100)
    assert got["default"] != 100_000  # (else the test could not tell)
    assert (got["kernel"], got["earlier"], got["later"]) == (100_000, 100_000, 100_000)
    raised = min(os.getpriority(os.PRIO_PROCESS, 0) + 2, 19) - os.getpriority(os.PRIO_PROCESS, 0)
    assert (got["nice"], got["earlier_nice"]) == (0, raised)
    assert got["reset"] == got["default"] // 1000
    assert got["kernel_after_reset"] == got["default"]


@needs_slices
def test_the_longest_slice_is_taken() -> None:
    assert _probe(100_000)["kernel"] == 100_000_000


@needs_slices
def test_a_slice_keeps_the_processs_niceness_and_reset_on_fork() -> None:
    """A server started with `nice -n 5 chrt -o -R 0` keeps both (niceness counted from
    the suite's, whatever it is): the call sets the
    whole attribute, and a zero niceness or a cleared flag would undo what the user
    chose (an unprivileged thread may not clear the flag: the call would fail)."""
    script = (
        "import os; from geo_server import timeslice; base = os.nice(0); os.nice(5); "
        "os.sched_setscheduler(0, os.SCHED_OTHER | os.SCHED_RESET_ON_FORK, os.sched_param(0)); "
        "print(timeslice.request(250), os.getpriority(os.PRIO_PROCESS, 0) - base, "
        "os.sched_getscheduler(0) == os.SCHED_OTHER | os.SCHED_RESET_ON_FORK)"
    )
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, check=True, timeout=60
    )
    assert out.stdout.split() == ["250", "5", "True"]


@needs_slices
def test_a_thread_of_another_policy_is_left_alone() -> None:
    """SCHED_IDLE (no privilege needed to choose it): no slice, and None said."""
    script = (
        "import os; from geo_server import timeslice; "
        "os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0)); "
        "print(timeslice.request(250), os.sched_getscheduler(0) == os.SCHED_IDLE)"
    )
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, check=True, timeout=60
    )
    assert out.stdout.split() == ["None", "True"]


@pytest.mark.parametrize("us", [1, 99, 100_001, -100])
def test_a_slice_out_of_the_kernels_range_is_refused(us: int) -> None:
    with pytest.raises(ValueError, match=r"0 \(the kernel's\) or 100-100000 µs"):
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
    assert f"--time-slice-us: a time slice is 0 (the kernel's) or 100-100000 µs, not {us}" in (
        out.stderr
    )


#: Starts `geo-server ARGS…` (`geo_server_running`'s launcher) with a slice of 300 µs
#: already asked for, as a parent with
#: its own (a benchmark's probe, a service manager) would hand it down.
_LAUNCH = "import os, sys; from geo_server import timeslice; timeslice.request(300); " + (
    "os.execv(sys.argv[1], sys.argv[1:])"
)


@pytest.mark.slow
@needs_slices
@pytest.mark.parametrize(("us", "server_ns"), [(None, 100_000), (400, 400_000), (0, None)])
def test_run_gives_every_server_thread_the_slice_and_opcua_the_kernels(
    us: int | None, server_ns: int | None, tmp_path: Path
) -> None:
    """`geo-server run` (default 100 µs, or `--time-slice-us`), started by a parent with
    a slice of 300 µs: every thread of the server — its loop, the cycle, the
    interfaces' — has the slice asked for; OPC UA's process, which the network drives,
    has the kernel's default; with 0, everyone has it."""
    default = _probe(100)["default"]
    args = ["run", "--homed", "--no-zenoh", "--status-period", "60", "--ads-udp-port", "0"]
    args += ["--ads-port", str(free_port()), "--modbus-port", str(free_port())]
    args += ["--opcua-endpoint", f"opc.tcp://127.0.0.1:{free_port()}", "--opcua-no-companions"]
    if us is not None:
        args += ["--time-slice-us", str(us)]
    launcher = [sys.executable, "-c", _LAUNCH]
    with geo_server_running(args, tmp_path, "opcua: ready", launcher) as proc:
        server = slices_ns(proc.pid)
        (child,) = (c for c in children(proc.pid) if spawned(c))
        opcua = slices_ns(child)
    assert len(server) >= 4, server  # (the loop, the cycle, OPC UA's pipe, …)
    assert set(server.values()) == {server_ns or default}, server
    assert set(opcua.values()) == {default}, opcua


@pytest.mark.slow
@needs_slices
@pytest.mark.parametrize("cycle_in", ["thread", "process"])
def test_the_punctual_cycle_keeps_the_kernels_slice(cycle_in: str, tmp_path: Path) -> None:
    """The punctual engine spins before each deadline: its thread, and it alone, keeps
    the kernel's slice, which a short one would hand away every 100 µs of the spin —
    a thread of the server, or the main thread of the cycle's process."""
    default = _probe(100)["default"]
    args = ["run", "--homed", "--engine", "punctual", "--cycle-in", cycle_in, "--no-zenoh"]
    args += ["--no-opcua", "--status-period", "60", "--ads-udp-port", "0"]
    args += ["--ads-port", str(free_port()), "--modbus-port", str(free_port())]
    # (its first line: the cycle starts after it)
    with geo_server_running(args, tmp_path, "geo-server ") as proc:
        deadline = time.monotonic() + 60
        while (slices := _cycle_slices(proc.pid, cycle_in))[-1] != default:
            assert time.monotonic() < deadline, slices  # (the cycle not started yet)
            time.sleep(0.05)
        server = slices_ns(proc.pid)
    assert slices.count(default) == 1, slices
    assert set(slices) <= {100_000, default}, slices
    if cycle_in == "process":  # (the server's own threads: all at the short one)
        assert set(server.values()) == {100_000}, server


def _cycle_slices(pid: int, cycle_in: str) -> list[int]:
    """The slices of the threads that may run the cycle: the server's, or its cycle
    process's (with OPC UA off, the one child `multiprocessing` spawned)."""
    if cycle_in == "thread":
        return sorted(slices_ns(pid).values())
    kids = [c for c in children(pid) if spawned(c)]
    return sorted(v for c in kids for v in slices_ns(c).values()) or [0]
