"""The object dictionary against the manuals' object table and the ADS encoding (§2, §9 of
docs/design.md)."""

from __future__ import annotations

import csv
import math
import struct
from pathlib import Path

import pytest

from geo_server.dictionary import (
    dictionary_markdown,
    load_dictionary,
    round_half_away,
    string_bytes,
)
from geo_server.errors import AdsError

# Every CNC object of the axis-compensation manuals (000–003), read off the manuals once:
# the independent table the dictionary is checked against.
OBJECTS_CSV = Path(__file__).resolve().parent / "data" / "research" / "objects.csv"
ACCESS = {"read": "r", "read/write": "rw"}


def _geo_rows() -> list[dict[str, str]]:
    with OBJECTS_CSV.open(encoding="utf-8") as fh:
        rows = [r for r in csv.DictReader(fh) if r["task"] == "GEO"]
    return [r for r in rows if r["name"] != "TEMPC::is_active"]


@pytest.fixture(scope="module")
def d():
    return load_dictionary()


def test_every_geo_object_of_the_research_table(d):
    rows = _geo_rows()
    assert len(rows) == 24
    for r in rows:
        obj = d.by_name(r["name"])
        assert obj.group == "geo" and obj.index_group == 0x120300
        assert obj.id == int(r["offset_id_hex"], 16), r["name"]
        assert obj.type.name == r["type"], r["name"]
        assert obj.length == int(r["length"]), r["name"]
        assert obj.access == ACCESS[r["access"]], r["name"]
    assert len(d.group_objects("geo")) == 24


def test_only_four_tempc_objects_are_writable(d):
    writable = sorted(o.name for o in d.group_objects("geo") if o.writable)
    assert writable == [
        "TEMPC::activated",
        "TEMPC::coefficient",
        "TEMPC::offset_0",
        "TEMPC::position_0",
    ]


def test_aliases_and_spellings(d):
    assert d.by_name("TEMPC::is_active").id == 0x41
    assert d.by_name("TEMPC:: activated").id == 0x41  # 000's table spelling
    assert d.by_name("tempc::actual_offset").id == 0x42  # not is_active (EN misprint)
    assert d.by_name("ssfk activated").id == 0x38
    with pytest.raises(AdsError) as e:
        d.by_name("TEMPC::nonsense")
    assert e.value.code == 0x703


def test_resolve_offsets_and_errors(d):
    obj, axis, attr = d.resolve(0x120300, 0x10043, [1, 2])
    assert (obj.name, axis, attr) == ("TEMPC::coefficient", 1, None)
    obj, axis, attr = d.resolve(0x120300, (2 << 16) | 0x93, [1, 2])
    assert (obj.name, axis) == ("BC::actual backlash", 2)
    obj, axis, attr = d.resolve(0x12F300, 0x00000001, [1])
    assert (obj.name, axis) == ("SIM::cycle_count", 0)
    for ig, io, code in [
        (0x120200, 0x10043, 0x702),  # unknown group
        (0x120300, 0x10099, 0x703),  # unknown element id
        (0x120300, 0x50043, 0x703),  # axis 5 not configured
        (0x120300, 0x00043, 0x703),  # axis 0 has no GEO objects
    ]:
        with pytest.raises(AdsError) as e:
            d.resolve(ig, io, [1, 2])
        assert e.value.code == code


def test_attribute_groups(d):
    obj, _, attr = d.resolve(0x120400, 0x10043, [1])
    assert attr == "name"
    assert obj.attribute("name") == b"TEMPC::coefficient".ljust(256, b"\0")
    assert obj.attribute("type").rstrip(b"\0") == b"REAL64"
    assert obj.attribute("length") == b"\x08\x00\x00\x00"
    assert obj.attribute("unit").rstrip(b"\0") == b"[um/m]"  # (ASCII: issue 45 #10)
    assert obj.attribute("writable") == b"\x01"
    _, _, attr = d.resolve(0x120800, 0x10093, [1])
    assert attr == "writable"
    assert d.by_name("BC::actual backlash").attribute("writable") == b"\x00"
    _, _, attr = d.resolve(0x12F700, 0x10005, [1])
    assert attr == "unit"


