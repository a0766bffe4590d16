"""What a command service is handed (docs/design.md §5.7): the machine's ports and the
object service's rules — the one timeout/withdraw rule for queued operations, the stall
refusal, the error list — and the result type of the list commands."""

from __future__ import annotations

import threading
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, field
from typing import Any, Protocol

from geo_server.errors import AdsError, AdsErrorCode
from geo_server.machine.port import CycleRunner, MachinePort, Pending
from geo_server.snapshot import Snapshot

#: ADS "syntax error in file" — a reload rejected because a list has errors.
ADSERR_DEVICE_SYNTAX = AdsErrorCode.DEVICE_SYNTAX


class Limits(Protocol):
    """The bounds a command keeps (`service.ServiceLimits`)."""

    @property
    def write_timeout(self) -> float: ...
    @property
    def swap_timeout(self) -> float: ...
    @property
    def command_wait(self) -> float: ...
    @property
    def nc_max_bytes(self) -> int: ...
    @property
    def nc_max_lines(self) -> int: ...
    @property
    def measure_deadline(self) -> float: ...


@dataclass(frozen=True)
class Ports:
    """The machine and its scheduler, with the object service's rules around them."""

    machine: MachinePort
    scheduler: CycleRunner
    limits: Limits
    #: 0x707 while the cycle is stalled: nothing is queued then
    refuse_when_stalled: Callable[[], None]
    #: wait for a queued operation; withdrawn and 0x719 after the timeout (§5.7)
    settle_sync: Callable[[Pending, float], Any]
    settle: Callable[[Pending, float | None], Coroutine[Any, Any, Any]]
    #: record a server error in the machine's list and wait until it is there
    report_now: Callable[[str, int], None]
    #: the snapshot of the cycle due now
    snapshot: Callable[[], Snapshot]
    #: put a refused value or NC text in the error list as well (at most ten a second)
    note_refusal: Callable[[AdsError, str], None]

    @property
    def running(self) -> bool:
        return self.scheduler.running

    def apply(self, op: Any) -> None:
        """Queue a machine operation; with cycles running, wait until it is applied."""
        pending = self.scheduler.submit(op)
        if self.running:
            self.settle_sync(pending, self.limits.write_timeout)


@dataclass
class CommandResult:
    """Outcome of `reload` / `save` / `volcomp_update`, as JSON for the transports."""

    ok: bool
    command: str
    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    files: list[str] = field(default_factory=list)
    #: The ADS code of a failure: 0x70D list errors, 0x708 busy, 0x719 not applied in time.
    code: int = 0
    #: The manual's error ID of the first problem (e.g. 110591), 0 if none has one.
    error_id: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {
            "ok": self.ok,
            "command": self.command,
            "errors": self.errors,
            "warnings": self.warnings,
            "files": self.files,
        }

    @property
    def message(self) -> str:
        """One line saying what happened (the reason of a rejection first)."""
        if self.ok:
            return f"{self.command} done" + (f": {', '.join(self.files)}" if self.files else "")
        head = (
            "reload rejected, machine unchanged"
            if self.command == "reload"
            else f"{self.command} failed"
        )
        return f"{head}: {'; '.join(self.errors)}"

    def error(self) -> AdsError:
        return AdsError(self.code or ADSERR_DEVICE_SYNTAX, self.message, self.command)


class CommandLock:
    """One list command at a time: another one waits at most `command_wait`, then it
    is answered 0x708 (busy); a failed command is recorded in the error list."""

    def __init__(self, ports: Ports) -> None:
        self._ports = ports
        self._lock = threading.Lock()

    def run(
        self, command: str, work: Callable[[], CommandResult], detail: bool = False
    ) -> CommandResult:
        """`work()` under the lock; `detail`: the report names each error too."""
        if not self._lock.acquire(timeout=self._ports.limits.command_wait):
            return CommandResult(
                False,
                command,
                errors=["another reload or save is still running; try again"],
                code=AdsErrorCode.DEVICE_BUSY,
            )
        try:
            result = work()
        finally:
            self._lock.release()
        if not result.ok:
            message = result.message
            if detail:
                message += ": " + "; ".join(result.errors)
            self._ports.report_now(message, result.error_id)
        return result
