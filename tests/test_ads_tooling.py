"""ADS for real tooling (docs/design.md §9): the AMS router's port connect, the system
service on AMS port 10000, the ADS state and symbol version, and the symbol server on the
GEO port (handles, info, upload), on loopback with raw frames and with pyads.

Expected symbol names, sizes and types follow from the scheme in docs/design.md §9 and the
dictionary's types (BOOLEAN -> BOOL, SGN32 -> DINT, UNS16 -> UINT, UNS32 -> UDINT,
REAL64 -> LREAL, STRING -> STRING(255)); layouts from TwinCAT's AdsSymbolEntry /
AdsDatatypeEntry (field by field below, independently of the encoder).
"""

from __future__ import annotations

import struct
from collections.abc import Iterator

import pyads
import pytest
import test_ads_server
from test_ads_server import GEO, TIMEOUT, Raw, start_server

import geo_server
from geo_server import access
from geo_server.transports.ads import codec
from geo_server.transports.ads.codec import AmsAddr, Command
from geo_server.transports.ads.server import AdsServer

SYSTEM = 10000
HNDBYNAME, VALBYNAME, VALBYHND, RELEASEHND = 0xF003, 0xF004, 0xF005, 0xF006
SYMVERSION, INFOBYNAMEEX, UPLOAD, UPLOADINFO = 0xF008, 0xF009, 0xF00B, 0xF00C
DT_UPLOAD, UPLOADINFO2, DT_INFOBYNAMEEX, DEVICE_DATA = 0xF00E, 0xF00F, 0xF011, 0xF100
COEFFICIENT_X = (1 << 16) | 0x43  # TEMPC::coefficient of axis 1 (X), 000 p.22

# the ADS tests' fixtures: an ADS server on the stepped default machine, a raw client and a
# pyads client on it
ads, raw, plc = test_ads_server.ads, test_ads_server.raw, test_ads_server.plc


def router_reply(raw: Raw) -> tuple[int, bytes]:
    head = b""
    while len(head) < 6:
        head += raw.sock.recv(6 - len(head))
    cmd, length = struct.unpack("<HI", head)
    data = b""
    while len(data) < length:
        data += raw.sock.recv(length - len(data))
    return cmd, data


def read_on(raw: Raw, port: int, ig: int, io: int, n: int) -> tuple[int, bytes]:
    pkt = raw.ask(Command.READ, codec.read_request(ig, io, n), port=port)
    return codec.parse_read_response(pkt.data)


def name(text: str) -> bytes:
    return text.encode() + b"\0"


# ---------------------------------------------------------------------- the router


def test_port_connect_gives_each_client_its_own_port(ads) -> None:
    a, b = Raw(ads.port), Raw(ads.port)
    try:
        a.sock.sendall(codec.port_connect_request(0))
        b.sock.sendall(codec.port_connect_request(0))
        (ca, da), (cb, db) = router_reply(a), router_reply(b)
        assert ca == cb == 0x1000 and len(da) == len(db) == 8
        assert da[:6] == db[:6] == bytes([127, 0, 0, 1, 1, 1])  # the router's NetId
        pa, pb = struct.unpack("<H", da[6:])[0], struct.unpack("<H", db[6:])[0]
        assert pa != pb and pa >= 32768 and pb >= 32768
        # each talks from its own address and gets its own answers
        for raw, port in ((a, pa), (b, pb)):
            raw.source = AmsAddr("127.0.0.1.1.1", port)
            pkt = raw.ask(Command.READ, codec.read_request(GEO, COEFFICIENT_X, 8))
            assert pkt.header.target == raw.source
            assert struct.unpack("<d", pkt.data[8:])[0] == 4000.0  # 000 p.24
        # a wanted port that is free is granted
        c = Raw(ads.port)
        c.sock.sendall(codec.port_connect_request(40000))
        assert router_reply(c) == (0x1000, bytes([127, 0, 0, 1, 1, 1]) + struct.pack("<H", 40000))
        c.sock.sendall(codec.router_frame(0x1002, b"\0\0\0\0"))
        assert router_reply(c) == (0x1002, bytes([127, 0, 0, 1, 1, 1]))
        # port close: the router closes the connection, the others go on
        c.sock.sendall(codec.router_frame(0x0001, struct.pack("<H", 40000)))
        assert c.wait_closed()
        assert a.read(GEO, COEFFICIENT_X, 8)[0] == 0
    finally:
        a.close()
        b.close()
    assert ads.stats.router_commands == 5


