"""Injected faults at the ADS interface (docs/faults.md): which request a fault's
filters see, and what the fault does to it.
"""

from __future__ import annotations

import contextlib

from geo_server.faults import carry_out
from geo_server.transports.ads import codec, handles
from geo_server.transports.ads.codec import (
    AmsPacket,
    Command,
    ReadRequest,
    ReadWriteRequest,
    SumGroup,
    WriteRequest,
)
from geo_server.transports.ads.connection import error_payload
from geo_server.transports.ads.device import Device
from geo_server.transports.ads.protocol import AdsConnection


def faulted(dev: Device, conn: AdsConnection, packet: AmsPacket) -> bool:
    """Carry out the injected fault that hits this request, if any (docs/faults.md):
    True when the request is dealt with (dropped, answered with the error, its
    connection closed, or delayed to be served later)."""
    op, name = _fault_target(dev, conn, packet)
    fault = dev.service.faults.decide("ads", op, name)
    if fault is None:
        return False
    h = packet.header
    dev.stats.faulted += 1

    async def later() -> None:
        await fault.delay()  # cut short when the fault is cleared
        if conn.transport is not None and not conn.transport.is_closing():
            dev.serve_packet(conn, packet)

    carry_out(
        fault,
        drop=lambda: None,
        error=lambda code: dev.respond(conn, h, error_payload(h.command, code)),
        disconnect=conn.abort,
        delay=lambda: conn.spawn(later()),
    )
    return True


def _fault_target(dev: Device, conn: AdsConnection, packet: AmsPacket) -> tuple[str, str]:
    """("read" | "write", object name or "") of a request, for the faults' filters:
    a write is a Write (also by handle) or a sum write; a ReadWrite otherwise reads
    (by name, handles, sum reads). The name is resolved on any task's port."""
    write = packet.header.command == Command.WRITE
    name = ""
    with contextlib.suppress(Exception):  # an unparsable request has no name
        req = codec.parse_request(packet)
        if isinstance(req, ReadWriteRequest):
            write = req.index_group in (SumGroup.WRITE, SumGroup.READ_WRITE)
        elif isinstance(req, ReadRequest | WriteRequest):
            ig, io = handles.address(dev, conn, None, req.index_group, req.index_offset)
            name = dev.service.resolve(ig, io)[0].name
    return ("write" if write else "read"), name
