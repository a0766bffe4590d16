"""The server's time slice: its wake-ups come before a busy neighbour's turn ends
(docs/design.md §5.11).

An ADS or Modbus request wakes the thread that answers it. On a small host whose cores
are busy — an OPC UA client decoding a Browse flood on the same machine, the OPC UA
process answering it, a compiler in the next terminal — Linux's fair scheduler (EEVDF,
since 6.6) lets the task on the core finish its time slice before the woken one runs:
with the default slice (1.4 ms on a 2-core VM) every answer may wait up to that long.

Since Linux 6.12 a task may ask for a shorter slice (`sched_setattr`'s `sched_runtime`
for SCHED_OTHER and SCHED_BATCH, 0.1-100 ms, no privilege needed); a task with a shorter
slice has an earlier deadline and preempts at its wake-up. Its processor time stays its
fair share; only who runs first at a wake-up changes. The composition root asks for one
(`request`, `geo-server run --time-slice-us`) for every thread the process has (a
library's started at import among them); threads and child processes started later
inherit it, and OPC UA's process gives it back (`request(0)`), so the interface an
attacker drives never preempts the others; so does the punctual engine's cycle thread
for itself (`request(0, process=False)`: it spins before each deadline).

Elsewhere (other systems, 32-bit builds, kernels before 6.12) `request` changes nothing
and says so with None; a thread of a real-time, deadline or idle policy (`chrt`) is left
as it is.
"""

from __future__ import annotations

import ctypes
import os
import platform
import struct
import sys
import threading

#: The shortest and longest slice the kernel takes (µs: `sched_runtime`'s clamp).
MIN_US, MAX_US = 100, 100_000
#: geo-server run's default: the shortest.
DEFAULT_US = MIN_US

#: `struct sched_attr` of SCHED_ATTR_SIZE_VER0: size, policy, flags, nice, priority,
#: runtime, deadline, period (include/uapi/linux/sched/types.h).
_ATTR = struct.Struct("IIQiIQQQ")
#: The policies a slice applies to: SCHED_OTHER, SCHED_BATCH.
_FAIR = (0, 3)
#: The one flag of a thread's attributes to keep (`chrt -R`): the kernel sets it from
#: the flags passed, and refuses an unprivileged thread's clearing it.
_RESET_ON_FORK = 0x01
#: `sched_setattr`, `sched_getattr` of a 64-bit process (glibc before 2.41 has no
#: wrapper), by the kernel's name of the machine.
_CALLS = {"x86_64": (314, 315), "aarch64": (274, 275)}
#: Passes over the process's threads: one another thread started meanwhile is in the next.
_PASSES = 3


def problem(us: int | None) -> str | None:
    """Why `us` is no slice to ask for (None: it is one, or None, not asked)."""
    if us and not MIN_US <= us <= MAX_US:
        return f"a time slice is 0 (the kernel's) or {MIN_US}-{MAX_US} µs, not {us}"
    return None


def _syscalls() -> tuple[ctypes.CDLL, int, int] | None:
    if sys.platform != "linux" or ctypes.sizeof(ctypes.c_void_p) != 8:
        return None
    numbers = _CALLS.get(platform.machine())
    if numbers is None:
        return None
    return ctypes.CDLL(None, use_errno=True), *numbers


def current_us() -> int | None:
    """The calling thread's slice (µs) as the kernel reports it; None where it does not
    (not Linux, a kernel before 6.12, a policy without slices)."""
    calls = _syscalls()
    if calls is None:
        return None
    libc, _, get_call = calls
    attr = _get(libc, get_call, 0)
    if attr is None or attr[1] not in _FAIR or not attr[5]:
        return None
    return int(attr[5] // 1000)


def request(us: int, *, process: bool = True) -> int | None:
    """Ask for a slice of `us` µs (`MIN_US`-`MAX_US`; 0: the kernel's default) for every
    thread of this process, those a library started at its import too (`process` False:
    the calling thread alone), and so for every thread and child process started
    afterwards, keeping each one's policy, niceness and reset-on-fork flag; a thread of
    another policy (real-time, deadline, idle) is left as it is. The calling thread's
    slice once it has it, else None: not Linux 6.12 or later on a 64-bit x86 or Arm, or
    the kernel refused it (see the module); the other threads may have been given it
    all the same."""
    if (why := problem(us)) is not None:
        raise ValueError(why)
    calls = _syscalls()
    if calls is None:
        return None
    libc, set_call, get_call = calls
    me = threading.get_native_id()
    done: set[int] = set()
    mine = False
    for _ in range(_PASSES if process else 1):
        tids = (_threads(me) if process else {me}) - done
        for tid in sorted(tids, key=lambda t: t != me):  # (this one first)
            done.add(tid)
            applied = _set(libc, set_call, get_call, tid, us)
            mine = applied if tid == me else mine
    now = current_us() if mine else None
    # (a kernel before 6.12 takes the call and ignores the runtime: it reports none)
    return now if now is not None and (not us or now == us) else None


def _threads(me: int) -> set[int]:
    """The process's threads (only the calling one where /proc does not list them)."""
    try:
        tids = {int(t) for t in os.listdir("/proc/self/task")}
    except (OSError, ValueError):
        return {me}
    return tids if me in tids else {me}  # (a /proc of another PID namespace)


def _set(libc: ctypes.CDLL, set_call: int, get_call: int, tid: int, us: int) -> bool:
    attr = _get(libc, get_call, tid)
    if attr is None or attr[1] not in _FAIR:
        return False  # (gone meanwhile, or another policy: left as it is)
    _, policy, flags, nice, _, _, _, _ = attr
    packed = _ATTR.pack(_ATTR.size, policy, flags & _RESET_ON_FORK, nice, 0, us * 1000, 0, 0)
    return int(libc.syscall(set_call, tid, ctypes.create_string_buffer(packed), 0)) == 0


def _get(libc: ctypes.CDLL, get_call: int, tid: int) -> tuple[int, ...] | None:
    buf = ctypes.create_string_buffer(_ATTR.size)
    if libc.syscall(get_call, tid, buf, _ATTR.size, 0) != 0:
        return None
    return _ATTR.unpack(buf.raw)


__all__ = ["DEFAULT_US", "MAX_US", "MIN_US", "current_us", "problem", "request"]
