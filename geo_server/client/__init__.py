"""Client library: talk to a running geo-server over one of its transports.

Every transport offers the same small API (`GeoClient`), so scripts, the `geo-client`
command, the PLC/HMI programs and test helpers can switch transports with one argument.
Values are decoded with the object dictionary; errors raise `AdsError` with the server's
ADS code.
"""

from __future__ import annotations

from typing import Any, Protocol

from geo_server.dictionary import ObjectDef, load_dictionary


class GeoClient(Protocol):
    """What every transport client can do."""

    def read_raw(self, index_group: int, index_offset: int, length: int) -> bytes: ...

    def write_raw(self, index_group: int, index_offset: int, data: bytes) -> None: ...

    def read(self, name: str, axis: int = 0) -> Any: ...

    def write(self, name: str, axis: int, value: Any) -> Any: ...

    def close(self) -> None: ...


def resolve(index_group: int, index_offset: int) -> ObjectDef:
    """The dictionary entry of an address (attribute groups resolve to their object)."""
    obj, _axis, _attr = load_dictionary().resolve(index_group, index_offset, [index_offset >> 16])
    return obj


def connect(via: str = "zenoh", **options: Any) -> GeoClient:
    """Open a client over `via` (`zenoh`, `modbus`, `ads`); `options` go to its constructor."""
    if via == "zenoh":
        from geo_server.client.zenoh_client import ZenohClient

        return ZenohClient(**options)
    if via == "modbus":
        from geo_server.client.modbus_client import ModbusClient

        return ModbusClient(**options)
    if via == "ads":
        from geo_server.client.ads_client import AdsClient

        return AdsClient(**options)
    raise ValueError(f"unknown transport {via!r} (available: {', '.join(TRANSPORTS)})")


#: The transports `connect()` knows.
TRANSPORTS = ("zenoh", "modbus", "ads")
