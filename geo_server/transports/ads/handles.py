"""The GEO task's symbol services (docs/ads-symbols.md, docs/design.md §9): symbol
uploads, values and handles by name, symbol and data type info, the address lookup
(group + 0x600) and values by handle. Sans-I/O: each function answers one request of
one device from the object service; `port` is the AMS port the request was sent to (the
COM task, 553, has none of these services: 0x702).
"""

from __future__ import annotations

import struct

from geo_server.dictionary import ADDRESS_LOOKUP, COM_AMS_PORT, TASK_GROUPS
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.transports.ads import codec, symbols
from geo_server.transports.ads.codec import AdsState, ReadWriteRequest
from geo_server.transports.ads.connection import Connection, HandleTable, fit_size, fixed
from geo_server.transports.ads.device import Device

NAME_SERVICES = frozenset(
    {
        symbols.SYM_HNDBYNAME,
        symbols.SYM_VALBYNAME,
        symbols.SYM_INFOBYNAMEEX,
        symbols.SYM_DT_INFOBYNAMEEX,
    }
)
LOOKUPS = frozenset(ig + ADDRESS_LOOKUP for ig in TASK_GROUPS.values())
_UPLOADS = frozenset(
    {symbols.SYM_UPLOAD, symbols.SYM_UPLOADINFO, symbols.SYM_UPLOADINFO2, symbols.SYM_DT_UPLOAD}
)
#: The GEO task's symbol services (reads)
_GEO_SERVICES = _UPLOADS | {symbols.SYM_VERSION}
#: Services a notification may watch besides the objects (constant values: one sample)
NOTIFIABLE_SERVICES = frozenset({symbols.DEVICE_DATA, symbols.SYM_VERSION})


def geo_port_only(port: int | None, ig: int) -> None:
    """The symbol, name and lookup services are the GEO task's: on the COM task's port
    (553, the volumetric objects) they answer 0x702, as a group that port does not know."""
    if port == COM_AMS_PORT:
        raise AdsError(
            AdsErrorCode.DEVICE_INVALIDGRP,
            f"index group 0x{ig:X} is a service of the GEO task (AMS port 551), not 553",
        )


def device_data(length: int) -> bytes:
    """0xF100: ADS state RUN, device state 0 (u16 each)."""
    return fixed(struct.pack("<HH", AdsState.RUN, 0), length, "the ADS state")


def service_read(dev: Device, port: int | None, ig: int, length: int) -> bytes | None:
    """Reads of the symbol and state services on a task port, None for the rest."""
    if ig in _GEO_SERVICES:
        geo_port_only(port, ig)
    if ig == symbols.DEVICE_DATA:
        return device_data(length)
    if ig == symbols.SYM_VERSION:
        return fixed(bytes([symbols.SYMBOL_VERSION]), length, "the symbol version")
    if ig not in _UPLOADS:
        return None
    table = dev.symbols
    if ig == symbols.SYM_UPLOAD or ig == symbols.SYM_DT_UPLOAD:
        blob = table.upload if ig == symbols.SYM_UPLOAD else table.datatype_upload
        fit_size(len(blob), length, dev.options.max_answer)  # all of it or 0x705
        return blob
    info = table.upload_info() if ig == symbols.SYM_UPLOADINFO else table.upload_info2()
    # never cut: clients tell its version by length
    fit_size(len(info), length, dev.options.max_answer)
    return info


def address(dev: Device, conn: Connection, port: int | None, ig: int, io: int) -> tuple[int, int]:
    """The object address behind a symbol handle (0xF005, offset = handle)."""
    if ig != symbols.SYM_VALBYHND:
        return ig, io
    geo_port_only(port, ig)
    sym = conn.table(dev).handles.get(io)
    if sym is None:
        raise AdsError(AdsErrorCode.DEVICE_SYMBOLNOTFOUND, f"no symbol handle 0x{io:X}")
    return sym.index_group, sym.index_offset


