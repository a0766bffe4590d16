"""The object dictionary: every CNC object geo-server serves, loaded from `objects/`.

One source of truth (docs/design.md §2): the TOML file in `objects/` names every object with its
element ID, type, access, unit and manual source. This module loads it, resolves names,
aliases and `(index group, index offset)` pairs, encodes and decodes values in the ADS
little-endian encoding and checks write ranges. Failures are `AdsError`s carrying the
ADS return code of docs/design.md §9, so every transport maps them the same way.

Addressing (docs/design.md §2): index group `0x120300` (GEO) or `0x12F300` (emulator), index
offset `(axis << 16) | id`; machine-wide emulator objects use axis 0. Attribute groups
sit at group + 0x100 (name), 0x200 (type name), 0x300 (length), 0x400 (unit),
0x500 (writable) with the same offsets.
"""

from __future__ import annotations

import difflib
import json
import math
import struct
import sys
import tomllib
import unicodedata
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import cache
from typing import Any

from geo_server.errors import AdsError, AdsErrorCode
from geo_server.paths import data_dir

#: The AMS port of the GEO task: the GEO and emulator objects are served there
#: (docs/design.md §2).
GEO_AMS_PORT = 551
#: The AMS port of the COM task: the volumetric compensation's CNC objects (004 p.19).
COM_AMS_PORT = 553
#: Index groups of the object groups (docs/design.md §2; 004 p.19 for "com").
GROUPS: dict[str, int] = {"geo": 0x120300, "sim": 0x12F300, "com": 0x120100}
#: The AMS port that serves each group.
GROUP_PORTS: dict[str, int] = {"geo": GEO_AMS_PORT, "sim": GEO_AMS_PORT, "com": COM_AMS_PORT}
#: The groups of the GEO task, which have attribute groups (+0x100 … +0x500) and the
#: address lookup (+0x600). The COM group has neither: 0x120100 + 0x200 is the GEO group.
TASK_GROUPS: dict[str, int] = {g: GROUPS[g] for g in ("geo", "sim")}
#: The AMS ports objects are served on.
AMS_PORTS: tuple[int, ...] = (GEO_AMS_PORT, COM_AMS_PORT)
#: Attribute group offsets relative to an object group (docs/design.md §2).
ATTRIBUTES: dict[int, str] = {
    0x100: "name",
    0x200: "type",
    0x300: "length",
    0x400: "unit",
    0x500: "writable",
}
#: Attribute group of the object address lookup (TF5200 "ADS access to CNC", classes:
#: "0x600: object address: in (channel, axis), out (IndexGroup, IndexOffset)"); ReadWrite.
ADDRESS_LOOKUP = 0x600
STRING_LENGTH = 256

#: ASCII for the characters the emulator's own texts use (units, messages): a STRING on
#: the wire is plain ASCII, which pyads (UTF-8 by default) and ads-client and TwinCAT
#: (Windows-1252) decode alike (issue 45 #10; Zenoh's JSON, OPC UA and the error lists
#: keep the full text).
_ASCII = str.maketrans(
    {
        "µ": "u",
        "…": "...",
        "°": "deg",
        "²": "^2",
        "³": "^3",
        "·": "*",
        "×": "x",
        "±": "+/-",
        "−": "-",
        "–": "-",
        "—": "-",
        "→": "->",
        "←": "<-",
        "≤": "<=",
        "≥": ">=",
        "≠": "!=",
        "‘": "'",
        "’": "'",
        "“": '"',
        "”": '"',
        "ä": "ae",
        "ö": "oe",
        "ü": "ue",
        "Ä": "Ae",
        "Ö": "Oe",
        "Ü": "Ue",
        "ß": "ss",
        "\u00a0": " ",
    }
)


def ascii_text(text: str) -> str:
    """`text` in plain ASCII: the emulator's characters spelled out (`µm` → `um`, `…` →
    `...`), accents dropped (`é` → `e`), anything else `?`."""
    spelled = unicodedata.normalize("NFKD", text.translate(_ASCII))
    bare = "".join(c for c in spelled if not unicodedata.combining(c))
    return bare.encode("ascii", errors="replace").decode("ascii")