def test_bad_router_frames(raw, ads) -> None:
    raw.sock.sendall(codec.router_frame(0x1000, b"\0"))  # port connect needs 2 bytes
    raw.sock.sendall(codec.router_frame(0x1001, b"\0\0"))  # a router note from a client
    assert raw.read(GEO, COEFFICIENT_X, 8)[0] == 0  # both skipped, the stream goes on
    assert ads.stats.dropped_frames == 2
    raw.sock.sendall(codec.router_frame(0x1000, b"\0" * 100))  # longer than any router frame
    assert raw.wait_closed()


# ---------------------------------------------------------------------- system service


def test_system_service_on_port_10000(raw) -> None:
    state = raw.ask(Command.READ_STATE, port=SYSTEM)
    assert codec.parse_read_state_response(state.data) == (0, 5, 0)  # RUN
    info = raw.ask(Command.READ_DEVICE_INFO, port=SYSTEM)
    result, _major, _minor, _build, device = codec.parse_read_device_info_response(info.data)
    assert result == 0 and device == "geo-server sys"  # 15 characters at most
    run = struct.pack("<HHI", 5, 0, 0)
    assert codec.parse_result(raw.ask(Command.WRITE_CONTROL, run, port=SYSTEM).data) == 0
    config = struct.pack("<HHI", 15, 0, 0)  # ADSSTATE_CONFIG
    assert codec.parse_result(raw.ask(Command.WRITE_CONTROL, config, port=SYSTEM).data) == 0x712
    # ADS state at 0xF100 on both ports; other groups are not the system port's
    for port in (SYSTEM, 551):
        assert read_on(raw, port, DEVICE_DATA, 0, 4) == (0, struct.pack("<HH", 5, 0))
    assert read_on(raw, SYSTEM, GEO, COEFFICIENT_X, 8)[0] == 0x702
    assert raw.read(SYMVERSION, 0, 1) == (0, b"\x01")
    assert raw.read(SYMVERSION, 0, 0)[0] == 0x705
    # a write or read-write to the system port is not served, in the command's own layout
    pkt = raw.ask(Command.WRITE, codec.write_request(DEVICE_DATA, 0, b"\0\0\0\0"), port=SYSTEM)
    assert codec.parse_result(pkt.data) == 0x701
    rw = codec.read_write_request(DEVICE_DATA, 0, 4, b"\0")
    pkt = raw.ask(Command.READ_WRITE, rw, port=SYSTEM)
    assert codec.parse_read_response(pkt.data) == (0x701, b"")
    assert raw.ask(Command.READ_STATE, port=SYSTEM).header.error_code == 0  # still served


def test_extended_system_state_on_port_10000(raw) -> None:
    """Index group 0xF0 on the system service: 16 bytes, as a TwinCAT 3 system service
    answers Node's ads-client `readTcSystemExtendedState()` (it answered 0x702 before)."""
    info = raw.ask(Command.READ_DEVICE_INFO, port=SYSTEM)
    _, major, minor, build, _ = codec.parse_read_device_info_response(info.data)
    result, data = read_on(raw, SYSTEM, 0xF0, 0, 16)
    assert result == 0 and len(data) == 16
    ads_state, device, restart, version, revision, build_, platform, os_type, flags = struct.unpack(
        "<HHHBBHBBH", data[:14]
    )
    assert (ads_state, device, restart) == (5, 0, 0)  # RUN, never restarted
    assert (version, revision, build_) == (major, minor, build)  # as ReadDeviceInfo
    assert (platform, os_type, flags) == (0, 0, 0) and data[14:] == b"\0\0"
    assert read_on(raw, SYSTEM, 0xF0, 0, 0)[0] == 0x705


