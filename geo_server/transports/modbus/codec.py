"""Modbus TCP framing and PDUs, sans I/O: bytes in, requests out; replies out as bytes.

Modbus application protocol v1.1b3 and Modbus messaging on TCP/IP v1.0b:

- an ADU is the 7-byte MBAP header — transaction id (2), protocol id (2, always 0),
  length (2: unit id + PDU), unit id (1) — and a PDU of at most 253 bytes (function
  code + data), so the length field is 2…254;
- `MbapFramer.feed` cuts a byte stream into frames whatever the TCP segmentation: one
  request split over many segments, or many requests (a pipelining client) in one;
- a header that cannot be a Modbus TCP header (protocol id ≠ 0, length outside 2…254)
  makes the stream unusable — nothing tells where the next frame starts — so the
  framer reports it once and the server closes the connection;
- `parse_pdu` checks what the protocol itself defines, in the order of the standard's
  state diagrams: unknown function code → exception 1 (also for codes 0x80–0xFF, which
  are reserved for exception responses); quantity outside its limits, a byte count that
  does not match the quantity, a PDU of the wrong length, or an FC 5 value other than
  0x0000/0xFF00 → exception 3. Addresses are checked against the register map by the
  server (exception 2).

Everything here is pure: the asyncio server (`geo_server.transports.modbus.server`) feeds bytes in
and writes the bytes these functions return.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from geo_server.transports.modbus.regmap import (
    MAX_READ_BITS,
    MAX_READ_REGISTERS,
    MAX_WRITE_BITS,
    MAX_WRITE_REGISTERS,
    ExcCode,
)

_MBAP = struct.Struct(">HHHB")
MBAP_SIZE = _MBAP.size  # 7
#: Largest PDU (function code + data) of Modbus over serial line and TCP alike.
MAX_PDU = 253
#: Largest ADU on TCP: MBAP header + PDU.
MAX_ADU = MBAP_SIZE + MAX_PDU
#: FC 43 with MEI type 14: read device identification.
MEI_DEVICE_ID = 0x0E
COIL_ON, COIL_OFF = 0xFF00, 0x0000


@dataclass(frozen=True)
class Frame:
    """One request ADU: MBAP fields and the PDU."""

    transaction: int
    unit: int
    pdu: bytes


class MbapFramer:
    """Bytes in, whole frames out (any split, any coalescing)."""

    def __init__(self) -> None:
        self._buf = bytearray()
        #: Why the stream is unusable (a header that is not Modbus TCP), else None.
        self.error: str | None = None

    @property
    def pending(self) -> int:
        """Bytes of an unfinished frame held."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[Frame]:
        """Frames completed by `data`, up to a header that is not Modbus TCP: then
        `error` says why, the rest of the stream is discarded and nothing more is read."""
        if self.error is not None:
            return []
        self._buf += data
        out: list[Frame] = []
        while len(self._buf) >= MBAP_SIZE:
            tid, pid, length, unit = _MBAP.unpack_from(self._buf)
            if pid != 0 or not 2 <= length <= MAX_PDU + 1:
                self.error = (
                    f"not a Modbus TCP header: protocol id {pid}, length {length} "
                    f"(transaction {tid})"
                )
                self._buf = bytearray()
                break
            end = MBAP_SIZE - 1 + length
            if len(self._buf) < end:
                break
            out.append(Frame(tid, unit, bytes(self._buf[MBAP_SIZE:end])))
            del self._buf[:end]
        return out


def adu(transaction: int, unit: int, pdu: bytes) -> bytes:
    """A reply ADU: MBAP header + PDU."""
    return _MBAP.pack(transaction, 0, len(pdu) + 1, unit) + pdu


# ---------------------------------------------------------------------- requests


@dataclass(frozen=True)
class ReadRequest:
    """FC 1, 2, 3, 4: `count` bits or registers from `address`."""

    function: int
    address: int
    count: int


@dataclass(frozen=True)
class WriteRequest:
    """FC 5, 6, 15, 16: `values` (bools for coils, 16-bit words for registers) from
    `address`. FC 5 and 6 are one value, echoed in the reply."""

    function: int
    address: int
    values: tuple[int, ...] | tuple[bool, ...]


@dataclass(frozen=True)
class DeviceIdRequest:
    """FC 43 / MEI 14: read device identification (`code` 1 basic, 2 regular,
    3 extended stream, 4 one object) from `object_id`."""

    code: int
    object_id: int


@dataclass(frozen=True)
class Refused:
    """A request the protocol itself refuses: reply exception `code`."""

    function: int
    code: ExcCode
    reason: str


Request = ReadRequest | WriteRequest | DeviceIdRequest | Refused

_READ_LIMIT = {1: MAX_READ_BITS, 2: MAX_READ_BITS, 3: MAX_READ_REGISTERS, 4: MAX_READ_REGISTERS}