def string_bytes(text: str, size: int = STRING_LENGTH) -> bytes:
    """`text` as a STRING of `size` bytes the server sends: ASCII (`ascii_text`),
    NUL-ended and padded. A longer text is cut and ends in `...`: after its last whole
    word when one ends in the second half of the room (issue 45 #18: before, always
    mid-word), else at the room's end (a long path or a run without blanks)."""
    if size <= 0:
        return b""
    s = ascii_text(text)
    limit = size - 1
    if len(s) > limit:
        room = limit - 3
        if room <= 0:
            s = s[:limit]
        else:
            cut = s.rfind(" ", 0, room + 1)
            s = s[: cut if cut > room // 2 else room].rstrip() + "..."
    return s.encode("ascii").ljust(size, b"\0")


def written_string(name: str, text: str, size: int = STRING_LENGTH) -> bytes:
    """`text` as a STRING of `size` bytes a client writes: CP1252, as TwinCAT's strings
    (a file name keeps its `ü`), NUL-padded; 0x706 for a character CP1252 lacks or a
    text longer than `size` − 1 bytes (never cut: a path cut short names another file)."""
    try:
        raw = text.encode("cp1252")
    except UnicodeEncodeError as exc:
        raise AdsError(
            AdsErrorCode.DEVICE_INVALIDDATA,
            f"{name}: {text[exc.start : exc.end]!r} is not a CP1252 character",
            name,
        ) from None
    if len(raw) > size - 1:
        raise AdsError(
            AdsErrorCode.DEVICE_INVALIDDATA,
            f"{name}: a text of {len(raw)} bytes is longer than {size - 1}",
            name,
        )
    return raw.ljust(size, b"\0")


#: The highest logical axis number (docs/design.md §2.1: the index offset's high word).
MAX_AXIS = 0xFFFF
#: Most characters a JSON integer may have. More than any object type can hold (a REAL64
#: ends near 1.8e308, 309 digits), so a longer one is refused (0x706) before Python
#: converts it: that conversion is quadratic in the length and fails over 4300 digits.
MAX_JSON_INT_CHARS = 330


@dataclass(frozen=True)
class DataType:
    """An ADS data type: wire size, struct code (little-endian) and value range."""

    name: str
    size: int
    code: str  # struct format character, "" for STRING
    lo: float
    hi: float
    #: the IEC 61131-3 / TwinCAT type name of the ADS symbol (docs/design.md §9)
    tc_type: str = ""
    #: the ADS data type id of the symbol (AdsDef.h `ADST_*`)
    ads_type: int = 0


TYPES: dict[str, DataType] = {
    t.name: t
    for t in (
        DataType("BOOLEAN", 1, "B", 0, 1, "BOOL", 33),
        DataType("UNS16", 2, "H", 0, 0xFFFF, "UINT", 18),
        DataType("UNS32", 4, "I", 0, 0xFFFF_FFFF, "UDINT", 19),
        DataType("SGN32", 4, "i", -(2**31), 2**31 - 1, "DINT", 3),
        DataType("REAL64", 8, "d", -math.inf, math.inf, "LREAL", 5),
        DataType("STRING", STRING_LENGTH, "", 0, 0, f"STRING({STRING_LENGTH - 1})", 30),
    )
}


def round_half_away(x: float) -> int:
    """Round half away from zero (docs/design.md §3: SGN32 objects from the internal float64)."""
    return int(math.copysign(math.floor(abs(x) + 0.5), x))


def _show(value: Any, limit: int = 40) -> str:
    """A value for an error message, never longer than about `limit` characters.

    Integers beyond 128 bits are shown by their size: Python refuses to turn an integer
    of more than 4300 digits into text at all (the message itself would fail).
    """
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 128:
        return f"<an integer of about {int(value.bit_length() * math.log10(2)) + 1} digits>"
    # (a long string is cut before `repr`, which would copy all of it)
    text = repr(value[: limit + 1] if isinstance(value, str) else value)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _json_kind(value: Any) -> str:
    """The JSON type name of a decoded value (for error messages)."""
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, int | float):
        return "number"
    if isinstance(value, str):
        return "string"
    if isinstance(value, dict):
        return "object"
    if isinstance(value, list | tuple):
        return "array"
    return "null" if value is None else type(value).__name__


