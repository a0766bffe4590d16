"""Small asyncio helpers shared by the interfaces."""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import os
import sys
import threading
from collections.abc import Coroutine
from typing import Any, TypeVar

T = TypeVar("T")


async def wait_set(event: asyncio.Event, timeout: float | None) -> bool:
    """Wait until `event` is set or `timeout` seconds have passed (None: no limit);
    True when it is set.

    Not `asyncio.wait_for(event.wait(), timeout)`: in Python 3.11, when the waiting task
    is cancelled in the loop step in which the event is set, `wait_for` returns the
    event's result and the cancellation is lost. A loop around it then never ends, and
    whoever cancelled it — an interface's `close`, waiting for its tasks — waits for
    ever (a Zenoh interface closing just as another session left: its matching status
    changed in that very step). `asyncio.timeout` awaits the event itself, so a
    cancellation always arrives.
    """
    if event.is_set():
        return True
    try:
        async with asyncio.timeout(timeout):
            await event.wait()
    except TimeoutError:
        return False
    return True


class LoopThread:
    """An event loop on a thread of its own, for an interface whose work is pure Python
    and would otherwise hold the process's main loop (OPC UA's asyncua: docs/design.md
    §9.1). Nothing runs at construction: `start` (the composition root's, through the
    interface's start) starts the thread; `stop` ends it.

    The thread is a daemon: a stop that times out (a library coroutine that ignores
    its cancellation) does not keep the process from ending."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> asyncio.AbstractEventLoop:
        """Start the thread and its loop (once); the loop, running."""
        if self.loop is not None:
            return self.loop
        ready: concurrent.futures.Future[asyncio.AbstractEventLoop] = concurrent.futures.Future()
        self._thread = threading.Thread(
            target=self._run, args=(ready,), name=self.name, daemon=True
        )
        self._thread.start()
        self.loop = ready.result()
        return self.loop

    @staticmethod
    def _run(ready: concurrent.futures.Future[asyncio.AbstractEventLoop]) -> None:
        try:
            loop = asyncio.new_event_loop()
        except BaseException as exc:  # (no loop: `start` raises it, never waits for ever)
            ready.set_exception(exc)
            return
        asyncio.set_event_loop(loop)
        loop.call_soon(ready.set_result, loop)
        try:
            loop.run_forever()
        finally:
            left = asyncio.all_tasks(loop)
            for task in left:
                task.cancel()
            if left:  # (their cancellation, a few steps; bounded all the same)
                loop.run_until_complete(asyncio.wait(left, timeout=STOP_TASKS_S))
            loop.close()  # (its executor shut down without waiting for its workers)

    async def run(self, work: Coroutine[Any, Any, T]) -> T:
        """Run `work` on this thread's loop and await its result on the caller's; a
        cancellation of the awaiting task cancels `work`. RuntimeError (and `work`
        closed, never run) when the loop is not running: not started, or stopped."""
        if self.loop is None:
            work.close()
            raise RuntimeError(f"{self.name}: no loop running")
        return await on_loop(self.loop, work)

    async def stop(self, timeout: float) -> bool:
        """Stop the loop (its tasks cancelled) and wait at most `timeout` seconds for
        the thread to end; True when it has."""
        loop, thread = self.loop, self._thread
        if loop is None or thread is None:
            return True
        with contextlib.suppress(RuntimeError):  # (closed already)
            loop.call_soon_threadsafe(loop.stop)
        await asyncio.to_thread(thread.join, timeout)
        if thread.is_alive():
            return False
        self.loop = self._thread = None  # (a `run` now raises; `start` starts anew)
        return True


def nice_this_thread(nice: int) -> None:
    """Make the calling thread `nice` (Linux: a thread's own niceness; elsewhere, where
    it would be the process's, nothing). Raising it needs no privileges; it is never
    lowered again, and threads this one starts from now on inherit it."""
    if sys.platform == "linux":
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)


async def on_loop(loop: asyncio.AbstractEventLoop | None, work: Coroutine[Any, Any, T]) -> T:
    """Await `work` run on `loop` (another thread's); the caller's own loop (or None:
    no other) runs it here. A cancellation of the awaiting task cancels `work`;
    RuntimeError, `work` closed and never run, when `loop` is closed."""
    if loop is None or loop is asyncio.get_running_loop():
        return await work
    try:
        done = asyncio.run_coroutine_threadsafe(work, loop)
    except RuntimeError:
        work.close()  # (never run: no "never awaited" warning)
        raise
    return await asyncio.wrap_future(done)


#: `LoopThread`: how long its tasks left at a stop get to end their cancellation
STOP_TASKS_S = 0.5
