"""The Modbus register map (docs/design.md §8) as pure functions: addresses, encoding, checks."""

from __future__ import annotations

import csv
import io
import math

import pytest

from geo_server.dictionary import load_dictionary
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.transports.modbus.regmap import (
    ExcCode,
    ModbusMap,
    RegisterError,
    Table,
    bit_address,
    decode,
    encode,
    exception_for,
    modbus_map,
    register_address,
    register_count,
)

D = load_dictionary()
MM = ModbusMap.build(D)
AX = MM.axis


def obj(name: str):
    return D.by_name(name)


def code_of(fn, *args) -> int:
    with pytest.raises(RegisterError) as info:
        fn(*args)
    return info.value.code


# ---------------------------------------------------------------------- addresses


def test_text_objects_own_128_registers_at_0x6000():
    """SIM::last_error (STRING, ID 9): registers 0x6000 + 128·9 = 0x6480 … 0x64FF, the
    first 125 (one request) carry two ASCII bytes each, first byte high, NUL-padded;
    249 characters at most. µ is spelled u (issue 45 #10: plain ASCII on the wire)."""
    o = D.by_name("SIM::last_error")
    assert register_address(o) == 0x6480 and register_count(o) == 125
    assert MM.machine.registers[0x6480] == (o, 0) and MM.machine.registers[0x64FF] == (o, 127)
    assert MM.machine.registers[0x6500][0] is D.by_name("SIM::axis_names")  # ID 10
    regs = encode(o, "ab\u00b5")  # "abu": 0x61 0x62, 0x75 0x00
    assert regs[:3] == [0x6162, 0x7500, 0] and len(regs) == 125
    assert decode(o, regs) == "abu"
    # 249 characters at most: a longer text ends in "..." (246 x and "...", then NUL)
    assert encode(o, "x" * 300)[122:] == [0x7878, 0x2E2E, 0x2E00]


@pytest.mark.parametrize(
    "o",
    [o for o in D.objects if o.type.name != "STRING" and o.group != "com"],
    ids=lambda o: o.name,
)
def test_every_object_address(o):
    base = 0 if o.group == "geo" else 0x4000
    assert register_address(o) == base + 4 * o.id
    assert (
        register_count(o)
        == {"BOOLEAN": 1, "UNS16": 1, "SGN32": 2, "UNS32": 2, "REAL64": 4}[o.type.name]
    )
    um = MM.machine if o.scope == "machine" else MM.axis
    for w in range(4):
        assert um.registers[register_address(o) + w] == (o, w)
    if o.type.name == "BOOLEAN":
        assert bit_address(o) == base + o.id
        assert um.discrete[bit_address(o)] is o
        assert (bit_address(o) in um.coils) == o.writable
    else:
        assert o not in um.discrete.values()


def test_known_addresses():
    assert register_address(obj("TEMPC::coefficient")) == 0x10C == 268
    assert register_address(obj("TEMPC::activated")) == 0x104
    assert register_address(obj("TEMPC::is_active")) == 0x104  # alias
    assert register_address(obj("SIM::command_position")) == 0x4004
    assert register_address(obj("SIM::cycle_count")) == 0x4004  # machine unit
    assert bit_address(obj("TEMPC::activated")) == 0x41
    assert bit_address(obj("SIM::homed")) == 0x4005
    assert bit_address(obj("SIM::drive_enable")) == 0x400E
    assert set(AX.coils) == {0x41, 0x4005, 0x400E}


def test_unit_maps():
    axes = (1, 2, 3)
    assert MM.for_unit(0, axes) is MM.machine
    assert MM.for_unit(2, axes) is MM.axis
    assert MM.for_unit(9, axes) is None
    assert {o.scope for o in MM.machine.objects} == {"machine"}
    assert {o.scope for o in MM.axis.objects} == {"axis"}
    # every object but the COM task's (port 553, ADS and Zenoh only)
    com = [o for o in D.objects if o.group == "com"]
    assert len(com) == 4
    assert len(MM.axis.objects) + len(MM.machine.objects) == len(D.objects) - len(com)


# ---------------------------------------------------------------------- encoding


