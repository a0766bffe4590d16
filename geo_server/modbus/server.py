"""The Modbus TCP interface (SPEC §8): a thin asyncio shell around pymodbus.

pymodbus' `ModbusTcpServer` does the framing; one `SimDevice` per unit (unit id = logical
axis number; unit 0 = the machine-wide emulator objects) describes the tables, and the
SimDevice `action` hook moves the data: a read fills the requested registers from ONE
published GEO-cycle snapshot (so a block read never mixes two cycles), a write is decoded
and handed to the object service, which applies it at the next cycle boundary. When
cycles run by themselves (free-running, real time) the reply waits until the cycle that
applied it has published its snapshot, so a read sent after the reply sees the value; in
stepped mode it is sent at once (nobody runs the cycle until the test steps).

Two checks need more than the `action` hook sees (it gets neither the unit id nor, for
coils and discrete inputs, the bit count), so the server's datastore core is a small
`SimCore` subclass that first validates every request with the sans-I/O register map
(`regmap.UnitMap.check_read` / `check_write`) and answers exception 11 for an unknown
unit id (stock pymodbus would route it to unit 0 or answer exception 4). Function codes
other than 1–6, 15, 16 and 43 are answered with exception 1 (pymodbus would otherwise
serve dummy file records for FC 20/21/24 and honour FC 8 "listen only").
"""

from __future__ import annotations

import asyncio
import functools
import logging
from collections.abc import Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

from pymodbus.constants import ExcCodes
from pymodbus.exceptions import NoSuchIdException
from pymodbus.framer import FramerType
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.pdu.device import ModbusDeviceIdentification
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice
from pymodbus.simulator.simcore import SimCore

import geo_server
from geo_server.dictionary import AdsError, ObjectDef
from geo_server.modbus.regmap import (
    MACHINE_UNIT,
    SLOT,
    ExcCode,
    ModbusMap,
    RegisterError,
    Table,
    UnitMap,
    exception_for,
    register_address,
)
from geo_server.service import ObjectService

log = logging.getLogger(__name__)

#: Function codes geo-server serves (43 = encapsulated interface, MEI 14 device id).
SUPPORTED_FUNCTIONS = frozenset({1, 2, 3, 4, 5, 6, 15, 16, 43})
#: Highest unit id a Modbus device can have.
MAX_UNIT = 255


@dataclass
class ModbusOptions:
    """Where and how the Modbus TCP interface listens (SPEC §8)."""

    host: str = "127.0.0.1"
    port: int = 5020  # 0 = an ephemeral port; `ModbusInterface.port` tells which
    read_only: bool = False  # reject every write with exception 2
    write_timeout: float = 2.0  # free-running mode: wait this long for a write to apply


def identity() -> ModbusDeviceIdentification:
    """Device identification (FC 43/14) of geo-server."""
    return ModbusDeviceIdentification(
        info_name={
            "VendorName": "geo-server",
            "ProductCode": "geo-server",
            "ProductName": "geo-server",
            "ModelName": "TwinCAT 3 CNC GEO task emulator",
            "MajorMinorRevision": geo_server.__version__,
        }
    )


def _unsupported_pdus() -> list[type[ModbusPDU]]:
    """Request classes answering exception 1 for every function code we do not serve."""

    async def reject(self: ModbusPDU, context: Any, device_id: int) -> ModbusPDU:
        return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_FUNCTION)

    return [
        type(
            f"UnsupportedFunction{fc}",
            (ModbusPDU,),
            {"function_code": fc, "datastore_update": reject, "decode": lambda self, d: None},
        )
        for fc in range(1, 0x80)
        if fc not in SUPPORTED_FUNCTIONS
    ]


