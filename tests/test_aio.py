"""`geo_server.aio.wait_set`: a wait for an event with a timeout that never loses a
cancellation (Python 3.11's `asyncio.wait_for(event.wait(), t)` returns the event's
result instead when the waiting task is cancelled in the step the event is set in)."""

from __future__ import annotations

import asyncio

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
