"""The Zenoh interface: the key space (`keys`, pure functions) and the server (`server`)."""

from geo_server.transports.zenoh.options import ZenohOptions
from geo_server.transports.zenoh.server import ZenohInterface

__all__ = ["ZenohInterface", "ZenohOptions"]