def _bounded_int(text: str) -> int:
    """`parse_int` of `loads_json`: refuse an integer too long for any object first."""
    if len(text) > MAX_JSON_INT_CHARS:
        raise AdsError(
            AdsErrorCode.DEVICE_INVALIDDATA,
            f"a JSON integer of {len(text)} characters is out of range for every object type",
        )
    return int(text)


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not JSON")


def loads_json(data: bytes | str, label: str, name: str = "", *, constants: bool = True) -> Any:
    """JSON that came over the network, decoded strictly (every interface that takes JSON:
    Zenoh's payloads, the web HMI's bodies); anything malformed is `AdsError` 0x706
    (invalid data) saying what (`label`: "TEMPC::coefficient: payload", "the body").

    Integers longer than `MAX_JSON_INT_CHARS` are refused before Python converts them;
    deep nesting ("[[[[…]]]]") is bad data like any other, not an internal error (the
    decoder's RecursionError); without `constants`, NaN and ±Infinity are refused too.
    The value itself is checked against its object by `ObjectDef.coerce_json`.
    """
    extra: dict[str, Any] = {} if constants else {"parse_constant": _no_constant}
    try:
        return json.loads(data, parse_int=_bounded_int, **extra)
    # ValueError: Python's own limit on long numbers, should one get past `_bounded_int`
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError, ValueError) as exc:
        raise AdsError(
            AdsErrorCode.DEVICE_INVALIDDATA, f"{label} is not JSON ({exc})", name
        ) from None
    except AdsError as exc:
        raise AdsError(exc.code, f"{label}: {exc.message}", name) from None


def _key_part(text: str) -> str:
    """Zenoh key part of docs/design.md §7: lower case, blanks and dots to `_`, no doubled `_`."""
    out = text.strip().lower().replace(" ", "_").replace(".", "_")
    while "__" in out:
        out = out.replace("__", "_")
    return out.strip("_")


