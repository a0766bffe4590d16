"""NC text and reset (docs/design.md §5.7, §5.9): MDI lines parsed now and started at
the next cycle boundary; a CNC reset at the next cycle boundary."""

from __future__ import annotations

import asyncio

from geo_server.commands.ports import ADSERR_DEVICE_SYNTAX, Ports
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.machine.nc import NcError, parse_program
from geo_server.machine.port import Pending, Reset, StartProgram


class NcService:
    """NC lines and reset of one machine."""

    def __init__(self, ports: Ports) -> None:
        self._ports = ports

    def run(self, text: str) -> Pending:
        """Parse NC lines now and start them as MDI lines at the next cycle boundary.

        Bad text -> 0x70D naming the line, also put in the error list
        (`Ports.note_refusal`); text over `nc_max_bytes` or `nc_max_lines` -> 0x705 (a
        long program belongs in a file: `geo-server run --program`)."""
        try:
            return self._start(text)
        except AdsError as exc:
            self._ports.note_refusal(exc, "NC text")
            raise

    def _start(self, text: str) -> Pending:
        size = len(text.encode("utf-8", errors="replace"))
        lines = text.count("\n") + 1
        lim = self._ports.limits
        if size > lim.nc_max_bytes or lines > lim.nc_max_lines:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDSIZE,
                f"NC text of {size} bytes / {lines} lines exceeds {lim.nc_max_bytes} bytes / "
                f"{lim.nc_max_lines} lines",
                "nc",
            )
        try:
            prog = parse_program(text, self._ports.machine.names, mdi=True)
        except NcError as exc:
            raise AdsError(ADSERR_DEVICE_SYNTAX, str(exc), "nc") from None
        self._ports.refuse_when_stalled()
        return self._ports.scheduler.submit(StartProgram(prog, True, text))

    async def run_applied(self, text: str, *, timeout: float | None = None) -> int:
        """`run`, parsed in a worker thread, and wait until the cycle started it (the
        service's timeout/withdraw rule); returns the cycle that started it."""
        pending = await asyncio.to_thread(self.run, text)
        started = await self._ports.settle(pending, timeout)
        # the cycle that ran its first block (not the snapshot's after the wait: by then
        # the program may have run on and said things of later cycles)
        return started if isinstance(started, int) else self._ports.snapshot().cycle

    def reset(self) -> Pending:
        """CNC reset at the next cycle boundary: program stopped, axes stopped."""
        self._ports.refuse_when_stalled()
        return self._ports.scheduler.submit(Reset())

    async def reset_applied(self, *, timeout: float | None = None) -> int:
        """`reset` and wait until a cycle applied it; returns that cycle."""
        await self._ports.settle(self.reset(), timeout)
        return self._ports.snapshot().cycle
