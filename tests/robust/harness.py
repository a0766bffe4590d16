"""A complete geo-server in the test process: real-time GEO cycle on its own thread, Zenoh,
Modbus and ADS on the `loop_thread`, all on ephemeral loopback ports; plus clients and
process probes (asyncio tasks, open file descriptors, RSS) for the robustness tests."""

from __future__ import annotations

import asyncio
import itertools
import os
from pathlib import Path

from conftest import free_port, run_in

from geo_server.client.ads_client import AdsClient
from geo_server.client.modbus_client import ModbusClient
from geo_server.client.zenoh_client import ZenohClient
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.machine.scheduler import Scheduler
from geo_server.paths import default_startup_list
from geo_server.service import ObjectService
from geo_server.transports.ads.server import AdsOptions, AdsServer
from geo_server.transports.modbus.server import ModbusInterface, ModbusOptions
from geo_server.transports.zenoh.options import ZenohOptions
from geo_server.transports.zenoh.server import ZenohInterface

#: Every Zenoh get / Modbus request / ADS request of these tests has this timeout (s).
TIMEOUT = 5.0

# pyads keeps one route per NetId in the process (one NetId <-> one endpoint): every ADS
# client of these tests gets a NetId of its own, from a range no other test file uses.
_netids = itertools.count(1)


def next_netid() -> str:
    n = next(_netids)
    return f"127.77.{n // 250}.{n % 250 + 1}.1.1"


class FullServer:
    """geo-server as `geo-server run` builds it, but in-process and on ephemeral ports."""

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        startup: Path | None = None,
        *,
        machine_name: str = "rb",
        mode: str = "realtime",
        cycle_s: float = 0.001,
        zenoh: bool = True,
        modbus: bool = True,
        ads: bool = True,
        ads_options: dict | None = None,
    ) -> None:
        self.loop = loop
        cfg = load_machine(startup or default_startup_list())
        self.machine = Machine(cfg, cycle_s=cycle_s, homed=True)
        self.scheduler = Scheduler(self.machine, mode=mode)
        self.service = ObjectService(self.machine, self.scheduler)
        self.machine_name = machine_name
        self.interfaces: list = []
        self.zenoh: ZenohInterface | None = None
        self.modbus: ModbusInterface | None = None
        self.ads: AdsServer | None = None
        try:
            if zenoh:
                self.zenoh_endpoint = f"tcp/127.0.0.1:{free_port()}"
                self.zenoh = ZenohInterface(
                    self.service,
                    ZenohOptions(
                        machine=machine_name, listen=[self.zenoh_endpoint], publish_period=0.02
                    ),
                )
                self._start(self.zenoh)
            if modbus:
                self.modbus = ModbusInterface(self.service, ModbusOptions(port=0))
                self._start(self.modbus)
            if ads:
                self.ads = AdsServer(self.service, AdsOptions(port=0, **(ads_options or {})))
                self._start(self.ads)
        except BaseException:
            self.close()
            raise
        self.scheduler.start()

    def _start(self, iface) -> None:
        run_in(self.loop, iface.start())
        self.interfaces.append(iface)

    def close(self) -> None:
        self.scheduler.stop()
        for iface in reversed(self.interfaces):
            run_in(self.loop, iface.close())
        self.interfaces.clear()

    def __enter__(self) -> FullServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ clients

    @property
    def endpoints(self) -> Endpoints:
        return Endpoints(
            self.machine_name,
            self.zenoh_endpoint if self.zenoh else "",
            self.modbus.port if self.modbus else 0,
            self.ads.port if self.ads else 0,
            len(self.service.info.axes),
        )

    def client(self, via: str):
        """A fresh client of the project's library over `via` (close it yourself)."""
        return self.endpoints.client(via)

    @property
    def cycle(self) -> int:
        return self.service.current(stale_ok=True).cycle


class Endpoints:
    """Where a server listens: enough to open clients (also in another process)."""

    def __init__(
        self, machine_name: str, zenoh_endpoint: str, modbus_port: int, ads_port: int, axes: int
    ) -> None:
        self.machine_name = machine_name
        self.zenoh_endpoint = zenoh_endpoint
        self.modbus_port = modbus_port
        self.ads_port = ads_port
        self.axes = axes

    def client(self, via: str):
        if via == "zenoh":
            return ZenohClient(
                machine=self.machine_name, connect=[self.zenoh_endpoint], timeout=TIMEOUT
            )
        if via == "modbus":
            return ModbusClient("127.0.0.1", self.modbus_port, timeout=TIMEOUT)
        return AdsClient("127.0.0.1", self.ads_port, netid=next_netid(), timeout=TIMEOUT)


# ---------------------------------------------------------------------- process probes


def open_fds() -> int:
    """Open file descriptors of this process (Linux)."""
    return len(os.listdir("/proc/self/fd"))