def test_encoding_is_little_endian(d):
    assert d.by_name("TEMPC::activated").encode(True) == b"\x01"
    assert d.by_name("TEMPC::actual_offset").encode(-2) == b"\xfe\xff\xff\xff"
    assert d.by_name("TEMPC::offset_0").encode(0x01020304) == b"\x04\x03\x02\x01"
    assert d.by_name("TEMPC::coefficient").encode(4000.0) == struct.pack("<d", 4000.0)
    assert d.by_name("SIM::reload").encode(1) == b"\x01\x00"
    assert d.by_name("SIM::cycle_count").encode(0x01020304) == b"\x04\x03\x02\x01"
    assert d.by_name("TEMPC::coefficient").decode(bytes.fromhex("0000000000407f40")) == 500.0
    assert d.by_name("TEMPC::position_0").decode(b"\x9c\xff\xff\xff") == -100


@pytest.mark.parametrize(
    ("name", "value", "wire"),
    [
        # docs/design.md §2: BOOLEAN 1 byte, UNS16 2, UNS32 4, SGN32 4, REAL64 8, little-endian
        ("TEMPC::activated", True, "01"),
        ("TEMPC::activated", False, "00"),
        ("SIM::save", 1, "0100"),  # the only UNS16 objects are commands: 1 … 1
        ("SIM::cycle_count", 0xFFFFFFFE, "feffffff"),
        ("TEMPC::position_0", -2_000_000_000, "006cca88"),
        ("TEMPC::coefficient", -0.5, "000000000000e0bf"),
    ],
)
def test_every_type_round_trips_with_its_bytes(d, name, value, wire):
    obj = d.by_name(name)
    assert obj.encode(value).hex() == wire
    assert obj.decode(bytes.fromhex(wire)) == value
    assert type(obj.decode(bytes.fromhex(wire))) is type(value)


def test_string_attribute_is_256_bytes_ascii_nul_padded(d):
    """Issue 45 #10: a STRING on the wire is plain ASCII, which pyads (UTF-8) and
    ads-client (CP1252) both decode: `[µm/m]` goes out as `[um/m]`."""
    unit = d.by_name("TEMPC::coefficient").attribute("unit")
    assert len(unit) == 256 and unit[:7] == b"[um/m]\0" and unit[7:] == bytes(249)
    assert d.by_name("TEMPC::coefficient").decode_attribute("unit", unit) == "[um/m]"


def test_a_string_is_ascii_and_cut_after_a_whole_word():
    """Issue 45 #10 and #18: the emulator's characters spelled out (µ → u, … → ..., °
    → deg, ≤ → <=), accents dropped, others `?`; a text longer than 255 characters is
    cut after its last whole word and ends in `...` (before: cut mid-word)."""
    assert string_bytes("0 … 100 µm/m, 20 °C, a ≤ b, é, 漢", 64).rstrip(b"\0") == (
        b"0 ... 100 um/m, 20 degC, a <= b, e, ?"
    )
    words = " ".join(["word"] * 60)  # 299 characters: "word word … word"
    out = string_bytes(words).rstrip(b"\0")
    # room for 252 characters before "...": 50 words with the 49 spaces between them
    # make 249, the 51st word would end at 254
    assert out == b" ".join([b"word"] * 50) + b"..."
    assert string_bytes("x" * 300) == b"x" * 252 + b"..." + b"\0"
    assert string_bytes("y" * 255) == b"y" * 255 + b"\0"  # exactly the limit: whole
    assert string_bytes("") == bytes(256)
    assert [string_bytes("abcdef", n) for n in (0, 1, 2, 4)] == [b"", b"\0", b"a\0", b"abc\0"]


def test_a_string_a_client_writes_is_cp1252_and_whole():
    """What a client writes (a volumetric file name) keeps its CP1252 characters and is
    never cut: a path cut short or spelled in ASCII names another file; 0x706 instead."""
    d = load_dictionary()
    obj = next(o for o in d.objects if o.type.name == "STRING" and o.writable)
    path = "/data/Prüfstand/vol é.txt"
    assert obj.encode(path) == path.encode("cp1252").ljust(256, b"\0")
    for bad in ("x" * 256, "漢"):
        with pytest.raises(AdsError) as err:
            obj.encode(bad)
        assert err.value.code == 0x706
    # what the server sends of the same text: ASCII
    assert obj.encode_reply(path).rstrip(b"\0") == b"/data/Pruefstand/vol e.txt"


