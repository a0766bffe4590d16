"""The Modbus register map, generated from the object dictionary — sans-I/O.

Everything here is a pure function of the dictionary and of values: which object sits at
which address, how a value becomes big-endian registers and back, and which Modbus
exception code a request earns. The server (`geo_server.transports.modbus.server`) is a thin shell
around these functions; tests drive them without sockets.

Layout (one map per unit; unit id = logical axis number, unit 0 = the machine-wide
emulator objects of index offset axis 0):

- holding registers (FC 3, 6, 16) and input registers (FC 4): an object with element ID
  `ID` owns the four-register *slot* `4·ID … 4·ID+3` — group `0x120300` at `4·ID`,
  emulator group `0x12F300` at `0x4000 + 4·ID`. Its value fills the first registers of
  the slot, big-endian bytes and words (high word first): BOOLEAN and UNS16 one register,
  SGN32/UNS32 two, REAL64 four. The unused registers of a slot read 0. Text objects
  (`SIM::last_error`) own 128 registers from `0x6000 + 128·ID`; the first 125 carry the
  text, two bytes per register (plain ASCII as the server sends it, CP1252 as a client
  writes it), the first byte in the high half, NUL-padded (249 characters at most; one
  request of 125 registers reads it).
- discrete inputs (FC 2): every BOOLEAN object at address `ID` (emulator group
  `0x4000 + ID`); coils (FC 1, 5, 15): the writable BOOLEAN objects at the same address.

Exceptions: a read must cover only slot registers (bits: only object addresses), else 2;
a write must cover whole objects (all value registers of every object it touches), else
3; writing a read-only object → 2; a value outside its range → 3; a quantity outside the
Modbus limits → 3; an unknown unit id → 11 (decided by the server). Unit 255 (the
MODBUS/TCP guide's identifier for a directly addressed device) is unit 0.
"""

from __future__ import annotations

import csv
import io
import math
import struct
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

from geo_server.dictionary import (
    TYPES,
    Dictionary,
    ObjectDef,
    load_dictionary,
    string_bytes,
    written_string,
)
from geo_server.errors import AdsError, AdsErrorCode, GeoError

#: First address of the emulator group `0x12F300` (registers and bits).
SIM_BASE = 0x4000
#: Registers per object slot.
SLOT = 4
#: Modbus quantity limits (Modbus application protocol v1.1b3, §6).
MAX_READ_REGISTERS = 125
MAX_WRITE_REGISTERS = 123
MAX_READ_BITS = 2000
MAX_WRITE_BITS = 1968
#: Unit id of the machine-wide emulator objects (index offset axis 0).
MACHINE_UNIT = 0
#: The unit id the MODBUS/TCP implementation guide (v1.0b, §4.4.2) recommends for a
#: device addressed directly by its IP address; served as `MACHINE_UNIT`, because clients
#: that treat unit 0 as a broadcast (modbus-cli, the pymodbus console up to 3.7, the
#: Node-RED Modbus node) cannot reach the machine-wide objects otherwise. An axis numbered
#: 255 therefore has no unit of its own.
DIRECT_UNIT = 255

