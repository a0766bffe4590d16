"""What every transport client offers beyond reading and writing objects by name.

Reload and save are writes of the emulator objects `SIM::reload` / `SIM::save` (group
`0x12F300`, axis 0) on every transport; when the server refuses one, the reason is read
back from `SIM::last_error`, so the message is the same over ADS, Modbus and Zenoh.
Axis names ("X") come from `SIM::axis_names`, the kind of an axis (linear or rotary, for
engineering units) from `SIM::axis_type`. Zenoh offers richer versions of `status` and
`errors` (the server's JSON); over ADS and Modbus they are built from the emulator
objects.
"""

from __future__ import annotations

import re
import socket
from typing import Any

from geo_server.dictionary import Dictionary
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.units import parse_axis_names

#: Machine objects the object-based `status` reads.
_STATUS = (
    ("cycle", "SIM::cycle_count"),
    ("cycle_time_us", "SIM::cycle_time_us"),
    ("overruns", "SIM::overruns"),
    ("program_running", "SIM::program_running"),
    ("program_line", "SIM::program_line"),
    ("last_error_id", "SIM::last_error_id"),
)


class ServerUnreachable(ConnectionError):
    """Nothing listens where the client was told the server is: one line that says where
    and why, the same on every transport (`geo-client` exits 2)."""


def probe(host: str, port: int, timeout: float, shown: str | None = None) -> None:
    """Open and close a TCP connection to `host:port` before a protocol library tries:
    pymodbus logs a refused connection and AdsLib prints four warnings before its own
    "0x6 target port not found"; this says it once (`ServerUnreachable`)."""
    where = shown or (f"[{host}]:{port}" if ":" in host else f"{host}:{port}")
    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except ConnectionRefusedError:
        raise ServerUnreachable(f"no geo-server at {where} (connection refused)") from None
    except TimeoutError:
        raise ServerUnreachable(f"no geo-server at {where} (no answer in {timeout:g} s)") from None
    except OSError as exc:
        raise ServerUnreachable(f"no geo-server at {where} ({exc.strerror or exc})") from None


#: A Zenoh TCP or TLS endpoint: `tcp/host:port`, `tls/[::1]:port`, `#…` options after it.
_ZENOH_TCP = re.compile(r"^(?:tcp|tls)/(?:\[(?P<v6>[^\]]+)\]|(?P<host>[^:/#]+)):(?P<port>\d+)")


def probe_zenoh(endpoints: list[str], timeout: float) -> None:
    """`probe` for Zenoh endpoints: unreachable only when every endpoint is a TCP or TLS
    one and none of them accepts a connection (other kinds are left to Zenoh)."""
    failures: list[ServerUnreachable] = []
    for ep in endpoints:
        m = _ZENOH_TCP.match(ep)
        if m is None:
            return
        try:
            probe(m["v6"] or m["host"], int(m["port"]), timeout, shown=ep)
        except ServerUnreachable as exc:
            failures.append(exc)
        else:
            return
    if failures:
        raise failures[0]


class ObjectClient:
    """Commands, axis names and status on top of `read`/`write` by name."""

    dictionary: Dictionary
    #: {"X": 1, …} once read (`axis_names`); each axis' kind once read (`axis_type`)
    _axis_names: dict[str, int] | None = None
    _axis_types: dict[int, int] | None = None

    def read(self, name: str, axis: int = 0) -> Any:
        raise NotImplementedError

    def write(self, name: str, axis: int, value: Any) -> Any:
        raise NotImplementedError

    # ------------------------------------------------------------------ axes

    def axis_names(self) -> dict[str, int]:
        """{"X": 1, …} from the server (read once)."""
        if self._axis_names is None:
            self._axis_names = parse_axis_names(str(self.read("SIM::axis_names", 0)))
        return self._axis_names

    def axis_number(self, axis: int | str) -> int:
        """A logical axis number from a number or an axis name ("X", "1")."""
        if isinstance(axis, int):
            return axis
        text = str(axis).strip()
        if text.isdigit():
            return int(text)
        try:
            names = self.axis_names()
        except AdsError as exc:
            # (a request of its own, which an injected fault may hit: say what was asked)
            raise AdsError(
                exc.code,
                f"axis {text!r}: its number could not be looked up "
                f"(the read of SIM::axis_names was answered with ADS 0x{exc.code:X})",
            ) from None
        try:
            return names[text.upper()]
        except KeyError:
            known = ", ".join(f"{n}={a}" for n, a in names.items())
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDOFFSET, f"no axis named {text!r} (axes: {known})"
            ) from None

    def axis_type(self, axis: int) -> int:
        """kenngr.achs_typ of an axis: 1 linear, 2 rotary, 4 spindle (read once)."""
        if self._axis_types is None:
            self._axis_types = {}
        if axis not in self._axis_types:
            self._axis_types[axis] = int(self.read("SIM::axis_type", axis))
        return self._axis_types[axis]

    # ------------------------------------------------------------------ commands

    def _command(self, name: str) -> dict[str, Any]:
        try:
            self.write(f"SIM::{name}", 0, 1)
        except AdsError as exc:
            reason = self._last_error() or exc.message
            head = "reload rejected, machine unchanged"
            if name == "reload":  # the server's text, without the error ID before it
                reason = reason[reason.index(head) :] if head in reason else f"{head}: {reason}"
            raise AdsError(exc.code, reason, name) from None
        return {"ok": True, "command": name, "cycle": self.read("SIM::cycle_count", 0)}

    def _last_error(self) -> str:
        try:
            return str(self.read("SIM::last_error", 0))
        except AdsError:
            return ""

    def reload(self) -> dict[str, Any]:
        """Reload the list files; a rejection raises AdsError with the reason."""
        return self._command("reload")

    def save(self) -> dict[str, Any]:
        """Save the live TEMPC parameters into the axis lists."""
        return self._command("save")

    def errors(self) -> list[dict[str, Any]]:
        """The latest error only (ADS and Modbus carry no list): `SIM::last_error`."""
        message = self._last_error()
        if not message:
            return []
        error_id = int(self.read("SIM::last_error_id", 0))
        return [{"error_id": error_id, "message": message}]

    def status(self) -> dict[str, Any]:
        """Cycle count, cycle time, overruns, the NC program and the axes."""
        st: dict[str, Any] = {key: self.read(name, 0) for key, name in _STATUS}
        st["axes"] = {a: n for n, a in self.axis_names().items()}
        return st


__all__ = ["ObjectClient"]
