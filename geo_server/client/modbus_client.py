"""Modbus TCP client for geo-server (docs/design.md §8), built on pymodbus' synchronous client.

Objects are addressed as everywhere else — by name and axis, or by ADS index group and
offset — and translated with the register map: unit id = axis (0 for machine-wide
objects), holding registers at `4·ID` (`0x4000 + 4·ID` for the emulator group), values
big-endian. Raw reads and writes carry ADS (little-endian) bytes, so a script can switch
between Zenoh, Modbus and ADS without changing its data. Attribute groups (name, type,
length, unit, writable) have no Modbus registers; they are answered from the dictionary.
Modbus exceptions come back as `AdsError` with the matching ADS code.
"""

from __future__ import annotations

from typing import Any

from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ModbusException
from pymodbus.pdu.mei_message import ReadDeviceInformationResponse

from geo_server.client.base import ObjectClient, probe
from geo_server.dictionary import ObjectDef, load_dictionary
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.transports.modbus.regmap import (
    ExcCode,
    decode,
    encode,
    mapped,
    register_address,
    register_count,
)

#: ADS error that stands for a Modbus device failure / unknown condition.
_GENERAL = 0x700


def ads_error(code: int, obj: ObjectDef, axis: int, write: bool) -> AdsError:
    """The `AdsError` for a Modbus exception answer to a request on `obj`."""
    where = f"{obj.name} (unit {axis})"
    if code == ExcCode.GATEWAY_NO_RESPONSE:
        return AdsError(
            AdsErrorCode.DEVICE_INVALIDOFFSET, f"axis {axis} is not configured", obj.name
        )
    if code == ExcCode.ILLEGAL_ADDRESS:
        if write:
            return AdsError(AdsErrorCode.DEVICE_INVALIDACCESS, f"{where}: write refused", obj.name)
        return AdsError(AdsErrorCode.DEVICE_INVALIDOFFSET, f"{where}: no such address", obj.name)
    if code == ExcCode.ILLEGAL_VALUE:
        return AdsError(
            AdsErrorCode.DEVICE_INVALIDDATA if write else AdsErrorCode.DEVICE_INVALIDSIZE,
            f"{where}: illegal data value",
            obj.name,
        )
    if code == ExcCode.DEVICE_BUSY:
        why = "device busy or write not applied in time" if write else "device busy"
        return AdsError(AdsErrorCode.DEVICE_BUSY, f"{where}: {why} (Modbus exception 6)", obj.name)
    return AdsError(_GENERAL, f"{where}: Modbus exception {code}", obj.name)


class ModbusClient(ObjectClient):
    """Read and write geo-server objects over Modbus TCP (implements `GeoClient`)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 5020, timeout: float = 2.0) -> None:
        self.host = host
        self.port = port
        self.dictionary = load_dictionary()
        probe(host, port, timeout)  # pymodbus would log a refused connection itself
        self._client = ModbusTcpClient(host, port=port, timeout=timeout, retries=0)
        if not self._client.connect():
            raise ConnectionError(f"no Modbus server at {host}:{port}")

    def close(self) -> None:
        self._client.close()

    def __enter__(self) -> ModbusClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ registers

    @staticmethod
    def _mapped(obj: ObjectDef) -> None:
        if not mapped(obj):
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDGRP,
                f"{obj.name} is the COM task's (AMS port 553): not on Modbus, use ADS or Zenoh",
                obj.name,
            )

    def read_value(self, obj: ObjectDef, axis: int) -> Any:
        """Decoded value of `obj` on unit `axis` (0 for machine-wide objects)."""
        self._mapped(obj)
        unit = 0 if obj.scope == "machine" else axis
        try:
            rr = self._client.read_holding_registers(
                register_address(obj), count=register_count(obj), device_id=unit
            )
        except ModbusException as exc:
            raise TimeoutError(f"Modbus read of {obj.name} failed: {exc}") from None
        if rr.isError():
            raise ads_error(rr.exception_code, obj, unit, write=False)
        return decode(obj, rr.registers, check=False)

    def write_value(self, obj: ObjectDef, axis: int, value: Any) -> Any:
        """Write a (decoded) value; FC 6 for one register, FC 16 for more. Returns it."""
        self._mapped(obj)
        unit = 0 if obj.scope == "machine" else axis
        v = obj.coerce(value)
        regs = encode(obj, v, written=True)
        try:
            if len(regs) == 1:
                rr = self._client.write_register(register_address(obj), regs[0], device_id=unit)
            else:
                rr = self._client.write_registers(register_address(obj), regs, device_id=unit)
        except ModbusException as exc:
            raise TimeoutError(f"Modbus write of {obj.name} failed: {exc}") from None
        if rr.isError():
            raise ads_error(rr.exception_code, obj, unit, write=True)
        return v

    # ------------------------------------------------------------------ GeoClient

    def read(self, name: str, axis: int = 0) -> Any:
        return self.read_value(self.dictionary.by_name(name), axis)

    def write(self, name: str, axis: int, value: Any) -> Any:
        return self.write_value(self.dictionary.by_name(name), axis, value)

    def read_raw(self, index_group: int, index_offset: int, length: int = 0) -> bytes:
        """ADS bytes of an object (or attribute) by address; `length` 0 = all of it."""
        axis = index_offset >> 16
        obj, axis, attr = self.dictionary.resolve(index_group, index_offset, [axis])
        data = obj.attribute(attr) if attr else obj.encode(self.read_value(obj, axis))
        if length and length < len(data):
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDSIZE,
                f"{obj.name}: read of {length} bytes, the value has {len(data)}",
                obj.name,
            )
        return data

    def write_raw(self, index_group: int, index_offset: int, data: bytes) -> None:
        """Write ADS bytes to an object by address."""
        obj, axis, attr = self.dictionary.resolve(index_group, index_offset, [index_offset >> 16])
        if attr is not None:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDACCESS, f"attribute of {obj.name} is read-only", obj.name
            )
        self.write_value(obj, axis, obj.decode(data))

    # ------------------------------------------------------------------ commands

    def device_information(self) -> dict[int, bytes]:
        """FC 43/14 basic device identification: {0: vendor, 1: product code, 2: version}."""
        rr = self._client.read_device_information()
        if rr.isError() or not isinstance(rr, ReadDeviceInformationResponse):
            raise AdsError(_GENERAL, f"device identification failed: {rr}")
        return dict(rr.information)


__all__ = ["ModbusClient", "ads_error"]
