"""List files a careless user or an attacker may hand the server, and how they are met.

* undecodable content (binary, NUL bytes, UTF-16 with or without BOM) and lists of which
  nothing can be read are refused whole, naming the file (and line); a reload keeps the
  running machine;
* CR-only and CRLF line ends read like LF, and `save` keeps them;
* a FIFO, a folder, a device or a socket named as a list is refused without opening it;
  files beyond `MAX_LIST_BYTES` are refused;
* `save` into a list replaced by a UTF-16/binary file since loading leaves it untouched;
* `init` into a full disk or a read-only folder: one error line, no half-copied files;
* orphan temporary files of a killed `save` are removed, and nothing else.

Expected values are typed from the default machine's lists (`lists/achsmd1.lis`:
`getriebe[0].lose 1000`, `lr_param.temp_comp_coefficient 4000` at line 32).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import errno
import os
import random
import shutil
import socket
import stat
import tempfile
from pathlib import Path

import pytest

import geo_server.listfile.syntax as syntax
from geo_server import access
from geo_server.cli import main
from geo_server.listfile import (
    MAX_LIST_BYTES,
    ListFileError,
    NotAListFileError,
    apply_changes,
    load_machine,
    parse_list,
    remove_orphan_temps,
    rewrite_values,
)
from geo_server.listfile.writer import TEMP_SUFFIX, temp_prefix
from geo_server.machine.machine import Machine
from geo_server.service import ObjectService

SAVE_AS_TEXT = "save it as ASCII/UTF-8"
UTF16_BOM = f"not a list file: UTF-16 text (byte order mark) — {SAVE_AS_TEXT}"
NUL = f"not a list file: contains NUL bytes (UTF-16?) — {SAVE_AS_TEXT}"
NOTHING = "not an axis parameter list: none of its lines is an entry of one"


def _axis_list(startup: Path) -> Path:
    return startup.parent / "achsmd1.lis"


def _utf16(text: str, codec: str) -> bytes:
    return text.encode(codec)


def _lf_text(startup: Path) -> str:
    return _axis_list(startup).read_text(encoding="utf-8")


# ----------------------------------------------------------------- undecodable / empty


#: (replacement bytes of achsmd1.lis given its LF text, ListFileError line, message)
BAD_AXIS_LISTS = {
    "empty": (lambda t: b"", 0, f"{NOTHING} (the file is empty or all comments)"),
    "comments only": (lambda t: b"# X\n#\n", 0, f"{NOTHING} (the file is empty or all comments)"),
    "random binary": (lambda t: random.Random(7).randbytes(4096), None, None),
    "utf-16 with bom": (lambda t: _utf16(t, "utf-16"), 1, UTF16_BOM),
    "utf-16-le without bom": (lambda t: _utf16(t, "utf-16-le"), 1, NUL),
    "utf-16-be without bom": (lambda t: _utf16(t, "utf-16-be"), 1, NUL),
    "nul on line 3": (lambda t: b"kopf.achs_nr 1\n#\nsim.homed 0\x00\n", 3, NUL),
    "neither utf-8 nor cp1252": (
        lambda t: b"kopf.achs_nr 1\r\nkopf.log_achs_name X\x81\r\n",
        2,
        f"not a list file: byte 0x81 is neither UTF-8 nor Windows-1252 text — {SAVE_AS_TEXT}",
    ),
    "control character, cr-only lines": (
        lambda t: b"kopf.achs_nr 1\r#\rsim.homed 0\x1b\r",
        3,
        "not a list file: control character 0x1B (binary data?)",
    ),
    "all garbage text": (
        lambda t: b"lorem ipsum\nfoo.bar 3\n= = =\n",
        0,
        f"{NOTHING} (unknown names or malformed lines from line 1 on)",
    ),
    "a compensation value list": (
        lambda t: b"# header\nkw.ssfk.interval 100\nkw.ssfk.kw_nr_max 2\n",
        0,
        f"{NOTHING}; they are entries of a compensation value list (the first at line 2)",
    ),
}


@pytest.mark.parametrize("case", list(BAD_AXIS_LISTS))
def test_undecodable_or_empty_axis_list_is_refused(lists_copy: Path, case: str) -> None:
    content, line, message = BAD_AXIS_LISTS[case]
    axis_list = _axis_list(lists_copy)
    axis_list.write_bytes(content(_lf_text(lists_copy)))
    with pytest.raises(ListFileError) as info:
        load_machine(lists_copy)
    err = info.value
    assert err.path == str(axis_list)
    if message is None:  # random bytes: refused as one of the "not text" kinds
        assert err.message.startswith("not a list file: ")
        assert err.line >= 1
    else:
        assert (err.line, err.message) == (line, message)
        where = f"{axis_list}:{line}" if line else str(axis_list)
        assert str(err) == f"{where}: {message}"


def test_random_binary_is_refused_at_its_first_nul(lists_copy: Path) -> None:
    data = random.Random(7).randbytes(4096)
    nul = data.index(b"\x00")
    axis_list = _axis_list(lists_copy)
    axis_list.write_bytes(data)
    with pytest.raises(ListFileError) as info:
        load_machine(lists_copy)
    lf = data[:nul].count(b"\n") + data[:nul].count(b"\r") - data[:nul].count(b"\r\n")
    assert (info.value.line, info.value.message) == (lf + 1, NUL)


def test_empty_compensation_list_is_refused(lists_copy: Path) -> None:
    comp = lists_copy.parent / "achskw2.lis"
    comp.write_bytes(b"")
    with pytest.raises(ListFileError) as info:
        load_machine(lists_copy)
    assert info.value.path == str(comp)
    assert info.value.message == (
        "not a compensation value list: none of its lines is an entry of one "
        "(the file is empty or all comments)"
    )


def test_empty_startup_list_is_refused(tmp_path: Path) -> None:
    startup = tmp_path / "hochlauf.lis"
    startup.write_bytes(b"garbage here\n")
    with pytest.raises(ListFileError) as info:
        load_machine(startup)
    assert str(info.value) == (
        f"{startup}: no axes: not a start-up list: none of its lines is an entry of one "
        "(unknown names or malformed lines from line 1 on)"
    )


def test_parse_list_raises_an_oserror_naming_the_line(tmp_path: Path) -> None:
    p = tmp_path / "x.lis"
    p.write_bytes("kopf.achs_nr 1\n".encode("utf-16"))
    with pytest.raises(NotAListFileError) as info:
        parse_list(p)
    assert isinstance(info.value, OSError)
    assert (info.value.filename, info.value.line, str(info.value)) == (str(p), 1, UTF16_BOM)


# ----------------------------------------------------------------- reload keeps the machine


def _service(startup: Path) -> ObjectService:
    svc = ObjectService(Machine(load_machine(startup), homed=True))
    access.step(svc, 3)
    return svc


def _axis_1_values(svc: ObjectService) -> tuple[object, ...]:
    return tuple(
        access.read_name(svc, name, 1)
        for name in ("TEMPC::coefficient", "TEMPC::offset_0", "BC::conf. backlash")
    )


@pytest.mark.parametrize(
    ("case", "reason"),
    [
        ("empty", "none of its lines is an entry of one"),
        ("random binary", "not a list file: "),
        ("utf-16 with bom", UTF16_BOM),
        ("utf-16-le without bom", NUL),
    ],
)
def test_rejected_reload_keeps_the_running_values(lists_copy: Path, case: str, reason: str):
    svc = _service(lists_copy)
    cfg_before = svc.info.config
    assert _axis_1_values(svc) == (4000.0, 40, 1000)
    axis_list = _axis_list(lists_copy)
    axis_list.write_bytes(BAD_AXIS_LISTS[case][0](_lf_text(lists_copy)))
    result = svc.commands.reload()
    assert not result.ok
    [error] = result.errors
    assert error.startswith(str(axis_list)) and reason in error
    assert svc.info.config is cfg_before
    access.step(svc, 3)
    assert _axis_1_values(svc) == (4000.0, 40, 1000)


# ----------------------------------------------------------------- line ends


def _entries(path: Path) -> list[tuple[str, str, int]]:
    return [(e.name, e.value, e.line) for e in parse_list(path).entries]


def _convert_machine(startup: Path, eol: str) -> None:
    for p in startup.parent.glob("*.lis"):
        p.write_bytes(p.read_bytes().replace(b"\n", eol.encode()))


def _summary(startup: Path) -> tuple[object, ...]:
    cfg = load_machine(startup)
    diags = [(Path(d.file).name, d.line, d.entry, d.message) for d in cfg.diagnostics]
    p = cfg.axes[1].params
    return (
        sorted(cfg.axes),
        diags,
        (p.lose, p.temp_comp_coefficient, p.temp_comp_offset_0, p.ssfk),
        p.sources["lr_param.temp_comp_coefficient"].line,
        cfg.axes[2].comp.lsec.neg.tolist(),
    )


@pytest.mark.parametrize("eol", ["\r", "\r\n"])
def test_cr_and_crlf_lists_read_like_lf(lists_copy: Path, tmp_path: Path, eol: str) -> None:
    lf = tmp_path / "lf"
    shutil.copytree(lists_copy.parent, lf)
    _convert_machine(lists_copy, eol)
    assert b"\n" not in _axis_list(lists_copy).read_bytes() or eol == "\r\n"
    assert _entries(_axis_list(lists_copy)) == _entries(lf / "achsmd1.lis")
    assert len(_entries(_axis_list(lists_copy))) == 20
    expected = _summary(lf / "hochlauf.lis")
    assert _summary(lists_copy) == expected
    assert expected[2:4] == ((1000, 4000.0, 40, True), 32)


def test_mixed_line_ends_count_lines_like_an_editor() -> None:
    text = "kopf.achs_nr 1\rsim.homed 1\r\nkopf.log_achs_name X\nsim.start_position 5"
    parsed = syntax.parse_text(text, "m.lis")
    assert [(e.name, e.value, e.line) for e in parsed.entries] == [
        ("kopf.achs_nr", "1", 1),
        ("sim.homed", "1", 2),
        ("kopf.log_achs_name", "X", 3),
        ("sim.start_position", "5", 4),
    ]


def test_check_reads_a_cr_only_machine(lists_copy: Path, capsys) -> None:
    _convert_machine(lists_copy, "\r")
    assert main(["check", str(lists_copy)]) == 0
    out = capsys.readouterr().out
    assert out == (
        f"{lists_copy}: 4 axes (1=X, 2=Y, 3=Z, 4=C), 0 diagnostics, "
        "0 compensations deactivated, 0 errors\n"
    )
    assert load_machine(lists_copy).axes[1].params.temp_comp_coefficient == 4000.0


def test_check_refuses_a_utf16_list_with_exit_2(lists_copy: Path, capsys) -> None:
    axis_list = _axis_list(lists_copy)
    axis_list.write_bytes(_lf_text(lists_copy).encode("utf-16"))
    assert main(["check", str(lists_copy)]) == 2
    out, err = capsys.readouterr()
    assert (out, err) == ("", f"error: {axis_list}:1: {UTF16_BOM}\n")


@pytest.mark.parametrize("eol", ["\r", "\r\n", "\n"])
def test_save_keeps_the_line_ends(tmp_path: Path, eol: str) -> None:
    p = tmp_path / "a.lis"
    lines = ["kopf.achs_nr 1", "lr_param.temp_comp_coefficient 4000 [µm/m]", "# End"]
    p.write_bytes(eol.join(lines).encode())  # no line end after the last line
    rewrite_values(p, {"lr_param.temp_comp_coefficient": "12.5", "sim.homed": "1"})
    assert p.read_bytes() == eol.join(
        [
            "kopf.achs_nr 1",
            "lr_param.temp_comp_coefficient 12.5 [µm/m]",
            "# End",
            "sim.homed 1",
            "",
        ]
    ).encode("utf-8")


def test_apply_changes_inserts_before_end_with_cr() -> None:
    text = "kopf.achs_nr 1\rEnd\r"
    assert apply_changes(text, {"sim.homed": "1"}) == "kopf.achs_nr 1\rsim.homed 1\rEnd\r"


# ----------------------------------------------------------------- misspelled names


@pytest.mark.parametrize(
    ("file", "line", "message"),
    [
        (
            "achsmd1.lis",
            "lr_param.temp_comp_coefficent 12",
            "unknown entry in the axis parameter list: ignored; "
            "did you mean lr_param.temp_comp_coefficient?",
        ),
        (
            "achsmd1.lis",
            "Lr_parm.ssfk 1",
            "unknown entry in the axis parameter list: ignored; did you mean lr_param.ssfk?",
        ),
        (
            "achskw1.lis",
            "kw.ssfk.tabel[3].pos 5",
            "unknown entry in the compensation value list: ignored; "
            "did you mean kw.ssfk.table[3].pos?",
        ),
        (
            "achsmd1.lis",
            "kw.ssfk.interval 100",
            "unknown entry in the axis parameter list: ignored "
            "(an entry of the compensation value list)",
        ),
        (
            "achsmd1.lis",
            "completely.different 1",
            "unknown entry in the axis parameter list: ignored",
        ),
    ],
)
def test_unknown_entry_names_the_nearest_known_one(
    lists_copy: Path, file: str, line: str, message: str
) -> None:
    p = lists_copy.parent / file
    text = p.read_text(encoding="utf-8")
    p.write_text(f"{line}\n{text}", encoding="utf-8")
    [d] = load_machine(lists_copy).diagnostics
    assert (Path(d.file).name, d.line, d.severity, d.message) == (file, 1, "warning", message)


# ----------------------------------------------------------------- non-regular files


def _named_as_axis_list(startup: Path, target: Path) -> None:
    text = startup.read_text(encoding="utf-8")
    startup.write_text(text.replace("achs_mds[0] achsmd1.lis", f"achs_mds[0] {target}"))


def _load_in_thread(startup: Path, unblock: Path | None = None) -> ListFileError:
    """load_machine in a worker with a bound; a reader stuck on a FIFO is set free."""
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        fut = pool.submit(load_machine, startup)
        try:
            fut.result(timeout=10)
        except ListFileError as exc:
            return exc
        except concurrent.futures.TimeoutError:
            if unblock is not None:  # a writer that closes at once gives the reader EOF
                with contextlib.suppress(OSError):
                    os.close(os.open(unblock, os.O_WRONLY | os.O_NONBLOCK))
            pytest.fail("load_machine blocked on a non-regular file")
    pytest.fail("load_machine accepted a non-regular file")


@pytest.mark.timeout(30)
def test_fifo_named_as_axis_list_is_refused_at_once(lists_copy: Path) -> None:
    fifo = lists_copy.parent / "fifo.lis"
    os.mkfifo(fifo)
    _named_as_axis_list(lists_copy, fifo)
    err = _load_in_thread(lists_copy, unblock=fifo)
    assert (err.path, err.line, err.message) == (str(fifo), 0, "is a FIFO, not a regular file")


@pytest.mark.timeout(30)
def test_fifo_replacing_an_axis_list_fails_the_reload(lists_copy: Path) -> None:
    svc = _service(lists_copy)
    axis_list = _axis_list(lists_copy)
    axis_list.unlink()
    os.mkfifo(axis_list)
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        fut = pool.submit(svc.commands.reload)
        try:
            result = fut.result(timeout=10)
        except concurrent.futures.TimeoutError:
            with contextlib.suppress(OSError):
                os.close(os.open(axis_list, os.O_WRONLY | os.O_NONBLOCK))
            pytest.fail("reload blocked on a FIFO")
    assert not result.ok
    assert result.errors == [f"{axis_list}: is a FIFO, not a regular file"]
    assert _axis_1_values(svc) == (4000.0, 40, 1000)


@pytest.mark.timeout(30)
@pytest.mark.parametrize("kind", ["directory", "character device", "socket"])
def test_other_non_regular_files_are_refused(lists_copy: Path, kind: str) -> None:
    with contextlib.ExitStack() as stack:
        if kind == "directory":
            target = lists_copy.parent / "folder.lis"
            target.mkdir()
        elif kind == "character device":
            target = Path("/dev/null")  # not /dev/zero: a regression would fill the memory
            if not target.exists():
                pytest.skip("no /dev/null")
        else:
            target = lists_copy.parent / "s.lis"
            if len(str(target)) > 100:
                pytest.skip("folder path too long for a unix socket")
            sock = stack.enter_context(socket.socket(socket.AF_UNIX, socket.SOCK_STREAM))
            sock.bind(str(target))
        _named_as_axis_list(lists_copy, target)
        err = _load_in_thread(lists_copy)
    assert (err.path, err.message) == (str(target), f"is a {kind}, not a regular file")


def test_a_list_beyond_the_size_bound_is_refused_unread(lists_copy: Path) -> None:
    assert MAX_LIST_BYTES == 64 * 2**20
    axis_list = _axis_list(lists_copy)
    with axis_list.open("r+b") as fh:  # sparse: costs no disk
        fh.truncate(MAX_LIST_BYTES + 1)
    with pytest.raises(ListFileError) as info:
        load_machine(lists_copy)
    assert (info.value.path, info.value.message) == (
        str(axis_list),
        "not a list file: larger than 67108864 bytes (64 MiB)",
    )


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="no /proc")
def test_size_bound_caps_the_read_itself(tmp_path: Path, monkeypatch) -> None:
    # a /proc file is a regular file of size 0 that reads as more: only the read can tell
    maps = Path("/proc/self/maps")
    startup = tmp_path / "hochlauf.lis"
    startup.write_text(f"achs_mds[0] {maps}\n")
    monkeypatch.setattr(syntax, "MAX_LIST_BYTES", 100)
    with pytest.raises(ListFileError) as info:
        load_machine(startup)
    assert (info.value.path, info.value.message) == (
        str(maps),
        "not a list file: larger than 100 bytes",
    )


# ----------------------------------------------------------------- save into a replaced file


@pytest.mark.parametrize(
    ("codec", "message"), [("utf-16", UTF16_BOM), ("utf-16-le", NUL), ("binary", NUL)]
)
def test_rewrite_refuses_a_file_replaced_by_utf16_or_binary(
    tmp_path: Path, codec: str, message: str
) -> None:
    p = tmp_path / "achsmd1.lis"
    text = "kopf.achs_nr 1\nlr_param.temp_comp_coefficient 4000\n"
    p.write_bytes(b"\x00\x01\x02" * 50 if codec == "binary" else text.encode(codec))
    before = p.read_bytes()
    with pytest.raises(NotAListFileError) as info:
        rewrite_values(p, {"lr_param.temp_comp_coefficient": "1"})
    assert isinstance(info.value, OSError)
    assert (info.value.filename, str(info.value)) == (str(p), message)
    assert p.read_bytes() == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["achsmd1.lis"]


def test_save_into_a_list_replaced_by_utf16_reports_it(lists_copy: Path) -> None:
    svc = _service(lists_copy)
    axis_list = _axis_list(lists_copy)
    axis_list.write_bytes(_lf_text(lists_copy).encode("utf-16"))
    before = axis_list.read_bytes()
    access.write_name(svc, "TEMPC::coefficient", 1, 1234.5)
    access.step(svc, 1)
    result = svc.commands.save()
    assert not result.ok
    assert result.files == []
    assert result.errors == [f"{axis_list}: {UTF16_BOM}"]
    assert axis_list.read_bytes() == before
    assert [p.name for p in lists_copy.parent.iterdir() if p.name.endswith(".tmp")] == []


# ----------------------------------------------------------------- init failures


def _copy_then_fill_the_disk(monkeypatch, good: int = 2) -> list[str]:
    """shutil.copyfile copies `good` files, then writes half a file and finds the disk full."""
    real = shutil.copyfile
    done: list[str] = []

    def copyfile(src, dst, *args, **kwargs):
        if len(done) >= good:
            Path(dst).write_bytes(Path(src).read_bytes()[:10])
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(dst))
        done.append(Path(src).name)
        return real(src, dst, *args, **kwargs)

    monkeypatch.setattr(shutil, "copyfile", copyfile)
    return done


def test_init_on_a_full_disk_leaves_nothing(tmp_path: Path, monkeypatch, capsys) -> None:
    dest = tmp_path / "new" / "machine"
    done = _copy_then_fill_the_disk(monkeypatch)
    assert main(["init", str(dest)]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err == f"error: cannot copy the default machine to {dest}: No space left on device\n"
    assert len(done) == 2
    assert list(tmp_path.iterdir()) == []  # the folders init created are gone too


def test_init_force_on_a_full_disk_keeps_the_old_files(tmp_path: Path, monkeypatch, capsys) -> None:
    dest = tmp_path / "machine"
    assert main(["init", str(dest)]) == 0
    capsys.readouterr()
    (dest / "achskw1.lis").write_text("# mine\n")
    before = {p.name: p.read_bytes() for p in dest.iterdir()}
    _copy_then_fill_the_disk(monkeypatch)
    assert main(["init", "--force", str(dest)]) == 2
    assert capsys.readouterr().err == (
        f"error: cannot copy the default machine to {dest}: No space left on device\n"
    )
    assert {p.name: p.read_bytes() for p in dest.iterdir()} == before


def test_init_copies_have_the_mode_of_a_new_file(tmp_path: Path, capsys) -> None:
    # copied through temporary names, the lists still get the mode any new file gets
    dest = tmp_path / "machine"
    assert main(["init", str(dest)]) == 0
    probe = tmp_path / "probe"
    probe.touch()
    modes = {stat.S_IMODE(p.stat().st_mode) for p in dest.iterdir()}
    assert modes == {stat.S_IMODE(probe.stat().st_mode)}
    assert len(list(dest.iterdir())) == 11  # 4 + 4 lists, hochlauf.lis, the NC demo, twin.toml


def test_init_below_a_regular_file(tmp_path: Path, capsys) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    dest = blocker / "machine"
    assert main(["init", str(dest)]) == 2
    assert capsys.readouterr().err == (
        f"error: cannot copy the default machine to {dest}: Not a directory\n"
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


@pytest.mark.skipif(
    hasattr(os, "geteuid") and os.geteuid() == 0, reason="root writes into read-only folders"
)
def test_init_into_a_read_only_folder(tmp_path: Path, capsys) -> None:
    dest = tmp_path / "ro"
    dest.mkdir()
    dest.chmod(0o500)
    try:
        assert main(["init", str(dest)]) == 2
        assert capsys.readouterr().err == (
            f"error: cannot copy the default machine to {dest}: Permission denied\n"
        )
        assert list(dest.iterdir()) == []
    finally:
        dest.chmod(0o700)


# ----------------------------------------------------------------- orphan temporary files


def test_remove_orphan_temps_removes_exactly_the_writer_temporaries(tmp_path: Path) -> None:
    a, b, c = (tmp_path / n for n in ("a.lis", "b.lis", "c.lis"))
    for p in (a, b, c):
        p.write_text("kopf.achs_nr 1\n")
    # what a killed write_atomic leaves: mkstemp with the writer's own prefix and suffix
    fd, real_tmp = tempfile.mkstemp(prefix=temp_prefix(b), suffix=TEMP_SUFFIX, dir=tmp_path)
    os.close(fd)
    orphans = [tmp_path / ".a.lis.k3j_x9a2.tmp", Path(real_tmp)]
    keep = [
        ".a.lis.k3j_x9a.tmp",  # 7 random characters
        ".a.lis.k3j_x9a22.tmp",  # 9
        ".a.lis.K3J_X9A2.tmp",  # upper case: not tempfile's
        "a.lis.k3j_x9a2.tmp",  # no leading dot
        ".a.lis.k3j_x9a2.tmp.bak",
        ".a.lis.k3j-x9a2.tmp",
        ".c.lis.k3j_x9a2.tmp",  # c.lis is not one of the lists given
        ".a.lisx.k3j_x9a2.tmp",
        "notes.txt",
    ]
    for p in orphans:
        p.write_text("half")
    for name in keep:
        (tmp_path / name).write_text("keep")
    (tmp_path / ".b.lis.abcdefgh.tmp").mkdir()  # a folder is never removed
    os.symlink(a, tmp_path / ".b.lis.symlink_.tmp")  # nor a link
    os.mkfifo(tmp_path / ".b.lis.fifo_123.tmp")  # nor a FIFO
    removed = remove_orphan_temps([a, str(b), tmp_path / "missing" / "d.lis"])
    assert removed == sorted(orphans)
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted(
        [
            "a.lis",
            "b.lis",
            "c.lis",
            *keep,
            ".b.lis.abcdefgh.tmp",
            ".b.lis.symlink_.tmp",
            ".b.lis.fifo_123.tmp",
        ]
    )
    assert stat.S_ISDIR((tmp_path / ".b.lis.abcdefgh.tmp").stat().st_mode)
    assert a.read_text() == "kopf.achs_nr 1\n"
    assert remove_orphan_temps([a, b]) == []
