"""List-file syntax (002/003 §1.3–1.4, 002 §1.3): one test per rule."""

from __future__ import annotations

import pytest

from geo_server.listfile import parse_list, parse_text
from geo_server.listfile.schema import ListKind, convert, lookup
from geo_server.model import CompKind


def one(line: str):
    parsed = parse_text(line + "\n", "t.lis")
    assert len(parsed.entries) == 1, parsed
    return parsed.entries[0]


@pytest.mark.parametrize(
    "line",
    ["# comment", "#", "#...", "#…", "# End", "# ****************", "   # indented"],
)
def test_full_line_comments_are_ignored(line: str) -> None:
    parsed = parse_text(line + "\nkw.ssfk.unit 1\n")
    assert [e.name for e in parsed.entries] == ["kw.ssfk.unit"]
    assert parsed.warnings == []
    assert parsed.end_line == 0


@pytest.mark.parametrize(
    ("line", "value"),
    [
        ("dummy[1] 1 Comment", "1"),  # 002 §1.4
        ("dummy[2] 1 # Comment", "1"),
        ("getriebe[0].lose 1000 #0,1 µm backlash", "1000"),  # 000 p.13
        ("dummy[3] 1 ( Comment", "1"),
        ("dummy[4] 1 /* Comment", "1"),
        ("kw.crosscomp.last_index 99  /*Last valid index of the table*/", "99"),
        ("lr_param.temp_comp_position_0 100 [0.1µm]", "100"),  # 000 p.24
        ("kw.crosstalk.acceleration 10000 ( mm/s^2)", "10000"),  # 000 p.91
        ("kw.crosscomp2.start_position_master1            -400000    /* -40 mm */", "-400000"),
    ],
)
def test_comment_after_numeric_value(line: str, value: str) -> None:
    assert one(line).value == value


@pytest.mark.parametrize(
    ("line", "value"),
    [
        ("kopf.log_achs_name Y AXIS", "Y AXIS"),  # 000 p.62: a string may hold blanks
        ("kopf.log_achs_name Y-ACHSE   ", "Y-ACHSE"),  # trailing blanks removed
        ("kopf.log_achs_name STRING_1 (comment requires a '(' bracket!)", "STRING_1"),
        ("kopf.log_achs_name A#1 /*x", "A#1 /*x"),  # only ( opens a comment after a string
        ("achs_kw[0] ..\\listen\\achskw1.lis", "..\\listen\\achskw1.lis"),  # 000 p.26
    ],
)
def test_string_value_runs_up_to_bracket(line: str, value: str) -> None:
    assert one(line).value == value


@pytest.mark.parametrize(
    ("line", "value"),
    [
        (
            "kopf.log_achs_name ″STRING_WITH_COMMENT( # /*)_CHARACTERS″",
            "STRING_WITH_COMMENT( # /*)_CHARACTERS",
        ),
        ("kopf.log_achs_name ″STRING_WITH_POST_SPACES ″", "STRING_WITH_POST_SPACES"),
        ('kopf.log_achs_name "X (1)" (comment)', "X (1)"),
        ("kopf.log_achs_name “Y AXIS”", "Y AXIS"),
        ("kopf.log_achs_name″ STRING_(2)″ (comment requires a '(' bracket!)", " STRING_(2)"),
    ],
)
def test_quoted_strings(line: str, value: str) -> None:
    assert one(line).value == value


@pytest.mark.parametrize(
    ("text", "value"),
    [("0", False), ("1", True), ("TRUE", True), ("FALSE", False), ("true", True), ("False", False)],
)
def test_boolean_values(text: str, value: bool) -> None:
    spec = lookup(ListKind.COMP, "kw.crosstalk.velocity_dependent")
    assert spec is not None
    assert convert(spec, one(f"kw.crosstalk.velocity_dependent {text}").value) is value


@pytest.mark.parametrize("text", ["2", "yes", "-1"])
def test_boolean_rejects_other_values(text: str) -> None:
    spec = lookup(ListKind.AXIS, "lr_param.temp_comp")
    assert spec is not None
    with pytest.raises(ValueError):
        convert(spec, text)


@pytest.mark.parametrize(
    ("line", "name", "indices"),
    [
        (
            "kw.crosscomp2.table[ 0][ 1].correction -1",
            "kw.crosscomp2.table[0][1].correction",
            (0, 1),
        ),
        (
            "kw.crosscomp2.table[200][ 71].correction 45",
            "kw.crosscomp2.table[200][71].correction",
            (200, 71),
        ),
        (
            "kw.crosscomp2.table[ 20][1000].correction 49",
            "kw.crosscomp2.table[20][1000].correction",
            (20, 1000),
        ),
    ],
)
def test_blanks_inside_brackets(line: str, name: str, indices: tuple[int, ...]) -> None:
    e = one(line)
    assert (e.name, e.indices, e.base) == (name, indices, "kw.crosscomp2.table[][].correction")


@pytest.mark.parametrize("word", ["End", "Ende", "END", "ende"])
def test_end_stops_the_list(word: str) -> None:
    parsed = parse_text(f"kw.ssfk.unit 1\n{word}\nkw.ssfk.modulo 1\n")
    assert [e.name for e in parsed.entries] == ["kw.ssfk.unit"]
    assert parsed.end_line == 2


def test_first_name_segment_is_case_insensitive() -> None:
    e = one("Kw.crosstalk.position[0].correction_decelerate_dir_pos 50")  # 000 p.92
    assert e.name == "kw.crosstalk.position[0].correction_decelerate_dir_pos"