@pytest.mark.parametrize(
    "name,value",
    [
        ("TEMPC::coefficient", 10000.5),
        ("TEMPC::coefficient", -10001),
        ("TEMPC::coefficient", math.nan),
        ("TEMPC::activated", 2),
        ("TEMPC::offset_0", 2**31),
        ("SIM::reload", 2),
        ("SIM::feed", 0),
    ],
)
def test_out_of_range_is_0x706(d, name, value):
    with pytest.raises(AdsError) as e:
        d.by_name(name).encode(value)
    assert e.value.code == 0x706


def test_wrong_length_is_0x705_and_bad_boolean_0x706(d):
    with pytest.raises(AdsError) as e:
        d.by_name("TEMPC::coefficient").decode(b"\0" * 4)
    assert e.value.code == 0x705
    with pytest.raises(AdsError) as e:
        d.by_name("TEMPC::activated").decode(b"\x02")
    assert e.value.code == 0x706


def test_round_half_away_from_zero():
    assert round_half_away(4039.6) == 4040
    assert round_half_away(2.5) == 3
    assert round_half_away(-2.5) == -3
    assert round_half_away(-2.4) == -2


def test_markdown_table_lists_every_object(d):
    md = dictionary_markdown(d)
    assert md.count("\n") == len(d.objects) + 2
    assert "| TEMPC::activated (alias `TEMPC::is_active`) | 0x120300 | 0x0041 |" in md


def test_saved_parameters_name_the_attributes_the_axis_list_reader_fills():
    """`save` and the kernels find a parameter's stored value by `param_attr`: it must be
    the attribute the axis list reader writes the `list_key` entry into."""
    from geo_server.listfile.axislist import _FIELDS

    d = load_dictionary()
    saved = d.saved_parameters()
    assert len(saved) == 4  # TEMPC activated, coefficient, offset_0, position_0
    for obj in saved:
        assert obj.list_key in _FIELDS, obj.name
        assert obj.param_attr == _FIELDS[obj.list_key][0], obj.name
    assert [o.key_group for o in d.tempc_parameters()] == ["tempc"] * 3


def test_only_the_objects_marked_varies_at_rest_change_at_rest(machine) -> None:
    """Issue 47: which objects may change while the machine rests is declared in
    objects.toml (`varies_at_rest`), and a read at rest is answered from the rest
    snapshot for every other one. So: homed and standing, the machine comes to rest;
    2 000 cycles more, each computed, leave every unmarked object of every axis as it
    was, while the marked cycle counter moved on by exactly 2 000."""
    from geo_server import access
    from geo_server.service import ObjectService

    service = ObjectService(machine)
    for _ in range(10_000):
        if machine.quiescent:
            break
        access.step(service, 1)
    assert machine.quiescent
    d = load_dictionary()
    slots = [
        (o, axis)
        for o in d.objects
        if o.readable
        for axis in (machine.axes if o.scope == "axis" else (0,))
    ]
    before = access.step(service, 1)
    after = access.step(service, 2000)
    changed = [
        f"{o.name}@{axis}"
        for o, axis in slots
        if not o.varies_at_rest and after.value(o, axis) != before.value(o, axis)
    ]
    assert changed == []
    count = d.by_name("SIM::cycle_count")
    assert count.varies_at_rest and after.value(count, 0) - before.value(count, 0) == 2000


def test_a_varies_at_rest_that_is_not_true_or_false_is_refused() -> None:
    from geo_server.dictionary import _load

    raw = {"name": "SIM::x", "group": "sim", "id": 1, "type": "UNS32", "access": "r"}
    assert _load(raw).varies_at_rest is False
    with pytest.raises(ValueError, match="SIM::x: varies_at_rest must be true or false"):
        _load(raw | {"varies_at_rest": "yes"})