def socket_fds() -> int:
    """Open sockets of this process (Linux)."""
    n = 0
    for fd in os.listdir("/proc/self/fd"):
        try:
            if os.readlink(f"/proc/self/fd/{fd}").startswith("socket:"):
                n += 1
        except OSError:
            pass  # closed in between
    return n


def rss_kib() -> int:
    """Resident set size of this process in KiB (VmRSS of /proc/self/status)."""
    with open("/proc/self/status", encoding="ascii") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    raise RuntimeError("no VmRSS in /proc/self/status")


def loop_tasks(loop: asyncio.AbstractEventLoop) -> int:
    """Number of unfinished asyncio tasks on `loop` (counted on the loop's own thread)."""

    async def count() -> int:
        return sum(1 for t in asyncio.all_tasks() if not t.done()) - 1  # minus this one

    return run_in(loop, count())


# ---------------------------------------------------------------------- a well-behaved client

#: The object each transport's checker owns on axis 4 (fuzzers never write axis 4).
CHECKER_OBJECT = {
    "zenoh": "TEMPC::position_0",
    "modbus": "TEMPC::offset_0",
    "ads": "TEMPC::coefficient",
}
CHECKER_AXIS = 4


class Checker:
    """A thread that keeps asking well-formed questions over one transport and checks
    the answers: write a new value to its own object, read it back (it must be the
    value just written: acknowledged writes are visible), read `SIM::cycle_count` (it
    must grow: every acknowledged write waited for a GEO cycle)."""

    def __init__(self, server: FullServer | Endpoints, via: str, pause: float = 0.002) -> None:
        import threading

        self.server, self.via, self.pause = server, via, pause
        self.name = CHECKER_OBJECT[via]
        self.rounds = 0
        self.errors: list[str] = []
        self.cycles: list[int] = []
        self._stop = threading.Event()
        self._client = server.client(via)
        self._thread = threading.Thread(target=self._run, name=f"checker-{via}", daemon=True)

    def value(self, n: int):
        # distinct per round and inside every object's range
        return float(n % 9000) + 0.5 if self.name == "TEMPC::coefficient" else n

    def check_once(self) -> None:
        v = self.value(self.rounds + 1)
        self._client.write(self.name, CHECKER_AXIS, v)
        got = self._client.read(self.name, CHECKER_AXIS)
        if got != v:
            raise AssertionError(f"{self.via}: wrote {v!r}, read back {got!r}")
        cycle = self._client.read("SIM::cycle_count", 0)
        if self.cycles and cycle <= self.cycles[-1]:
            raise AssertionError(f"{self.via}: cycle count {cycle} after {self.cycles[-1]}")
        self.cycles.append(cycle)
        self.rounds += 1

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.check_once()
            except Exception as exc:  # collected, asserted by the test
                self.errors.append(f"{type(exc).__name__}: {exc}")
                if len(self.errors) > 20:
                    return
            self._stop.wait(self.pause)

    def start(self) -> Checker:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(3 * TIMEOUT)
        try:
            if not self.errors:
                self.check_once()  # and once more after the load
        except Exception as exc:
            self.errors.append(f"after: {type(exc).__name__}: {exc}")
        finally:
            self._client.close()


class Reader:
    """Bulk reads over one transport in a loop (Zenoh wildcard get and status, Modbus
    block read, ADS sum read of a whole axis); counts requests and errors."""

    def __init__(self, server: FullServer | Endpoints, via: str) -> None:
        import threading

        ep = server.endpoints if isinstance(server, FullServer) else server
        self.ep, self.via = ep, via
        self.requests = 0
        self.errors: list[str] = []
        self._stop = threading.Event()
        self._client = ep.client(via)
        self._thread = threading.Thread(target=self._run, name=f"reader-{via}", daemon=True)

    def once(self) -> None:
        c = self._client
        if self.via == "zenoh":
            replies = c.get(f"cnc/{self.ep.machine_name}/axis/*/tempc/*")
            assert len(replies) == 6 * self.ep.axes, len(replies)
            assert c.status()["cycle"] > 0
        elif self.via == "modbus":
            # one block read of every TEMPC register of axis 2 (0x41…0x45: 260…279)
            rr = c._client.read_holding_registers(260, count=20, device_id=2)
            assert not rr.isError(), rr
            assert len(rr.registers) == 20
        else:
            values = c.read_axis(3)  # one sum read of every GEO object of axis 3
            assert values["TEMPC::coefficient"] == c.read("TEMPC::coefficient", 3)
        self.requests += 1

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.once()
            except Exception as exc:
                self.errors.append(f"{type(exc).__name__}: {exc}")
                if len(self.errors) > 20:
                    return
            self._stop.wait(0.001)

    def start(self) -> Reader:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(3 * TIMEOUT)
        self._client.close()
