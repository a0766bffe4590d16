"""The correction files of the volumetric compensation: ISG CSV and Etalon exchange (004 §6.3).

The examples are typed from the manual (004 p.23, p.32, p.33, p.34, p.38) without the
elision marks it prints, unless a test is about those; expected values are typed from
the same pages or worked out by hand, never produced by the code under test.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from geo_server.errors import GeoError
from geo_server.volcomp import names
from geo_server.volcomp.paramfile import (
    Block,
    ParamFile,
    ParamFileError,
    parse_etalon,
    parse_isg_csv,
    read_param_file,
    write_etalon,
    write_isg_csv,
)

EXAMPLES = Path(__file__).resolve().parents[1] / "lists" / "examples" / "volumetric"
Parser = Callable[[str, str], ParamFile]

# --- 004 p.32 ---------------------------------------------------------------------------

POSITION_ERRORS_P32 = """\
// The header only contains position errors.
Y0A Z0A X0B
// Position errors are typically (but not necessarily)
// constant. Therefore, one data row is usually sufficient here.
0.1 0.2 0.11
"""

COMPONENT_ERRORS_P32 = """\
// The header contains the argument "X" and component errors.
X EXX EYX EZX EAX EBX ECX
0.0 0.02 0.01 0.07 0.00 0.0042 0.003
10.0 0.00 -0.1 0.01 0.00 0.0011 0.002
// Further records depending on X
"""

SAG_P32 = """\
// The argument "Z" now crops up in the header.
Z X EXX EYX EZX EAX EBX ECX
// In the first block Z is always = 0.
0.0 0.0 0.02 0.01 0.07 0.00 0.0042 0.003
0.0 10.0 0.00 -0.1 0.01 0.00 0.0011 0.002
// In the second block Z is always = 100.
100.0 0.0 0.01 0.02 0.03 0.07 0.0040 0.003
100.0 10.0 0.03 -0.09 0.03 0.06 0.0015 0.000
"""

X_COMPONENTS = ("EXX", "EYX", "EZX", "EAX", "EBX", "ECX")

# --- 004 p.33, p.34, p.38 -----------------------------------------------------------------

ETALON_P33 = """\
// Every parameter is specified in a block.
// The block begins with the name of the parameter in square brackets.
[C0B]
VALUE = 0.000022355737
[A0B]
VALUE = 0.000047622950
// Lookup tables are specified via a 2D array called "Gridpoints".
[EXY]
Gridpoints = {
-280.0 -0.001358635132
-270.0 -0.000240680764
-260.0 0.000877273605
// Further records in the form of "Parameter argument"
260.0 -0.001297146744
270.0 -0.000316265101
} // end of EXY
"""

EXC_P34 = """\
[EXC]
Gridpoints = {
0.0 -0.000833484486
10.0 -0.000845857719
340.0 -0.001687237526
350.0 -0.001699610758
360.0 -0.000833484486// <- duplicate of the 0° row
} // end of EXC
"""

C_AXIS_P38 = """\
// Etalon Exchange Format
// Created by TRAC-CAL V30 Build: 0017 dated 2015-04-28
// Parametric errors of one rotary axis by mulitlateration
// Date: 24-Jun-2015
// --------------------------------------
//
[HEADER]
MACHINE_TYPE = Exeron HSC 600
MACHINE_NO =
CUSTOMER = ETALON AG
DATE_OF_CALIBRATION = -
OPERATOR = Etalon master
FILE_TYPE = rotary
USERSPECIFIC_COMMENT = -
[EZC]
Gridpoints = {
0.0 -0.000423728477
5.0 -0.000351288461
10.0 -0.000278665223
15.0 -0.000205672612
20.0 -0.000132112763
:
335.0 -0.000001094701
340.0 -0.000120503607
345.0 -0.000239848892
350.0 -0.000359170264
355.0 -0.000478491636
360.0 -0.000423728477
} // end of EZC
// The example is curtailed at this point
"""


def _error(parse: Parser, text: str, path: str = "f") -> ParamFileError:
    with pytest.raises(ParamFileError) as info:
        parse(text, path)
    return info.value


def _keys(blocks: tuple[Block, ...] | list[Block]) -> list[object]:
    return [b.key() for b in blocks]


# --- names (004 p.30) -------------------------------------------------------------------


def test_parameter_names_of_p30() -> None:
    assert names.POSITION_ERRORS[:7] == ("X0X", "Y0X", "Z0X", "A0X", "B0X", "C0X", "X0Y")
    assert names.POSITION_ERRORS[-1] == "C0C"
    assert names.COMPONENT_ERRORS[:7] == ("EXX", "EYX", "EZX", "EAX", "EBX", "ECX", "EXY")
    assert names.COMPONENT_ERRORS[-1] == "ECC"
    # 6 + 9 centres + 18 orientations + 6 offsets + 6 axis numbers
    assert len(names.ISG_PARAMETERS) == 45
    assert {"P0Z", "N0X", "PZA", "PXC", "VZX", "VXC", "IDB", "LNC"} <= names.PARAMETERS
    assert len(names.PARAMETERS) == 36 + 36 + 45
    assert "X" not in names.PARAMETERS
    assert names.ARGUMENTS == ("X", "Y", "Z", "A", "B", "C")


def test_axis_of_and_is_angle() -> None:
    assert [names.axis_of(n) for n in ("EYX", "X0B", "EZC", "VXA", "IDY", "LNC", "PYB")] == [
        "X",
        "B",
        "C",
        "A",
        "Y",
        "C",
        "B",
    ]
    assert names.axis_of("P0X") == names.axis_of("N0Z") == ""
    assert [names.is_angle(n) for n in ("A0X", "EBX", "ECC", "X0A", "EXA", "P0X", "VXA")] == [
        True,
        True,
        True,
        False,
        False,
        False,
        False,
    ]
    with pytest.raises(ValueError, match="'FOO' is not a volumetric error parameter"):
        names.axis_of("FOO")


# --- ISG CSV: the manual's examples ---------------------------------------------------------


def test_csv_position_errors_p32() -> None:
    pf = parse_isg_csv(POSITION_ERRORS_P32, "pos.csv")
    assert pf.format == "ISG_CSV" and pf.path == "pos.csv" and pf.warnings == ()
    (block,) = pf.blocks
    assert block == Block((), ("Y0A", "Z0A", "X0B"), ((0.1, 0.2, 0.11),), "pos.csv", 2)
    assert pf.records == 1


def test_csv_component_errors_p32() -> None:
    (block,) = parse_isg_csv(COMPONENT_ERRORS_P32).blocks
    assert block.arguments == ("X",) and block.parameters == X_COMPONENTS
    assert block.rows == (
        (0.0, 0.02, 0.01, 0.07, 0.00, 0.0042, 0.003),
        (10.0, 0.00, -0.1, 0.01, 0.00, 0.0011, 0.002),
    )
    eyx = 1 + X_COMPONENTS.index("EYX")
    assert block.rows[1][0] == 10.0 and block.rows[1][eyx] == -0.1


def test_csv_two_dimensional_p32() -> None:
    # as printed: one header, Z = 0 and Z = 100 rows in one table (no '#' between them)
    pf = parse_isg_csv(SAG_P32)
    (block,) = pf.blocks
    assert block.arguments == ("Z", "X") and block.parameters == X_COMPONENTS
    assert pf.records == 4 and block.line == 2
    z100_x10 = block.rows[3]
    assert z100_x10[:2] == (100.0, 10.0)
    assert z100_x10[2 + X_COMPONENTS.index("ECX")] == 0.0
    assert z100_x10[2 + X_COMPONENTS.index("EYX")] == -0.09


def test_csv_file_break_starts_a_new_block() -> None:
    text = "Z X EXX\n0.0 10.0 0.5\n# second block: Z = 100\nZ X EXX\n100.0 10.0 0.25\n"
    pf = parse_isg_csv(text)
    assert _keys(pf.blocks) == [
        (("Z", "X"), ("EXX",), ((0.0, 10.0, 0.5),)),
        (("Z", "X"), ("EXX",), ((100.0, 10.0, 0.25),)),
    ]
    assert [b.line for b in pf.blocks] == [1, 4]


def test_csv_columns_in_any_order_are_reordered() -> None:
    (block,) = parse_isg_csv("EYX X EXX Z\n1.5 10.0 2.5 -3.0\n").blocks
    assert block.arguments == ("X", "Z") and block.parameters == ("EYX", "EXX")
    assert block.rows == ((10.0, -3.0, 1.5, 2.5),)


def test_csv_separators_comments_and_numbers() -> None:
    text = "X,\tEXX ; EYX // header\n  -1.5e+2;1E-07,  +.5//no blank before the comment\n"
    (block,) = parse_isg_csv(text).blocks
    assert block.rows == ((-150.0, 1e-07, 0.5),)


def test_csv_example_file_p23() -> None:
    path = EXAMPLES / "004_p23_volcomp1.csv"
    pf = read_param_file(path, "ISG_CSV")
    assert pf.path == str(path) and pf.format == "ISG_CSV"
    (block,) = pf.blocks
    assert block.arguments == ("X", "Y", "Z") and block.parameters == ("EXX", "EYY")
    assert block.line == 2 and pf.records == 9
    assert block.rows[0] == (0.0, 0.0, 0.0, 0.0, 0.0)
    assert block.rows[-1] == (0.0, 40.0, 0.0, 0.008, 0.008)
    # line 1 is the '# Source:' file break, line 12 the printed '…'
    assert pf.warnings == ((12, "elision mark ignored"),)


@pytest.mark.parametrize("mark", ["…", "...", ":", " … "])
def test_csv_elision_row_is_skipped(mark: str) -> None:
    pf = parse_isg_csv(f"X EXX\n0.0 1.0\n{mark}\n20.0 2.0\n")
    assert pf.blocks[0].rows == ((0.0, 1.0), (20.0, 2.0))
    assert pf.warnings == ((3, "elision mark ignored"),)


def test_csv_header_without_rows_is_a_warning() -> None:
    pf = parse_isg_csv("X EXX\n#\nY EYY\n1.0 2.0\n")
    assert _keys(pf.blocks) == [(("Y",), ("EYY",), ((1.0, 2.0),))]
    assert pf.warnings == ((1, "header without rows: block ignored"),)


def test_csv_empty_file() -> None:
    pf = parse_isg_csv("// nothing\n\n#\n")
    assert pf.blocks == () and pf.records == 0
    assert pf.warnings == ((0, "no records in the file"),)


# --- ISG CSV: errors ------------------------------------------------------------------------


def test_csv_error_message_format() -> None:
    exc = _error(parse_isg_csv, "X EXX\n0.0 1.0\n\n0.5 abc\n", "c.csv")
    assert isinstance(exc, GeoError)
    assert (exc.path, exc.line) == ("c.csv", 4)
    assert exc.message == "value 'abc' in column EXX is not a number"
    assert str(exc) == "c.csv:4: value 'abc' in column EXX is not a number"
    assert str(_error(parse_isg_csv, "X EXX\n1 x\n", "")) == (
        "line 2: value 'x' in column EXX is not a number"
    )


@pytest.mark.parametrize(
    ("text", "line", "message"),
    [
        (
            "// c\n1.0 2.0\n",
            2,
            "data row before any header: a header naming the columns comes first",
        ),
        (
            "X EXX\n#\n1.0 2.0\n",
            3,
            "data row before any header: a header naming the columns comes first",
        ),
        ("X EXX EYX\n0 1 2\n\n0 1\n", 4, "row has 2 values, the header (line 1) names 3 columns"),
        ("X EXX\n0 1 2\n", 2, "row has 3 values, the header (line 1) names 2 columns"),
        # a decimal comma is a column separator: one value too many
        ("X;EXX\n0,5;1\n", 2, "row has 3 values, the header (line 1) names 2 columns"),
        ("X EXX\n0 nan\n", 2, "value 'nan' in column EXX is not a number"),
        ("X EXX\n0 1e999\n", 2, "value '1e999' in column EXX is not a number"),
        ("X EXX\n1_0 1\n", 2, "value '1_0' in column X is not a number"),
        ("X EXX\n0 1 …\n", 2, "row has 3 values, the header (line 1) names 2 columns"),
        (
            "\nX EXX FOO\n",
            2,
            "unknown column 'FOO': neither an argument (X Y Z A B C) nor a parameter of 004 p.30",
        ),
        (
            "x exx\n",
            1,
            "unknown column 'x': neither an argument (X Y Z A B C) nor a parameter of 004 p.30",
        ),
        ("X EXX X\n", 1, "column 'X' named twice"),
        ("X EXX EXX\n", 1, "column 'EXX' named twice"),
        ("X Y\n", 1, "header without a parameter column: X, Y are arguments"),
        ("X EXX\n0 1\nY EYY\n", 3, "a new header must follow a '#' line (file break, 004 p.32)"),
    ],
)
def test_csv_errors(text: str, line: int, message: str) -> None:
    exc = _error(parse_isg_csv, text)
    assert exc.line == line
    assert exc.message == message and str(exc).endswith(message)


# --- Etalon exchange: the manual's examples --------------------------------------------------


def test_etalon_p33() -> None:
    pf = parse_etalon(ETALON_P33, "k.exc")
    assert pf.format == "ETALON_EXCHANGE" and pf.warnings == ()
    assert _keys(pf.blocks) == [
        ((), ("C0B",), ((0.000022355737,),)),
        ((), ("A0B",), ((0.000047622950,),)),
        (
            ("Y",),
            ("EXY",),
            (
                (-280.0, -0.001358635132),
                (-270.0, -0.000240680764),
                (-260.0, 0.000877273605),
                (260.0, -0.001297146744),
                (270.0, -0.000316265101),
            ),
        ),
    ]
    assert [(b.file, b.line) for b in pf.blocks] == [("k.exc", 3), ("k.exc", 5), ("k.exc", 8)]
    assert pf.records == 7


def test_etalon_p33_with_the_printed_elision() -> None:
    text = ETALON_P33.replace("// Further records", "…\n// Further records")
    pf = parse_etalon(text)
    assert pf.blocks[2].rows[2:4] == ((-260.0, 0.000877273605), (260.0, -0.001297146744))
    assert pf.warnings == ((13, "elision mark ignored"),)


def test_etalon_comment_right_after_a_number_p34() -> None:
    (block,) = parse_etalon(EXC_P34).blocks
    assert block.arguments == ("C",) and block.parameters == ("EXC",)
    assert block.rows[-1] == (360.0, -0.000833484486) and block.rows[0][1] == block.rows[-1][1]
    assert len(block.rows) == 5


def test_etalon_c_axis_p38() -> None:
    pf = parse_etalon(C_AXIS_P38, "C_axis.exc")
    (block,) = pf.blocks  # [HEADER] is metadata
    assert block.arguments == ("C",) and block.parameters == ("EZC",) and block.line == 15
    assert len(block.rows) == 11 and pf.records == 11
    assert block.rows[0] == (0.0, -0.000423728477)
    assert block.rows[4] == (20.0, -0.000132112763)
    assert block.rows[5] == (335.0, -0.000001094701)
    assert block.rows[-1] == (360.0, -0.000423728477)  # spliced by hand (004 p.34)
    assert pf.warnings == ((22, "elision mark ignored"),)


def test_etalon_values_on_the_gridpoints_line_and_elision_among_numbers() -> None:
    pf = parse_etalon("[EXX]\nGridpoints = { 0.0 1.5\n10.0 : 2.5 }\n")
    assert pf.blocks[0].rows == ((0.0, 1.5), (10.0, 2.5))
    assert pf.warnings == ((3, "elision mark ignored"),)


def test_etalon_unknown_block_and_key_are_warnings() -> None:
    pf = parse_etalon("[INFO]\nA = b\n[X0Y]\nUNIT = rad\nvalue = -1e-05\n")
    assert _keys(pf.blocks) == [((), ("X0Y",), ((-1e-05,),))]
    assert pf.warnings == (
        (1, "block [INFO] is not a parameter of 004 p.30: ignored"),
        (4, "unknown key 'UNIT' in [X0Y] ignored"),
    )


# --- Etalon exchange: errors ----------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "line", "message"),
    [
        (
            "// c\n[EXY]\nGridpoints = {\n0.0 1.0\n10.0\n}\n",
            3,
            "Gridpoints of EXY (lines 3-6) has 3 values: pairs 'argument value' expected",
        ),
        (
            "[EXY]\nGridpoints = { }\n",
            2,
            "Gridpoints of EXY (lines 2-2) has 0 values: pairs 'argument value' expected",
        ),
        (
            "[EXY]\nGridpoints = {\n0.0 1.0\n10.0 x2\n}\n",
            4,
            "value 'x2' in Gridpoints of EXY is not a number",
        ),
        (
            "[EXY]\nGridpoints = {\n0.0 1.0\n\n",
            2,
            "Gridpoints of EXY not closed: no '}' before the end of the file",
        ),
        (
            "[EXY]\nGridpoints = {\n0.0 1.0\n[EYY]\n",
            4,
            "Gridpoints of EXY (line 2) not closed: '}' missing",
        ),
        ("[EXY]\nGridpoints = {\n0.0 1.0 } x\n", 3, "unexpected 'x' after '}'"),
        ("[EXY]\nGridpoints = 0.0 1.0\n", 2, "Gridpoints of EXY: '{' expected after '='"),
        ("[C0B]\n// nothing\n[A0B]\nVALUE = 1\n", 1, "[C0B] has neither VALUE nor Gridpoints"),
        ("[A0B]\nVALUE = 1\n[EXY]\n", 3, "[EXY] has neither VALUE nor Gridpoints"),
        ("// c\nVALUE = 1\n[C0B]\n", 2, "VALUE = … outside any [block]"),
        (
            "[X0B]\nGridpoints = {\n0.0 1.0\n}\n",
            2,
            "X0B is a position error, a constant: VALUE, not Gridpoints (004 p.31)",
        ),
        (
            "[P0X]\nGridpoints = {\n0.0 1.0\n}\n",
            2,
            "P0X is a constant (not a component error): VALUE, not Gridpoints",
        ),
        ("[C0B]\nVALUE = 0,5\n", 2, "VALUE of C0B: '0,5' is not a number"),
        ("[C0B]\nVALUE =\n", 2, "VALUE of C0B: '' is not a number"),
        ("[C0B]\nVALUE = 1\nVALUE = 2\n", 3, "[C0B] has a second VALUE or Gridpoints"),
        ("[EXY]\nVALUE = 1\nGridpoints = {\n}\n", 3, "[EXY] has a second VALUE or Gridpoints"),
        (
            "[C0B]\nVALUE = 1\n[HEADER]\n[C0B]\nVALUE = 2\n",
            4,
            "[C0B] given twice (first at line 1)",
        ),
        (
            "[HEADER]\nno equals sign\n",
            2,
            "expected 'KEY = value' or '[NAME]', not 'no equals sign'",
        ),
    ],
)
def test_etalon_errors(text: str, line: int, message: str) -> None:
    exc = _error(parse_etalon, text, "e.exc")
    assert exc.line == line
    assert exc.message == message
    assert str(exc) == f"e.exc:{line}: {message}"


# --- read_param_file ------------------------------------------------------------------------


def test_read_etalon_and_encodings(tmp_path: Path) -> None:
    f = tmp_path / "c.exc"
    # Latin-1 (not UTF-8): the degree sign of a Windows tool in a comment
    f.write_bytes(b"// 0\xb0 row\r\n[EZC]\r\nGridpoints = {\r\n0.0 -1.5\r\n}\r\n")
    pf = read_param_file(f, "ETALON_EXCHANGE")
    assert pf.path == str(f) and pf.format == "ETALON_EXCHANGE"
    assert _keys(pf.blocks) == [(("C",), ("EZC",), ((0.0, -1.5),))]
    assert pf.blocks[0].line == 2
    g = tmp_path / "bom.csv"
    g.write_bytes("\ufeffX EXX // ±\n1.0 2.0\n".encode())
    assert _keys(read_param_file(str(g), "ISG_CSV").blocks) == [(("X",), ("EXX",), ((1.0, 2.0),))]


def test_read_unknown_format_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ParamFileError) as info:
        read_param_file("x.csv", "CSV")
    assert info.value.line == 0
    assert (
        str(info.value) == "x.csv: unknown file format 'CSV': ISG_CSV or ETALON_EXCHANGE (004 p.12)"
    )
    with pytest.raises(FileNotFoundError):
        read_param_file(tmp_path / "missing.csv", "ISG_CSV")


# --- writers and round trips ----------------------------------------------------------------


def test_write_isg_csv_text() -> None:
    blocks = [
        Block(("X",), ("EXX",), ((0.0, 1e-07), (-10.0, -0.5))),
        Block((), ("C0Y",), ((0.30000000000000004,),)),
    ]
    assert write_isg_csv(blocks) == (
        "// written by geo-server\nX EXX\n0.0 1e-07\n-10.0 -0.5\n#\nC0Y\n0.30000000000000004\n"
    )


CSV_BLOCKS = (
    Block(
        ("Z", "X"),
        ("EXX", "EYX"),
        ((0.0, -10.5, 1e-07, -2.5e-06), (100.0, 10.0, -0.0001, 3.0), (1e3, -1e-300, 0.1, -0.0)),
    ),
    Block((), ("X0B", "C0Y", "P0Z"), ((1.5e-05, -4e-06, 123.456),)),
    Block(("C",), ("EZC",), ((0.0, -0.000423728477), (360.0, -0.000423728477))),
)


def test_isg_csv_round_trip() -> None:
    pf = parse_isg_csv(write_isg_csv(CSV_BLOCKS), "rt.csv")
    assert pf.warnings == ()
    assert _keys(pf.blocks) == _keys(CSV_BLOCKS)
    assert all(a.same_data(b) for a, b in zip(pf.blocks, CSV_BLOCKS, strict=True))
    # comment, header, 3 rows, "#", header, 1 row, "#", header
    assert [b.line for b in pf.blocks] == [2, 7, 10]


def test_write_etalon_text() -> None:
    blocks = [
        Block((), ("C0B",), ((2.2355737e-05,),)),
        Block(("Y",), ("EXY",), ((-280.0, -0.001358635132), (270.0, 1e-07))),
    ]
    assert write_etalon(blocks) == (
        "// written by geo-server\n\n[C0B]\nVALUE = 2.2355737e-05\n\n"
        "[EXY]\nGridpoints = {\n-280.0 -0.001358635132\n270.0 1e-07\n} // end of EXY\n"
    )


def test_etalon_round_trip() -> None:
    blocks = (
        Block((), ("C0B",), ((0.000022355737,),)),
        Block((), ("A0B",), ((-4.762295e-05,),)),
        Block(("C",), ("EZC",), ((0.0, -0.000423728477), (355.0, 1e-07), (360.0, -0.000423728477))),
        Block(("Y",), ("EXY",), ((-280.0, -0.001358635132), (-2.5e-3, 5e-10))),
    )
    pf = parse_etalon(write_etalon(blocks))
    assert pf.warnings == ()
    assert _keys(pf.blocks) == _keys(blocks)


def test_etalon_splits_blocks_per_parameter() -> None:
    block = Block(("X",), ("EXX", "EYX"), ((0.0, 1.0, -1.0), (10.0, 2.0, -2.0)))
    pf = parse_etalon(write_etalon([block, Block((), ("X0Y", "Y0X"), ((0.5, -0.5),))]))
    assert _keys(pf.blocks) == [
        (("X",), ("EXX",), ((0.0, 1.0), (10.0, 2.0))),
        (("X",), ("EYX",), ((0.0, -1.0), (10.0, -2.0))),
        ((), ("X0Y",), ((0.5,),)),
        ((), ("Y0X",), ((-0.5,),)),
    ]


ETALON_LIMIT = "which has only 1-D tables over the parameter's own axis"


@pytest.mark.parametrize(
    "block",
    [
        Block(("Z", "X"), ("EXX",), ((0.0, 0.0, 1.0),)),  # 2-D
        Block(("X",), ("EXY",), ((0.0, 1.0),)),  # not EXY's own axis Y
        Block((), ("C0B",), ((1.0,), (2.0,))),  # several rows without arguments
        Block(("B",), ("X0B",), ((0.0, 1.0),)),  # a position error is a constant
        Block(("X",), ("IDX",), ((0.0, 1.0),)),  # so is an ISG parameter
    ],
)
def test_write_etalon_refuses_what_the_format_cannot_hold(block: Block) -> None:
    with pytest.raises(ValueError, match=ETALON_LIMIT):
        write_etalon([block])
    write_isg_csv([block])  # the CSV holds any of them


@pytest.mark.parametrize(
    ("block", "match"),
    [
        (Block(("X",), (), ((0.0,),)), "no parameter column"),
        (Block(("X",), ("EXX",), ()), "has no rows"),
        (Block(("X",), ("EXX",), ((0.0,),)), "has 1 values"),
        (Block(("Q",), ("EXX",), ((0.0, 1.0),)), "column 'Q' unknown or twice"),
        (Block(("X",), ("X",), ((0.0, 1.0),)), "column 'X' unknown or twice"),
        (Block(("X",), ("EXX", "EXX"), ((0.0, 1.0, 2.0),)), "column 'EXX' unknown or twice"),
        (Block(("X",), ("EXX",), ((0.0, float("inf")),)), "not a finite number"),
    ],
)
def test_writers_refuse_malformed_blocks(block: Block, match: str) -> None:
    for write in (write_isg_csv, write_etalon):
        with pytest.raises(ValueError, match=match):
            write([block])


def test_write_etalon_refuses_a_parameter_twice() -> None:
    blocks = [Block((), ("C0B",), ((1.0,),)), Block((), ("A0B", "C0B"), ((1.0, 2.0),))]
    with pytest.raises(ValueError, match="C0B in two blocks"):
        write_etalon(blocks)
