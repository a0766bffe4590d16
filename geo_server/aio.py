"""Small asyncio helpers shared by the interfaces."""

from __future__ import annotations

import asyncio


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