#: First register of the text (STRING) objects: each owns `TEXT_SLOT` registers from
#: `TEXT_BASE + TEXT_SLOT·ID`; its value is the first `TEXT_REGISTERS` of them (the most
#: one FC 3/4 request reads): two bytes per register (first byte high), at most 249
#: characters of the text and a NUL.
TEXT_BASE = 0x6000
TEXT_SLOT = 128
TEXT_REGISTERS = 125
#: Registers per dictionary type: the type's size in 16-bit words (a BOOLEAN takes one
#: register), a STRING the `TEXT_REGISTERS` of its text slot.
REGISTERS: dict[str, int] = {
    name: TEXT_REGISTERS if name == "STRING" else max(1, t.size // 2) for name, t in TYPES.items()
}
#: Big-endian struct format of each numeric type, from its ADS struct code; a BOOLEAN
#: is a 16-bit register holding 0 or 1.
_STRUCT: dict[str, str] = {
    name: ">H" if name == "BOOLEAN" else ">" + t.code for name, t in TYPES.items() if t.code
}
_BASE: dict[str, int] = {"geo": 0, "sim": SIM_BASE}


class ExcCode(IntEnum):
    """Modbus exception codes used by geo-server (same values as pymodbus `ExcCodes`)."""

    ILLEGAL_FUNCTION = 0x01
    ILLEGAL_ADDRESS = 0x02
    ILLEGAL_VALUE = 0x03
    DEVICE_FAILURE = 0x04
    DEVICE_BUSY = 0x06
    GATEWAY_NO_RESPONSE = 0x0B


class Table(IntEnum):
    """The four Modbus tables; the value is the read function code."""

    COILS = 1
    DISCRETE_INPUTS = 2
    HOLDING_REGISTERS = 3
    INPUT_REGISTERS = 4


#: Function code → (table, is a write).
FUNCTIONS: dict[int, tuple[Table, bool]] = {
    1: (Table.COILS, False),
    2: (Table.DISCRETE_INPUTS, False),
    3: (Table.HOLDING_REGISTERS, False),
    4: (Table.INPUT_REGISTERS, False),
    5: (Table.COILS, True),
    6: (Table.HOLDING_REGISTERS, True),
    15: (Table.COILS, True),
    16: (Table.HOLDING_REGISTERS, True),
}


class RegisterError(GeoError):
    """A request earns Modbus exception `code`; `message` says precisely why."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(f"Modbus exception {int(code)}: {message}")
        self.code = ExcCode(code)
        self.message = message


#: Object-service (ADS) error → Modbus exception. "Try again later" conditions — busy,
#: the GEO cycle stalled, a write withdrawn because it was not applied in time — are 6
#: (server device busy); a rejected command (reload with list errors, save refused) and
#: anything unexpected are 4 (server device failure); the reason is in the error list.
EXCEPTIONS: dict[int, ExcCode] = {
    AdsErrorCode.DEVICE_INVALIDGRP: ExcCode.ILLEGAL_ADDRESS,
    AdsErrorCode.DEVICE_INVALIDOFFSET: ExcCode.ILLEGAL_ADDRESS,
    AdsErrorCode.DEVICE_INVALIDACCESS: ExcCode.ILLEGAL_ADDRESS,
    AdsErrorCode.DEVICE_INVALIDSIZE: ExcCode.ILLEGAL_VALUE,
    AdsErrorCode.DEVICE_INVALIDDATA: ExcCode.ILLEGAL_VALUE,
    AdsErrorCode.DEVICE_NOTREADY: ExcCode.DEVICE_BUSY,
    AdsErrorCode.DEVICE_BUSY: ExcCode.DEVICE_BUSY,
    AdsErrorCode.DEVICE_TIMEOUT: ExcCode.DEVICE_BUSY,
    AdsErrorCode.DEVICE_SYNTAX: ExcCode.DEVICE_FAILURE,
    AdsErrorCode.DEVICE_ERROR: ExcCode.DEVICE_FAILURE,
}


def exception_for(exc: AdsError) -> ExcCode:
    """The Modbus exception code for an object-service error (see `EXCEPTIONS`)."""
    return EXCEPTIONS.get(exc.code, ExcCode.DEVICE_FAILURE)


# ---------------------------------------------------------------------- addresses


def mapped(obj: ObjectDef) -> bool:
    """True when the object has a Modbus representation (every object of the GEO task:
    numbers in 4-register slots, texts in `TEXT_SLOT` registers). The COM task's
    objects (port 553, 004 p.19) are ADS and Zenoh only: write-only commands that name
    files, which the read-back `VOLC::*` objects show on Modbus."""
    return obj.type.name in REGISTERS and obj.group != "com"


def slot_size(obj: ObjectDef) -> int:
    """Registers the object owns (its value and the unused rest of its slot)."""
    return TEXT_SLOT if obj.type.name == "STRING" else SLOT


def register_count(obj: ObjectDef) -> int:
    """Registers that carry the object's value (1, 2 or 4)."""
    return REGISTERS[obj.type.name]


def register_address(obj: ObjectDef) -> int:
    """First register of the object's slot: `4·ID` (+ 0x4000 in the emulator group)."""
    if obj.type.name == "STRING":
        return TEXT_BASE + TEXT_SLOT * obj.id
    return _BASE[obj.group] + SLOT * obj.id


def bit_address(obj: ObjectDef) -> int:
    """Coil / discrete-input address of a BOOLEAN object: `ID` (+ 0x4000 emulator group)."""
    return _BASE[obj.group] + obj.id


def is_bit(obj: ObjectDef) -> bool:
    return obj.type.name == "BOOLEAN"


def is_coil(obj: ObjectDef) -> bool:
    return is_bit(obj) and obj.writable


# ---------------------------------------------------------------------- value codec


def _clamp_int(obj: ObjectDef, value: Any) -> int:
    v = int(value)
    return max(int(obj.type.lo), min(int(obj.type.hi), v))


def encode(obj: ObjectDef, value: Any, written: bool = False) -> list[int]:
    """A decoded object value as big-endian registers (high word first).

    Reads never fail: an integer outside its type saturates, a non-finite REAL64 is sent
    as it is (IEEE-754); a text is sent in plain ASCII, cut to fit (`string_bytes`).
    `written`: a client's write, a text in CP1252 and whole (`written_string`, 0x706).
    """
    t = obj.type.name
    if t == "STRING":
        size = 2 * TEXT_REGISTERS
        text = str(value)
        raw = written_string(obj.name, text, size) if written else string_bytes(text, size)
    elif t == "REAL64":
        raw = struct.pack(_STRUCT[t], float(value))
    elif t == "BOOLEAN":
        raw = struct.pack(">H", 1 if value else 0)
    else:
        raw = struct.pack(_STRUCT[t], _clamp_int(obj, value))
    return [int.from_bytes(raw[i : i + 2], "big") for i in range(0, len(raw), 2)]


def decode(obj: ObjectDef, registers: Sequence[int], check: bool = True) -> Any:
    """Big-endian registers → the object's Python value, checked against its range.

    Raises `RegisterError` 3 (illegal data value) for a wrong register count, a BOOLEAN
    other than 0/1, a non-finite REAL64 or a value outside the documented range.
    `check=False` (a client decoding what the server sent) skips the value checks.
    """
    n = register_count(obj)
    if len(registers) != n:
        raise RegisterError(
            ExcCode.ILLEGAL_VALUE, f"{obj.name} takes {n} registers, got {len(registers)}"
        )
    if any(not 0 <= r <= 0xFFFF for r in registers):
        raise RegisterError(ExcCode.ILLEGAL_VALUE, f"{obj.name}: register out of 0…0xFFFF")
    raw = b"".join(int(r).to_bytes(2, "big") for r in registers)
    t = obj.type.name
    if t == "STRING":
        return raw.split(b"\0", 1)[0].decode("cp1252", errors="replace")
    (v,) = struct.unpack(_STRUCT[t], raw)
    if not check:
        return bool(v) if t == "BOOLEAN" else v
    if t == "BOOLEAN" and v > 1:
        raise RegisterError(ExcCode.ILLEGAL_VALUE, f"{obj.name}: BOOLEAN must be 0 or 1, got {v}")
    if t == "REAL64" and not math.isfinite(v):
        raise RegisterError(ExcCode.ILLEGAL_VALUE, f"{obj.name}: {v} is not finite")
    try:
        return obj.coerce(bool(v) if t == "BOOLEAN" else v)
    except AdsError as exc:
        raise RegisterError(exception_for(exc), exc.message) from None


# ---------------------------------------------------------------------- the map


@dataclass(frozen=True)
class UnitMap:
    """The register and bit layout of one kind of unit (axis or machine)."""

    scope: str
    objects: tuple[ObjectDef, ...]
    #: register address → (object, word index in the slot: 0…3; ≥ count = unused)
    registers: dict[int, tuple[ObjectDef, int]] = field(repr=False)
    #: discrete-input address → BOOLEAN object
    discrete: dict[int, ObjectDef] = field(repr=False)
    #: coil address → writable BOOLEAN object
    coils: dict[int, ObjectDef] = field(repr=False)

    @classmethod
    def build(cls, objects: Iterable[ObjectDef], scope: str) -> UnitMap:
        objs = tuple(
            sorted((o for o in objects if o.scope == scope and mapped(o)), key=register_address)
        )
        regs: dict[int, tuple[ObjectDef, int]] = {}
        discrete: dict[int, ObjectDef] = {}
        coils: dict[int, ObjectDef] = {}
        for o in objs:
            base = register_address(o)
            for word in range(slot_size(o)):
                if base + word in regs:
                    raise ValueError(f"Modbus map: {o.name} overlaps {regs[base + word][0].name}")
                regs[base + word] = (o, word)
            if is_bit(o):
                discrete[bit_address(o)] = o
                if is_coil(o):
                    coils[bit_address(o)] = o
        return cls(scope, objs, regs, discrete, coils)

    def bits(self, table: Table) -> dict[int, ObjectDef]:
        return self.coils if table == Table.COILS else self.discrete

    # ------------------------------------------------------------------ checks

    def check_read(self, function_code: int, address: int, count: int) -> Table:
        """Check a read request; returns its table or raises `RegisterError`."""
        table, is_write = _function(function_code)
        if is_write:
            raise RegisterError(ExcCode.ILLEGAL_FUNCTION, f"FC {function_code} is not a read")
        limit = MAX_READ_BITS if table <= Table.DISCRETE_INPUTS else MAX_READ_REGISTERS
        if not 1 <= count <= limit:
            raise RegisterError(ExcCode.ILLEGAL_VALUE, f"quantity {count} outside 1…{limit}")
        if address + count > 0x10000:
            raise RegisterError(ExcCode.ILLEGAL_ADDRESS, "request runs past address 0xFFFF")
        where = self.bits(table) if table <= Table.DISCRETE_INPUTS else self.registers
        for a in range(address, address + count):
            if a not in where:
                raise RegisterError(
                    ExcCode.ILLEGAL_ADDRESS,
                    f"no {table.name.lower().replace('_', ' ')} object at address {a}"
                    f" (0x{a:04X}) on a {self.scope} unit",
                )
        return table

    def check_write(self, function_code: int, address: int, count: int) -> list[ObjectDef]:
        """Check the addresses of a write; returns the objects it writes, in order.

        Every address must belong to an object (else 2); every object touched must be
        writable (else 2) and wholly covered (else 3). Values are checked by `decode_write`.
        """
        table, is_write = _function(function_code)
        if not is_write:
            raise RegisterError(ExcCode.ILLEGAL_FUNCTION, f"FC {function_code} is not a write")
        limit = MAX_WRITE_BITS if table == Table.COILS else MAX_WRITE_REGISTERS
        if not 1 <= count <= limit:
            raise RegisterError(ExcCode.ILLEGAL_VALUE, f"quantity {count} outside 1…{limit}")
        if address + count > 0x10000:
            raise RegisterError(ExcCode.ILLEGAL_ADDRESS, "request runs past address 0xFFFF")
        if table == Table.COILS:
            objs = []
            for a in range(address, address + count):
                obj = self.discrete.get(a)
                if obj is None:
                    raise RegisterError(ExcCode.ILLEGAL_ADDRESS, f"no coil at address {a}")
                if not obj.writable:
                    raise RegisterError(ExcCode.ILLEGAL_ADDRESS, f"{obj.name} is read-only")
                objs.append(obj)
            return objs
        touched: dict[str, tuple[ObjectDef, set[int]]] = {}
        for a in range(address, address + count):
            hit = self.registers.get(a)
            if hit is None:
                raise RegisterError(ExcCode.ILLEGAL_ADDRESS, f"no object at register {a}")
            obj, word = hit
            if not obj.writable:
                raise RegisterError(ExcCode.ILLEGAL_ADDRESS, f"{obj.name} is read-only")
            touched.setdefault(obj.name, (obj, set()))[1].add(word)
        for obj, words in touched.values():
            if not set(range(register_count(obj))) <= words:
                raise RegisterError(
                    ExcCode.ILLEGAL_VALUE,
                    f"{obj.name} is {register_count(obj)} registers at "
                    f"{register_address(obj)}; a write must cover all of them",
                )
        return [obj for obj, _ in touched.values()]

    # ------------------------------------------------------------------ data

    def read_registers(
        self, address: int, count: int, value_of: Callable[[ObjectDef], Any]
    ) -> list[int]:
        """Registers `address … address+count-1` (already checked); unused words read 0."""
        out: list[int] = []
        cache: dict[str, list[int]] = {}
        for a in range(address, address + count):
            obj, word = self.registers[a]
            regs = cache.get(obj.name)
            if regs is None:
                regs = cache[obj.name] = encode(obj, value_of(obj))
            out.append(regs[word] if word < len(regs) else 0)
        return out

    def read_bits(
        self, table: Table, address: int, count: int, value_of: Callable[[ObjectDef], Any]
    ) -> list[bool]:
        """Bits `address … address+count-1` of a bit table (already checked)."""
        where = self.bits(table)
        return [bool(value_of(where[a])) for a in range(address, address + count)]

    def decode_write(
        self, function_code: int, address: int, values: Sequence[int] | Sequence[bool]
    ) -> list[tuple[ObjectDef, Any]]:
        """Check a write and decode its values: `[(object, value), …]` in address order."""
        objs = self.check_write(function_code, address, len(values))
        table, _ = _function(function_code)
        if table == Table.COILS:
            return [(o, bool(v)) for o, v in zip(objs, values, strict=True)]
        out = []
        for obj in objs:
            first = register_address(obj) - address
            words = [int(v) for v in values[first : first + register_count(obj)]]
            out.append((obj, decode(obj, words)))
        return out


def _function(function_code: int) -> tuple[Table, bool]:
    try:
        return FUNCTIONS[function_code]
    except KeyError:
        raise RegisterError(
            ExcCode.ILLEGAL_FUNCTION, f"function code {function_code} is not supported"
        ) from None


@dataclass(frozen=True)
class ModbusMap:
    """The maps of axis units and of the machine unit (unit 0)."""

    axis: UnitMap
    machine: UnitMap

    @classmethod
    def build(cls, dictionary: Dictionary | None = None) -> ModbusMap:
        d = dictionary or load_dictionary()
        return cls(UnitMap.build(d.objects, "axis"), UnitMap.build(d.objects, "machine"))

    def for_unit(self, unit: int, axes: Iterable[int]) -> UnitMap | None:
        """The map served on `unit`, or None when the unit id is unknown (→ exception 11)."""
        if unit in (MACHINE_UNIT, DIRECT_UNIT):
            return self.machine
        return self.axis if unit in set(axes) else None


# ---------------------------------------------------------------------- documentation

MAP_COLUMNS = ("unit", "table", "address", "object", "group", "id", "type", "registers", "access")
#: The CSV's columns: the map's, then the first address and the number of registers (or
#: bits) of the value as plain numbers, for tools that read the file.
CSV_COLUMNS = (*MAP_COLUMNS, "start", "count")

_TABLE_NAMES = {
    Table.COILS: "coil",
    Table.DISCRETE_INPUTS: "discrete input",
    Table.HOLDING_REGISTERS: "holding+input register",
}


def map_rows(dictionary: Dictionary | None = None) -> list[dict[str, str]]:
    """Every entry of the map: one row per object and table (holding and input registers
    share a row; FC 4 reads the same values as FC 3)."""
    mm = ModbusMap.build(dictionary)
    rows: list[dict[str, str]] = []
    for um, unit in ((mm.axis, "axis number"), (mm.machine, "0 (machine)")):
        for o in um.objects:
            base = register_address(o)
            n = register_count(o)
            unused = slot_size(o) - n
            access = {"r": "read", "rw": "read/write", "w": "write"}[o.access]
            common = {
                "unit": unit,
                "object": o.name,
                "group": f"0x{o.index_group:06X}",
                "id": f"0x{o.id:04X}",
                "type": o.type.name,
            }
            rows.append(
                {
                    **common,
                    "table": _TABLE_NAMES[Table.HOLDING_REGISTERS],
                    "address": f"{base}…{base + slot_size(o) - 1} (0x{base:04X})",
                    "registers": f"{n} (+{unused} unused)" if unused else str(n),
                    "start": str(base),
                    "count": str(n),
                    "access": access
                    + {"r": " (FC 3/4)", "rw": " (FC 3/4, 6/16)", "w": " (FC 6/16; reads 0)"}[
                        o.access
                    ],
                }
            )
            if is_bit(o):
                b = bit_address(o)
                rows.append(
                    {
                        **common,
                        "table": _TABLE_NAMES[Table.DISCRETE_INPUTS],
                        "address": f"{b} (0x{b:04X})",
                        "registers": "1 bit",
                        "access": "read (FC 2)",
                        "start": str(b),
                        "count": "1",
                    }
                )
                if is_coil(o):
                    rows.append(
                        {
                            **common,
                            "table": _TABLE_NAMES[Table.COILS],
                            "address": f"{b} (0x{b:04X})",
                            "registers": "1 bit",
                            "access": "read/write (FC 1, 5/15)",
                            "start": str(b),
                            "count": "1",
                        }
                    )
    return rows


def modbus_map(format: str = "md", dictionary: Dictionary | None = None) -> str:
    """The complete Modbus map from the dictionary, as Markdown (`md`) or CSV (`csv`)."""
    rows = map_rows(dictionary)
    if format == "csv":
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
        return buf.getvalue()
    if format != "md":
        raise ValueError(f"unknown format {format!r} (md or csv)")
    lines = ["| " + " | ".join(MAP_COLUMNS) + " |", "|" + "---|" * len(MAP_COLUMNS)]
    for r in rows:
        lines.append("| " + " | ".join(r[c].replace("|", "\\|") for c in MAP_COLUMNS) + " |")
    return "\n".join(lines) + "\n"


__all__ = [
    "DIRECT_UNIT",
    "MACHINE_UNIT",
    "SIM_BASE",
    "SLOT",
    "TEXT_BASE",
    "TEXT_REGISTERS",
    "TEXT_SLOT",
    "ExcCode",
    "ModbusMap",
    "RegisterError",
    "Table",
    "UnitMap",
    "bit_address",
    "decode",
    "encode",
    "exception_for",
    "map_rows",
    "modbus_map",
    "register_address",
    "register_count",
]
