"""AMS port 10000, the TwinCAT system service (docs/design.md §9): ReadState (always
RUN: the emulator has no config mode), ReadDeviceInfo, WriteControl to RUN (anything
else 0x712), the ADS state at 0xF100 (read and notification), the extended system state.
"""

from __future__ import annotations

from geo_server.errors import AdsError, AdsErrorCode
from geo_server.transports.ads import codec, handles, sampling, symbols
from geo_server.transports.ads.codec import (
    SYSTEM_SERVICE_PORT,
    AddNotificationRequest,
    AdsState,
    AmsPacket,
    DeleteNotificationRequest,
    ReadDeviceInfoRequest,
    ReadRequest,
    ReadStateRequest,
    WriteControlRequest,
)
from geo_server.transports.ads.connection import Connection, Reply, fixed
from geo_server.transports.ads.device import Device


def serve_system(dev: Device, conn: Connection, packet: AmsPacket) -> Reply:
    """Answer one request to the system service."""
    req = codec.parse_request(packet)
    if isinstance(req, ReadStateRequest):
        return codec.read_state_response(0, AdsState.RUN, 0)
    if isinstance(req, ReadDeviceInfoRequest):
        return codec.read_device_info_response(0, *dev.version, dev.options.system_name)
    if isinstance(req, WriteControlRequest):
        if req.ads_state != AdsState.RUN:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDSTATE,
                f"ADS state {req.ads_state}: the emulator only runs",
            )
        return codec.result_response(0)
    if isinstance(req, ReadRequest) and req.index_group == symbols.DEVICE_DATA:
        return codec.read_response(0, handles.device_data(req.length))
    if isinstance(req, ReadRequest) and req.index_group == symbols.SYSTEM_STATE_EXTENDED:
        state = symbols.system_state_extended(dev.version)
        return codec.read_response(0, fixed(state, req.length, "the system state"))
    if isinstance(req, AddNotificationRequest) and req.index_group == symbols.DEVICE_DATA:
        return sampling.add_notification(dev, conn, packet.header, req, SYSTEM_SERVICE_PORT)
    if isinstance(req, DeleteNotificationRequest):
        sampling.delete_notification(dev, conn, req.handle, update_status=False)
        return codec.result_response(0)
    if isinstance(req, ReadRequest | AddNotificationRequest):
        raise AdsError(
            AdsErrorCode.DEVICE_INVALIDGRP,
            f"index group 0x{req.index_group:X} is not served on the system port",
        )
    # (raised, so that the error payload has the layout of the command's response)
    raise AdsError(AdsErrorCode.DEVICE_SRVNOTSUPP, "not served on the system port")
