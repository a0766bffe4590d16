"""Token writer for `save` (docs/design.md §4): only value tokens change, atomically."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from geo_server.listfile import apply_changes, load_machine, parse_list, rewrite_values

AXIS_LF = (
    "# Axis X\n"
    "kopf.achs_nr 1\n"
    "lr_param.temp_comp 1\n"
    "lr_param.temp_comp_position_0 100 [0.1µm]\n"
    "lr_param.temp_comp_offset_0    40    [0.1µm]\n"
    "lr_param.temp_comp_coefficient 4000 [µm/m]\n"
    "lr_param. n_backlash_cyc 10 #Number of filter cycles\n"
    'kopf.log_achs_name "X AXIS" (name)\n'
)


def test_changes_only_the_value_token_lf() -> None:
    out = apply_changes(AXIS_LF, {"lr_param.temp_comp_coefficient": "-12.5"})
    assert out == AXIS_LF.replace("coefficient 4000 [", "coefficient -12.5 [")


def test_changes_only_the_value_token_crlf() -> None:
    crlf = AXIS_LF.replace("\n", "\r\n")
    out = apply_changes(crlf, {"lr_param.temp_comp_offset_0": "-7", "lr_param.temp_comp": "0"})
    expected = crlf.replace("offset_0    40    [", "offset_0    -7    [").replace(
        "lr_param.temp_comp 1\r\n", "lr_param.temp_comp 0\r\n"
    )
    assert out == expected


def test_unchanged_when_no_changes() -> None:
    assert apply_changes(AXIS_LF, {}) == AXIS_LF
    assert apply_changes(AXIS_LF, []) == AXIS_LF


def test_name_with_blank_after_dot_and_quoted_string() -> None:
    out = apply_changes(AXIS_LF, {"lr_param.n_backlash_cyc": "5", "kopf.log_achs_name": '"Y AXIS"'})
    assert "lr_param. n_backlash_cyc 5 #Number of filter cycles\n" in out
    assert 'kopf.log_achs_name "Y AXIS" (name)\n' in out
    assert out.count("\n") == AXIS_LF.count("\n")


def test_change_by_line_number() -> None:
    out = apply_changes(AXIS_LF, [(4, "250")])
    assert out == AXIS_LF.replace("position_0 100 [", "position_0 250 [")
    with pytest.raises(KeyError):
        apply_changes(AXIS_LF, [(1, "9")])  # a comment line holds no entry


def test_case_insensitive_first_segment() -> None:
    out = apply_changes("Kw.crosstalk.n_cycles 5\n", {"kw.crosstalk.n_cycles": "7"})
    assert out == "Kw.crosstalk.n_cycles 7\n"


def test_duplicate_entry_changes_the_last() -> None:
    text = "lr_param.temp_comp 1\nlr_param.temp_comp 1\n"
    assert (
        apply_changes(text, {"lr_param.temp_comp": "0"})
        == "lr_param.temp_comp 1\nlr_param.temp_comp 0\n"
    )


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("kopf.achs_nr 1\n", "kopf.achs_nr 1\nlr_param.temp_comp 1\n"),
        ("kopf.achs_nr 1", "kopf.achs_nr 1\nlr_param.temp_comp 1\n"),  # no final newline
        ("kopf.achs_nr 1\r\n", "kopf.achs_nr 1\r\nlr_param.temp_comp 1\r\n"),
        ("kopf.achs_nr 1\nEnd\n# after\n", "kopf.achs_nr 1\nlr_param.temp_comp 1\nEnd\n# after\n"),
        ("kopf.achs_nr 1\r\nEnde\r\n", "kopf.achs_nr 1\r\nlr_param.temp_comp 1\r\nEnde\r\n"),
        ("", "lr_param.temp_comp 1\n"),
    ],
)
def test_missing_entry_is_appended(text: str, expected: str) -> None:
    assert apply_changes(text, {"lr_param.temp_comp": "1"}) == expected


def test_rewrite_file_keeps_every_other_byte(tmp_path: Path) -> None:
    p = tmp_path / "achsmd1.lis"
    original = AXIS_LF.replace("\n", "\r\n").encode("utf-8")
    p.write_bytes(original)
    rewrite_values(p, {"lr_param.temp_comp_coefficient": "3999.5"})
    assert p.read_bytes() == original.replace(b"coefficient 4000 ", b"coefficient 3999.5 ")
    assert [f.name for f in tmp_path.iterdir()] == ["achsmd1.lis"]


def test_rewrite_keeps_cp1252_encoding(tmp_path: Path) -> None:
    p = tmp_path / "w.lis"
    p.write_bytes(b"lr_param.temp_comp_position_0 100 [0.1\xb5m]\n")
    rewrite_values(p, {"lr_param.temp_comp_position_0": "-3"})
    assert p.read_bytes() == b"lr_param.temp_comp_position_0 -3 [0.1\xb5m]\n"


def test_rewrite_keeps_utf8_bom(tmp_path: Path) -> None:
    p = tmp_path / "b.lis"
    p.write_bytes(b"\xef\xbb\xbfkw.ssfk.unit 1\n")
    rewrite_values(p, {"kw.ssfk.unit": "0"})
    assert p.read_bytes() == b"\xef\xbb\xbfkw.ssfk.unit 0\n"


def test_rewritten_file_loads_with_new_value(tmp_path: Path) -> None:
    (tmp_path / "md1.lis").write_text(AXIS_LF, encoding="utf-8")
    (tmp_path / "h.lis").write_text("achs_mds[0] md1.lis\n")
    rewrite_values(tmp_path / "md1.lis", {"lr_param.temp_comp_coefficient": "12.25"})
    cfg = load_machine(tmp_path / "h.lis")
    assert cfg.axes[1].params.temp_comp_coefficient == 12.25
    assert cfg.axes[1].params.sources["lr_param.temp_comp_coefficient"].line == 6
    assert [e.name for e in parse_list(tmp_path / "md1.lis").entries][-1] == "kopf.log_achs_name"


@pytest.mark.parametrize("fail_at", ["replace", "fsync", "write"])
def test_crash_leaves_old_file_and_no_temp(tmp_path: Path, monkeypatch, fail_at: str) -> None:
    p = tmp_path / "achsmd1.lis"
    p.write_bytes(AXIS_LF.encode("utf-8"))

    def boom(*args, **kwargs):
        raise OSError("simulated crash")

    if fail_at == "replace":
        monkeypatch.setattr(os, "replace", boom)
    elif fail_at == "fsync":
        monkeypatch.setattr(os, "fsync", boom)
    else:
        real_fdopen = os.fdopen
        monkeypatch.setattr(os, "fdopen", lambda fd, mode: _HalfWriter(real_fdopen(fd, mode)))
    with pytest.raises(OSError, match="simulated crash"):
        rewrite_values(p, {"lr_param.temp_comp_coefficient": "1"})
    assert p.read_bytes() == AXIS_LF.encode("utf-8")
    assert [f.name for f in tmp_path.iterdir()] == ["achsmd1.lis"]


class _HalfWriter:
    """A temporary file that dies after writing half of the data."""

    def __init__(self, fh) -> None:
        self.fh = fh

    def __enter__(self) -> _HalfWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.fh.close()

    def write(self, data: bytes) -> int:
        self.fh.write(data[: len(data) // 2])
        raise OSError("simulated crash")


def test_file_mode_is_kept(tmp_path: Path) -> None:
    p = tmp_path / "m.lis"
    p.write_text("kw.ssfk.unit 1\n")
    p.chmod(0o640)
    rewrite_values(p, {"kw.ssfk.unit": "0"})
    assert p.stat().st_mode & 0o777 == 0o640