def test_state_notifications(raw, service) -> None:
    """0xF100 (ADS state RUN, device state 0) and 0xF008 (symbol version 1) on change:
    one first sample each, then nothing (they do not change)."""
    req = codec.add_notification_request(DEVICE_DATA, 0, 4, 4, 0, 0)
    pkt = raw.ask(Command.ADD_DEVICE_NOTIFICATION, req)
    result, handle = codec.parse_add_notification_response(pkt.data)
    assert result == 0 and handle
    req = codec.add_notification_request(SYMVERSION, 0, 1, 4, 0, 0)
    result, handle2 = codec.parse_add_notification_response(
        raw.ask(Command.ADD_DEVICE_NOTIFICATION, req).data
    )
    assert result == 0 and handle2 != handle
    access.step(service, 1)
    got: dict[int, bytes] = {}
    while len(got) < 2:
        pkt = raw.packet()
        assert pkt.header.command == Command.DEVICE_NOTIFICATION
        for stamp in codec.parse_device_notification(pkt.data):
            for sample in stamp.samples:
                got[sample.handle] = sample.data
    assert got == {handle: struct.pack("<HH", 5, 0), handle2: b"\x01"}


# ---------------------------------------------------------------------- symbols


def parse_symbol(entry: bytes) -> dict:
    """AdsSymbolEntry, field by field."""
    length, ig, io, size, adst, flags, dims, ln, lt, lc = struct.unpack_from("<IIIIIHHHHH", entry)
    pos = 30  # strings are CP1252, as pyads and ads-client decode them
    nm = entry[pos : pos + ln].decode("cp1252")
    pos += ln + 1
    tp = entry[pos : pos + lt].decode("cp1252")
    pos += lt + 1
    cm = entry[pos : pos + lc].decode("cp1252")
    assert entry[30 + ln] == 0 and length % 4 == 0 and length >= pos + lc + 1
    return dict(length=length, ig=ig, io=io, size=size, adst=adst, flags=flags, dims=dims,
                name=nm, type=tp, comment=cm)  # fmt: skip


def test_symbol_info_by_name(raw) -> None:
    code, data = raw.read_write(INFOBYNAMEEX, 0, 0xFFFF, name("GEO.X.TEMPC.coefficient"))
    assert code == 0
    s = parse_symbol(data)
    assert (s["ig"], s["io"], s["size"], s["adst"]) == (GEO, COEFFICIENT_X, 8, 5)  # LREAL
    assert s["type"] == "LREAL" and s["flags"] == 0 and s["dims"] == 0
    assert s["name"] == "GEO.X.TEMPC.coefficient" and s["comment"] == "TEMPC::coefficient [um/m]"
    assert s["length"] == len(data)
    code, data = raw.read_write(INFOBYNAMEEX, 0, 0xFFFF, name("geo.z.lsec.SUM_EPSILON"))
    s = parse_symbol(data)  # names are case-insensitive
    assert s["name"] == "GEO.Z.LSEC.sum_epsilon" and s["io"] == (3 << 16) | 0x1D
    assert s["type"] == "DINT" and s["flags"] == 0x20  # read-only
    code, data = raw.read_write(INFOBYNAMEEX, 0, 0xFFFF, name("GEO.SIM.last_error"))
    s = parse_symbol(data)
    assert (s["type"], s["size"], s["adst"], s["io"]) == ("STRING(255)", 256, 30, 9)
    assert raw.read_write(INFOBYNAMEEX, 0, 0xFFFF, name("GEO.Q.TEMPC.coefficient"))[0] == 0x710


