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


#: The transports and their default endpoints (docs/design.md §7, §8, §9).
DEFAULT_ENDPOINTS: dict[str, str] = {
    "zenoh": "tcp/127.0.0.1:7447",
    "modbus": "127.0.0.1:5020",
    "ads": "127.0.0.1:48898",
}
TRANSPORTS = tuple(DEFAULT_ENDPOINTS)


def split_host_port(endpoint: str, default_port: int) -> tuple[str, int]:
    """`host:port` (or `tcp/host:port`, or `host`) as a tuple."""
    text = endpoint.split("/", 1)[1] if endpoint.startswith("tcp/") else endpoint
    host, sep, port = text.rpartition(":")
    if not sep:
        return text or "127.0.0.1", default_port
    return host or "127.0.0.1", int(port)


def open_client(
    via: str,
    endpoint: str | None = None,
    *,
    machine: str = "local",
    timeout: float = 2.0,
    netid: str = "127.0.0.1.1.1",
) -> GeoClient:
    """A connected client of `via` for the server at `endpoint` (its default if None).

    Endpoints are written as the transports name them: Zenoh `tcp/127.0.0.1:7447`,
    Modbus and ADS `host:port`; the ADS AMS NetId is `netid`.
    """
    if via not in DEFAULT_ENDPOINTS:
        raise ValueError(f"unknown transport {via!r} (use one of {', '.join(TRANSPORTS)})")
    ep = endpoint or DEFAULT_ENDPOINTS[via]
    if via == "zenoh":
        from geo_server.client.zenoh_client import ZenohClient

        return ZenohClient(machine=machine, connect=[ep], timeout=timeout)
    if via == "modbus":
        from geo_server.client.modbus_client import ModbusClient

        host, port = split_host_port(ep, 5020)
        return ModbusClient(host, port, timeout=timeout)
    from geo_server.client.ads_client import AdsClient

    host, port = split_host_port(ep, 48898)
    return AdsClient(host, port, netid=netid, timeout=timeout)


def connect(via: str = "zenoh", **options: Any) -> GeoClient:
    """Open a client over `via` with the client class' own keyword arguments
    (`ZenohClient(machine=, connect=[…])`, `ModbusClient(host=, port=)`,
    `AdsClient(host=, port=, netid=)`); `open_client` takes one endpoint string instead."""
    if via == "zenoh":
        from geo_server.client.zenoh_client import ZenohClient

        return ZenohClient(**options)
    if via == "modbus":
        from geo_server.client.modbus_client import ModbusClient

        return ModbusClient(**options)
    if via == "ads":
        from geo_server.client.ads_client import AdsClient

        return AdsClient(**options)
    raise ValueError(f"unknown transport {via!r} (use one of {', '.join(TRANSPORTS)})")
