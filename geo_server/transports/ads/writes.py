"""ADS writes (docs/design.md §5.7, §9): validated at once (an invalid write answers at
once), answered once the cycle applied them; a sum write applies its valid items
together in one cycle. `port` is the AMS port of the request (a task serves only its
own groups).
"""

from __future__ import annotations

from collections.abc import Awaitable, Sequence

from geo_server.errors import AdsError, AdsErrorCode
from geo_server.service import PreparedWrite
from geo_server.transports.ads import codec
from geo_server.transports.ads.device import Device

#: A sum write item: the object address and data, or the ADS code it earned already.
WriteItem = tuple[int, int, bytes] | int


def check_writes_allowed(dev: Device) -> None:
    if dev.options.read_only:
        raise AdsError(AdsErrorCode.DEVICE_INVALIDACCESS, "the ADS interface is read-only")


def write_reply(dev: Device, port: int | None, ig: int, io: int, data: bytes) -> Awaitable[bytes]:
    """Validate now (an invalid write raises at once), answer once applied."""
    check_writes_allowed(dev)
    prepared = dev.service.prepare(ig, io, data, port=port)

    async def applied() -> bytes:
        (error,) = await dev.service.apply_writes([prepared], dev.options.write_timeout)
        return codec.result_response(error.code if error is not None else 0)

    return applied()


def write_many(
    dev: Device, port: int | None, items: Sequence[WriteItem | None]
) -> Awaitable[list[int]]:
    """Sum write: validate each item (its own code), apply the valid ones together
    in one cycle; per item 0 or the ADS code it earned. A command object (reload,
    save) must be written on its own, not inside a sum command (0x704)."""
    codes: list[int] = []
    valid: list[tuple[int, PreparedWrite]] = []
    for i, item in enumerate(items):
        codes.append(0)
        if item is None:
            continue
        if isinstance(item, int):  # the item's code is known already
            codes[i] = item
            continue
        try:
            check_writes_allowed(dev)
            w = dev.service.prepare(*item, port=port)
            if w.obj.command:
                raise AdsError(
                    AdsErrorCode.DEVICE_INVALIDACCESS,
                    f"{w.obj.name} cannot be written inside a sum command",
                )
            valid.append((i, w))
        except AdsError as exc:
            codes[i] = exc.code

    async def applied() -> list[int]:
        if not valid:
            return codes
        try:
            errors = await dev.service.apply_writes(
                [w for _, w in valid], dev.options.write_timeout
            )
        except AdsError as exc:  # the whole batch: stalled (0x707), withdrawn (0x719)
            errors = [exc] * len(valid)
        for (i, _w), err in zip(valid, errors, strict=True):
            codes[i] = err.code if err is not None else 0
        return codes

    return applied()
