"""Child of tests/test_security_recorder.py: records every object over `golden.csv` in a
loop until killed.

Imports geo-server once, then, per line `go` on stdin, forks a worker that builds the
default machine (stepped) with the recordings folder argv[1], prints `ready <pid>`, and
then records `*` into `golden.csv` with `overwrite` — argv[2] cycles, stop (the rest
written, the file replaced, `replaced` printed), again — as fast as it can, until the
parent kills it with SIGKILL. The zygote reaps the worker and prints `dead <signal>`.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from geo_server import access
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.paths import default_startup_list
from geo_server.service import ObjectService


def worker(folder: str, rows: int) -> None:
    service = ObjectService(Machine(load_machine(default_startup_list()), homed=True))
    service.recordings.record_dir = Path(folder)
    print(f"ready {os.getpid()}", flush=True)
    for _ in range(100_000):  # killed long before the end
        service.recordings.start({"objects": ["*"]}, "golden.csv", "kill", overwrite=True)
        access.step(service, rows)
        service.recordings.stop()
        print("replaced", flush=True)  # (the parent may wait for one before its kill)
    os._exit(0)


def main() -> None:
    folder, rows = sys.argv[1], int(sys.argv[2])
    print("zygote", flush=True)
    for _line in sys.stdin:
        sys.stdout.flush()
        pid = os.fork()
        if pid == 0:
            try:
                worker(folder, rows)
            finally:
                os._exit(4)
        _pid, status = os.waitpid(pid, 0)
        sig = os.WTERMSIG(status) if os.WIFSIGNALED(status) else -os.WEXITSTATUS(status)
        print(f"dead {sig}", flush=True)


if __name__ == "__main__":
    main()