class _GeoCore(SimCore):
    """The datastore core: address checks by the register map, unknown unit → 11."""

    def __init__(self, devices: list[SimDevice], interface: ModbusInterface) -> None:
        super().__init__(devices)
        self._interface = interface

    def _map(self, device_id: int) -> UnitMap:
        if device_id not in self.devices:
            raise NoSuchIdException(f"unit id {device_id} is not an axis of this machine")
        return self._interface.unit_maps[device_id]

    async def async_getValues(
        self, device_id: int, func_code: int, address: int, count: int = 1
    ) -> list[int] | list[bool] | ExcCodes:
        um = self._map(device_id)
        if func_code not in (5, 6):  # FC 5/6 read back what they wrote: the echo
            try:
                um.check_read(func_code, address, count)
            except RegisterError as exc:
                log.debug("modbus unit %d: %s", device_id, exc)
                return ExcCodes(exc.code)
        return await super().async_getValues(device_id, func_code, address, count)

    async def async_setValues(
        self, device_id: int, func_code: int, address: int, values: list[int] | list[bool]
    ) -> ExcCodes | None:
        um = self._map(device_id)
        try:
            um.check_write(func_code, address, len(values))
            if self._interface.options.read_only:
                raise RegisterError(ExcCode.ILLEGAL_ADDRESS, "this interface is read-only")
        except RegisterError as exc:
            log.debug("modbus unit %d: %s", device_id, exc)
            return ExcCodes(exc.code)
        return await super().async_setValues(device_id, func_code, address, values)


def _simdevice(unit: int, um: UnitMap, action: Any) -> SimDevice:
    """The pymodbus device of one unit: four separate tables laid out like the map."""
    regs = [
        SimData(register_address(o), count=SLOT, datatype=DataType.REGISTERS) for o in um.objects
    ]

    def bits(table: Table) -> list[SimData]:
        addrs = sorted(um.bits(table))
        # pymodbus needs at least one entry per table; the register map keeps a
        # placeholder unreachable (the machine unit has no BOOLEAN objects).
        return [SimData(a, values=False, datatype=DataType.BITS) for a in addrs] or [
            SimData(0, values=False, datatype=DataType.BITS)
        ]

    return SimDevice(
        id=unit,
        simdata=(bits(Table.COILS), bits(Table.DISCRETE_INPUTS), regs, list(regs)),
        action=action,
    )