def test_blank_after_dot_accepted_with_warning() -> None:
    parsed = parse_text("lr_param. n_backlash_cyc 10 #Number of filter cycles\n", "a.lis")
    assert [(e.name, e.value) for e in parsed.entries] == [("lr_param.n_backlash_cyc", "10")]
    (w,) = parsed.warnings
    assert (w.severity, w.file, w.line, w.entry) == (
        "warning",
        "a.lis",
        1,
        "lr_param.n_backlash_cyc",
    )


@pytest.mark.parametrize("line", [":", "::", "...", "…", "etc.", "etc"])
def test_elision_lines_are_ignored(line: str) -> None:
    parsed = parse_text(f"kw.ssfk.unit 1\n{line}\nkw.ssfk.modulo 1\n")
    assert [e.name for e in parsed.entries] == ["kw.ssfk.unit", "kw.ssfk.modulo"]
    assert parsed.warnings == []


def test_blank_lines_are_ignored() -> None:
    assert len(parse_text("\n   \nkw.ssfk.unit 1\n\n").entries) == 1


def test_entry_keeps_name_indices_span_file_and_line() -> None:
    text = "# head\nkw.ssfk.table[3].pos      -102  /* c */\n"
    (e,) = parse_text(text, "x.lis").entries
    assert (e.name, e.indices, e.raw, e.file, e.line) == (
        "kw.ssfk.table[3].pos",
        (3,),
        "-102",
        "x.lis",
        2,
    )
    assert e.span == (26, 30)


def test_quoted_span_includes_the_quotes() -> None:
    e = one('kopf.log_achs_name "Y AXIS " (c)')
    assert e.span == (19, 28)
    assert e.raw == '"Y AXIS "'


@pytest.mark.parametrize(
    ("text", "mask"),
    [
        ("LEAD | CROSS", CompKind.LEAD | CompKind.CROSS),  # 000 p.98
        ("backlash|temp", CompKind.BACKLASH | CompKind.TEMP),
        ("0x1A", CompKind.LEAD | CompKind.CROSS | CompKind.PLANE),
        ("3", CompKind.BACKLASH | CompKind.LEAD),
    ],
)
def test_symbolic_and_numeric_masks(text: str, mask: CompKind) -> None:
    e = one(f"lr_param.prog_movement_requires_compensations {text} # comment")
    spec = lookup(ListKind.AXIS, e.base)
    assert spec is not None
    assert e.value == text
    assert convert(spec, e.value) == mask


@pytest.mark.parametrize("text", ["LEAD | FOO", "0x100", "-1"])
def test_bad_masks_are_defective(text: str) -> None:
    spec = lookup(ListKind.AXIS, "lr_param.prog_movement_requires_compensations")
    assert spec is not None
    with pytest.raises(ValueError):
        convert(spec, text)


@pytest.mark.parametrize(
    ("type_entry", "text"),
    [
        ("kw.ssfk.kw_nr_max", "abc"),
        ("kw.ssfk.kw_nr_max", "1.5"),
        ("lr_param.temp_comp_coefficient", "x1"),
    ],
)
def test_numeric_parse_failure_raises(type_entry: str, text: str) -> None:
    spec = lookup(ListKind.COMP, type_entry) or lookup(ListKind.AXIS, type_entry)
    assert spec is not None
    with pytest.raises(ValueError):
        convert(spec, text)


def test_real64_and_hex_integers() -> None:
    coeff = lookup(ListKind.AXIS, "lr_param.temp_comp_coefficient")
    nr = lookup(ListKind.COMP, "kw.ssfk.kw_nr_max")
    assert coeff is not None and nr is not None
    assert convert(coeff, "-12.5e2") == -1250.0
    assert convert(nr, "0x10") == 16


def test_malformed_line_warns() -> None:
    parsed = parse_text("N10 G01 X10\n= 5\n", "m.lis")
    assert len(parsed.entries) == 1  # `N10 G01` looks like an entry (unknown later)
    assert [(w.line, w.file) for w in parsed.warnings] == [(2, "m.lis")]


def test_name_without_value_warns() -> None:
    parsed = parse_text("kw.ssfk.unit\n")
    assert parsed.entries == []
    assert parsed.warnings[0].entry == "kw.ssfk.unit"


def test_utf8_file(tmp_path) -> None:
    p = tmp_path / "u.lis"
    p.write_bytes("kopf.log_achs_name Z # µ\nkw.ssfk.unit 1 [0.1µm]\n".encode())
    parsed = parse_list(p)
    assert parsed.encoding == "utf-8"
    assert [e.value for e in parsed.entries] == ["Z # µ", "1"]


def test_cp1252_fallback(tmp_path) -> None:
    p = tmp_path / "w.lis"
    p.write_bytes(b"kw.ssfk.unit 1 [0.1\xb5m]\r\nkopf.log_achs_name \xc4CHSE\r\n")
    parsed = parse_list(p)
    assert parsed.encoding == "cp1252"
    assert [e.value for e in parsed.entries] == ["1", "ÄCHSE"]
    assert parsed.entries[1].line == 2


def test_text_after_closing_quote_warns() -> None:
    # 002 §1.4: after a string only `( comment` is a comment
    parsed = parse_text('kopf.log_achs_name "A B"extra (c)\n', "q.lis")
    assert parsed.entries[0].value == "A B"
    [w] = parsed.warnings
    assert (w.file, w.line, w.entry) == ("q.lis", 1, "kopf.log_achs_name")
    assert "'extra (c)'" in w.message
    # a `(` comment after the quote is fine
    assert parse_text('kopf.log_achs_name "A B" (c)\n').warnings == []
