"""The ADS symbol table of the GEO port, derived from the object dictionary (sans-I/O).

Every object gets one symbol per axis of the machine (machine objects one symbol):

    GEO.<axis name>.<GROUP>.<field>     GEO.X.TEMPC.coefficient, GEO.Z.LSEC.sum_epsilon
    GEO.<GROUP>.<field>                 GEO.SIM.cycle_count, GEO.TWIN.ambient_temperature

`<GROUP>` is the dictionary key group in capitals, `<field>` its key field without a
repeated group prefix (`FRICT::additive_current` -> `GEO.X.FRICT.additive_current`). The
symbol's index group and offset are the object's own (`0x120300`, `(axis << 16) | ID`),
its type the TwinCAT name of the dictionary type (`DataType.tc_type`). Names are
case-insensitive, as in TwinCAT. Nothing here is typed twice: add an object to
`objects/objects.toml` and it has a symbol.

Binary layouts (what TwinCAT's symbol server sends and pyads / ads-client parse):

* symbol entry (upload 0xF00B, info by name 0xF009): entryLength u32, iGroup u32,
  iOffs u32, size u32, dataType u32 (`ADST_*`), flags u16, arrayDim u16, nameLength u16,
  typeLength u16, commentLength u16, then name, type and comment each NUL-terminated,
  padded to a multiple of 4 bytes;
* data type entry (upload 0xF00E, info by name 0xF011): entryLength u32, version u32,
  hashValue u32, typeHashValue u32, size u32, offs u32, dataType u32, flags u32,
  nameLength u16, typeLength u16, commentLength u16, arrayDim u16, subItems u16, then the
  three NUL-terminated strings, padded to a multiple of 4;
* upload info (0xF00C): symbol count, symbol bytes; upload info 2 (0xF00F): symbol count,
  symbol bytes, data type count, data type bytes, max. and used dynamic symbols.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from geo_server.dictionary import (
    GEO_AMS_PORT,
    GROUPS,
    DataType,
    Dictionary,
    ObjectDef,
    ascii_text,
)
from geo_server.errors import AdsError, AdsErrorCode

#: Reserved index groups of the symbol and state services (AdsDef.h `ADSIGRP_*`).
SYM_HNDBYNAME = 0xF003  # ReadWrite name -> handle
SYM_VALBYNAME = 0xF004  # ReadWrite name -> value
SYM_VALBYHND = 0xF005  # Read / Write / notification by handle (index offset)
SYM_RELEASEHND = 0xF006  # Write handle
SYM_VERSION = 0xF008  # Read u8, notification
SYM_INFOBYNAMEEX = 0xF009  # ReadWrite name -> symbol entry
SYM_UPLOAD = 0xF00B  # Read every symbol entry
SYM_UPLOADINFO = 0xF00C  # Read 8 bytes
SYM_DT_UPLOAD = 0xF00E  # Read every data type entry
SYM_UPLOADINFO2 = 0xF00F  # Read 24 bytes
SYM_DT_INFOBYNAMEEX = 0xF011  # ReadWrite type name -> data type entry
DEVICE_DATA = 0xF100  # Read / notification: ADS state u16, device state u16
#: Read on the system service (port 10000): its extended state, 16 bytes (TwinCAT 3.1.4022
#: and later; `system_state_extended`)
SYSTEM_STATE_EXTENDED = 0xF0

#: AdsDef.h `ADSSYMBOLFLAG_READONLY`
SYMBOL_FLAG_READONLY = 0x0020
#: `ADSDATATYPEFLAG_DATATYPE`: the entry describes a type
DATATYPE_FLAG_DATATYPE = 0x0001
#: The symbol version a client caches against (TwinCAT counts it up on an online
#: change; the machine's axes never change on a reload, so neither do the symbols).
SYMBOL_VERSION = 1

_SYMBOL_HEAD = struct.Struct("<IIIIIHHHHH")
_DATATYPE_HEAD = struct.Struct("<IIIIIIIIHHHHH")


@dataclass(frozen=True)
class Symbol:
    name: str
    index_group: int
    index_offset: int
    type: DataType
    read_only: bool
    comment: str
    obj: ObjectDef
    axis: int  # 0 for machine objects


def has_symbol(obj: ObjectDef) -> bool:
    """Whether the GEO task's symbol service (port 551) serves `obj`: the COM task's
    objects (port 553, 004 p.19) are addressed by index group and offset only."""
    return obj.ams_port == GEO_AMS_PORT


def symbol_name(obj: ObjectDef, axis_name: str | None) -> str:
    """`GEO.<axis>.<GROUP>.<field>` (axis objects) or `GEO.<GROUP>.<field>`."""
    group = obj.key_group.upper()
    field = obj.key_field
    prefix = obj.key_group + "_"
    if field.startswith(prefix):
        field = field[len(prefix) :]
    return ".".join(p for p in ("GEO", axis_name, group, field) if p)


def _enc(text: str) -> bytes:
    """Symbol strings (names, types, comments) in plain ASCII, which pyads (UTF-8) and
    ads-client (CP1252, as every CNC string, TF5200) decode alike (`ascii_text`)."""
    return ascii_text(text).encode("ascii")


def _strings(*texts: str) -> bytes:
    return b"".join(_enc(t) + b"\0" for t in texts)


def _pad4(data: bytes) -> bytes:
    return data + b"\0" * (-len(data) % 4)


def symbol_entry(sym: Symbol) -> bytes:
    """One TwinCAT symbol entry (module docstring)."""
    name, tc, comment = (_enc(t) for t in (sym.name, sym.type.tc_type, sym.comment))
    tail = _strings(sym.name, sym.type.tc_type, sym.comment)
    flags = SYMBOL_FLAG_READONLY if sym.read_only else 0
    size = _SYMBOL_HEAD.size + len(tail)
    size += -size % 4
    head = _SYMBOL_HEAD.pack(
        size,
        sym.index_group,
        sym.index_offset,
        sym.type.size,
        sym.type.ads_type,
        flags,
        0,  # array dimensions
        len(name),
        len(tc),
        len(comment),
    )
    return _pad4(head + tail)


def datatype_entry(t: DataType) -> bytes:
    """One TwinCAT data type entry of a base type (no array, no sub-items)."""
    name = _enc(t.tc_type)
    tail = _strings(t.tc_type, "", "")
    size = _DATATYPE_HEAD.size + len(tail)
    size += -size % 4
    head = _DATATYPE_HEAD.pack(
        size, 1, 0, 0, t.size, 0, t.ads_type, DATATYPE_FLAG_DATATYPE, len(name), 0, 0, 0, 0
    )
    return _pad4(head + tail)


class SymbolTable:
    """Every symbol of one machine, with the upload blobs built once."""

    def __init__(self, dictionary: Dictionary, axis_names: Mapping[int, str]) -> None:
        """`axis_names`: axis number -> name (`X`), in the machine's order."""
        symbols: list[Symbol] = []
        for obj in dictionary.objects:
            if not has_symbol(obj):
                continue
            targets: Iterable[tuple[int, str | None]] = (
                axis_names.items() if obj.scope == "axis" else [(0, None)]
            )
            for axis, name in targets:
                symbols.append(
                    Symbol(
                        symbol_name(obj, name),
                        GROUPS[obj.group],
                        (axis << 16) | obj.id,
                        obj.type,
                        "w" not in obj.access,
                        _comment(obj),
                        obj,
                        axis,
                    )
                )
        self.symbols = symbols
        self._by_name = {s.name.lower(): s for s in symbols}
        if len(self._by_name) != len(symbols):
            raise ValueError("two objects map to one ADS symbol name")
        self.types = sorted({s.type.tc_type: s.type for s in symbols}.values(), key=_type_key)
        self._types_by_name = {t.tc_type.lower(): t for t in self.types}
        self.upload = b"".join(symbol_entry(s) for s in symbols)
        self.datatype_upload = b"".join(datatype_entry(t) for t in self.types)

    def __len__(self) -> int:
        return len(self.symbols)

    def lookup(self, name: str) -> Symbol:
        """Symbol by name (case-insensitive); unknown -> 0x710."""
        sym = self._by_name.get(name.strip().lower())
        if sym is None:
            raise AdsError(AdsErrorCode.DEVICE_SYMBOLNOTFOUND, f"no symbol {name!r}")
        return sym

    def datatype(self, name: str) -> DataType:
        t = self._types_by_name.get(name.strip().lower())
        if t is None:
            raise AdsError(AdsErrorCode.DEVICE_SYMBOLNOTFOUND, f"no data type {name!r}")
        return t

    def upload_info(self) -> bytes:
        """0xF00C: symbol count, symbol bytes."""
        return struct.pack("<II", len(self.symbols), len(self.upload))

    def upload_info2(self) -> bytes:
        """0xF00F: symbol count and bytes, data type count and bytes, dynamic symbols."""
        return struct.pack(
            "<IIIIII",
            len(self.symbols),
            len(self.upload),
            len(self.types),
            len(self.datatype_upload),
            0,
            0,
        )