class ModbusInterface:
    """Serve one machine's objects over Modbus TCP."""

    def __init__(self, service: ObjectService, options: ModbusOptions | None = None) -> None:
        self.service = service
        self.options = options or ModbusOptions()
        self.map = ModbusMap.build(service.dictionary)
        units = [MACHINE_UNIT]
        for axis in service.axes:
            if 1 <= axis <= MAX_UNIT:
                units.append(axis)
            else:
                log.warning("axis %d has no Modbus unit id (1…255); not served", axis)
        self.unit_maps: dict[int, UnitMap] = {
            u: self.map.machine if u == MACHINE_UNIT else self.map.axis for u in units
        }
        self._server: ModbusTcpServer | None = None
        self.requests = 0

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        """Listen on `options.host:options.port` (port 0: see `port`)."""
        devices = [
            _simdevice(u, um, functools.partial(self._action, u))
            for u, um in self.unit_maps.items()
        ]
        server = ModbusTcpServer(
            devices,
            framer=FramerType.SOCKET,
            identity=identity(),
            address=(self.options.host, self.options.port),
            custom_pdu=_unsupported_pdus(),
        )
        server.context = _GeoCore(devices, self)
        await server.serve_forever(background=True)
        self._server = server
        log.info("Modbus TCP listening on %s:%d", self.options.host, self.port)

    async def close(self) -> None:
        """Stop listening and drop every connection."""
        if self._server is not None:
            server, self._server = self._server, None
            await server.shutdown()

    @property
    def port(self) -> int:
        """The bound TCP port (useful with `port=0`)."""
        if self._server is None or self._server.transport is None:
            return self.options.port
        return self._server.transport.sockets[0].getsockname()[1]

    @property
    def endpoint(self) -> str:
        return f"{self.options.host}:{self.port}"

    # ------------------------------------------------------------------ data

    async def _action(
        self,
        unit: int,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        """pymodbus `SimDevice` hook: fill a read from one snapshot or route a write.

        For coils and discrete inputs `address` is the bit address, `registers` holds
        16 bits per word and `count` is the number of words the request touches.
        """
        if values is None:
            if function_code in (5, 6):
                return None  # read-back of a single write: keep the echo
            self.requests += 1
            self._fill(unit, function_code, start_address, address, count, registers)
            return None
        self.requests += 1
        return await self._write(unit, function_code, address, values)

    def _fill(
        self,
        unit: int,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
    ) -> None:
        um = self.unit_maps[unit]
        snap = self.service.snapshot  # ONE snapshot for the whole request

        def value_of(obj: ObjectDef) -> Any:
            return snap.value(obj, unit)

        table = Table(function_code)
        if table >= Table.HOLDING_REGISTERS:
            offset = address - start_address
            registers[offset : offset + count] = um.read_registers(address, count, value_of)
            return
        offset = address // 16 - start_address
        where = um.bits(table)
        first_bit = (start_address + offset) * 16
        for w in range(count):
            word = 0
            for i in range(16):
                obj = where.get(first_bit + 16 * w + i)
                if obj is not None and value_of(obj):
                    word |= 1 << i
            registers[offset + w] = word

    async def _write(
        self, unit: int, function_code: int, address: int, values: Sequence[int] | Sequence[bool]
    ) -> ExcCodes | None:
        um = self.unit_maps[unit]
        try:
            pairs = um.decode_write(function_code, address, values)
        except RegisterError as exc:
            log.debug("modbus unit %d: %s", unit, exc)
            return ExcCodes(exc.code)
        loop = asyncio.get_running_loop()
        futures: list[Future] = []
        try:
            for obj, value in pairs:
                if obj.scope == "machine":  # reload / save read files: off the loop
                    fut = await loop.run_in_executor(
                        None, self.service.write_name, obj.name, unit, value
                    )
                else:
                    fut = self.service.write_name(obj.name, unit, value)
                futures.append(fut)
        except AdsError as exc:
            log.debug("modbus unit %d: %s", unit, exc)
            return ExcCodes(exception_for(exc))
        for fut in futures:  # commands (reload, save) complete at once
            if fut.done() and isinstance(fut.exception(), AdsError):
                return ExcCodes(exception_for(fut.exception()))
        if not self.service.scheduler.running:
            return None  # stepped: applied at the next step; acknowledge now
        try:
            await asyncio.wait_for(self._applied(futures), self.options.write_timeout)
        except TimeoutError:
            return ExcCodes.DEVICE_BUSY
        except AdsError as exc:
            return ExcCodes(exception_for(exc))
        except Exception:  # the write's function failed on the cycle thread: answer, log
            log.exception("modbus unit %d: write failed", unit)
            return ExcCodes.DEVICE_FAILURE
        return None

    @staticmethod
    async def _applied(futures: list[Future]) -> None:
        """Wait until the object service has applied every write of the request.

        That is already "visible": the machine publishes the snapshot of the cycle that
        applied a write before it resolves the write's future (`Machine.run_cycle`), and
        `_fill` reads the published snapshot, so a read sent after this reply sees the
        written value. Waiting for yet another snapshot here only cost a GEO cycle per
        write. The service hands out detached futures, so the cancellation a timeout
        causes never reaches the machine's own future.
        """
        await asyncio.gather(*(asyncio.wrap_future(f) for f in futures))


async def start_modbus(
    service: ObjectService, options: ModbusOptions | None = None
) -> ModbusInterface:
    """Create and start a Modbus interface (convenience for `geo-server run`)."""
    iface = ModbusInterface(service, options)
    await iface.start()
    return iface


__all__ = ["ModbusInterface", "ModbusOptions", "identity", "start_modbus"]
