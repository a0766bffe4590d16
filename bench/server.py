"""`geo-server run` for benchmarks: the same transports, plus demo machines and raw timings.

    python bench/server.py [--demo-axes N] [--stats-size N] [--dump FILE] -- RUN-OPTIONS

RUN-OPTIONS are those of `geo-server run` (`--homed --cycle-ms 1 --zenoh-listen …`). The
machine is built as `geo-server run` builds it, and the interfaces are started by the
very same `geo_server.cli._serve`; the differences are:

- `--demo-axes N` serves `support.machines.full_machine(N)` (N axes, every
  compensation at the manuals' table sizes) instead of list files;
- `--stats-size N` additionally keeps the first N cycles' lateness, compute time and
  start time (the scheduler's own 10 000-cycle ring and its `status()` stay as they are,
  so the status costs what it costs in `geo-server run`);
- `--dump FILE` writes those arrays (µs, in cycle order) to an `.npz` file after a clean
  stop (SIGTERM), so a benchmark can cut exact windows and see the gaps between cycles.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from geo_server import cli, jit
from geo_server.machine.machine import Machine
from geo_server.machine.scheduler import CycleStats, Scheduler
from geo_server.service import ObjectService


class KeepingStats(CycleStats):
    """The scheduler's stats plus a record of the first `keep` cycles (bounded)."""

    def __init__(self, keep: int) -> None:
        super().__init__()
        # np.full touches every page now: RSS must not creep up as cycles are recorded
        # (np.zeros maps pages lazily, which would look like a leak in the soak).
        self.kept_lateness = np.full(keep, np.nan)
        self.kept_cycle = np.full(keep, np.nan)
        self.kept_start = np.full(keep, np.nan)  # µs since the first record, monotonic
        self._t0 = 0
        self._clock = time.monotonic_ns

    def record(self, lateness_us: float, cycle_us: float, kernel_us: float = 0.0) -> None:
        i = self.count
        super().record(lateness_us, cycle_us, kernel_us)
        if i < len(self.kept_lateness):
            now = self._clock()
            if i == 0:
                self._t0 = now
            self.kept_lateness[i] = lateness_us
            self.kept_cycle[i] = cycle_us
            # the cycle started `cycle_us` before now
            self.kept_start[i] = (now - self._t0) / 1000 - cycle_us

    def kept(self) -> int:
        return min(self.count, len(self.kept_lateness))


def build_machine(args: argparse.Namespace, demo_axes: int) -> Machine:
    """The default (or given) lists, or a demo machine of `demo_axes` full axes."""
    if demo_axes:
        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
        from support.machines import full_machine

        cfg = full_machine(demo_axes)
    else:
        from geo_server.listfile import load_machine
        from geo_server.paths import default_startup_list

        cfg = load_machine(Path(args.startup) if args.startup else default_startup_list())
    return Machine(cfg, cycle_s=args.cycle_ms / 1000.0, homed=args.homed)


def main() -> int:
    jit.load()  # the cycle's machine code before anything is timed (geo_server/jit.py)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--demo-axes", type=int, default=0, help="serve full_machine(N) (0: lists)")
    ap.add_argument("--stats-size", type=int, default=0, help="cycles to keep for --dump")
    ap.add_argument("--dump", help="write lateness/cycle times (.npz) after a clean stop")
    ap.add_argument("run_options", nargs=argparse.REMAINDER, help="-- geo-server run options")
    own = ap.parse_args()
    rest = own.run_options[1:] if own.run_options[:1] == ["--"] else own.run_options
    args = cli.build_parser().parse_args(["run", *rest])
    if args.cycle_in is None:
        args.cycle_in = cli.default_cycle_in(engine=args.engine)
    cli.ask_time_slice(args.time_slice_us)  # (as `geo-server run`'s composition root)

    local = build_machine(args, own.demo_axes)
    scheduler: Any
    if args.cycle_in == "process":
        from geo_server.machine.process import ProcessScheduler, RemoteMachine

        machine: Any = RemoteMachine(local.cfg, cycle_s=local.cycle_s, homed=args.homed)
        setup = partial(keep_and_dump, own.stats_size, own.dump) if own.stats_size else None
        scheduler = ProcessScheduler(
            machine, args.mode, args.cycles, child_setup=setup, engine=args.engine
        )
    else:
        machine = local
        scheduler = Scheduler(machine, mode=args.mode, max_cycles=args.cycles, engine=args.engine)
        finish = keep_and_dump(own.stats_size, own.dump, scheduler) if own.stats_size else None
    service = ObjectService(machine, scheduler)
    print(
        f"bench server: axes {list(machine.axes)}, cycle {args.cycle_ms} ms ({args.mode}, "
        f"cycle in its own {args.cycle_in})",
        flush=True,
    )
    try:
        asyncio.run(cli._serve(args, service, scheduler))
    finally:
        scheduler.stop()
    if args.cycle_in == "thread" and finish is not None:
        finish()
    print(f"stopped after {machine.cycle} cycles", flush=True)
    return 0


def keep_and_dump(keep: int, dump: str | None, scheduler: Scheduler) -> Callable[[], None]:
    """Give `scheduler` a `KeepingStats`; the returned function writes `dump` (.npz).
    Runs where the cycle runs: in this process, or in the GEO-cycle process."""
    stats = KeepingStats(keep)
    scheduler.stats = stats

    def finish() -> None:
        if not dump:
            return
        n = stats.kept()
        np.savez(
            dump,
            lateness_us=stats.kept_lateness[:n],
            cycle_us=stats.kept_cycle[:n],
            start_us=stats.kept_start[:n],
            first_cycle=1,
            overruns=scheduler.machine.overruns,
            cycle_errors=scheduler.cycle_errors,
        )

    return finish


if __name__ == "__main__":
    sys.exit(main())