def test_handles(raw, service) -> None:
    code, data = raw.read_write(HNDBYNAME, 0, 4, name("GEO.Y.TEMPC.coefficient"))
    assert code == 0 and len(data) == 4
    handle = struct.unpack("<I", data)[0]
    assert raw.read(VALBYHND, handle, 8) == (0, service.read(GEO, (2 << 16) | 0x43))
    # writes by handle: the same range checks and codes as by address
    pkt = raw.ask(Command.WRITE, codec.write_request(VALBYHND, handle, struct.pack("<d", 12.5)))
    assert codec.parse_result(pkt.data) == 0
    access.step(service, 1)
    assert access.read_name(service, "TEMPC::coefficient", 2) == 12.5
    bad = raw.ask(Command.WRITE, codec.write_request(VALBYHND, handle, b"\0\0\0\0"))
    assert codec.parse_result(bad.data) == 0x705  # 4 bytes for an LREAL
    nan = raw.ask(
        Command.WRITE, codec.write_request(VALBYHND, handle, struct.pack("<d", float("nan")))
    )
    assert codec.parse_result(nan.data) == 0x706
    code, ro = raw.read_write(HNDBYNAME, 0, 4, name("GEO.X.TEMPC.actual_offset"))
    ro_handle = struct.unpack("<I", ro)[0]
    denied = raw.ask(Command.WRITE, codec.write_request(VALBYHND, ro_handle, b"\0\0\0\0"))
    assert codec.parse_result(denied.data) == 0x704
    assert raw.read(VALBYHND, 0xDEAD, 8)[0] == 0x710  # unknown handle
    assert raw.read(VALBYHND, handle, 4)[0] == 0x705  # too short
    # value by name, release, and the handle is gone
    assert raw.read_write(VALBYNAME, 0, 8, name("GEO.Y.TEMPC.coefficient")) == (
        0,
        struct.pack("<d", 12.5),
    )
    rel = raw.ask(Command.WRITE, codec.write_request(RELEASEHND, 0, struct.pack("<I", handle)))
    assert codec.parse_result(rel.data) == 0
    assert raw.read(VALBYHND, handle, 8)[0] == 0x710
    rel = raw.ask(Command.WRITE, codec.write_request(RELEASEHND, 0, struct.pack("<I", handle)))
    assert codec.parse_result(rel.data) == 0x710
    assert raw.read_write(HNDBYNAME, 0, 4, name("GEO.X.NO.such"))[0] == 0x710
    assert raw.read_write(HNDBYNAME, 0, 2, name("GEO.X.TEMPC.coefficient"))[0] == 0x705


def test_handles_and_services_inside_sum_commands(raw) -> None:
    """Sum sub-requests answer as the plain requests do: an unknown handle 0x710, the ADS
    state and symbol version readable, handles created (0xF082 + 0xF003) and released
    (0xF081 + 0xF006) in one request (ads-client's createVariableHandleMulti)."""
    names = [name("GEO.X.TEMPC.coefficient"), name("GEO.NO.such")]
    subs = b"".join(struct.pack("<IIII", HNDBYNAME, 0, 4, len(n)) for n in names) + b"".join(names)
    code, data = raw.read_write(0xF082, 2, 1000, subs)
    assert code == 0
    results = codec.parse_sum_read_ex_response(data, 2)
    assert results[0][0] == 0 and len(results[0][1]) == 4 and results[1] == (0x710, b"")
    handle = struct.unpack("<I", results[0][1])[0]
    items = [(VALBYHND, handle, 8), (VALBYHND, 0xBAD, 8), (DEVICE_DATA, 0, 4), (SYMVERSION, 0, 1)]
    code, data = raw.read_write(0xF080, 4, 1000, codec.sum_read_request(items))
    assert code == 0
    codes = struct.unpack_from("<4I", data)
    assert codes == (0, 0x710, 0, 0)
    assert data[16:24] == struct.pack("<d", 4000.0)
    assert data[32:36] == struct.pack("<HH", 5, 0) and data[36:37] == b"\x01"
    release = struct.pack("<III", RELEASEHND, 0, 4) * 2 + struct.pack("<II", handle, 0xBAD)
    code, data = raw.read_write(0xF081, 2, 8, release)
    assert code == 0 and struct.unpack("<II", data) == (0, 0x710)
    assert raw.read(VALBYHND, handle, 8)[0] == 0x710  # released