@pytest.mark.parametrize(
    ("name", "value", "regs"),
    [
        ("TEMPC::coefficient", 4000.0, [0x40AF, 0x4000, 0x0000, 0x0000]),
        ("TEMPC::coefficient", -1.5, [0xBFF8, 0, 0, 0]),
        ("TEMPC::coefficient", 0.1, [0x3FB9, 0x9999, 0x9999, 0x999A]),
        ("TEMPC::offset_0", -2, [0xFFFF, 0xFFFE]),
        ("TEMPC::offset_0", 0x12345678, [0x1234, 0x5678]),
        ("TEMPC::offset_0", -(2**31), [0x8000, 0x0000]),
        ("TEMPC::activated", True, [1]),
        ("TEMPC::activated", False, [0]),
        ("SIM::cycle_count", 0xDEADBEEF, [0xDEAD, 0xBEEF]),
        ("SIM::reload", 1, [1]),
    ],
)
def test_encode_decode(name, value, regs):
    o = obj(name)
    assert encode(o, value) == regs
    assert decode(o, regs) == value


def test_encode_saturates_and_decode_unchecked():
    o = obj("TEMPC::offset_0")
    assert encode(o, 2**40) == [0x7FFF, 0xFFFF]
    assert encode(o, -(2**40)) == [0x8000, 0x0000]
    feed = obj("SIM::feed")
    assert decode(feed, [0, 0], check=False) == 0  # a reader accepts what it gets
    assert code_of(decode, feed, [0, 0]) == ExcCode.ILLEGAL_VALUE  # range 1…


@pytest.mark.parametrize(
    ("name", "regs"),
    [
        ("TEMPC::activated", [2]),
        ("TEMPC::coefficient", [0x7FF8, 0, 0, 0]),  # NaN
        ("TEMPC::coefficient", [0x7FF0, 0, 0, 0]),  # +inf
        ("TEMPC::coefficient", encode(D.by_name("TEMPC::coefficient"), 10000.5)),  # > max
        ("TEMPC::coefficient", [0, 0]),  # wrong count
        ("SIM::reload", [2]),  # range 1…1
        ("TEMPC::offset_0", [0x1_0000, 0]),
    ],
)
def test_decode_rejects(name, regs):
    assert code_of(decode, obj(name), regs) == ExcCode.ILLEGAL_VALUE


def test_nonfinite_real_reads_as_is():
    regs = encode(obj("TEMPC::coefficient"), math.inf)
    assert regs == [0x7FF0, 0, 0, 0]


# ---------------------------------------------------------------------- reads


def values(snapshot: dict[str, object]):
    return lambda o: snapshot.get(o.name, 0)


def test_block_read_across_objects_with_unused_words():
    # 0x41 activated (BOOLEAN), 0x42 actual_offset (SGN32), 0x43 coefficient (REAL64)
    a = register_address(obj("TEMPC::activated"))
    assert AX.check_read(3, a, 12) == Table.HOLDING_REGISTERS
    regs = AX.read_registers(
        a,
        12,
        values(
            {"TEMPC::activated": True, "TEMPC::actual_offset": -2, "TEMPC::coefficient": 4000.0}
        ),
    )
    assert regs == [1, 0, 0, 0, 0xFFFF, 0xFFFE, 0, 0, 0x40AF, 0x4000, 0, 0]
    # a read may start or stop inside a slot
    assert AX.read_registers(a + 5, 4, values({"TEMPC::actual_offset": -2})) == [0xFFFE, 0, 0, 0]


