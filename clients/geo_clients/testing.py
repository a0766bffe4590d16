"""Integration-test helpers: a stepped geo-server on free loopback ports (docs/design.md §10).

`GeoTestServer` owns a machine (the default machine or any start-up list), its object
service in **stepped** mode (no cycle runs until the test steps, so every value is
deterministic: docs/design.md §5) and an asyncio loop thread on which the transports run. The
transports start on demand, each on an ephemeral port of 127.0.0.1: Zenoh in peer mode
with multicast scouting off and an explicit listen endpoint, Modbus TCP, ADS/AMS-TCP —
built by the composition root (`geo_server.compose.loopback_interface`) as `geo-server
run`'s are.

    with GeoTestServer() as srv:                  # default machine, every axis homed
        srv.move("X", 1_000_000)                  # 100 mm, steps until in position
        srv.step(25)                              # temp_comp_n_cycles 20 (000 p.18)
        assert srv.read("TEMPC::actual_offset", "X") == 4040      # 000 p.17 example
        z = srv.via("zenoh")                      # the same over a real Zenoh session
        z.assert_value("TEMPC::coefficient", 1, 4000.0)
        z.assert_raw(0x120300, 0x10042, 4040)     # by (index group, index offset)

`via(name)` returns a `GeoView`: reads, writes and assertions over one transport
(`service` = in-process, `zenoh`, `modbus`, `ads`), plus the machine control of the
server (step, move, home, NC). The pytest fixtures in `geo_clients.pytest_plugin` build on
this module; it has no pytest dependency itself.

Writes are queued by the object service and applied at the next cycle boundary (docs/design.md §5),
so `GeoView.write(..., apply=True)` (the default) steps one cycle after the write.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import math
import shutil
import tempfile
import threading
from collections.abc import Callable, Coroutine, Iterable, Iterator
from pathlib import Path
from typing import Any

from geo_clients.common import open_client
from geo_server import access, jit
from geo_server.client import GeoClient
from geo_server.compose import EngineOptions, build_machine, loopback_interface
from geo_server.dictionary import ObjectDef, load_dictionary
from geo_server.errors import AdsError
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.paths import default_startup_list
from geo_server.recorder import Comparison, Recorder, RecordSpec, Trace, compare, load_trace
from geo_server.recorder.compare import Tolerance
from geo_server.service import ObjectService
from geo_server.snapshot import Snapshot

#: Transports a `GeoTestServer` can serve; `service` is the in-process object service.
VIAS = ("service", "zenoh", "modbus", "ads")
#: Bound for `move`, `nc` and `run_until`: never step forever.
MAX_CYCLES = 200_000

_netids = itertools.count(1)


def _next_netid() -> str:
    """A distinct AMS NetId per server: pyads maps one NetId to one endpoint per process."""
    n = next(_netids)
    return f"127.0.{(n >> 8) & 0xFF}.{n & 0xFF}.1.1"


class ServiceClient:
    """The `GeoClient` protocol over an in-process `ObjectService` (no transport).

    Reads come from the latest snapshot; writes are validated at once and applied at the
    next cycle boundary, exactly as over the transports in stepped mode.
    """

    def __init__(self, service: ObjectService) -> None:
        self.service = service

    def read(self, name: str, axis: int = 0) -> Any:
        return access.read_name(self.service, name, axis)

    def write(self, name: str, axis: int, value: Any) -> Any:
        obj = self.service.lookup(name, axis)
        v = obj.coerce(value)
        fut = access.write_name(self.service, name, axis, v)
        if fut.done():
            fut.result()  # reload/save run at once: raise their error
        return v

    def read_raw(self, index_group: int, index_offset: int, length: int = 0) -> bytes:
        return self.service.read(index_group, index_offset, length or None)

    def write_raw(self, index_group: int, index_offset: int, data: bytes) -> None:
        fut = access.write(self.service, index_group, index_offset, data)
        if fut.done():
            fut.result()

    def close(self) -> None:
        """Nothing to release."""


class GeoTestServer:
    """A stepped geo-server with transports on free loopback ports (see module docstring).

    `startup`: a start-up list (`hochlauf.lis`); None = the default machine in `lists/`.
    `homed`: start with every axis homed (temperature compensation needs it, 000 p.15).
    `machine_name`: the Zenoh key prefix `cnc/<machine_name>` (docs/design.md §7).
    `time_scale`: simulated seconds of the twin per cycle second (docs/twin.md; default:
    the twin file's), so a warm-up of hours takes a few thousand steps.
    `record_dir`: the recordings folder of recordings asked for over an interface
    (`cmd/record`, docs/recorder.md §7); None = a private temporary folder, removed by
    `close` (`record()` records in memory and needs none).
    """

    def __init__(
        self,
        startup: str | Path | None = None,
        *,
        homed: bool = True,
        cycle_ms: float = 1.0,
        machine_name: str = "test",
        timeout: float = 5.0,
        publish_period: float = 0.01,
        status_period: float = 0.1,
        time_scale: float | None = None,
        record_dir: str | Path | None = None,
    ) -> None:
        self.startup = Path(startup) if startup else default_startup_list()
        self.cfg = load_machine(self.startup)
        jit.load()  # the stepped cycles compiled from the first one (geo_server/jit.py)
        built = build_machine(
            self.cfg, EngineOptions(cycle_ms=cycle_ms, homed=homed, time_scale=time_scale)
        )
        assert isinstance(built.machine, Machine)  # the cycle in this process: stepped
        self.machine = built.machine
        self.service = built.service
        #: the private recordings folder `close` removes (only that one)
        self._own_record_dir = None if record_dir else tempfile.mkdtemp(prefix="geo-rec-")
        self.service.recordings.record_dir = Path(record_dir or self._own_record_dir or "")
        self.machine_name = machine_name
        self.timeout = timeout
        self.publish_period = publish_period
        self.status_period = status_period
        self.dictionary = load_dictionary()
        self.netid = _next_netid()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._interfaces: dict[str, Any] = {}
        self._clients: dict[str, GeoClient] = {"service": ServiceClient(self.service)}
        self._recorders: list[Recorder] = []
        self._closed = False

    # ------------------------------------------------------------------ lifecycle

    def __enter__(self) -> GeoTestServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the clients, then the transports, then the loop thread."""
        if self._closed:
            return
        self._closed = True
        for rec in self._recorders:
            rec.stop()
        recordings = self.service.recordings
        if recordings.recording is not None:  # one an interface started: not written
            recordings.recording.abort()
            recordings.recording = None
        for via, client in list(self._clients.items()):
            if via != "service":
                with contextlib.suppress(Exception):
                    client.close()
        self._clients.clear()
        for iface in reversed(list(self._interfaces.values())):
            with contextlib.suppress(Exception):
                self._run(iface.close())
        self._interfaces.clear()
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self._loop.stop)
            if self._thread is not None:
                self._thread.join(5)
            self._loop.close()
            self._loop = None
        if self._own_record_dir:
            shutil.rmtree(self._own_record_dir, ignore_errors=True)

    def _run(self, coro: Coroutine[Any, Any, Any], timeout: float = 15.0) -> Any:
        if self._loop is None:
            self._loop = asyncio.new_event_loop()
            self._thread = threading.Thread(
                target=self._loop.run_forever, name="geo-test-loop", daemon=True
            )
            self._thread.start()
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(timeout)

    def start(self, *vias: str) -> GeoTestServer:
        """Start the transports `vias` (`zenoh`, `modbus`, `ads`) if not yet running."""
        for via in vias:
            if via == "service" or via in self._interfaces:
                continue
            if via not in VIAS:
                raise ValueError(f"unknown transport {via!r} (one of {', '.join(VIAS)})")
            iface = loopback_interface(  # built by the composition root, as `run`'s are
                via,
                self.service,
                machine=self.machine_name,
                netid=self.netid,
                publish_period=self.publish_period,
                status_period=self.status_period,
            )
            self._run(iface.start())
            self._interfaces[via] = iface
        return self

    def endpoint(self, via: str) -> str:
        """Where a client connects: `tcp/127.0.0.1:<port>` (zenoh) or `127.0.0.1:<port>`."""
        self.start(via)
        iface = self._interfaces[via]  # Any: ZenohInterface, ModbusInterface or AdsServer
        endpoint: str
        if via == "zenoh":
            endpoint = iface.endpoints[0]
        elif via == "modbus":
            endpoint = iface.endpoint
        else:
            endpoint = iface.address
        return endpoint

    def client_options(self, via: str) -> dict[str, Any]:
        """Keyword arguments of `geo_clients.common.open_client` for this server."""
        return {
            "endpoint": self.endpoint(via),
            "machine": self.machine_name,
            "timeout": self.timeout,
            "netid": self.netid,
        }

    def client(self, via: str = "service") -> GeoClient:
        """A client of this server over `via` (opened once, closed with the server)."""
        if via not in self._clients:
            self._clients[via] = open_client(via, **self.client_options(via))
        return self._clients[via]

    def via(self, via: str = "service") -> GeoView:
        """Reads, writes and assertions over one transport."""
        return GeoView(self, via)

    # ------------------------------------------------------------------ machine control

    @property
    def axes(self) -> tuple[int, ...]:
        return self.service.info.axes

    @property
    def cycle(self) -> int:
        return self.machine.cycle

    @property
    def snapshot(self) -> Snapshot:
        return self.service.current(stale_ok=True)

    def axis(self, axis: int | str) -> int:
        """Logical axis number of `axis` (a number or an axis name such as `"X"`)."""
        if isinstance(axis, str) and not axis.isdigit():
            slot = self.machine.names.get(axis.upper())
            if slot is None:
                raise KeyError(f"no axis named {axis!r} (axes: {', '.join(self.machine.names)})")
            return self.axes[slot]
        return int(axis)

    def step(self, n: int = 1) -> Snapshot:
        """Run `n` GEO cycles now."""
        return access.step(self.service, n)

    def run_until(
        self, predicate: Callable[[GeoTestServer], bool], max_cycles: int = MAX_CYCLES
    ) -> int:
        """Step until `predicate(self)` holds; returns the cycles run (bounded)."""
        for n in range(max_cycles + 1):
            if predicate(self):
                return n
            self.step(1)
        raise TimeoutError(f"condition not met within {max_cycles} cycles")

    def move(
        self,
        axis: int | str,
        position: float,
        *,
        feed: float | None = None,
        wait: bool = True,
        max_cycles: int = MAX_CYCLES,
    ) -> int:
        """Move `axis` to `position` [0.1 µm / 0.0001°] (SIM::target_position) and, with
        `wait`, step until it is in position. `feed` in µm/s (SIM::feed). Returns cycles."""
        a = self.axis(axis)
        if feed is not None:
            access.write_name(self.service, "SIM::feed", a, feed)
        access.write_name(self.service, "SIM::target_position", a, round(position))
        self.step(1)
        if not wait:
            return 1
        slot = self.machine.slot(a)
        return 1 + self.run_until(lambda s: s.machine.nc_side.in_position([slot]), max_cycles)

    def set_position(self, axis: int | str, position: float) -> None:
        """Jump the command position without motion (SIM::set_position) and step once."""
        access.write_name(self.service, "SIM::set_position", self.axis(axis), round(position))
        self.step(1)

    def home(self, axis: int | str) -> None:
        """Home `axis` in place (SIM::homed := TRUE) and step once."""
        access.write_name(self.service, "SIM::homed", self.axis(axis), True)
        self.step(1)

    def nc(self, text: str, *, wait: bool = True, max_cycles: int = MAX_CYCLES) -> int:
        """Run NC lines (docs/design.md §5 player) and, with `wait`, step until they are done."""
        self.service.nc.run(text)
        self.step(1)
        if not wait:
            return 1
        return 1 + self.run_until(
            lambda s: s.machine.player is None or not s.machine.player.running, max_cycles
        )

    # ------------------------------------------------------------------ recording

    def record(
        self,
        *objects: str,
        every: int = 1,
        trigger: str | None = None,
        pre: int = 0,
        post: int = 1000,
    ) -> Recorder:
        """Start recording `objects` (selectors of docs/recorder.md: `TEMPC::*`,
        `SIM::command_position@1`, `0x120300:0x10043`) every `every` cycles, and the
        inputs; `.stop()` returns the `Trace` (`.inputs`: what to replay)."""
        spec = RecordSpec(list(objects), every, trigger, pre, post)
        rec = Recorder(self.service, spec, self.machine_name).start()
        self._recorders.append(rec)
        return rec

    # ------------------------------------------------------------------ faults

    def inject(self, fault: str) -> dict[str, Any]:
        """Inject a fault (docs/faults.md: `ads:error=0x707,count=2`, `sensor@X:stuck`,
        …); returns it as `status()["faults"]` lists it (its `id` clears it)."""
        # a sensor fault lands at the next cycle boundary: in stepped mode, now
        result = self.service.faults.inject(fault)
        if result["target"] == "sensor":
            self.step(1)
        return result

    def clear_faults(self, ident: int | None = None) -> list[dict[str, Any]]:
        """Clear fault `ident`, or every fault (None); returns those cleared."""
        cleared = self.service.faults.clear(ident)
        if any(f["target"] == "sensor" for f in cleared):
            self.step(1)
        return cleared

    @contextlib.contextmanager
    def fault(self, fault: str) -> Iterator[dict[str, Any]]:
        """`with srv.fault("modbus:error=6"): …` — injected for the block, cleared after
        it (unless its count was used up already)."""
        injected = self.inject(fault)
        try:
            yield injected
        finally:
            if any(f["id"] == injected["id"] for f in self.service.faults.status()):
                self.clear_faults(injected["id"])

    def faults(self) -> list[dict[str, Any]]:
        """The active faults, as `status()["faults"]`."""
        return self.service.faults.status()

    def errors(self) -> list[dict[str, Any]]:
        return self.service.errors()

    # ------------------------------------------------------------------ shortcuts

    def read(self, name: str, axis: int | str = 0, via: str = "service") -> Any:
        return self.via(via).read(name, axis)

    def write(self, name: str, axis: int | str, value: Any, via: str = "service") -> Any:
        return self.via(via).write(name, axis, value)