def test_handle_with_its_type(raw) -> None:
    """A handle asked for with a long read length comes with size, type decoration and
    type name (what ads-client's createVariableHandle parses)."""
    code, data = raw.read_write(HNDBYNAME, 0, 0xFFFFFFFF, name("GEO.Z.LSEC.sum_epsilon"))
    assert code == 0
    handle, size, decoration, tlen = struct.unpack_from("<IIIH", data)
    assert (size, decoration, data[14 : 14 + tlen], data[14 + tlen :]) == (4, 0, b"DINT", b"\0")
    assert raw.read(VALBYHND, handle, 4)[0] == 0


def test_handles_belong_to_their_connection(ads, raw) -> None:
    _, data = raw.read_write(HNDBYNAME, 0, 4, name("GEO.X.TEMPC.coefficient"))
    other = Raw(ads.port)
    try:
        assert other.read(VALBYHND, struct.unpack("<I", data)[0], 8)[0] == 0x710
    finally:
        other.close()


def test_upload(raw, service) -> None:
    code, info = raw.read(UPLOADINFO, 0, 8)
    assert code == 0
    count, size = struct.unpack("<II", info)
    # every object of the GEO task's port (the COM task's, port 553, has no symbols)
    geo = [o for o in service.info.dictionary.objects if o.group != "com"]
    axis_objects = sum(1 for o in geo if o.scope == "axis")
    machine_objects = len(geo) - axis_objects
    assert count == axis_objects * 4 + machine_objects  # X, Y, Z, C
    code, info2 = raw.read(UPLOADINFO2, 0, 64)
    assert code == 0 and len(info2) == 24
    assert struct.unpack("<II", info2[:8]) == (count, size)
    n_types, dt_size = struct.unpack_from("<II", info2, 8)
    assert n_types == 6  # BOOL, DINT, LREAL, STRING(255), UDINT, UINT
    code, blob = raw.read(UPLOAD, 0, size)
    assert code == 0 and len(blob) == size
    names, pos = [], 0
    for _ in range(count):
        s = parse_symbol(blob[pos:])
        names.append(s["name"])
        pos += s["length"]
    assert pos == size
    assert "GEO.C.SIM.axis_type" in names and "GEO.TWIN.time" in names
    assert len(set(names)) == count
    assert raw.read(UPLOAD, 0, size - 1)[0] == 0x705  # all of it or nothing
    assert raw.read(UPLOADINFO2, 0, 12)[0] == 0x705  # never cut (clients read its version)
    code, dts = raw.read(DT_UPLOAD, 0, dt_size)
    assert code == 0 and len(dts) == dt_size
    types, pos = {}, 0
    for _ in range(n_types):
        length, _v, _h, _th, tsize, _o, adst, _f, ln, _lt, _lc, dims, subs = struct.unpack_from(
            "<IIIIIIIIHHHHH", dts, pos
        )
        types[dts[pos + 42 : pos + 42 + ln].decode()] = (tsize, adst, dims, subs)
        pos += length
    assert types == {
        "BOOL": (1, 33, 0, 0),
        "DINT": (4, 3, 0, 0),
        "LREAL": (8, 5, 0, 0),
        "STRING(255)": (256, 30, 0, 0),
        "UDINT": (4, 19, 0, 0),
        "UINT": (2, 18, 0, 0),
    }
    code, one = raw.read_write(DT_INFOBYNAMEEX, 0, 0xFFFF, name("lreal"))
    assert code == 0 and one[42:48] == b"LREAL\0"
    assert raw.read_write(DT_INFOBYNAMEEX, 0, 0xFFFF, name("ST_Unknown"))[0] == 0x710