def name_service(
    dev: Device, conn: Connection, port: int | None, ig: int, data: bytes, read_length: int
) -> bytes:
    """Handle by name (0xF003), value by name (0xF004), symbol info (0xF009) and
    data type info (0xF011) by name: the write data is the name. A handle asked for
    with more than 4 bytes of read length comes with size, type decoration and type
    name (as ads-client's `createVariableHandle` reads it)."""
    geo_port_only(port, ig)
    name = symbols.decode_name(data)
    max_answer = dev.options.max_answer
    if ig == symbols.SYM_DT_INFOBYNAMEEX:
        entry = symbols.datatype_entry(dev.symbols.datatype(name))
        fit_size(len(entry), read_length, max_answer)
        return entry
    sym = dev.symbols.lookup(name)
    if ig == symbols.SYM_INFOBYNAMEEX:
        entry = symbols.symbol_entry(sym)
        fit_size(len(entry), read_length, max_answer)
        return entry
    if ig == symbols.SYM_VALBYNAME:
        return dev.service.read(sym.index_group, sym.index_offset, read_length, port=port)
    # SYM_HNDBYNAME
    table = conn.table(dev)
    answer = symbols.handle_answer(table.next_handle + 1, sym, extended=read_length > 4)
    fit_size(len(answer), read_length, max_answer)
    _check_handles(dev, table)
    table.next_handle += 1
    table.handles[table.next_handle] = sym
    dev.handles_held += 1
    dev.head.fleet_handles += 1
    return answer


def _check_handles(dev: Device, table: HandleTable) -> None:
    """0x716 when one more symbol handle would pass a cap: the connection's at this
    machine, this machine's, or (at the head) every machine's behind the port."""
    head = dev.head
    for held, cap, where in (
        (len(table.handles), dev.options.max_handles, "on this connection"),
        (dev.handles_held, dev.options.max_handles_machine, "at this machine"),
        (head.fleet_handles, head.options.max_handles_fleet, "at the machines of this port"),
    ):
        if held >= cap:
            raise AdsError(
                AdsErrorCode.DEVICE_NOMOREHDLS, f"{held} symbol handles are open {where}"
            )


def lookup_address(dev: Device, port: int | None, req: ReadWriteRequest) -> bytes:
    """Group + 0x600: in (channel, axis) as two UNS32 (or two UNS16), the element in
    the index offset's low word; out (IndexGroup, IndexOffset), (0, 0) for none."""
    geo_port_only(port, req.index_group)
    if len(req.data) == 8:
        channel, axis = struct.unpack("<II", req.data)
    elif len(req.data) == 4:
        channel, axis = struct.unpack("<HH", req.data)
    else:
        raise AdsError(
            AdsErrorCode.DEVICE_INVALIDSIZE,
            f"address lookup: (channel, axis) has 8 bytes, not {len(req.data)}",
        )
    fit_size(8, req.read_length, dev.options.max_answer)
    ig, io = dev.service.info.lookup_address(
        req.index_group, req.index_offset & 0xFFFF, channel, axis
    )
    return codec.read_response(0, struct.pack("<II", ig, io))


def release_handle(dev: Device, conn: Connection, data: bytes) -> bytes:
    """0xF006: give a handle back (unknown -> 0x710). A notification registered on
    it keeps its object address: it stays until it is deleted itself."""
    if len(data) != 4:
        raise AdsError(AdsErrorCode.DEVICE_INVALIDSIZE, f"a handle has 4 bytes, not {len(data)}")
    handle = struct.unpack("<I", data)[0]
    if conn.table(dev).handles.pop(handle, None) is None:
        raise AdsError(AdsErrorCode.DEVICE_SYMBOLNOTFOUND, f"no symbol handle 0x{handle:X}")
    conn.repeats.clear()  # (one may be a read by this handle: `repeats`)
    dev.handles_held -= 1
    dev.head.fleet_handles -= 1
    return codec.result_response(0)
