"""Load generator: clients hammering geo-server's three transports at once.

    python bench/load.py --zenoh P --modbus P --ads P --seconds S [--mix read|soak] [--json]

One thread per transport, each a closed loop (one request in flight, as fast as the
server answers), bounded in time and count; latencies go into bounded reservoirs.

- `--mix read`: single-object reads only (Zenoh raw key, Modbus FC 3, ADS Read).
- `--mix soak`: reads plus every 10th request a write of a TEMPC parameter on that
  transport (Zenoh `TEMPC::coefficient`, Modbus `TEMPC::offset_0`, ADS
  `TEMPC::position_0`; values toggle within range), every 10th ADS request a sum read
  of the TEMPC group, an NC line over Zenoh every `--nc-period` s (X moves between ±50 mm), an
  ADS on-change notification on `SIM::command_position` of X and a Zenoh subscription
  on `cnc/local/axis/1/**`.

Prints one JSON object (per operation: count, errors, p50/p99/max µs; notifications and
publications received) at the end.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

from common import HOST, Reservoir, address, summary_us

#: the objects of the mixes, from the dictionary: X's TEMPC parameters
COEFF = address("TEMPC::coefficient")
COEFF_ADS = (COEFF.index_group, COEFF.index_offset)
OFFSET_0 = address("TEMPC::offset_0")
POSITION_0 = address("TEMPC::position_0")
TEMPC = [address(n) for n in ("TEMPC::activated", "TEMPC::actual_offset")] + [
    COEFF,
    OFFSET_0,
    POSITION_0,
]

MAX_PER_OP = 2_000_000  # hard bound on requests per operation
RESERVOIR = 100_000  # latency samples kept per operation


class Op:
    """Counters and latencies of one kind of request."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.lat = Reservoir(RESERVOIR)
        self.errors: Counter[str] = Counter()
        self.examples: dict[str, str] = {}  # first message of each kind (bounded)

    def call(self, fn: Callable[[], Any]) -> None:
        t0 = time.perf_counter_ns()
        try:
            fn()
        except Exception as exc:  # counted, the load goes on
            key = type(exc).__name__
            if len(self.errors) < 20 or key in self.errors:
                self.errors[key] += 1
                self.examples.setdefault(key, str(exc)[:300])
            return
        self.lat.add((time.perf_counter_ns() - t0) / 1000)

    def result(self) -> dict[str, Any]:
        s = summary_us(self.lat.values())
        return {
            "ok": self.lat.n,
            "errors": sum(self.errors.values()),
            "error_kinds": dict(self.errors),
            "error_examples": self.examples,
            "p50_us": s["p50"],
            "p99_us": s["p99"],
            "max_us": s["max"],
        }


