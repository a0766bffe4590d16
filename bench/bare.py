"""Bare transport floors: trivial servers that answer one read with fixed bytes.

    python bench/bare.py zenoh  --port P   # queryable on cnc/local/** answering 8 fixed bytes
    python bench/bare.py modbus --port P   # pymodbus SimDevice, unit 1, TEMPC::coefficient
    python bench/bare.py ads    --port P   # asyncio responder: every Read gets 8 fixed bytes
    python bench/bare.py pyads  --port P   # pyads' own AdsTestServer (AdvancedHandler)

Each serves on 127.0.0.1 until SIGTERM/SIGINT, at the scheduler slice `geo-server run` asks
for by default (`--time-slice-us`, geo_server/timeslice.py). They are the denominators of
the transport ratios (docs/design.md §11): the same client library talks to these and to
geo-server, both at the same slice.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import signal
import struct
import sys
import threading

from common import address

from geo_server import timeslice

#: What every bare server answers: TEMPC::coefficient 4000.0 as REAL64, at its addresses.
VALUE = struct.pack("<d", 4000.0)
COEFF = address("TEMPC::coefficient")
HOST = "127.0.0.1"


def _wait_for_signal() -> None:
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    while not stop.wait(0.5):
        pass


def serve_zenoh(port: int) -> None:
    """A queryable answering every get on `cnc/local/**` with 8 fixed bytes."""
    import zenoh

    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("listen/endpoints", f'["tcp/{HOST}:{port}"]')
    octet = zenoh.Encoding.APPLICATION_OCTET_STREAM

    def on_query(query: zenoh.Query) -> None:
        with query:
            query.reply(query.key_expr, VALUE, encoding=octet)

    session = zenoh.open(cfg)
    q = session.declare_queryable("cnc/local/**", on_query)
    print(f"bare zenoh on tcp/{HOST}:{port}", flush=True)
    try:
        _wait_for_signal()
    finally:
        q.undeclare()
        session.close()


def serve_modbus(port: int) -> None:
    """pymodbus `ModbusTcpServer` with one `SimDevice` (unit 1, TEMPC::coefficient)."""
    from pymodbus.server import ModbusTcpServer
    from pymodbus.simulator import DataType, SimData, SimDevice

    regs = list(struct.unpack(">4H", struct.pack(">d", 4000.0)))

    async def run() -> None:
        device = SimDevice(
            id=1,
            simdata=[
                SimData(
                    COEFF.register,
                    count=COEFF.registers,
                    values=regs,
                    datatype=DataType.REGISTERS,
                )
            ],
        )
        server = ModbusTcpServer(device, address=(HOST, port))
        await server.serve_forever(background=True)
        print(f"bare modbus on {HOST}:{port}", flush=True)
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        await stop.wait()
        await server.shutdown()

    asyncio.run(run())


class _AdsResponder(asyncio.Protocol):
    """Answers every AMS Read with `VALUE` (geo-server's codec does the framing)."""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        from geo_server.transports.ads import codec

        self.codec = codec
        self.framer = codec.Framer()
        self.transport = transport

    def data_received(self, data: bytes) -> None:
        c = self.codec
        for ev in self.framer.feed(data):
            if isinstance(ev, c.AmsPacket):
                h = ev.header
                if h.command == c.Command.READ:
                    payload = c.read_response(0, VALUE)
                else:
                    payload = c.result_response(c.AdsErrorCode.DEVICE_SRVNOTSUPP)
                self.transport.write(c.response_frame(h, payload))  # type: ignore[attr-defined]


def serve_ads(port: int) -> None:
    """A trivial asyncio ADS responder."""

    async def run() -> None:
        loop = asyncio.get_running_loop()
        server = await loop.create_server(_AdsResponder, HOST, port)
        print(f"bare ads on {HOST}:{port}", flush=True)
        stop = asyncio.Event()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        await stop.wait()
        server.close()
        await server.wait_closed()

    asyncio.run(run())


def serve_pyads(port: int) -> None:
    """pyads' `AdsTestServer` with one variable at TEMPC::coefficient's address (LREAL 4000.0).

    Quirks (pyads 3.6.0 test server): thread per connection, `recvfrom(4096)` without framing, AMS
    port ignored; an unknown index kills the connection thread. Its `request_history`
    grows with every request, so it is swapped for a bounded deque here.
    """
    import pyads
    from pyads.testserver import AdsTestServer, AdvancedHandler, PLCVariable

    handler = AdvancedHandler()
    handler.add_variable(
        PLCVariable(
            "TEMPC.coefficient",
            VALUE,
            ads_type=pyads.constants.ADST_REAL64,
            symbol_type="LREAL",
            index_group=COEFF.index_group,
            index_offset=COEFF.index_offset,
        )
    )
    server = AdsTestServer(handler=handler, ip_address=HOST, port=port, logging=False)
    server.request_history = collections.deque(maxlen=100)  # type: ignore[assignment]
    server.start()
    print(f"pyads AdsTestServer on {HOST}:{port}", flush=True)
    try:
        _wait_for_signal()
    finally:
        server.stop()


SERVERS = {"zenoh": serve_zenoh, "modbus": serve_modbus, "ads": serve_ads, "pyads": serve_pyads}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("kind", choices=sorted(SERVERS))
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument(
        "--time-slice-us",
        type=int,
        default=timeslice.DEFAULT_US,
        help="the scheduler slice to ask Linux for, as geo-server run does by default "
        "(0: the kernel's)",
    )
    args = ap.parse_args()
    timeslice.request(args.time_slice_us)
    SERVERS[args.kind](args.port)
    return 0


if __name__ == "__main__":
    sys.exit(main())
