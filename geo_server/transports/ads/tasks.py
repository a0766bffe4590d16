"""The CNC tasks' ADS services (docs/design.md §2, §9): the GEO task on AMS port 551 (the
GEO and emulator objects with their attributes, the symbol services of `handles`, the
address lookup, sum commands, notifications) and the COM task on 553 (the volumetric
compensation's objects; the GEO task's services answer 0x702 there). One dispatcher
serves both: the AMS port of the request is passed down explicitly and decides which
groups resolve. Read, Write and ReadWrite as the CNC object interface offers them
(TF5200); ReadState, ReadDeviceInfo; WriteControl and unknown commands answer 0x701.
"""

from __future__ import annotations

from geo_server.errors import AdsErrorCode
from geo_server.transports.ads import codec, handles, repeats, sampling, symbols
from geo_server.transports.ads.codec import (
    AddNotificationRequest,
    AdsState,
    AmsPacket,
    DeleteNotificationRequest,
    ReadDeviceInfoRequest,
    ReadRequest,
    ReadStateRequest,
    ReadWriteRequest,
    WriteRequest,
)
from geo_server.transports.ads.connection import Connection, Reply
from geo_server.transports.ads.device import Device
from geo_server.transports.ads.sums import SUM_GROUPS, serve_sum
from geo_server.transports.ads.writes import write_reply


def serve_task(dev: Device, conn: Connection, packet: AmsPacket, port: int) -> Reply:
    """Answer one request to the task on AMS port `port` (551 or 553)."""
    req = codec.parse_request(packet)
    if isinstance(req, ReadRequest):
        constant = handles.service_read(dev, port, req.index_group, req.length)
        if constant is not None:
            return codec.read_response(0, constant)
        ig, io = handles.address(dev, conn, port, req.index_group, req.index_offset)
        return repeats.read(dev, conn.repeats, packet, port, ig, io, req.length)
    if isinstance(req, ReadWriteRequest):
        if req.index_group in handles.NAME_SERVICES:
            return codec.read_response(
                0,
                handles.name_service(dev, conn, port, req.index_group, req.data, req.read_length),
            )
        return _read_write(dev, conn, port, req)
    if isinstance(req, WriteRequest):
        if req.index_group == symbols.SYM_RELEASEHND:
            return handles.release_handle(dev, conn, req.data)
        ig, io = handles.address(dev, conn, port, req.index_group, req.index_offset)
        return write_reply(dev, port, ig, io, req.data)
    if isinstance(req, AddNotificationRequest):
        return sampling.add_notification(dev, conn, packet.header, req, port)
    if isinstance(req, DeleteNotificationRequest):
        sampling.delete_notification(dev, conn, req.handle)
        return codec.result_response(0)
    if isinstance(req, ReadStateRequest):
        return codec.read_state_response(0, AdsState.RUN, 0)
    if isinstance(req, ReadDeviceInfoRequest):
        return codec.read_device_info_response(0, *dev.version, dev.options.device_name)
    # WriteControl and anything else: the CNC object interface offers Read, Write and
    # ReadWrite only (TF5200)
    return codec.result_response(AdsErrorCode.DEVICE_SRVNOTSUPP)


def _read_write(dev: Device, conn: Connection, port: int, req: ReadWriteRequest) -> Reply:
    ig, io = req.index_group, req.index_offset
    if ig in SUM_GROUPS:
        return serve_sum(dev, conn, port, req)
    if ig in handles.LOOKUPS:
        return handles.lookup_address(dev, port, req)
    ig, io = handles.address(dev, conn, port, ig, io)
    if not req.data:
        return codec.read_response(0, dev.service.read(ig, io, req.read_length, port=port))
    # Write, then read the object back once the write is applied (stepped mode: the
    # value read back is still the one of the current snapshot).
    write = write_reply(dev, port, ig, io, req.data)

    async def read_back() -> bytes:
        result = codec.parse_result(await write)
        if result:
            return codec.read_response(result)
        return codec.read_response(0, dev.service.read(ig, io, req.read_length, port=port))

    return read_back()