class Load:
    """The three client threads and their operations."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.end = time.monotonic() + args.seconds + 30  # reset when all are connected
        # Three client threads and the main thread meet once every client is connected;
        # the measured time starts then (the parent is told with a "ready" line).
        self.barrier = threading.Barrier(4, action=self._start_clock, timeout=30)
        self.ops: dict[str, Op] = {}
        self.counts = Counter[str]()
        self.setup_errors: list[str] = []
        self._lock = threading.Lock()

    def op(self, name: str) -> Op:
        with self._lock:
            return self.ops.setdefault(name, Op(name))

    def _start_clock(self) -> None:
        self.end = time.monotonic() + self.args.seconds

    def connected(self) -> None:
        """Called by each client thread once connected: wait for the others."""
        with contextlib.suppress(threading.BrokenBarrierError):
            self.barrier.wait()

    def running(self, i: int) -> bool:
        return i < MAX_PER_OP and time.monotonic() < self.end

    # ------------------------------------------------------------------ zenoh

    def zenoh(self) -> None:
        from common import zenoh_session

        soak = self.args.mix == "soak"
        s = zenoh_session(f"tcp/{HOST}:{self.args.zenoh}")
        subs = []
        try:
            if soak:
                subs.append(
                    s.declare_subscriber("cnc/local/axis/1/**", lambda _s: self._count("zenoh_pub"))
                )

            def get(key: str, payload: bytes | None = None) -> None:
                kw: dict[str, Any] = {"timeout": 2.0}
                if payload is not None:
                    kw["payload"] = payload
                for reply in s.get(key, **kw):
                    if reply.ok is None:
                        raise RuntimeError(reply.err.payload.to_bytes()[:200])
                    return
                raise TimeoutError(key)

            read = self.op("zenoh read (raw key)")
            write = self.op("zenoh write TEMPC::coefficient")
            nc = self.op("zenoh NC line")
            raw = COEFF.raw_key
            coef = COEFF.named_key
            next_nc = time.monotonic() + 0.5
            lines = 0
            self.connected()
            i = 0
            while self.running(i):
                i += 1
                if soak and time.monotonic() >= next_nc:
                    next_nc += self.args.nc_period
                    lines += 1
                    x = 50 if lines % 2 else -50
                    line = f"G90 G01 X{x} F6000".encode()
                    nc.call(lambda line=line: get("cnc/local/nc", line))
                elif soak and i % 10 == 0:
                    v = b"4100" if i % 20 else b"4000"
                    write.call(lambda v=v: get(coef, v))
                else:
                    read.call(lambda: get(raw))
        finally:
            for sub in subs:
                sub.undeclare()
            s.close()

    # ------------------------------------------------------------------ modbus

    def modbus(self) -> None:
        from pymodbus.client import ModbusTcpClient

        soak = self.args.mix == "soak"
        c = ModbusTcpClient(HOST, port=self.args.modbus, timeout=2)
        if not c.connect():
            raise ConnectionError("modbus")
        try:
            read = self.op("modbus read FC 3")
            write = self.op("modbus write TEMPC::offset_0 FC 16")
            regs = {
                v: c.convert_to_registers(v, c.DATATYPE.INT32) for v in (40, 41)
            }  # offset_0 of X is 40 in the default machine

            def rd() -> None:
                rr = c.read_holding_registers(COEFF.register, count=COEFF.registers, device_id=1)
                if rr.isError():
                    raise RuntimeError(str(rr))

            def wr(v: int) -> None:
                rr = c.write_registers(OFFSET_0.register, regs[v], device_id=1)
                if rr.isError():
                    raise RuntimeError(str(rr))

            self.connected()
            i = 0
            while self.running(i):
                i += 1
                if soak and i % 10 == 0:
                    write.call(lambda i=i: wr(41 if i % 20 else 40))
                else:
                    read.call(rd)
        finally:
            c.close()

    # ------------------------------------------------------------------ ads

    def ads(self) -> None:
        import pyads

        from geo_server.client.ads_client import AdsClient

        soak = self.args.mix == "soak"
        client = AdsClient(HOST, self.args.ads, netid="127.0.0.1.1.1")
        try:
            conn = client.conn
            if soak:
                client.subscribe("SIM::command_position", 1, lambda _v, _t: self._count("ads_note"))
            read = self.op("ads read")
            write = self.op("ads write TEMPC::position_0")
            sumr = self.op("ads sum read (TEMPC, 5 objects)")
            tempc = [(a.index_group, a.index_offset, a.size) for a in TEMPC]

            def sr() -> None:
                for r in client.sum_read_raw(tempc):
                    if not isinstance(r, bytes):
                        raise r

            self.connected()
            i = 0
            while self.running(i):
                i += 1
                if soak and i % 10 == 0:
                    v = 100 if i % 20 else 101  # X position_0 is 100 in the default machine
                    write.call(
                        lambda v=v: conn.write(
                            POSITION_0.index_group, POSITION_0.index_offset, v, pyads.PLCTYPE_DINT
                        )
                    )
                elif soak and i % 10 == 5:
                    sumr.call(sr)
                else:
                    read.call(lambda: conn.read(*COEFF_ADS, pyads.PLCTYPE_LREAL))
        finally:
            client.close()

    # ------------------------------------------------------------------ running

    def _count(self, what: str) -> None:
        self.counts[what] += 1  # a Counter update is atomic enough for a statistic

    def _guard(self, fn: Callable[[], None]) -> Callable[[], None]:
        def run() -> None:
            try:
                fn()
            except Exception as exc:
                self.setup_errors.append(f"{fn.__name__}: {type(exc).__name__}: {exc}")
                self.barrier.abort()

        return run

    def run(self) -> dict[str, Any]:
        threads = [
            threading.Thread(target=self._guard(fn), name=fn.__name__, daemon=True)
            for fn in (self.zenoh, self.modbus, self.ads)
        ]
        for t in threads:
            t.start()
        self.connected()
        t0 = time.monotonic()
        print("ready", flush=True)
        for t in threads:
            t.join(self.args.seconds + 30)
        return {
            "seconds": time.monotonic() - t0,
            "ops": {
                name: op.result() for name, op in sorted(self.ops.items()) if op.lat.n or op.errors
            },
            "received": dict(self.counts),
            "setup_errors": self.setup_errors,
            "stuck_threads": [t.name for t in threads if t.is_alive()],
        }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--zenoh", type=int, required=True, help="Zenoh TCP port")
    ap.add_argument("--modbus", type=int, required=True, help="Modbus TCP port")
    ap.add_argument("--ads", type=int, required=True, help="ADS TCP port")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--mix", choices=("read", "soak"), default="read")
    ap.add_argument(
        "--nc-period",
        type=float,
        default=2.0,
        help="soak: seconds between NC lines (a 100 mm move takes ~1.1 s; a line sent "
        "while X still moves fails the GEO cycle, see bench/README_SECTION.md)",
    )
    args = ap.parse_args()
    print(json.dumps(Load(args).run()), flush=True)


if __name__ == "__main__":
    main()
