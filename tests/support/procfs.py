"""What Linux's /proc says of a process the test started (its children, its threads'
scheduling): the kernel's own view, not the server's account of itself."""

from __future__ import annotations

from pathlib import Path


def children(pid: int) -> list[int]:
    """The child processes of `pid`, whichever of its threads started them."""
    tasks = Path(f"/proc/{pid}/task").iterdir()
    return [int(c) for t in tasks for c in (t / "children").read_text().split()]


def spawned(pid: int) -> bool:
    """Whether `pid` is a process `multiprocessing` spawned (OPC UA's)."""
    return b"spawn_main" in Path(f"/proc/{pid}/cmdline").read_bytes()


def slices_ns(pid: int) -> dict[str, int]:
    """Each thread of `pid` (by its name and id) and the time slice the scheduler gives
    it (`se.slice` of /proc/PID/task/TID/sched, ns)."""
    out = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            name = (task / "comm").read_text().strip()
            lines = (task / "sched").read_text().splitlines()
        except (FileNotFoundError, ProcessLookupError):
            continue  # (a thread that ended meanwhile)
        for line in lines:
            if line.startswith("se.slice"):
                out[f"{name}/{task.name}"] = int(line.split(":")[1])
    return out