@dataclass(frozen=True)
class ObjectDef:
    """One CNC object of the dictionary."""

    name: str
    group: str  # "geo" | "sim"
    id: int
    type: DataType
    access: str  # "r" | "rw" | "w"
    unit: str
    scope: str  # "axis" | "machine"
    description: str
    source: str
    aliases: tuple[str, ...] = ()
    min: float | None = None
    max: float | None = None
    #: "reload" / "save": writing this object runs that command (list files are read or
    #: written) instead of queueing a value for the next cycle.
    command: str | None = None
    #: The axis-parameter-list entry (`lr_param.temp_comp_coefficient`) this object's
    #: live value is saved to; its last segment is the `AxisParams` attribute.
    list_key: str | None = None
    #: "position" | "offset" | "velocity": how clients show the raw value in engineering
    #: units (see `geo_server.units`); None: shown as it is.
    quantity: str | None = None
    #: Whether the value can change while the machine rests (the counters, the twin's
    #: clock and temperatures); every other object keeps the value of the cycle the
    #: machine came to rest in (`Machine.skip`, docs/design.md §13): an on-change
    #: observer of it needs no snapshot of a quiescent stretch, and a read at rest no
    #: catch-up.
    varies_at_rest: bool = False

    @property
    def index_group(self) -> int:
        return GROUPS[self.group]

    @property
    def length(self) -> int:
        return self.type.size

    @property
    def readable(self) -> bool:
        return "r" in self.access

    @property
    def writable(self) -> bool:
        return "w" in self.access

    def index_offset(self, axis: int) -> int:
        """`(axis << 16) | id` (docs/design.md §2); axis 0 for machine-wide objects."""
        return (axis << 16) | self.id

    @property
    def ams_port(self) -> int:
        """The AMS port its task is served on (551 GEO, 553 COM)."""
        return GROUP_PORTS[self.group]

    @property
    def key_group(self) -> str:
        """Zenoh `<group>` (docs/design.md §7): `bc`, `tempc`, …; `ssfk activated` is `lsec`."""
        if self.group == "com":
            return "com"
        if "::" not in self.name:
            return "lsec"
        return _key_part(self.name.split("::", 1)[0])

    @property
    def key_field(self) -> str:
        """Zenoh `<field>` (docs/design.md §7): `actual_backlash`, `sum_epsilon`, …"""
        rest = self.name.split("::", 1)[1] if "::" in self.name else self.name
        if self.group == "sim" and self.key_group != "sim":
            return _key_part(f"{self.key_group}_{rest}")
        return _key_part(rest)

    # ------------------------------------------------------------------ value codec

    def encode(self, value: Any) -> bytes:
        """Encode a Python value as ADS bytes (little-endian) to write it; checks type
        and range (a STRING in CP1252, whole: `written_string`)."""
        v = self.coerce(value)
        if self.type.name == "STRING":
            return written_string(self.name, str(v))
        return struct.pack("<" + self.type.code, v)

    def encode_reply(self, value: Any) -> bytes:
        """The ADS bytes the server sends for a value: as `encode`, but a STRING in plain
        ASCII, cut to fit (`string_bytes`: what pyads and ads-client both decode)."""
        if self.type.name == "STRING":
            return string_bytes(str(value))
        return self.encode(value)

    def decode(self, data: bytes) -> Any:
        """Decode ADS bytes; wrong length -> 0x705, invalid BOOLEAN/NaN -> 0x706. A
        STRING may be written shorter than its 256 bytes (a client writes the text and
        its terminating NUL, as pyads does), never longer."""
        short_string = self.type.name == "STRING" and 0 < len(data) <= self.length
        if len(data) != self.length and not short_string:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDSIZE,
                f"{self.name} is {self.type.name} of {self.length} bytes, got {len(data)}",
                self.name,
            )
        if self.type.name == "STRING":
            return data.split(b"\0", 1)[0].decode("cp1252", errors="replace")
        (v,) = struct.unpack("<" + self.type.code, data)
        if self.type.name == "BOOLEAN":
            if v > 1:
                raise AdsError(
                    AdsErrorCode.DEVICE_INVALIDDATA, f"{self.name}: BOOLEAN must be 0 or 1, got {v}"
                )
            return bool(v)
        self.check_range(v)
        return v

    def coerce(self, value: Any) -> Any:
        """Turn a decoded/JSON value into this type's Python value, checking the range."""
        t = self.type.name
        try:
            if t == "BOOLEAN":
                if isinstance(value, str):
                    low = value.strip().lower()
                    if low not in ("0", "1", "true", "false"):
                        raise ValueError(value)
                    return low in ("1", "true")
                if value not in (0, 1, True, False):
                    raise ValueError(value)
                return bool(value)
            if t == "STRING":
                return str(value)
            if t == "REAL64":
                v = float(value)
            else:
                if isinstance(value, float) and not value.is_integer():
                    raise ValueError(value)
                v = int(value)
        except (TypeError, ValueError) as exc:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDDATA,
                f"{self.name}: {_show(value)} is not a valid {t}",
                self.name,
            ) from exc
        self.check_range(v)
        return v

    def coerce_json(self, value: Any) -> Any:
        """Strict `coerce` for a value decoded from JSON (the Zenoh interface's writes).

        JSON carries its own types, so the value must already be of the object's kind:
        BOOLEAN takes `true`/`false` or the numbers 0 and 1; UNS16/UNS32/SGN32 take an
        integer (or a number without fraction such as `5.0`, which some JSON writers emit
        for integers); REAL64 takes any number; STRING takes a string. A string, a
        boolean or a number of the wrong kind is refused with 0x706 (invalid data), not
        converted: a writer that sends `"12"` or `true` into a coefficient has a bug that
        a silent conversion would hide. (`coerce` stays lenient for text typed by people,
        e.g. on a command line.)

        The range is checked before any conversion: Python compares integers of any size
        with the limits exactly, while turning a huge one into a float (or into text, over
        4300 digits) fails. So a 5000-digit integer is refused with 0x706 like any other
        value out of range.
        """
        t = self.type.name
        if t == "BOOLEAN":
            if isinstance(value, bool):
                return value
            if isinstance(value, int | float) and value in (0, 1):
                return bool(value)
            raise self._wrong_json(value, "true, false, 0 or 1")
        if t == "STRING":
            if isinstance(value, str):
                return value
            raise self._wrong_json(value, "a string")
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self._wrong_json(value, "a number" if t == "REAL64" else "an integer")
        if t != "REAL64" and isinstance(value, float) and not value.is_integer():
            raise self._wrong_json(value, "an integer")
        self.check_range(value)
        if t == "REAL64":
            if isinstance(value, int) and abs(value) > sys.float_info.max:
                raise AdsError(
                    AdsErrorCode.DEVICE_INVALIDDATA,
                    f"{self.name}: {_show(value)} is outside the REAL64 range",
                    self.name,
                )
            return float(value)
        return int(value)

    def _wrong_json(self, value: Any, expected: str) -> AdsError:
        got = "null" if value is None else f"{_json_kind(value)} {_show(value)}"
        return AdsError(
            AdsErrorCode.DEVICE_INVALIDDATA,
            f"{self.name} is {self.type.name}: needs {expected}, got {got}",
            self.name,
        )

    def check_range(self, v: float) -> None:
        """Raise 0x706 when `v` is outside the type or the documented range."""
        lo = self.type.lo if self.min is None else self.min
        hi = self.type.hi if self.max is None else self.max
        if isinstance(v, float) and not math.isfinite(v):
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDDATA, f"{self.name}: {v} is not finite", self.name
            )
        if not lo <= v <= hi:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDDATA,
                f"{self.name}: {_show(v)} outside the range {lo:g} … {hi:g} {self.unit}",
                self.name,
            )

    def attribute(self, kind: str) -> bytes:
        """Value of an attribute group (docs/design.md §2) as ADS bytes."""
        if kind == "length":
            return struct.pack("<I", self.length)
        if kind == "writable":
            return struct.pack("<B", int(self.writable))
        text = {"name": self.name, "type": self.type.name, "unit": self.unit}[kind]
        return string_bytes(text)

    def decode_attribute(self, kind: str, data: bytes) -> Any:
        """Decode the bytes of an attribute group read (inverse of `attribute`)."""
        if kind == "length":
            return struct.unpack_from("<I", data)[0]
        if kind == "writable":
            return bool(data[0])
        return data.split(b"\0", 1)[0].decode("cp1252")

    @property
    def param_attr(self) -> str | None:
        """The `AxisParams` attribute behind `list_key` (`temp_comp_coefficient`): the
        axis list reader stores entry `lr_param.<name>` in attribute `<name>`
        (tests/test_dictionary.py checks this against the reader's table)."""
        return self.list_key.split(".", 1)[1] if self.list_key else None

    def as_row(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "index_group": f"0x{self.index_group:06X}",
            "id": f"0x{self.id:04X}",
            "scope": self.scope,
            "type": self.type.name,
            "length": self.length,
            "access": {"r": "read", "rw": "read/write", "w": "write"}[self.access],
            "unit": self.unit,
            "min": self.min,
            "max": self.max,
            "aliases": list(self.aliases),
            "description": self.description,
            "source": self.source,
        }


