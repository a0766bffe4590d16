"""ADS client for geo-server (docs/design.md §9) on top of pyads (Beckhoff AdsLib inside).

    with AdsClient(port=48898) as c:
        c.read("TEMPC::coefficient", 1)          # 4000.0
        c.write("TEMPC::coefficient", 1, 4100.0)
        c.read_raw(0x120300, 0x10043, 8)         # ADS bytes

pyads facts that shape this class (pyads 3.6.0, verified, verified with pyads 3.6.0 on Linux):

- `pyads.Connection(netid, 551, "host:port")` needs no TwinCAT router: `open()` adds a
  route NetId -> `host:port` in the in-process AdsLib router and opens a local AMS port
  (30000+). The NetId is purely logical — our server answers whichever NetId the client
  uses — but **within one process one NetId maps to one TCP endpoint**: a second client
  for another endpoint with the same NetId fails with 1286 (0x506 port already in use)
  until the first is closed. Use distinct NetIds (e.g. `127.0.0.2.1.1`) for distinct
  servers in one process.
- ADS errors arrive as `pyads.ADSError` with `err_code`; this client raises
  `geo_server.dictionary.AdsError` with the same code, like the other transports.
- Raw reads go straight to `AdsSyncReadReqEx2` to learn how many bytes the server
  returned (a server never returns more than requested, but may return fewer).

pyads is an optional dependency (`pip install geo-server[test]` or `pip install pyads`).
"""

from __future__ import annotations

import contextlib
import ctypes
import threading
from collections.abc import Callable, Sequence
from typing import Any

from geo_server.client.base import ObjectClient, probe
from geo_server.dictionary import COM_AMS_PORT, GEO_AMS_PORT, GROUPS, load_dictionary
from geo_server.errors import AdsError

#: AdsLib: no answer within the timeout (ADSERR_CLIENT_SYNCTIMEOUT)
CLIENT_SYNCTIMEOUT = 0x745
SUMUP_READ = 0xF080


def _pyads() -> Any:
    try:
        import pyads
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise RuntimeError(
            "the ADS client needs pyads: pip install pyads (or geo-server[test])"
        ) from exc
    return pyads


def close_port_first(conn: Any) -> None:
    """Close a `pyads.Connection` safely even with live notifications: AMS port first
    (AdsLib deletes the notifications with the server), then the route."""
    pyads = _pyads()
    if not conn.is_open:
        return
    if conn._port is not None:
        pyads.pyads_ex.adsPortCloseEx(conn._port)
        conn._port = None
    conn.close()  # only the route is left to delete


def _ads_error(exc: Exception) -> AdsError:
    code = int(getattr(exc, "err_code", 0x700) or 0x700)
    return AdsError(code, str(getattr(exc, "msg", exc)))


def _label(obj: Any, axis: int) -> str:
    return f"{obj.name} of axis {axis}" if obj.scope == "axis" else obj.name


def _where(index_group: int, index_offset: int, label: str) -> str:
    address = f"0x{index_group:X}/0x{index_offset:X}"
    return f"{label} ({address})" if label else address


def quiet_adslib(pyads: Any) -> None:
    """Keep AdsLib's informational messages off stderr (warnings and errors stay).

    AdsLib (inside pyads on Linux and macOS) prints "Info: connection closed by remote"
    whenever a connection ends — every time a client closes, which reads like an error.
    Its `Logger::logLevel` (Verbose 0, Info 1, Warn 2, Error 3) is raised to Warn. On
    Windows pyads uses TwinCAT's own DLL, which has no such switch: nothing to do."""
    try:
        level = ctypes.c_size_t.in_dll(pyads.pyads_ex._adsDLL, "_ZN6Logger8logLevelE")
    except (AttributeError, ValueError):
        return
    level.value = max(level.value, 2)


