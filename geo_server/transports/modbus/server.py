"""The Modbus TCP interface: a thin asyncio shell around the sans-I/O codec and the
register map, over the object service.

One `asyncio.Protocol` per connection feeds received bytes to an `MbapFramer`. Requests
on one connection are answered strictly one after the other, in arrival order, each
with its own transaction id: a client that pipelines (sends the next request before
the answer to the previous one) gets exactly one reply per request, in order, and every
acknowledged write has been applied. Reads are answered from one published snapshot (a
block read never mixes two cycles); writes are validated with the register map and the
object service, and the reply is sent after the cycle that applied them (in stepped mode
as soon as they are queued). Unit id = logical axis number; unit 0 (and 255, the
MODBUS/TCP guide's unit of a directly addressed device) = the machine-wide emulator
objects; any other unit id → exception 11.

pymodbus' server keeps one "last request" per connection and starts handling it from a
scheduled callback, so a second request arriving while the first waits for its cycle
overwrites the first (duplicated or missing replies, a dropped write), and two requests
in one TCP segment leave the second unread until more bytes arrive. None of its public
hooks (the SimDevice `action`, `trace_packet`, `custom_pdu`) can serialise a connection,
so the server speaks Modbus TCP itself; pymodbus stays the client library (geo-client,
tests) and the bare floor of the benchmarks.

Limits (docs/limits.md): `max_connections` (beyond: the new connection is closed at
once), `max_pipeline` requests queued per connection (beyond: the server stops reading
that connection until it has answered), `incomplete_frame_timeout` for a frame that
never completes (the connection is closed). A header that is not Modbus TCP closes the
connection after the replies already due.
"""

from __future__ import annotations

import asyncio
import logging
import time
from bisect import bisect_left
from collections import deque
from collections.abc import Awaitable
from dataclasses import dataclass
from typing import Any

import geo_server
from geo_server.dictionary import ObjectDef
from geo_server.errors import AdsError
from geo_server.faults import Fault, carry_out
from geo_server.service import ObjectService, varies_at_rest
from geo_server.transports.modbus.codec import (
    DeviceIdRequest,
    Frame,
    MbapFramer,
    ReadRequest,
    Refused,
    WriteRequest,
    adu,
    device_id_pdu,
    exception_pdu,
    parse_pdu,
    read_bits_pdu,
    read_registers_pdu,
    write_reply_pdu,
)
from geo_server.transports.modbus.regmap import (
    DIRECT_UNIT,
    MACHINE_UNIT,
    ExcCode,
    ModbusMap,
    RegisterError,
    Table,
    UnitMap,
    exception_for,
)
from geo_server.transports.share import STATUS_KEY, LoopShare
from geo_server.transports.tcp import BACKLOG, Listener

log = logging.getLogger(__name__)

#: Highest unit id an axis can have (255 is `DIRECT_UNIT`, the machine's).
MAX_UNIT = DIRECT_UNIT - 1


class DropConnection(Exception):
    """An injected `disconnect` fault: the connection is cut instead of answered."""


@dataclass
class ModbusOptions:
    """Where and how the Modbus TCP interface listens."""

    host: str = "127.0.0.1"
    port: int = 5020  # 0 = an ephemeral port; `ModbusInterface.port` tells which
    read_only: bool = False  # reject every write with exception 2
    #: running cycles: a write not applied by then is withdrawn (None: the service's
    #: `ServiceLimits.write_timeout`)
    write_timeout: float | None = None
    max_connections: int = 64
    #: connections the listening socket queues before they are accepted (a fleet's
    #: machines take fewer: `plug.FLEET_BACKLOG`; geo_server/descriptors.py)
    backlog: int = BACKLOG
    max_pipeline: int = 32  # requests queued per connection before reading pauses
    incomplete_frame_timeout: float = 5.0


