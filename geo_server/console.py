"""What both command-line programs share about their terminal."""

from __future__ import annotations

import functools
import os
import sys
from collections.abc import Callable
from typing import Any


def closes_quietly_on_broken_pipe(main: Callable[..., int]) -> Callable[..., int]:
    """`geo-server objects | head` must not end in a traceback.

    When the reader of stdout goes away, Python raises BrokenPipeError at the next write
    and again when it flushes stdout at exit. Point stdout at /dev/null so the exit flush
    succeeds, and end with status 0: the reader took what it wanted (the recipe of the
    Python documentation, "Note on SIGPIPE").
    """

    @functools.wraps(main)
    def wrapper(*args: object, **kwargs: object) -> int:
        try:
            return main(*args, **kwargs)
        except BrokenPipeError:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            return 0

    return wrapper


def engine_figures(st: dict[str, Any]) -> str:
    """What the engine did, from a status (`ObjectService.status()`): for the exact
    engine the cycles it computed (the rest were skipped at rest) and what catching up
    added to requests; for the punctual one its lateness. The same words in the status
    line of `geo-server run` and in `geo-client status`."""

    def us(key: str) -> str:
        return f"{float(st.get(key) or 0):.0f} µs"

    tail = (
        f"overruns {st.get('overruns', 0)}  cycle p50 {us('cycle_p50_us')} "
        f"(kernel {us('kernel_p50_us')})"
    )
    if st.get("compiled") is False:  # its machine code still loading (geo_server/jit.py)
        tail += "  interpreted"
    if st.get("engine") == "exact":
        return (
            f"computed {st.get('computed_cycles', 0)} ({st.get('engine_wakes', 0)} wake-ups)  "
            f"catch-up p50 {us('sync_p50_us')} p99 {us('sync_p99_us')}  " + tail
        )
    return (
        f"lateness p50 {us('lateness_p50_us')} p99 {us('lateness_p99_us')} "
        f"max {us('lateness_max_us')}  " + tail
    )


def status_line(st: dict[str, Any]) -> str:
    """The status line `geo-server run` prints every `--status-period`."""
    return f"cycle {st['cycle']}  " + engine_figures(st)