def _normalize_name(name: str) -> str:
    """Case-insensitive name key; `TEMPC:: activated` (000's spelling) == `TEMPC::activated`."""
    return " ".join(name.replace(":: ", "::").split()).lower()


@dataclass
class Dictionary:
    """All objects, indexed by name/alias and by `(group, id, scope)`."""

    objects: list[ObjectDef]
    _by_name: dict[str, ObjectDef] = field(default_factory=dict, repr=False)
    _keys: dict[str, ObjectDef] | None = field(default=None, repr=False)
    _by_id: dict[tuple[str, int, str], ObjectDef] = field(default_factory=dict, repr=False)
    #: the longest object name `by_name` considers (set from the objects' names)
    max_name_chars: int = field(default=0, init=False)

    def __post_init__(self) -> None:
        for obj in self.objects:
            for n in (obj.name, *obj.aliases):
                key = _normalize_name(n)
                if key in self._by_name:
                    raise ValueError(f"object dictionary: duplicate name {n!r}")
                self._by_name[key] = obj
            k = (obj.group, obj.id, obj.scope)
            if k in self._by_id:
                raise ValueError(f"object dictionary: duplicate id {k}")
            self._by_id[k] = obj
        # The longest spelling any name may have (docs/design.md §2.2): name, alias or Zenoh
        # key spelling, with 000's blank after `::`, followed by the longest axis suffix
        # a caller may leave on it (`NAME@65535`, `NAME[65535]`). A longer name cannot
        # be any object's: `by_name` refuses it before normalising or matching it, so
        # the cost of an unknown name is bounded whatever its length.
        spellings = [*self._by_name, *self._by_key()]
        longest = max(len(s.replace("::", ":: ")) for s in spellings)
        self.max_name_chars = longest + max(len(f"@{MAX_AXIS}"), len(f"[{MAX_AXIS}]"))

    def by_name(self, name: str) -> ObjectDef:
        """Resolve a name or alias (case-insensitive), also in the spelling of the Zenoh
        keys (`BC::actual_backlash`, `lsec::sum_epsilon`); unknown -> AdsError 0x703
        naming the nearest known names. A name longer than `max_name_chars` is refused
        (0x703) before any matching: the nearest-name search costs time in proportion to
        its length (a 1 MB name: ~170 ms of the event loop every interface shares)."""
        if len(name) > self.max_name_chars:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDOFFSET,
                f"unknown object name {_show(name)}: {len(name)} characters, longer than "
                f"any object's name (at most {self.max_name_chars})",
                _show(name),
            )
        key = _normalize_name(name)
        obj = self._by_name.get(key) or self._by_key().get(key.replace("/", "::"))
        if obj is not None:
            return obj
        near = difflib.get_close_matches(key, self._by_name, n=3, cutoff=0.6)
        hint = "; did you mean " + " or ".join(repr(self._by_name[n].name) for n in near)
        raise AdsError(
            AdsErrorCode.DEVICE_INVALIDOFFSET,
            f"unknown object name {name!r}" + (hint + "?" if near else ""),
            name,
        )

    def _by_key(self) -> dict[str, ObjectDef]:
        """Objects by `<group>::<field>` of their Zenoh key (`bc::actual_backlash`)."""
        if self._keys is None:
            self._keys = {f"{o.key_group}::{o.key_field}": o for o in self.objects}
        return self._keys

    def group_objects(self, group: str, scope: str = "axis") -> list[ObjectDef]:
        return [o for o in self.objects if o.group == group and o.scope == scope]

    def saved_parameters(self) -> list[ObjectDef]:
        """Writable objects whose live value `save` writes back into the axis list
        (those with a `list_key`), in element-ID order."""
        return sorted((o for o in self.objects if o.list_key), key=lambda o: o.id)

    def tempc_parameters(self) -> list[ObjectDef]:
        """The numeric TEMPC parameters a PLC retunes live (coefficient, offset_0,
        position_0; 000 §3.2.3), in element-ID order."""
        return [
            o
            for o in self.saved_parameters()
            if o.key_group == "tempc" and o.type.name != "BOOLEAN"
        ]

    def lookup_address(
        self, index_group: int, element: int, channel: int, axis: int, axes: Iterable[int]
    ) -> tuple[int, int]:
        """The address lookup (group + 0x600): the (index group, index offset) of element
        `element` for (`channel`, `axis`), or (0, 0) when there is no such instance. The
        GEO objects are platform-global (channel 0): another channel has no instance;
        machine objects answer for axis 0, axis objects for a configured axis. Unknown
        group -> 0x702, unknown element -> 0x703."""
        group = next(
            (g for g, ig in TASK_GROUPS.items() if ig + ADDRESS_LOOKUP == index_group), None
        )
        if group is None:
            raise AdsError(AdsErrorCode.DEVICE_INVALIDGRP, f"unknown index group 0x{index_group:X}")
        scopes = {o.scope for o in self.objects if o.group == group and o.id == element}
        if not scopes:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDOFFSET,
                f"no element 0x{element:04X} in group 0x{GROUPS[group]:X}",
            )
        scope = "machine" if axis == 0 else "axis"
        if channel != 0 or scope not in scopes or (axis and axis not in set(axes)):
            return 0, 0
        return GROUPS[group], (axis << 16) | element

    def resolve(
        self, index_group: int, index_offset: int, axes: Iterable[int], port: int | None = None
    ) -> tuple[ObjectDef, int, str | None]:
        """Resolve an ADS address to (object, axis, attribute kind or None).

        Unknown index group -> 0x702, also a group of another task than the AMS port
        asked (`port`: the ADS request's target port, passed explicitly; None: any
        port, as a name-based interface asks); unknown element ID or axis -> 0x703
        (docs/design.md §9).
        """
        attr: str | None = None
        group = next((g for g, ig in GROUPS.items() if ig == index_group), None)
        if group is None:
            for g, ig in TASK_GROUPS.items():
                if index_group - ig in ATTRIBUTES:
                    group, attr = g, ATTRIBUTES[index_group - ig]
                    break
        if group is None:
            raise AdsError(AdsErrorCode.DEVICE_INVALIDGRP, f"unknown index group 0x{index_group:X}")
        if port is not None and port != GROUP_PORTS[group]:
            task = "COM" if GROUP_PORTS[group] == COM_AMS_PORT else "GEO"
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDGRP,
                f"index group 0x{index_group:X} is the {task} task's, served on AMS port "
                f"{GROUP_PORTS[group]}, not {port}",
            )
        axis, oid = index_offset >> 16, index_offset & 0xFFFF
        scope = "machine" if axis == 0 else "axis"
        obj = self._by_id.get((group, oid, scope))
        if obj is None:
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDOFFSET,
                f"no object 0x{oid:04X} in group 0x{GROUPS[group]:X} for "
                + ("the machine (axis 0)" if axis == 0 else f"axis {axis}"),
            )
        if scope == "axis" and axis not in set(axes):
            raise AdsError(
                AdsErrorCode.DEVICE_INVALIDOFFSET,
                f"axis {axis} is not configured (offset 0x{index_offset:X})",
                obj.name,
            )
        return obj, axis, attr