def device_objects() -> dict[int, bytes]:
    """Device identification objects (FC 43/14): vendor, product code, revision,
    product and model name."""
    return {
        0: b"geo-server",
        1: b"geo-server",
        2: geo_server.__version__.encode(),
        4: b"geo-server",
        5: b"TwinCAT 3 CNC GEO task emulator",
    }


#: Conformity level: regular identification, stream and individual access.
CONFORMITY = 0x82
_BASIC = range(0, 3)
_REGULAR = range(0, 0x80)


def _varying_addresses(um: UnitMap) -> dict[Table, list[int]]:
    """The sorted addresses of `um` whose object can vary while the machine is at rest
    (`varies_at_rest`): of the registers (both register tables: `HOLDING_REGISTERS`),
    the discrete inputs and the coils."""
    registers = {a: o for a, (o, _) in um.registers.items()}
    return {
        table: sorted(a for a, o in where.items() if varies_at_rest(o))
        for table, where in (
            (Table.HOLDING_REGISTERS, registers),
            (Table.DISCRETE_INPUTS, um.discrete),
            (Table.COILS, um.coils),
        )
    }


class ModbusInterface:
    """Serve one machine's objects over Modbus TCP."""

    def __init__(
        self,
        service: ObjectService,
        options: ModbusOptions | None = None,
        share: LoopShare | None = None,
    ) -> None:
        """`share`: the machine's share of the event loop in a fleet (`transports.share`,
        the one its ADS device draws on too); None: no limit."""
        self.service = service
        self.options = options or ModbusOptions()
        self.share = share
        if share is not None:
            service.status_extra[STATUS_KEY] = share.status
        self.map = ModbusMap.build(service.info.dictionary)
        #: unit id -> the axis of its objects' index offsets (0: machine-wide)
        self.unit_axis = {MACHINE_UNIT: 0, DIRECT_UNIT: 0}
        for axis in service.info.axes:
            if 1 <= axis <= MAX_UNIT:
                self.unit_axis[axis] = axis
            else:
                log.warning("axis %d has no Modbus unit id (1…%d); not served", axis, MAX_UNIT)
        self.unit_maps: dict[int, UnitMap] = {
            u: self.map.machine if a == 0 else self.map.axis for u, a in self.unit_axis.items()
        }
        self._device = device_objects()
        #: per unit map (by scope) and table kind, the sorted addresses whose object can
        #: vary at rest (`_read` bisects them)
        self._varying = {
            um.scope: _varying_addresses(um) for um in (self.map.machine, self.map.axis)
        }
        o = self.options
        self.listener = Listener(o.host, o.port, o.max_connections, o.backlog)
        self.requests = 0
        self.faulted = 0  # requests an injected fault dropped, answered, delayed or cut off
        self.closed_for_framing = 0
        self.held_requests = 0  # waited for the machine's share of the loop (a fleet)

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        """Listen on `options.host:options.port` (port 0: see `port`)."""
        await self.listener.listen(lambda: ModbusConnection(self))
        log.info("Modbus TCP listening on %s", self.endpoint)

    async def close(self) -> None:
        """Stop listening and drop every connection."""
        await self.listener.close()

    @property
    def port(self) -> int:
        """The bound TCP port (useful with `port=0`)."""
        return self.listener.port

    @property
    def endpoint(self) -> str:
        return self.listener.endpoint

    @property
    def connection_count(self) -> int:
        return len(self.listener.connections)

    @property
    def refused_connections(self) -> int:
        return self.listener.refused

    # ------------------------------------------------------------------ requests

    def handle(self, frame: Frame) -> bytes | Awaitable[bytes]:
        """The reply ADU to one request: bytes now (reads), or an awaitable (writes);
        an injected fault (docs/faults.md) may make it empty bytes (no reply), an
        exception reply, a delayed one, or an awaitable that raises `DropConnection`."""
        self.requests += 1
        faults = self.service.faults
        if faults.active:
            fault = faults.decide("modbus", *self._fault_target(frame))
            if fault is not None:
                self.faulted += 1
                return self._faulted(frame, fault)
        return self.serve(frame)

    def _fault_target(self, frame: Frame) -> tuple[str, str]:
        """("read" | "write", name of the first object addressed or "")."""
        req = parse_pdu(frame.pdu)
        um = self.unit_maps.get(frame.unit)
        name = ""
        if um is not None and isinstance(req, ReadRequest | WriteRequest):
            entry = um.registers.get(req.address)
            if req.function in (1, 2, 5, 15):  # bits: coils and discrete inputs
                bit = um.bits(Table.COILS if req.function != 2 else Table.DISCRETE_INPUTS)
                name = bit[req.address].name if req.address in bit else ""
            elif entry is not None:
                name = entry[0].name
        return ("write" if isinstance(req, WriteRequest) else "read"), name

    def _faulted(self, frame: Frame, fault: Fault) -> bytes | Awaitable[bytes]:
        fc = frame.pdu[0] if frame.pdu else 0

        def error(code: int) -> bytes | Awaitable[bytes]:
            exc = code if code < 0x100 else exception_for(AdsError(code, "injected fault"))
            return adu(frame.transaction, frame.unit, exception_pdu(fc, exc))

        async def disconnect() -> bytes:
            raise DropConnection

        async def delayed() -> bytes:
            await fault.delay()  # cut short when the fault is cleared
            reply = self.serve(frame)
            return reply if isinstance(reply, bytes) else await reply

        def drop() -> bytes | Awaitable[bytes]:
            return b""  # no reply

        return carry_out(
            fault,
            drop=drop,
            error=error,
            disconnect=disconnect,  # the awaitable raises: the connection is closed
            delay=delayed,
        )

    def serve(self, frame: Frame) -> bytes | Awaitable[bytes]:
        """The reply to one request (no fault decided any more)."""
        req = parse_pdu(frame.pdu)
        fc = frame.pdu[0] if frame.pdu else 0
        try:
            if isinstance(req, Refused):
                log.debug("modbus unit %d: %s", frame.unit, req.reason)
                return adu(frame.transaction, frame.unit, exception_pdu(fc, req.code))
            um = self.unit_maps.get(frame.unit)
            if um is None:
                code = ExcCode.GATEWAY_NO_RESPONSE  # an unknown unit id (axis)
                return adu(frame.transaction, frame.unit, exception_pdu(fc, code))
            if isinstance(req, ReadRequest):
                pdu = self._read(self.unit_axis[frame.unit], um, req)
            elif isinstance(req, DeviceIdRequest):
                pdu = self._device_id(req)
            else:
                return self._write(frame, um, req)
        except RegisterError as exc:
            log.debug("modbus unit %d: %s", frame.unit, exc.message)
            pdu = exception_pdu(fc, exc.code)
        except AdsError as exc:
            log.debug("modbus unit %d: %s", frame.unit, exc.message)
            pdu = exception_pdu(fc, exception_for(exc))
        return adu(frame.transaction, frame.unit, pdu)

    def _read(self, axis: int, um: UnitMap, req: ReadRequest) -> bytes:
        table = um.check_read(req.function, req.address, req.count)
        varying = self._varying[um.scope][min(table, Table.HOLDING_REGISTERS)]
        i = bisect_left(varying, req.address)
        # ONE snapshot for the whole request; none caught up at rest unless the request
        # covers an object that can vary at rest (docs/design.md §13, *Reads at rest*)
        snap = self.service.current(
            at_rest_ok=i == len(varying) or varying[i] >= req.address + req.count
        )

        def value_of(obj: ObjectDef) -> Any:
            return snap.value(obj, axis)

        if table >= Table.HOLDING_REGISTERS:
            regs = um.read_registers(req.address, req.count, value_of)
            return read_registers_pdu(req.function, regs)
        return read_bits_pdu(req.function, um.read_bits(table, req.address, req.count, value_of))

    def _device_id(self, req: DeviceIdRequest) -> bytes:
        objects = self._device
        if req.code == 4:
            if req.object_id not in objects:
                raise RegisterError(ExcCode.ILLEGAL_ADDRESS, f"no device object {req.object_id}")
            chosen = [req.object_id]
        else:
            span = _BASIC if req.code == 1 else _REGULAR
            start = req.object_id if req.object_id in objects and req.object_id in span else 0
            chosen = [i for i in sorted(objects) if i >= start and i in span]
        return device_id_pdu(req.code, [(i, objects[i]) for i in chosen], CONFORMITY)

    def _write(self, frame: Frame, um: UnitMap, req: WriteRequest) -> bytes | Awaitable[bytes]:
        if self.options.read_only:
            raise RegisterError(ExcCode.ILLEGAL_ADDRESS, "this interface is read-only")
        pairs = um.decode_write(req.function, req.address, req.values)
        svc = self.service
        axis = self.unit_axis[frame.unit]
        prepared = [svc.prepare_name(obj, axis, value) for obj, value in pairs]

        async def applied() -> bytes:
            try:
                errors = await svc.apply_writes(prepared, self.options.write_timeout)
                failed = next((e for e in errors if e is not None), None)
                if failed is not None:
                    raise failed
                pdu = write_reply_pdu(req)
            except AdsError as exc:
                log.debug("modbus unit %d: %s", frame.unit, exc.message)
                pdu = exception_pdu(req.function, exception_for(exc))
            return adu(frame.transaction, frame.unit, pdu)

        return applied()

    # ------------------------------------------------------------------ connections

    def _connected(self, conn: ModbusConnection) -> bool:
        if self.listener.admit(conn):
            return True
        self.listener.say_refused("modbus", conn.peer)
        return False

    def _disconnected(self, conn: ModbusConnection) -> None:
        self.listener.forget(conn)