def check_golden(
    trace: Trace,
    path: str | Path,
    tolerances: Iterable[str | Tolerance] = (),
    *,
    default: float = 0.0,
    update: bool = False,
) -> Comparison | None:
    """Hold `trace` to the golden trace at `path` (docs/recorder.md §6): an
    `AssertionError` with the readable diff when they differ. `update` (pytest
    `--geo-update-golden`) writes `trace` as the new golden one instead. A golden file
    that does not exist yet is written and the check fails once, so that a new golden
    trace is looked at before it is trusted."""
    p = Path(path)
    if update or not p.exists():
        p.parent.mkdir(parents=True, exist_ok=True)
        trace.save(p)
        if update:
            return None
        raise AssertionError(f"{p}: no golden trace yet; written now — check it, then rerun")
    result = compare(load_trace(p), trace, list(tolerances), default)
    if not result.ok:
        raise AssertionError(f"{p}:\n{result.report()}")
    return result


class GeoView:
    """One transport's view of a `GeoTestServer`: read, write, assert; control forwards."""

    def __init__(self, server: GeoTestServer, via: str) -> None:
        if via not in VIAS:
            raise ValueError(f"unknown transport {via!r} (one of {', '.join(VIAS)})")
        self.server = server
        self.name = via

    def __repr__(self) -> str:
        return f"GeoView({self.name!r})"

    @property
    def client(self) -> GeoClient:
        return self.server.client(self.name)

    # machine control is the server's (there is one machine)
    def step(self, n: int = 1) -> Snapshot:
        return self.server.step(n)

    def move(self, axis: int | str, position: float, **kw: Any) -> int:
        return self.server.move(axis, position, **kw)

    def home(self, axis: int | str) -> None:
        self.server.home(axis)

    def nc(self, text: str, **kw: Any) -> int:
        return self.server.nc(text, **kw)

    # ------------------------------------------------------------------ objects

    def _obj(self, name: str) -> ObjectDef:
        return self.server.dictionary.by_name(name)

    def read(self, name: str, axis: int | str = 0) -> Any:
        """Decoded value of an object by name over this transport."""
        return self.client.read(name, self.server.axis(axis))

    def write(self, name: str, axis: int | str, value: Any, *, apply: bool = True) -> Any:
        """Write by name over this transport; `apply` steps one cycle so it takes effect."""
        v = self.client.write(name, self.server.axis(axis), value)
        if apply:
            self.server.step(1)
        return v

    def read_raw(self, index_group: int, index_offset: int, length: int = 0) -> bytes:
        """ADS bytes by address (docs/design.md §2) over this transport."""
        return self.client.read_raw(index_group, index_offset, length)

    def read_address(self, index_group: int, index_offset: int) -> Any:
        """Decoded value of the object at `(index_group, index_offset)`."""
        obj, _axis, attr = self.server.dictionary.resolve(
            index_group, index_offset, self.server.axes
        )
        data = self.read_raw(index_group, index_offset, obj.length if attr is None else 0)
        if attr is None:
            return obj.decode(data)
        if attr in ("length", "writable"):
            return int.from_bytes(data, "little")
        return data.split(b"\0", 1)[0].decode("cp1252")

    def write_raw(
        self, index_group: int, index_offset: int, data: bytes, *, apply: bool = True
    ) -> None:
        self.client.write_raw(index_group, index_offset, data)
        if apply:
            self.server.step(1)

    # ------------------------------------------------------------------ assertions

    def assert_value(
        self, name: str, axis: int | str, expected: Any, *, abs_tol: float = 0.0
    ) -> Any:
        """Assert an object's value by name (exact, or within `abs_tol`)."""
        got = self.read(name, axis)
        _check(f"{name} (axis {axis}) over {self.name}", got, expected, abs_tol)
        return got

    def assert_raw(
        self, index_group: int, index_offset: int, expected: Any, *, abs_tol: float = 0.0
    ) -> Any:
        """Assert the object at `(group, offset)`: `expected` is its decoded value or bytes."""
        where = f"0x{index_group:X}/0x{index_offset:X} over {self.name}"
        if isinstance(expected, bytes | bytearray):
            got: Any = self.read_raw(index_group, index_offset, len(expected))
            _check(where, got, bytes(expected), 0.0)
            return got
        got = self.read_address(index_group, index_offset)
        _check(where, got, expected, abs_tol)
        return got

    def assert_values(self, axis: int | str, expected: dict[str, Any]) -> None:
        """Assert several objects of one axis; reports every mismatch at once."""
        problems = []
        for name, want in expected.items():
            try:
                self.assert_value(name, axis, want)
            except AssertionError as exc:
                problems.append(str(exc))
        if problems:
            raise AssertionError("\n".join(problems))

    def expect_error(self, code: int, fn: Callable[[], Any]) -> AdsError:
        """Run `fn` and assert it raises `AdsError` with ADS code `code` (docs/design.md §9)."""
        try:
            fn()
        except AdsError as exc:
            if exc.code != code:
                raise AssertionError(
                    f"expected ADS error 0x{code:X} over {self.name}, got 0x{exc.code:X}: "
                    f"{exc.message}"
                ) from exc
            return exc
        raise AssertionError(f"expected ADS error 0x{code:X} over {self.name}, got none")


def _check(what: str, got: Any, expected: Any, abs_tol: float) -> None:
    if abs_tol and isinstance(got, int | float) and isinstance(expected, int | float):
        ok = math.isclose(float(got), float(expected), rel_tol=0.0, abs_tol=abs_tol)
    else:
        ok = bool(got == expected)
    if not ok:
        tol = f" ± {abs_tol}" if abs_tol else ""
        raise AssertionError(f"{what}: expected {expected!r}{tol}, got {got!r}")


@contextlib.contextmanager
def geo_test_server(startup: str | Path | None = None, **options: Any) -> Iterator[GeoTestServer]:
    """`with geo_test_server() as srv:` — a `GeoTestServer` that is always closed."""
    srv = GeoTestServer(startup, **options)
    try:
        yield srv
    finally:
        srv.close()


__all__ = ["MAX_CYCLES", "VIAS", "GeoTestServer", "GeoView", "ServiceClient", "geo_test_server"]