# ---------------------------------------------------------------------- pyads


def test_pyads_by_name(plc, service) -> None:
    assert plc.read_by_name("GEO.X.TEMPC.coefficient") == 4000.0  # type from 0xF009
    assert plc.read_by_name("GEO.X.TEMPC.activated") is True
    assert plc.read_by_name("GEO.SIM.axis_names") == "1=X 2=Y 3=Z 4=C"
    plc.write_by_name("GEO.X.TEMPC.offset_0", 55)
    access.step(service, 1)
    assert access.read_name(service, "TEMPC::offset_0", 1) == 55
    with pytest.raises(pyads.ADSError) as err:
        plc.write_by_name("GEO.X.TEMPC.coefficient", float("inf"))
    assert err.value.err_code == 0x706
    # issue 45 #10: the refusal's text, in ASCII, which pyads decodes as UTF-8 (before:
    # "…" and "µ" in CP1252, and pyads failed with UnicodeDecodeError)
    with pytest.raises(pyads.ADSError) as err:
        plc.write_by_name("GEO.X.TEMPC.coefficient", 20000.0)
    assert err.value.err_code == 0x706
    refused = (
        "TEMPC::coefficient: write refused: TEMPC::coefficient: 20000.0 outside the range "
        "-10000 ... 10000 [um/m] (ADS 0x706)"
    )
    assert plc.read_by_name("GEO.SIM.last_error") == refused
    assert plc.read_list_by_name(["GEO.SIM.last_error", "GEO.SIM.axis_names"]) == {
        "GEO.SIM.last_error": refused,
        "GEO.SIM.axis_names": "1=X 2=Y 3=Z 4=C",
    }
    with pytest.raises(pyads.ADSError) as err:
        plc.read_by_name("GEO.X.TEMPC.nothing")
    assert err.value.err_code == 0x710


def test_pyads_symbols(plc) -> None:
    symbols = plc.get_all_symbols()
    by_name = {s.name: s for s in symbols}
    s = by_name["GEO.Z.TEMPC.coefficient"]
    assert (s.index_group, s.index_offset, s.symbol_type) == (GEO, (3 << 16) | 0x43, "LREAL")
    sym = plc.get_symbol("GEO.X.TEMPC.coefficient")
    assert sym.read() == 4000.0
    assert (sym.index_group, sym.index_offset) == (GEO, COEFFICIENT_X)


def test_pyads_state_info_and_notification_by_name(ads, plc, service) -> None:
    system = pyads.Connection(plc.ams_netid, SYSTEM, ads.address)
    system.open()
    try:
        assert system.read_state() == (5, 0)
        name_, _version = system.read_device_info()
        assert name_ == "geo-server sys"
    finally:
        system.close()
    assert plc.read_state() == (5, 0)
    got: list[float] = []
    attr = pyads.NotificationAttrib(8)

    @plc.notification(pyads.PLCTYPE_LREAL)
    def on_change(handle, name_, timestamp, value) -> None:
        got.append(value)

    handles = plc.add_device_notification("GEO.X.TEMPC.coefficient", attr, on_change)
    try:
        access.step(service, 1)
        import time

        deadline = time.monotonic() + TIMEOUT
        while not got and time.monotonic() < deadline:
            access.step(service, 1)
            time.sleep(0.01)
        assert got and got[0] == 4000.0
    finally:
        plc.del_device_notification(*handles)


# ---------------------------------------------------------------------- UDP 48899


#: the add-route credentials the UDP fixtures' server is started with
ROUTE_USER, ROUTE_PASSWORD = "Administrator", "s3cret-1"


def _udp_server(loop_thread, service, **options) -> AdsServer:
    """On 127.0.0.2 (loopback): pyads' UDP functions always send to port 48899."""
    from conftest import run_in

    srv = start_server(
        loop_thread, service, host="127.0.0.2", udp_port=48899, netid="5.6.7.8.1.1", **options
    )
    if srv.udp_port != 48899:
        run_in(loop_thread, srv.close())
        pytest.skip(f"UDP 48899 is taken on this host: {srv.udp_error}")
    return srv


