"""Child of tests/test_robust_save_kill.py: saves TEMPC values in a loop until killed.

Imports geo-server once, then, per line `go <coefA> <offA> <coefB> <offB>` on stdin,
forks a worker that loads the machine from the start-up list given as argv[1] (the
current state of the lists), prints `ready <pid>`, and then alternately writes the A and
the B values of axis 1 and calls `service.commands.save()` — as fast as it can, until the
parent kills it with SIGKILL; after its first save it prints `saved`. The zygote reaps
the worker and prints `dead <signal>`.
Forking keeps the 30 rounds cheap (no interpreter start, numpy import or loading of the
compiled cycle per kill: the zygote runs a cycle once before it forks).
"""

from __future__ import annotations

import os
import sys

from geo_server import access, jit
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.service import ObjectService


def worker(startup: str, a: tuple[float, int], b: tuple[float, int]) -> None:
    service = ObjectService(Machine(load_machine(startup), homed=True))
    print(f"ready {os.getpid()}", flush=True)
    for j in range(100_000):  # killed long before the end
        coef, off = a if j % 2 == 0 else b
        access.write_name(service, "TEMPC::coefficient", 1, coef)
        access.write_name(service, "TEMPC::offset_0", 1, off)
        access.step(service, 1)
        result = service.commands.save()
        if not result.ok:
            print(f"save failed: {result.errors}", flush=True)
            os._exit(3)
        if j == 0:
            print("saved", flush=True)
    os._exit(0)


def main() -> None:
    startup = sys.argv[1]
    jit.load()  # the compiled cycle loaded once, here (a fork must not copy a loading thread)
    print("zygote", flush=True)
    for line in sys.stdin:
        _go, ca, oa, cb, ob = line.split()
        sys.stdout.flush()
        pid = os.fork()
        if pid == 0:
            try:
                worker(startup, (float(ca), int(oa)), (float(cb), int(ob)))
            finally:
                os._exit(4)
        _pid, status = os.waitpid(pid, 0)
        sig = os.WTERMSIG(status) if os.WIFSIGNALED(status) else -os.WEXITSTATUS(status)
        print(f"dead {sig}", flush=True)


if __name__ == "__main__":
    main()
