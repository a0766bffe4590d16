"""The server's time slice: its wake-ups come before a busy neighbour's turn ends
(docs/design.md §5, docs/security.md *OPC UA*).

An ADS or Modbus request wakes the thread that answers it. On a small host whose cores
are busy — an OPC UA client decoding a Browse flood on the same machine, the OPC UA
process answering it, a compiler in the next terminal — Linux's fair scheduler (EEVDF,
since 6.6) lets the task on the core finish its time slice before the woken one runs:
with the default slice (0.75 ms times one plus the log2 of the cores) every answer may
wait up to that long. A bare responder that shares nothing with geo-server but the cores
showed it: its p99 rose 6-10× under a Browse flood (docs/benchmarks.md).

Since Linux 6.12 a task may ask for a shorter slice (`sched_setattr`'s `sched_runtime`
for SCHED_OTHER, 0.1-100 ms, no privilege needed); a task with a shorter slice has an
earlier deadline and preempts at its wake-up. The composition root asks for one
(`request`, `geo-server run --time-slice-us`) for every thread it has (a library's
started at import among them); every thread and child process started later inherits
it, and OPC UA's process gives it back (`request(0)`), so the
interface an attacker drives never preempts the others. Its own processor time is
unchanged; only who runs first at a wake-up.

Elsewhere (other systems, older kernels, another scheduling policy chosen with `chrt`)
`request` changes nothing and says so with None.
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
#: `sched_setattr`, `sched_getattr` per machine (glibc before 2.41 has no wrapper).
_CALLS = {"x86_64": (314, 315), "aarch64": (274, 275), "arm64": (274, 275)}


def _syscalls() -> tuple[ctypes.CDLL, int, int] | None:
    if sys.platform != "linux":
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
    attr = _get(libc, get_call)
    if attr is None or attr[1] not in _FAIR or not attr[5]:
        return None
    return int(attr[5] // 1000)


def request(us: int) -> int | None:
    """Ask for a slice of `us` µs (`MIN_US`-`MAX_US`; 0: the kernel's default) for every
    thread of this process — those a library started at its import too — and so for
    every thread and child process started afterwards, keeping each one's policy and
    niceness. The calling thread's slice once applied, else None (see the module;
    nothing is changed then)."""
    if us and not MIN_US <= us <= MAX_US:
        raise ValueError(f"a time slice is {MIN_US}-{MAX_US} µs (0: the kernel's), not {us}")
    calls = _syscalls()
    if calls is None:
        return None
    libc, set_call, get_call = calls
    tids = [int(t) for t in os.listdir("/proc/self/task")]
    for tid in sorted(tids, key=lambda t: t != threading.get_native_id()):  # (this one first)
        attr = _get(libc, get_call, tid)
        if attr is None or attr[1] not in _FAIR:
            continue  # (gone meanwhile, or another policy: left as it is)
        _, policy, _, nice, _, _, _, _ = attr
        packed = _ATTR.pack(_ATTR.size, policy, 0, nice, 0, us * 1000, 0, 0)
        libc.syscall(set_call, tid, ctypes.create_string_buffer(packed), 0)
    now = current_us()
    # (a kernel before 6.12 takes the call and ignores the runtime: it reports none)
    return now if now is not None and (not us or now == us) else None


def _get(libc: ctypes.CDLL, get_call: int, tid: int = 0) -> tuple[int, ...] | None:
    buf = ctypes.create_string_buffer(_ATTR.size)
    if libc.syscall(get_call, tid, buf, _ATTR.size, 0) != 0:
        return None
    return _ATTR.unpack(buf.raw)


__all__ = ["DEFAULT_US", "MAX_US", "MIN_US", "current_us", "request"]