def _load(raw: dict[str, Any]) -> ObjectDef:
    return ObjectDef(
        name=raw["name"],
        group=raw["group"],
        id=int(raw["id"]),
        type=TYPES[raw["type"].split()[0]],
        access=raw["access"],
        unit=raw.get("unit", "[-]"),
        scope=raw.get("scope", "axis"),
        description=raw.get("description", ""),
        source=raw.get("source", ""),
        aliases=tuple(raw.get("aliases", ())),
        min=raw.get("min"),
        max=raw.get("max"),
        command=raw.get("command"),
        list_key=raw.get("list_key"),
        quantity=raw.get("quantity"),
        varies_at_rest=_flag(raw, "varies_at_rest"),
    )


def _flag(raw: dict[str, Any], key: str) -> bool:
    """A true/false field of an object (absent: false); anything else is a defect of the
    dictionary, said with the object's name."""
    value = raw.get(key, False)
    if not isinstance(value, bool):
        raise ValueError(f"objects.toml: {raw.get('name')}: {key} must be true or false")
    return value


@cache
def load_dictionary() -> Dictionary:
    """Load `objects/objects.toml` (installed copy or repository checkout)."""
    with (data_dir("objects") / "objects.toml").open("rb") as fh:
        raw = tomllib.load(fh)
    return Dictionary([_load(o) for o in raw["object"]])


# ---------------------------------------------------------------------- documentation

COLUMNS = ("name", "index_group", "id", "scope", "type", "length", "access", "unit", "source")


def dictionary_markdown(d: Dictionary | None = None) -> str:
    """The object table as Markdown (README and `geo-server objects`)."""
    d = d or load_dictionary()
    lines = [
        "| " + " | ".join(COLUMNS) + " |",
        "|" + "---|" * len(COLUMNS),
    ]
    for o in d.objects:
        row = o.as_row()
        name = row["name"] + ("".join(f" (alias `{a}`)" for a in o.aliases[:1]))
        cells = [name] + [str(row[c]) for c in COLUMNS[1:]]
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return "\n".join(lines) + "\n"
