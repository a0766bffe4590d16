"""Raw reads the tests time nothing with: one request on a fresh socket, the answer's
code (tests that check an interface answers while another is busy)."""

from __future__ import annotations

import socket
import struct

from geo_server.dictionary import ObjectDef
from geo_server.transports.modbus.regmap import register_address, register_count


def modbus_read(port: int, obj: ObjectDef, timeout: float) -> int:
    """FC 3 of `obj`'s registers (unit 1: axis 1) on 127.0.0.1:`port`: the exception
    code, or 0 for an answer."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
        s.sendall(
            struct.pack(">HHHBBHH", 1, 0, 6, 1, 3, register_address(obj), register_count(obj))
        )
        buf = b""
        while len(buf) < 9:
            chunk = s.recv(64)
            assert chunk
            buf += chunk
        return 0 if buf[7] == 3 else buf[8]
