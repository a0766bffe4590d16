"""ADS sum commands (docs/design.md §9): 0xF080 read, 0xF081 write, 0xF082 read-write,
0xF083 read-ex, 0xF084 read-ex2 — each sub-request answered as the plain request would
be, the reads from one snapshot, the writes applied together in one cycle.
"""

from __future__ import annotations

from geo_server.errors import AdsError, AdsErrorCode
from geo_server.snapshot import Snapshot
from geo_server.transports.ads import codec, handles, symbols
from geo_server.transports.ads.codec import ReadWriteRequest, SumGroup
from geo_server.transports.ads.connection import Connection, Reply, fit_size
from geo_server.transports.ads.device import Device
from geo_server.transports.ads.writes import WriteItem, write_many

#: The sum groups a ReadWrite may carry (notification sums are not served)
SUM_GROUPS = frozenset(int(g) for g in SumGroup) - {
    SumGroup.ADD_DEVICE_NOTIFICATION,
    SumGroup.DELETE_DEVICE_NOTIFICATION,
}


def fit(dev: Device, out: bytes, read_length: int) -> bytes:
    fit_size(len(out), read_length, dev.options.max_answer)
    return codec.read_response(0, out)


def sub_read(
    dev: Device,
    conn: Connection,
    port: int | None,
    ig: int,
    io: int,
    length: int,
    snap: Snapshot,
) -> tuple[int, bytes]:
    """One sub-request of a sum read, as a plain Read would answer it."""
    try:
        constant = handles.service_read(dev, port, ig, length)
        if constant is not None:
            return 0, constant
        ig, io = handles.address(dev, conn, port, ig, io)
        return 0, dev.service.read(ig, io, length, snap, port=port)
    except AdsError as exc:
        return exc.code, b""


def _sub_write(
    dev: Device, conn: Connection, port: int | None, ig: int, io: int, data: bytes
) -> WriteItem:
    """One sub-request of a sum write: the object address to write, or the code it
    earned already (a handle released here, an unknown handle)."""
    try:
        if ig == symbols.SYM_RELEASEHND:
            return codec.parse_result(handles.release_handle(dev, conn, data))
        ig, io = handles.address(dev, conn, port, ig, io)
    except AdsError as exc:
        return int(exc.code)
    return ig, io, data


def serve_sum(dev: Device, conn: Connection, port: int | None, req: ReadWriteRequest) -> Reply:
    group = req.index_group
    if group in (SumGroup.READ, SumGroup.READ_EX, SumGroup.READ_EX2):
        return _sum_read(dev, conn, port, req)
    if group == SumGroup.WRITE:
        writes = codec.parse_sum_write(req.index_offset, req.data)
        pending = write_many(
            dev,
            port,
            [_sub_write(dev, conn, port, w.index_group, w.index_offset, w.data) for w in writes],
        )

        async def written() -> bytes:
            return fit(dev, codec.sum_write_response(await pending), req.read_length)

        return written()
    if group == SumGroup.READ_WRITE:
        return _sum_read_write(dev, conn, port, req)
    raise AdsError(AdsErrorCode.DEVICE_SRVNOTSUPP, f"sum command 0x{group:X} is not supported")


def _sum_read(dev: Device, conn: Connection, port: int | None, req: ReadWriteRequest) -> bytes:
    group = req.index_group
    subs = codec.parse_sum_read(req.index_offset, req.data)
    if group != SumGroup.READ_EX2:
        # The answer holds every requested length: check it fits the read buffer
        # before building it (a sub-request may ask for gigabytes).
        head = 4 if group == SumGroup.READ else 8
        fit_size(
            head * len(subs) + sum(s.length for s in subs),
            req.read_length,
            dev.options.max_answer,
        )
    snap = dev.service.current()
    results = [
        sub_read(dev, conn, port, s.index_group, s.index_offset, s.length, snap) for s in subs
    ]
    if group == SumGroup.READ_EX2:
        out = codec.sum_read_ex_response(results)
    elif group == SumGroup.READ_EX:
        out = codec.sum_read_ex_response(results, [s.length for s in subs])
    else:
        out = codec.sum_read_response(results, [s.length for s in subs])
    return fit(dev, out, req.read_length)


def _sum_read_write(
    dev: Device, conn: Connection, port: int | None, req: ReadWriteRequest
) -> Reply:
    subs_rw = codec.parse_sum_read_write(req.index_offset, req.data)
    # name services (handles by name: ads-client's createVariableHandleMulti) are
    # answered at once; the others write, then read back
    named: dict[int, tuple[int, bytes]] = {}
    for i, s in enumerate(subs_rw):
        if s.index_group in handles.NAME_SERVICES:
            try:
                named[i] = (
                    0,
                    handles.name_service(dev, conn, port, s.index_group, s.data, s.read_length),
                )
            except AdsError as exc:
                named[i] = (int(exc.code), b"")
    pending = write_many(
        dev,
        port,
        [
            None
            if i in named or not s.data
            else _sub_write(dev, conn, port, s.index_group, s.index_offset, s.data)
            for i, s in enumerate(subs_rw)
        ],
    )

    async def written_then_read() -> bytes:
        write_codes = await pending
        snap = dev.service.current()
        results: list[tuple[int, bytes]] = []
        for i, (s, code) in enumerate(zip(subs_rw, write_codes, strict=True)):
            if i in named:
                results.append(named[i])
            elif code:
                results.append((code, b""))
            else:
                results.append(
                    sub_read(dev, conn, port, s.index_group, s.index_offset, s.read_length, snap)
                )
        return fit(dev, codec.sum_read_ex_response(results), req.read_length)

    return written_then_read()