def parse_pdu(pdu: bytes) -> Request:
    """Decode a request PDU (see the module docstring for the checks and their order)."""
    if not pdu:
        return Refused(0, ExcCode.ILLEGAL_FUNCTION, "empty PDU")
    fc, body = pdu[0], pdu[1:]
    if fc in _READ_LIMIT:
        return _read(fc, body)
    if fc in (5, 6):
        return _write_single(fc, body)
    if fc == 15:
        return _write_coils(body)
    if fc == 16:
        return _write_registers(body)
    if fc == 43:
        return _device_id(body)
    return Refused(fc, ExcCode.ILLEGAL_FUNCTION, f"function code {fc} is not supported")


def _bad(fc: int, reason: str) -> Refused:
    return Refused(fc, ExcCode.ILLEGAL_VALUE, reason)


def _read(fc: int, body: bytes) -> Request:
    if len(body) != 4:
        return _bad(fc, f"FC {fc} request of {len(body) + 1} bytes, expected 5")
    address, count = struct.unpack(">HH", body)
    limit = _READ_LIMIT[fc]
    if not 1 <= count <= limit:
        return _bad(fc, f"quantity {count} outside 1…{limit}")
    return ReadRequest(fc, address, count)


def _write_single(fc: int, body: bytes) -> Request:
    if len(body) != 4:
        return _bad(fc, f"FC {fc} request of {len(body) + 1} bytes, expected 5")
    address, value = struct.unpack(">HH", body)
    if fc == 5:
        if value not in (COIL_ON, COIL_OFF):
            return _bad(fc, f"FC 5 value 0x{value:04X}: must be 0xFF00 (on) or 0x0000 (off)")
        return WriteRequest(5, address, (value == COIL_ON,))
    return WriteRequest(6, address, (value,))


def _write_coils(body: bytes) -> Request:
    if len(body) < 5:
        return _bad(15, "FC 15 request too short")
    address, count, nbytes = struct.unpack_from(">HHB", body)
    if not 1 <= count <= MAX_WRITE_BITS:
        return _bad(15, f"quantity {count} outside 1…{MAX_WRITE_BITS}")
    if nbytes != (count + 7) // 8 or len(body) != 5 + nbytes:
        return _bad(15, f"byte count {nbytes} does not match {count} coils")
    data = body[5:]
    bits = tuple(bool(data[i // 8] >> (i % 8) & 1) for i in range(count))
    return WriteRequest(15, address, bits)


def _write_registers(body: bytes) -> Request:
    if len(body) < 5:
        return _bad(16, "FC 16 request too short")
    address, count, nbytes = struct.unpack_from(">HHB", body)
    if not 1 <= count <= MAX_WRITE_REGISTERS:
        return _bad(16, f"quantity {count} outside 1…{MAX_WRITE_REGISTERS}")
    if nbytes != 2 * count or len(body) != 5 + nbytes:
        return _bad(16, f"byte count {nbytes} does not match {count} registers")
    return WriteRequest(16, address, struct.unpack_from(f">{count}H", body, 5))


def _device_id(body: bytes) -> Request:
    if not body or body[0] != MEI_DEVICE_ID:
        mei = body[0] if body else None
        return Refused(43, ExcCode.ILLEGAL_FUNCTION, f"MEI type {mei} is not supported")
    if len(body) != 3:
        return _bad(43, "FC 43/14 request must be 4 bytes")
    code, object_id = body[1], body[2]
    if code not in (1, 2, 3, 4):
        return _bad(43, f"read device id code {code} outside 1…4")
    return DeviceIdRequest(code, object_id)


# ---------------------------------------------------------------------- replies


def exception_pdu(function: int, code: int) -> bytes:
    """Exception reply: the function code with its high bit set, then the code."""
    return bytes(((function | 0x80) & 0xFF, int(code)))


def read_bits_pdu(function: int, bits: list[bool]) -> bytes:
    packed = bytearray((len(bits) + 7) // 8)
    for i, on in enumerate(bits):
        if on:
            packed[i // 8] |= 1 << (i % 8)
    return bytes((function, len(packed))) + bytes(packed)


def read_registers_pdu(function: int, registers: list[int]) -> bytes:
    return bytes((function, 2 * len(registers))) + struct.pack(f">{len(registers)}H", *registers)


def write_reply_pdu(req: WriteRequest) -> bytes:
    """FC 5/6 echo the request; FC 15/16 answer address and quantity."""
    if req.function == 5:
        return struct.pack(">BHH", 5, req.address, COIL_ON if req.values[0] else COIL_OFF)
    if req.function == 6:
        return struct.pack(">BHH", 6, req.address, int(req.values[0]))
    return struct.pack(">BHH", req.function, req.address, len(req.values))


def device_id_pdu(code: int, objects: list[tuple[int, bytes]], conformity: int) -> bytes:
    """FC 43/14 reply with every object in one message (no "more follows")."""
    out = bytearray((43, MEI_DEVICE_ID, code, conformity, 0, 0, len(objects)))
    for oid, value in objects:
        out += bytes((oid, len(value))) + value
    return bytes(out)


__all__ = [
    "MAX_ADU",
    "MBAP_SIZE",
    "DeviceIdRequest",
    "Frame",
    "MbapFramer",
    "ReadRequest",
    "Refused",
    "Request",
    "WriteRequest",
    "adu",
    "device_id_pdu",
    "exception_pdu",
    "parse_pdu",
    "read_bits_pdu",
    "read_registers_pdu",
    "write_reply_pdu",
]
