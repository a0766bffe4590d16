"""`geo_server.aio.wait_set`: a wait for an event with a timeout that never loses a
cancellation (Python 3.11's `asyncio.wait_for(event.wait(), t)` returns the event's
result instead when the waiting task is cancelled in the step the event is set in)."""

from __future__ import annotations

import asyncio
import contextlib

import pytest

from geo_server.aio import wait_set


def test_set_and_timed_out() -> None:
    async def main() -> tuple[bool, bool, bool]:
        ev = asyncio.Event()
        timed_out = await wait_set(ev, 0.01)
        asyncio.get_running_loop().call_soon(ev.set)
        woken = await wait_set(ev, 10.0)
        return timed_out, woken, await wait_set(ev, 0)  # set already: no wait at all

    assert asyncio.run(main()) == (False, True, True)


def test_a_cancellation_in_the_step_the_event_is_set_ends_the_loop() -> None:
    """A loop waiting with `wait_set`, cancelled in the very step its event is set,
    ends (with `asyncio.wait_for` it went on for ever)."""

    async def main() -> tuple[bool, bool, int]:
        ev = asyncio.Event()
        laps = 0

        async def forever() -> None:
            nonlocal laps
            while True:
                await wait_set(ev, 10.0)
                ev.clear()
                laps += 1

        task = asyncio.ensure_future(forever())
        await asyncio.sleep(0)  # waiting for the event
        ev.set()
        task.cancel()
        done, _ = await asyncio.wait({task}, timeout=2.0)
        task.cancel()
        return task in done, task.cancelled(), laps

    assert asyncio.run(main()) == (True, True, 0)


def test_a_loop_thread_runs_work_on_its_own_thread_and_loop() -> None:
    """`LoopThread`: nothing runs before `start`; `run` awaits work done on the
    thread's own loop; a cancelled wait cancels the work there; `stop` ends the thread.
    `nice_this_thread` there makes that thread, and only it, nicer on Linux (read back
    from the kernel; the OPC UA interface's serving thread: docs/design.md §9.1)."""
    import os
    import sys
    import threading
    from pathlib import Path

    from geo_server.aio import LoopThread, nice_this_thread

    own = LoopThread("own-loop")
    # (a process already nicer than 7 cannot lower it without privileges: it stays)
    expected = max(7, os.getpriority(os.PRIO_PROCESS, 0)) if sys.platform == "linux" else -1
    assert own.loop is None and "own-loop" not in {t.name for t in threading.enumerate()}

    def niceness_of(tid: int) -> int:
        stat = Path(f"/proc/self/task/{tid}/stat").read_text()
        return int(stat[stat.rindex(")") + 2 :].split()[16])  # (field 19: nice)

    async def where() -> tuple[str, int, asyncio.AbstractEventLoop]:
        niceness = -1
        nice_this_thread(7)
        if sys.platform == "linux":
            niceness = niceness_of(threading.get_native_id())
        return threading.current_thread().name, niceness, asyncio.get_running_loop()

    async def main() -> None:
        own.start()
        name, niceness, loop = await own.run(where())
        assert name == "own-loop" and loop is own.loop
        assert loop is not asyncio.get_running_loop()
        assert niceness == expected
        if sys.platform == "linux":  # (the caller's thread is not touched)
            assert niceness_of(threading.get_native_id()) == os.getpriority(os.PRIO_PROCESS, 0)
        started, cancelled = threading.Event(), threading.Event()

        async def forever() -> None:
            started.set()
            try:
                await asyncio.Event().wait()
            except asyncio.CancelledError:
                cancelled.set()
                raise

        waiting = asyncio.ensure_future(own.run(forever()))
        # (begun on the other loop: a cancel before that would keep it from ever running)
        assert await asyncio.to_thread(started.wait, 10.0)
        waiting.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await waiting
        assert await asyncio.to_thread(cancelled.wait, 10.0)
        assert await own.stop(10.0)
        assert own.loop is None and not loop.is_running() and loop.is_closed()
        with pytest.raises(RuntimeError):  # (stopped: nothing runs, nothing is left pending)
            await own.run(where())

    asyncio.run(main())
    assert "own-loop" not in {t.name for t in threading.enumerate()}


def test_a_loop_thread_whose_loop_cannot_be_made_raises_at_start(monkeypatch) -> None:
    """`start` raises what kept the thread from making its loop (here: no file
    descriptors left); before, it waited for that loop for ever, the caller's loop with
    it, so not even SIGTERM's handler ran."""
    from geo_server.aio import LoopThread

    def no_loop() -> asyncio.AbstractEventLoop:
        raise OSError(24, "Too many open files")

    monkeypatch.setattr(asyncio, "new_event_loop", no_loop)
    with pytest.raises(OSError, match="Too many open files"):
        LoopThread("no-loop").start()
