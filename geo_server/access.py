"""Reads and writes by name over the narrow object service (docs/design.md §5.7), for
tests, the command line, the clients and the name-based interfaces: each is a few calls
of `ObjectService`'s public methods (`lookup`, `current`, `prepare`/`prepare_name`,
`submit_writes`, `apply_writes`), so it follows the same rules as every transport —
validation at once, the write applied at the next cycle boundary, 0x707 while stalled,
the one timeout/withdraw rule.

    read_name(service, "TEMPC::actual_offset", 1)
    await write_name_applied(service, "TEMPC::coefficient", 1, 4000.0)
    step(service, 20)       # stepped mode: run 20 cycles now
"""

from __future__ import annotations

from typing import Any

from geo_server.machine.port import Pending, chained
from geo_server.service import ObjectService
from geo_server.snapshot import Snapshot


def read_name(
    service: ObjectService, name: str, axis: int = 0, snapshot: Snapshot | None = None
) -> Any:
    """Decoded value of an object by name (a write-only one shows what its snapshot
    column holds: the Modbus view; ADS and Zenoh refuse it with `check_readable`)."""
    obj = service.lookup(name, axis)
    return (snapshot or service.current()).value(obj, axis)


def read_axis(service: ObjectService, axis: int, group: str = "geo") -> dict[str, Any]:
    """Every object of `group` for one axis, decoded, from one snapshot."""
    snap = service.current()
    info = service.info
    return {
        o.name: snap.value(o, axis)
        for o in info.dictionary.group_objects(group)
        if axis in info.axes
    }


def write(service: ObjectService, index_group: int, index_offset: int, data: bytes) -> Pending:
    """Validate ADS bytes now and apply them at the next cycle boundary (a command
    object runs its command here, in the caller's thread). The future's result is
    None, or it raises the error applying the value raised."""
    return _single(service.submit_writes([service.prepare(index_group, index_offset, data)]))


def write_name(service: ObjectService, name: str, axis: int, value: Any) -> Pending:
    """Validate a decoded value (JSON, CLI) and apply it at the next cycle boundary."""
    return _single(service.submit_writes([service.prepare_name(name, axis, value)]))


async def write_applied(
    service: ObjectService,
    index_group: int,
    index_offset: int,
    data: bytes,
    *,
    timeout: float | None = None,
) -> None:
    """Validate, queue and wait until applied (`ObjectService.apply_writes`)."""
    prepared = service.prepare(index_group, index_offset, data)
    errors = await service.apply_writes([prepared], timeout)
    if errors[0] is not None:
        raise errors[0]


async def write_name_applied(
    service: ObjectService, name: str, axis: int, value: Any, *, timeout: float | None = None
) -> Any:
    """`write_applied` by name with a decoded value; returns the value as stored."""
    w = service.prepare_name(name, axis, value)
    errors = await service.apply_writes([w], timeout)
    if errors[0] is not None:
        raise errors[0]
    return w.value


def step(service: ObjectService, n: int = 1) -> Snapshot:
    """Run `n` cycles now (stepped mode: tests, replay, `geo-server measure`) and return
    the latest snapshot."""
    service.stepper().step(n)
    return service.current(stale_ok=True)


def _single(pending: Pending) -> Pending:
    """The outcome of a one-item `WriteObjects` as None or its error raised (a command's
    CommandResult is passed on as it is)."""

    def first(outcome: Any) -> Any:
        if isinstance(outcome, tuple):
            if outcome[0] is not None:
                raise outcome[0]
            return None
        return outcome

    return chained(pending, first)


__all__ = [
    "read_axis",
    "read_name",
    "step",
    "write",
    "write_applied",
    "write_name",
    "write_name_applied",
]