@pytest.mark.parametrize(
    ("fc", "address", "count", "code"),
    [
        (3, 0, 1, ExcCode.ILLEGAL_ADDRESS),  # no object with ID 0
        (3, 4 * 0x45, 8, ExcCode.ILLEGAL_ADDRESS),  # runs past position_0 into a gap
        (4, 4 * 0x45 + 3, 2, ExcCode.ILLEGAL_ADDRESS),
        (3, 0xFFFF, 2, ExcCode.ILLEGAL_ADDRESS),
        (3, 4 * 0x41, 0, ExcCode.ILLEGAL_VALUE),
        (3, 4 * 0x41, 126, ExcCode.ILLEGAL_VALUE),
        (1, 0x40, 1, ExcCode.ILLEGAL_ADDRESS),  # no coil at 0x40
        (1, 0x41, 2, ExcCode.ILLEGAL_ADDRESS),
        (1, 0x1D8, 1, ExcCode.ILLEGAL_ADDRESS),  # f_is_active: discrete input, not a coil
        (2, 0x42, 1, ExcCode.ILLEGAL_ADDRESS),  # SGN32 is not a bit
        (2, 0x41, 2001, ExcCode.ILLEGAL_VALUE),
        (7, 0, 1, ExcCode.ILLEGAL_FUNCTION),
        (6, 4 * 0x41, 1, ExcCode.ILLEGAL_FUNCTION),  # a write FC is not a read
    ],
)
def test_read_exceptions(fc, address, count, code):
    assert code_of(AX.check_read, fc, address, count) == code


def test_read_bits():
    assert AX.check_read(2, 0x1D6, 3) == Table.DISCRETE_INPUTS
    bits = AX.read_bits(
        Table.DISCRETE_INPUTS, 0x1D6, 3, values({"CC2::activated": 1, "TEMPC::f_is_active": 1})
    )
    assert bits == [False, True, True]
    assert AX.read_bits(Table.COILS, 0x41, 1, values({"TEMPC::activated": True})) == [True]


def test_machine_unit():
    mu = MM.machine
    assert mu.check_read(3, 0x4004, 24) == Table.HOLDING_REGISTERS
    assert code_of(mu.check_read, 3, 4 * 0x43, 4) == ExcCode.ILLEGAL_ADDRESS
    assert code_of(mu.check_read, 1, 0x41, 1) == ExcCode.ILLEGAL_ADDRESS
    assert mu.read_registers(0x4004, 2, values({"SIM::cycle_count": 70000})) == [1, 4464]


# ---------------------------------------------------------------------- writes


def test_write_real64_and_sgn32_block():
    c = register_address(obj("TEMPC::coefficient"))
    assert AX.decode_write(16, c, [0x40AF, 0x4000, 0, 0]) == [(obj("TEMPC::coefficient"), 4000.0)]
    # offset_0 and position_0 in one FC 16, unused words included and ignored
    o = register_address(obj("TEMPC::offset_0"))
    pairs = AX.decode_write(16, o, [0xFFFF, 0xFFFE, 9, 9, 0, 7])
    assert pairs == [(obj("TEMPC::offset_0"), -2), (obj("TEMPC::position_0"), 7)]
    assert AX.decode_write(6, 4 * 0x41, [1]) == [(obj("TEMPC::activated"), True)]
    assert AX.decode_write(5, 0x41, [False]) == [(obj("TEMPC::activated"), False)]
    assert AX.decode_write(15, 0x4005, [True]) == [(obj("SIM::homed"), True)]
    assert MM.machine.decode_write(6, 0x4010, [1]) == [(obj("SIM::reload"), 1)]