@pytest.fixture
def udp_ads(loop_thread, service) -> Iterator[AdsServer]:
    from conftest import run_in

    srv = _udp_server(loop_thread, service, route_user=ROUTE_USER, route_password=ROUTE_PASSWORD)
    yield srv
    run_in(loop_thread, srv.close())


def _add_route(user: str, password: str) -> bool:
    """pyads' add-route against the fixture's server: True accepted, False refused.
    pyads reads TwinCAT's refusal (status 0x704) one byte off and raises for it."""
    try:
        return pyads.add_route_to_plc(
            "10.1.2.3.1.1", "tester", "127.0.0.2", user, password, route_name="geo-test"
        )
    except RuntimeError as exc:
        assert "Unexpected response" in str(exc)
        return False


def _route_status(user: bytes, password: bytes) -> int:
    """The status tag of the server's answer to a raw add-route (pyads' layout)."""
    import socket

    body = b"".join(
        struct.pack("<HH", tag, len(data)) + data
        for tag, data in ((12, b"geo-test\0"), (13, user), (2, password), (5, b"tester\0"))
    )
    head = struct.pack("<III", 0x71146603, 7, 6) + bytes([10, 1, 2, 3, 1, 1])
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.settimeout(TIMEOUT)
        s.sendto(head + struct.pack("<HI", 10000, 4) + body, ("127.0.0.2", 48899))
        reply = s.recv(2048)
    assert struct.unpack_from("<I", reply, 8)[0] == 0x8000_0006
    tag, length = struct.unpack_from("<HH", reply, 24)
    assert (tag, length) == (1, 4)
    return struct.unpack_from("<I", reply, 28)[0]


def test_pyads_discovery_and_add_route(udp_ads) -> None:
    assert pyads.pyads_ex.adsGetNetIdForPLC("127.0.0.2") == "5.6.7.8.1.1"
    assert _add_route(ROUTE_USER, ROUTE_PASSWORD) is True
    assert udp_ads.stats.udp_answered == 2


def test_add_route_refuses_wrong_credentials(udp_ads) -> None:
    """Issue 30: add-route accepted any user name and password. Now only the ones given
    at start, and a refusal is what TwinCAT answers to wrong credentials: 0x704."""
    assert _add_route(ROUTE_USER, "wrong") is False
    assert _add_route("Guest", ROUTE_PASSWORD) is False
    assert _add_route("", "") is False
    assert _add_route(ROUTE_USER, ROUTE_PASSWORD + "x") is False  # a prefix is not enough
    assert _route_status(b"Administrator\0", b"s3cret-1\0") == 0
    assert _route_status(b"Administrator\0", b"s3cret-\0") == 0x704
    assert _route_status(b"", b"") == 0x704  # no credential tags at all
    assert _add_route(ROUTE_USER, ROUTE_PASSWORD) is True  # the server still answers


def test_add_route_refused_without_configured_credentials(loop_thread, service) -> None:
    from conftest import run_in

    srv = _udp_server(loop_thread, service)
    try:
        assert _add_route("Administrator", "1") is False
        assert _add_route("", "") is False
        assert _route_status(b"Administrator\0", b"1\0") == 0x704
    finally:
        run_in(loop_thread, srv.close())


