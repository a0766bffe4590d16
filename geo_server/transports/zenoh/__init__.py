"""The Zenoh interface: the key space (`keys`, pure functions) and the server (`server`)."""

from geo_server.transports.zenoh.server import ZenohInterface, ZenohOptions

__all__ = ["ZenohInterface", "ZenohOptions"]