class ModbusConnection(asyncio.Protocol):
    """One TCP client: frames in, replies out, strictly in order."""

    def __init__(self, iface: ModbusInterface) -> None:
        self.iface = iface
        self.framer = MbapFramer()
        self.transport: asyncio.Transport | None = None
        self.peer: Any = None
        self._queue: deque[Frame] = deque()
        self._worker: asyncio.Task[None] | None = None
        self._closing = False  # framing failed: answer what is due, then close
        self._paused = False
        self._stale: asyncio.TimerHandle | None = None
        #: serving frames as they are read in a fleet: the loop thread's CPU time when
        #: the machine's share was last charged (`_charge`)
        self._mark: float | None = None

    # asyncio callbacks

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        self.peer = transport.get_extra_info("peername")
        if not self.iface._connected(self):
            transport.abort()
            self.transport = None

    def connection_lost(self, exc: Exception | None) -> None:
        self.iface._disconnected(self)
        self._cancel_stale()
        if self._worker is not None:
            self._worker.cancel()
        self._queue.clear()
        self.transport = None

    def data_received(self, data: bytes) -> None:
        if self.iface.share is None:
            self._receive(data)
            return
        # a fleet: the loop thread's CPU time is charged to the machine's share as the
        # frames are served (`_charge`), so the share is looked at between them
        self._mark = time.thread_time()
        try:
            self._receive(data)
        finally:
            self._charge()
            self._mark = None

    def _receive(self, data: bytes) -> None:
        """The frames in `data`, answered (`data_received`)."""
        frames = self.framer.feed(data)
        if self.framer.error is not None and not self._closing:
            self.iface.closed_for_framing += 1
            log.warning("modbus: closing %s: %s", self.peer, self.framer.error)
            self._closing = True
        self._watch_unfinished(progress=bool(frames))
        for frame in frames:
            self._accept(frame)
        if self._closing and self._worker is None and not self._queue:
            self._close()

    # request pipeline

    def _accept(self, frame: Frame) -> None:
        if self._worker is None and not self._queue:
            self._charge()
            wait = self._share_wait()
            if not wait:
                reply = self.iface.handle(frame)
                if isinstance(reply, bytes):
                    self._send(reply)
                else:
                    self._worker = asyncio.ensure_future(self._run(reply))
                return
            self._queue.append(frame)
            self._worker = asyncio.ensure_future(self._run(None, wait))
            return
        self._queue.append(frame)
        if len(self._queue) >= self.iface.options.max_pipeline and not self._paused:
            self._paused = True
            if self.transport is not None:
                self.transport.pause_reading()

    def _serve(self, frame: Frame) -> Awaitable[bytes] | None:
        """Answer `frame` (`_run`): a reply that is ready is sent now (None), a later one
        is returned. In a fleet the loop thread's CPU time it took is charged to the
        machine's share."""
        share = self.iface.share
        start = time.thread_time() if share is not None else 0.0
        reply = self.iface.handle(frame)
        later = None
        if isinstance(reply, bytes):
            self._send(reply)
        else:
            later = reply
        if share is not None:
            share.charge(time.thread_time() - start)
        return later

    def _charge(self) -> None:
        """In `data_received` (a fleet): charge the loop time since the last charge."""
        share = self.iface.share
        if share is not None and self._mark is not None:
            now = time.thread_time()
            share.charge(now - self._mark)
            self._mark = now

    def _share_wait(self) -> float:
        """0.0, or how long (seconds) the next request must wait for the machine's share
        of the loop (a fleet, docs/design.md §13.1): its connection meanwhile queues up
        to `max_pipeline` requests, then stops reading."""
        share = self.iface.share
        if share is None:
            return 0.0
        wait = share.wait()
        if wait:
            self.iface.held_requests += 1
        return wait

    async def _run(self, first: Awaitable[bytes] | None, wait: float = 0.0) -> None:
        """Answer the waiting requests one by one, in order: `first`'s reply, then the
        queue's (after `wait` seconds, and whenever the machine's share is used up)."""
        try:
            if wait:
                await asyncio.sleep(wait)
            if first is not None:
                self._send(await first)
            while self._queue:
                wait = self._share_wait()
                if wait:
                    await asyncio.sleep(wait)
                    continue
                later = self._serve(self._queue.popleft())
                if self._paused and len(self._queue) < self.iface.options.max_pipeline // 2:
                    self._paused = False
                    if self.transport is not None and not self.transport.is_closing():
                        self.transport.resume_reading()
                if later is not None:
                    self._send(await later)
        except DropConnection:  # an injected fault: cut the connection, answer nothing
            self._queue.clear()
            self.abort()
        except Exception:  # a defect: answer nothing more on this connection
            log.exception("modbus: request failed; closing %s", self.peer)
            self._queue.clear()
            self._closing = True
        finally:
            self._worker = None
        if self._closing:
            self._close()

    # helpers

    def _send(self, data: bytes) -> None:
        if data and self.transport is not None and not self.transport.is_closing():
            self.transport.write(data)

    def _watch_unfinished(self, progress: bool) -> None:
        """Close a connection whose frame stays unfinished (slow or stuck senders): the
        clock runs from the first byte of a frame that is not complete yet."""
        if self.framer.pending == 0 or progress:
            self._cancel_stale()
        if self.framer.pending and self._stale is None:
            loop = asyncio.get_running_loop()
            self._stale = loop.call_later(
                self.iface.options.incomplete_frame_timeout, self._unfinished_timeout
            )

    def _unfinished_timeout(self) -> None:
        self._stale = None
        if self.framer.pending:
            log.warning("modbus: closing %s: frame unfinished", self.peer)
            self.abort()

    def _cancel_stale(self) -> None:
        if self._stale is not None:
            self._stale.cancel()
            self._stale = None

    def _close(self) -> None:
        if self.transport is not None:
            self.transport.close()  # flushes the replies already written

    def abort(self) -> None:
        if self.transport is not None:
            self.transport.abort()


__all__ = ["ModbusInterface", "ModbusOptions", "device_objects"]