class AdsClient(ObjectClient):
    """Read and write geo-server objects over ADS/AMS-TCP with pyads."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 48898,
        netid: str = "127.0.0.1.1.1",
        ams_port: int = GEO_AMS_PORT,
        timeout: float = 2.0,
    ) -> None:
        pyads = _pyads()
        quiet_adslib(pyads)
        self._pyads = pyads
        self.host, self.port, self.netid, self.ams_port = host, port, netid, ams_port
        self.dictionary = load_dictionary()
        #: the COM task (AMS port 553: the volumetric objects), opened when first used
        self._com: Any = None
        self._timeout = timeout
        self._lock = threading.Lock()
        self._notifications: dict[int, tuple[int, Any]] = {}
        self._lost = False  # the connection failed: open a new one before the next request
        self.reconnects = 0
        probe(host, port, timeout)  # AdsLib would print four warnings, then 0x6
        self.conn = self._open(ams_port)

    def _open(self, ams_port: int) -> Any:
        conn = self._pyads.Connection(self.netid, ams_port, f"{self.host}:{self.port}")
        try:
            conn.open()
            conn.set_timeout(max(1, int(self._timeout * 1000)))
        except self._pyads.ADSError as exc:
            conn.close()
            raise _ads_error(exc) from None
        return conn

    def _failed(self, err: int, what: str) -> Exception:
        """The exception for AdsLib's return code `err`. A timeout or a broken socket
        (AdsLib never reconnects by itself) marks the connection lost: the next request
        opens a new one, as a TwinCAT router re-establishes its route. A lost socket is a
        `ConnectionError`, a timeout stays ADS 0x745 (both transient for a retry)."""
        if (err < 0 or err == CLIENT_SYNCTIMEOUT) and not self._notifications:
            self._lost = True
        if err < 0:
            return ConnectionError(f"{what}: connection to {self.host}:{self.port} lost")
        return AdsError(err, what)

    def _reopen(self) -> None:
        """Replace a lost connection (and the COM task's) before the next request."""
        with contextlib.suppress(Exception):
            close_port_first(self.conn)
        if self._com is not None:
            with contextlib.suppress(Exception):
                close_port_first(self._com)
            self._com = None
        self.conn = self._open(self.ams_port)
        self._lost = False
        self.reconnects += 1

    # ------------------------------------------------------------------ lifecycle

    def close(self) -> None:
        """Delete our notifications, close the AMS port, then drop the route.

        This order matters: pyads' `Connection.close()` deletes the route (and with it the
        TCP connection) *before* closing the port, and AdsLib's port close then deletes
        any remaining notifications over the freed connection — a segmentation fault
        (pyads 3.6.0, verified). Closing the port first lets AdsLib delete them cleanly.
        """
        for handle in list(self._notifications):
            with contextlib.suppress(AdsError):
                self.unsubscribe(handle)
        close_port_first(self.conn)
        if self._com is not None:
            close_port_first(self._com)

    def __enter__(self) -> AdsClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _call(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except self._pyads.ADSError as exc:
            raise _ads_error(exc) from None

    def _addr(self, conn: Any = None) -> Any:
        return ctypes.pointer((conn or self.conn)._adr.amsAddrStruct())

    def _conn_for(self, index_group: int) -> Any:
        """The connection of the task that serves `index_group`: the COM task's objects
        (0x120100) are on AMS port 553 (004 p.19), everything else on the GEO port."""
        if self._lost:
            self._reopen()
        if index_group != GROUPS["com"]:
            return self.conn
        if self._com is None:
            com = self._pyads.Connection(self.netid, COM_AMS_PORT, f"{self.host}:{self.port}")
            try:
                com.open()
                com.set_timeout(max(1, int(self._timeout * 1000)))
            except self._pyads.ADSError as exc:
                com.close()
                raise _ads_error(exc) from None
            self._com = com
        return self._com

    # ------------------------------------------------------------------ raw access

    def read_raw(self, index_group: int, index_offset: int, length: int, label: str = "") -> bytes:
        """The bytes the server returns for a Read of `length` bytes (maybe fewer);
        `label` names the object in an error (else the address alone)."""
        buf = (ctypes.c_ubyte * max(length, 1))()
        got = ctypes.c_ulong()
        conn = self._conn_for(index_group)
        err = self._pyads.pyads_ex._adsDLL.AdsSyncReadReqEx2(
            conn._port,
            self._addr(conn),
            ctypes.c_ulong(index_group),
            ctypes.c_ulong(index_offset),
            ctypes.c_ulong(length),
            ctypes.pointer(buf),
            ctypes.pointer(got),
        )
        if err:
            where = _where(index_group, index_offset, label)
            raise self._failed(err, f"read {where} failed")
        return bytes(buf)[: got.value]

    def write_raw(self, index_group: int, index_offset: int, data: bytes, label: str = "") -> None:
        buf = (ctypes.c_ubyte * max(len(data), 1)).from_buffer_copy(data.ljust(1, b"\0"))
        conn = self._conn_for(index_group)
        err = self._pyads.pyads_ex._adsDLL.AdsSyncWriteReqEx(
            conn._port,
            self._addr(conn),
            ctypes.c_ulong(index_group),
            ctypes.c_ulong(index_offset),
            ctypes.c_ulong(len(data)),
            ctypes.pointer(buf),
        )
        if err:
            where = _where(index_group, index_offset, label)
            raise self._failed(err, f"write {where} failed")

    def sum_read_raw(self, items: Sequence[tuple[int, int, int]]) -> list[bytes | AdsError]:
        """One sum read (0xF080) of (group, offset, length) items; per item bytes or the
        AdsError of its return code."""
        if not items:
            return []
        data = self._call(
            self._pyads.pyads_ex.adsSumReadBytes, self.conn._port, self.conn._adr, list(items)
        )
        out: list[bytes | AdsError] = []
        pos = 4 * len(items)
        for i, (ig, io, length) in enumerate(items):
            code = int.from_bytes(data[4 * i : 4 * i + 4], "little")
            chunk = bytes(data[pos : pos + length])
            pos += length
            out.append(AdsError(code, f"read 0x{ig:X}/0x{io:X} failed") if code else chunk)
        return out

    # ------------------------------------------------------------------ by name

    def read(self, name: str, axis: int = 0) -> Any:
        obj = self.dictionary.by_name(name)
        raw = self.read_raw(obj.index_group, obj.index_offset(axis), obj.length, _label(obj, axis))
        return obj.decode(raw)

    def write(self, name: str, axis: int, value: Any) -> Any:
        obj = self.dictionary.by_name(name)
        v = obj.coerce(value)
        self.write_raw(obj.index_group, obj.index_offset(axis), obj.encode(v), _label(obj, axis))
        return v

    def read_axis(self, axis: int, group: str = "geo") -> dict[str, Any]:
        """Every object of `group` for one axis in one sum read (one snapshot)."""
        objs = self.dictionary.group_objects(group)
        raw = self.sum_read_raw([(o.index_group, o.index_offset(axis), o.length) for o in objs])
        out: dict[str, Any] = {}
        for o, r in zip(objs, raw, strict=True):
            if isinstance(r, AdsError):
                raise r
            out[o.name] = o.decode(r)
        return out

    def device_info(self) -> tuple[str, str]:
        name, version = self._call(self.conn.read_device_info)
        return name, f"{version.version}.{version.revision}.{version.build}"

    def read_state(self) -> tuple[int, int]:
        state: tuple[int, int] = self._call(self.conn.read_state)
        return state

    # ------------------------------------------------------------------ notifications

    def subscribe(
        self,
        name: str,
        axis: int,
        callback: Callable[[Any, int], None],
        cycle_time_s: float = 0.0,
        on_change: bool = True,
    ) -> int:
        """Call `callback(value, filetime)` from AdsLib's thread for each sample.

        On-change (default) or cyclic every `cycle_time_s` (rounded by the server to
        whole GEO cycles). Returns a handle for `unsubscribe`.
        """
        pyads = self._pyads
        obj = self.dictionary.by_name(name)
        mode = pyads.ADSTRANS_SERVERONCHA if on_change else pyads.ADSTRANS_SERVERCYCLE
        ms = cycle_time_s * 1000.0
        attr = pyads.NotificationAttrib(obj.length, mode, max_delay=ms, cycle_time=ms)

        def on_note(notification: Any, _data: Any) -> None:
            contents = notification.contents
            raw = bytes(
                (ctypes.c_ubyte * contents.cbSampleSize).from_address(
                    ctypes.addressof(contents) + pyads.structs.SAdsNotificationHeader.data.offset
                )
            )
            callback(obj.decode(raw[: obj.length]), contents.nTimeStamp)

        address = (obj.index_group, obj.index_offset(axis))
        handle: int
        handle, user = self._call(self.conn.add_device_notification, address, attr, on_note)
        self._notifications[handle] = (user, on_note)
        return handle

    def unsubscribe(self, handle: int) -> None:
        user, _cb = self._notifications.pop(handle, (None, None))
        self._call(self.conn.del_device_notification, handle, user)


__all__ = ["AdsClient", "quiet_adslib"]
