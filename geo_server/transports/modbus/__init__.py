"""Modbus TCP interface (SPEC §8): the register map (`regmap`, sans-I/O) and the server."""

from geo_server.transports.modbus.regmap import ModbusMap, modbus_map

__all__ = ["ModbusMap", "modbus_map"]