@pytest.mark.parametrize(
    ("fc", "address", "vals", "code"),
    [
        (16, 4 * 0x43, [0x40AF, 0x4000], ExcCode.ILLEGAL_VALUE),  # half a REAL64
        (16, 4 * 0x43 + 1, [0, 0, 0], ExcCode.ILLEGAL_VALUE),
        (6, 4 * 0x44, [1], ExcCode.ILLEGAL_VALUE),  # one word of an SGN32
        (6, 4 * 0x41 + 1, [1], ExcCode.ILLEGAL_VALUE),  # only an unused word
        (16, 4 * 0x44, [0, 0, 0, 0, 0], ExcCode.ILLEGAL_VALUE),  # half of position_0
        (6, 4 * 0x42, [1], ExcCode.ILLEGAL_ADDRESS),  # read-only actual_offset
        (16, 4 * 0x42, [0, 0, 0, 0, 0, 0, 0, 0], ExcCode.ILLEGAL_ADDRESS),
        (6, 0, [1], ExcCode.ILLEGAL_ADDRESS),  # nothing there
        (5, 0x1D8, [True], ExcCode.ILLEGAL_ADDRESS),  # read-only BOOLEAN
        (5, 0x42, [True], ExcCode.ILLEGAL_ADDRESS),
        (15, 0x41, [True, True], ExcCode.ILLEGAL_ADDRESS),
        (6, 4 * 0x41, [2], ExcCode.ILLEGAL_VALUE),  # BOOLEAN 2
        (16, 4 * 0x43, encode(D.by_name("TEMPC::coefficient"), 20000.0), ExcCode.ILLEGAL_VALUE),
        (16, 4 * 0x43, [0x7FF8, 0, 0, 0], ExcCode.ILLEGAL_VALUE),  # NaN
        (16, 0x4020, [0, 0], ExcCode.ILLEGAL_VALUE),  # SIM::feed 0 < 1
        (3, 4 * 0x41, [1], ExcCode.ILLEGAL_FUNCTION),
        (16, 4 * 0x41, [0] * 124, ExcCode.ILLEGAL_VALUE),
    ],
)
def test_write_exceptions(fc, address, vals, code):
    assert code_of(AX.decode_write, fc, address, vals) == code


def test_machine_write_exceptions():
    assert code_of(MM.machine.decode_write, 6, 0x4010, [2]) == ExcCode.ILLEGAL_VALUE
    assert code_of(MM.machine.decode_write, 16, 0x4004, [0, 1]) == ExcCode.ILLEGAL_ADDRESS


def test_exception_for_ads_codes():
    assert exception_for(AdsError(AdsErrorCode.DEVICE_INVALIDACCESS, "")) == 2
    assert exception_for(AdsError(AdsErrorCode.DEVICE_INVALIDOFFSET, "")) == 2
    assert exception_for(AdsError(AdsErrorCode.DEVICE_INVALIDDATA, "")) == 3
    assert exception_for(AdsError(AdsErrorCode.DEVICE_INVALIDSIZE, "")) == 3
    assert exception_for(AdsError(AdsErrorCode.DEVICE_SYNTAX, "")) == 4


# ---------------------------------------------------------------------- the printed map


def test_modbus_map_csv_is_complete():
    rows = list(csv.DictReader(io.StringIO(modbus_map("csv"))))
    regs = {(r["unit"], r["object"]) for r in rows if r["table"].startswith("holding")}
    assert len(regs) == len([o for o in D.objects if o.group != "com"])  # COM: ADS, Zenoh
    coils = [r for r in rows if r["table"] == "coil"]
    assert {r["object"] for r in coils} == {
        "TEMPC::activated",
        "SIM::homed",
        "SIM::drive_enable",
        "TWIN::spindle_on",
    }
    coef = next(r for r in rows if r["object"] == "TEMPC::coefficient")
    assert coef["address"].startswith("268…271")
    assert coef["type"] == "REAL64" and coef["registers"] == "4"
    assert "6/16" in coef["access"]
    # plain numbers for tools: TEMPC::coefficient is ID 0x43, slot 4·0x43 = 268, REAL64 = 4
    assert (coef["start"], coef["count"]) == ("268", "4")
    # a text object: 128 registers from 0x6000 + 128·ID, 125 carry the text, 3 unused
    text = next(r for r in rows if r["object"] == "SIM::last_error")
    assert text["registers"] == "125 (+3 unused)"
    assert int(text["start"]) == 0x6000 + 128 * int(text["id"], 16)
    assert text["count"] == "125"
    tempc_bit = next(r for r in rows if r["object"] == "TEMPC::activated" and r["table"] == "coil")
    assert (tempc_bit["start"], tempc_bit["count"]) == (str(0x41), "1")


def test_modbus_map_markdown():
    md = modbus_map("md")
    lines = md.strip().splitlines()
    assert lines[0].startswith("| unit | table | address | object")
    assert len(lines) == 2 + len(list(csv.DictReader(io.StringIO(modbus_map("csv")))))
    assert "| TEMPC::coefficient |" in md
    with pytest.raises(ValueError):
        modbus_map("html")
