"""The concurrency map (docs/design.md §5.10), where running can check it: library code
starts no thread and changes no process-wide setting, a status is a copy, and a
subscriber that leaves while a snapshot is handed out makes no other subscriber miss it.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
import threading

from geo_server.machine.machine import Machine
from geo_server.machine.scheduler import Scheduler
from geo_server.service import ObjectService

#: imports every module of the package, then makes a machine, its stepped engine and
#: its service and runs a few cycles; prints what changed in the process
PROBE = textwrap.dedent(
    """
    import importlib, json, pkgutil, sys, threading
    from numba.core import config
    before = (threading.active_count(), sys.getswitchinterval(), config.CACHE_DIR)
    import geo_server
    for m in pkgutil.walk_packages(geo_server.__path__, "geo_server."):
        if m.name.endswith("__main__"):
            continue
        importlib.import_module(m.name)
    from geo_server import access, jit
    from geo_server.listfile import load_machine
    from geo_server.machine.machine import Machine
    from geo_server.paths import default_startup_list
    from geo_server.service import ObjectService
    svc = ObjectService(Machine(load_machine(default_startup_list()), homed=True))
    access.step(svc, 3)
    after = (threading.active_count(), sys.getswitchinterval(), config.CACHE_DIR)
    print(json.dumps({"before": before, "after": after, "loaded": jit.loaded(),
                      "threads": [t.name for t in threading.enumerate()]}))
    """
)


def test_library_code_starts_no_thread_and_changes_no_process_setting() -> None:
    """Importing every module and making a machine, its engine and its service: the
    same threads, the same GIL switch interval, numba's cache folder untouched, and the
    compiled cycle not loading (the composition root starts that)."""
    done = subprocess.run(
        [sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert got["after"] == got["before"], got
    assert got["threads"] == ["MainThread"], got
    assert got["loaded"] is False


def test_a_status_is_a_copy_of_the_counters_it_shows(service: ObjectService) -> None:
    """An interface's counters go on counting on their own thread while a status taken
    from them is serialized elsewhere: the status holds copies."""
    busy = {"gets_refused": 0}
    service.status_extra["zenoh_busy"] = busy
    st = service.status()
    busy["gets_refused"] = 7
    service.status_extra["late"] = 1
    assert st["zenoh_busy"] == {"gets_refused": 0}
    assert "late" not in st


def test_a_subscriber_leaving_during_a_publication_makes_no_other_miss_it(
    machine: Machine,
) -> None:
    """The first subscriber unsubscribes itself when it is handed a snapshot (as a
    client that closes does, from whatever thread): the second still gets that snapshot
    (handed out from a list changed in place, it was skipped)."""
    service = ObjectService(machine)
    second: list[int] = []
    leave: list[object] = []

    def first(snap: object) -> None:
        leave[0]()  # type: ignore[operator]

    leave.append(service.subscribe(first))
    service.subscribe(lambda snap: second.append(snap.cycle))
    service.stepper().step(1)
    assert second == [1]


def test_counting_a_catch_up_from_many_threads_loses_none(machine: Machine) -> None:
    """Catch-ups are timed by whichever thread asked (the loop, Zenoh's, a worker)."""
    stats = Scheduler(machine, mode="stepped").sync_stats
    n, threads = 20_000, 4
    start = threading.Barrier(threads)

    def count() -> None:
        start.wait()
        for _ in range(n):
            stats.record(0.0, 1.0)

    workers = [threading.Thread(target=count) for _ in range(threads)]
    before = stats.count
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    assert stats.count - before == n * threads