@pytest.mark.slow
def test_discovery_answer_and_garbage(udp_ads) -> None:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.settimeout(0.3)
        for junk in (
            b"",
            b"\x03\x66\x14\x71",
            b"x" * 40,
            b"\x03\x66\x14\x71" + b"\0" * 4 + b"\x06\x00\x00\x80" + b"\0" * 8,
        ):
            s.sendto(junk, ("127.0.0.2", 48899))
            with pytest.raises(TimeoutError):
                s.recvfrom(2048)
        s.settimeout(TIMEOUT)
        request = struct.pack("<III6sHI", 0x71146603, 77, 1, bytes([1] * 6), 10000, 0)
        s.sendto(request, ("127.0.0.2", 48899))
        reply, _ = s.recvfrom(2048)
    magic, invoke, service, netid, port, count = struct.unpack_from("<III6sHI", reply)
    assert (magic, invoke, service, port) == (0x71146603, 77, 0x80000001, 10000)
    assert netid == bytes([5, 6, 7, 8, 1, 1]) and count == 2
    tags, pos = {}, 24
    for _ in range(count):
        tag, length = struct.unpack_from("<HH", reply, pos)
        tags[tag] = reply[pos + 4 : pos + 4 + length]
        pos += 4 + length
    assert pos == len(reply)
    assert tags[5] == b"geo-server\0"  # host name
    # tag 3: TwinCAT version major, minor (u8), build (u16), as TwinCAT sends it
    major, minor, build = struct.unpack("<BBH", tags[3])
    assert (major, minor, build) == tuple(int(x) for x in geo_server.__version__.split(".")[:3])
    assert udp_ads.stats.udp_dropped == 4


def test_discovery_port_in_use_leaves_ads_running(loop_thread, service, udp_ads) -> None:
    """A second server on the same host and UDP port: TCP works, discovery is off."""
    from conftest import run_in

    srv = start_server(loop_thread, service, host="127.0.0.2", udp_port=48899)
    try:
        assert srv.udp_port is None and "48899" in srv.udp_error
        raw = Raw.__new__(Raw)
        import socket

        raw.sock = socket.create_connection(("127.0.0.2", srv.port), timeout=TIMEOUT)
        raw.target, raw.framer, raw.pending = AmsAddr("127.0.0.1.1.1", 551), codec.Framer(), []
        import itertools

        raw.invoke = itertools.count(1)
        assert raw.read(GEO, COEFFICIENT_X, 8)[0] == 0
        raw.close()
    finally:
        run_in(loop_thread, srv.close())


# ---------------------------------------------------------------------- address lookup


def test_address_lookup_attribute_group(raw) -> None:
    """Group + 0x600 (TF5200 "ADS access to CNC": in (channel, axis), out (IndexGroup,
    IndexOffset)); the position controller's objects are platform-global, channel 0."""

    def lookup(ig: int, element: int, channel: int, axis: int) -> tuple[int, bytes]:
        return raw.read_write(ig, element, 8, struct.pack("<II", channel, axis))

    def addr(data: bytes) -> tuple[int, int]:
        return struct.unpack("<II", data)

    code, data = lookup(0x120900, 0x43, 0, 2)  # TEMPC::coefficient of Y
    assert code == 0 and addr(data) == (0x120300, 0x20043)
    assert addr(lookup(0x120900, 0x43, 0, 9)[1]) == (0, 0)  # no axis 9
    assert addr(lookup(0x120900, 0x43, 1, 2)[1]) == (0, 0)  # no channel instance
    assert addr(lookup(0x120900, 0x43, 0, 0)[1]) == (0, 0)  # an axis object
    assert addr(lookup(0x12F900, 0x1, 0, 0)[1]) == (0x12F300, 0x1)  # SIM::cycle_count
    assert addr(lookup(0x12F900, 0x1, 0, 3)[1]) == (0x12F300, 0x30001)  # SIM::command_position
    assert lookup(0x120900, 0x7777, 0, 1)[0] == 0x703
    assert raw.read_write(0x120900, 0x43, 8, b"\0\0")[0] == 0x705
    assert raw.read_write(0x120900, 0x43, 4, struct.pack("<II", 0, 1))[0] == 0x705
    assert raw.read(0x120900, 0x10043, 8)[0] == 0x702  # ReadWrite only
    # the 16-bit form of (channel, axis)
    code, data = raw.read_write(0x120900, 0x43, 8, struct.pack("<HH", 0, 4))
    assert addr(data) == (0x120300, 0x40043)
