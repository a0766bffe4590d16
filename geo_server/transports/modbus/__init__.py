"""Modbus TCP interface (docs/design.md §8): codec and register map (sans-I/O), server."""

from geo_server.transports.modbus.regmap import ModbusMap, modbus_map

__all__ = ["ModbusMap", "modbus_map"]