def _comment(obj: ObjectDef) -> str:
    unit = obj.unit if obj.unit.startswith("[") else f"[{obj.unit}]"
    return f"{obj.name} {unit}" if obj.unit else obj.name


def handle_answer(handle: int, sym: Symbol, extended: bool) -> bytes:
    """0xF003: the handle (u32); extended (a read length over 4 bytes, ads-client):
    handle, size, type decoration (0) (u32 each), type name length (u16), type name."""
    if not extended:
        return struct.pack("<I", handle)
    tc = _enc(sym.type.tc_type)
    return struct.pack("<IIIH", handle, sym.type.size, 0, len(tc)) + tc + b"\0"


def _type_key(t: DataType) -> str:
    return t.tc_type


def decode_name(data: bytes) -> str:
    """A name sent with ReadWrite: up to the first NUL (clients send it with or without)."""
    raw = bytes(data).split(b"\0", 1)[0]
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def system_state_extended(version: tuple[int, int, int]) -> bytes:
    """The system service's extended state (index group 0xF0, 16 bytes, little-endian):
    ADS state u16 (RUN), device state u16 (0), restart index u16 (0: the emulator's
    system service never restarts), version u8, revision u8, build u16 (as ReadDeviceInfo
    and discovery tell them), platform u8 and OS type u8 (0: not told), flags u16 (0: no
    router-only mode, no redundancy, no data folder), 2 bytes reserved. This is what
    Node's ads-client reads first (`readTcSystemExtendedState`) before ReadState."""
    major, minor, build = version
    run = 5  # ADSSTATE_RUN
    return struct.pack(
        "<HHHBBHBBH2x", run, 0, 0, major & 0xFF, minor & 0xFF, build & 0xFFFF, 0, 0, 0
    )
