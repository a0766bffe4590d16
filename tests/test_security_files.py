"""File names from the network stay inside the machine (issue 30 item 3, docs/security.md
"Files"; docs/volumetric.md §4, §7).

Attacked the way the issue describes, over the real interfaces on loopback: the VOLC
file write `cnc_interpr_vol_comp_file_w` (AMS port 553, index group 0x120100, offset
0x27C) with pyads and as raw ADS bytes on Zenoh's `cnc/<m>/ads/553/…` key, an NC
`#VOLCOMP [ID0 UPDATE]` sent on `cnc/<m>/nc`, and VOLC lists whose `file[0]` names
another file. Every name outside the machine's folders (absolute, `..`, a symbolic link
out, a drive path), and every name a VOLC list cannot be read from (missing, a folder, a
FIFO, a device, not a VOLC list, too large), gets ADS 0x70D and one and the same text;
no answer carries a line of another file; a FIFO never blocks; `/dev/zero` and a sparse
file of a GiB are never read (the traced memory stays far below what one read would
take); the server keeps answering, and reload and save answer afterwards. The machine
runs stepped (nothing runs unless the test steps it).
"""

from __future__ import annotations

import json
import os
import tracemalloc
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyads
import pytest
import zenoh
from conftest import run_in
from support.machines import updates_read
from test_volcomp import add_volc, smooth_files
from test_zenoh_commands import OCTET, Served, get

from geo_server import access
from geo_server.client.ads_client import close_port_first
from geo_server.dictionary import load_dictionary
from geo_server.errors import AdsErrorCode
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.safefile import LIMITS, REFUSED, FileRefused, read_regular
from geo_server.service import ObjectService
from geo_server.transports.ads.server import AdsOptions, AdsServer
from geo_server.volcomp.paramfile import NOT_CSV, NOT_ETALON

pytestmark = [
    pytest.mark.timeout(120),
    pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs and symbolic links"),
]

D = load_dictionary()
COM_GROUP, FILE_W, INDEX_W = 0x120100, 0x27C, 0x27D
#: what a name that is not read is answered with, whatever it names
REFUSAL = f"[990525] volumetric compensation 0: {REFUSED}"
#: ... as SIM::last_error (a STRING(255)) says it after a refused 0x27C write: cut
#: after the last whole word that leaves room for "..." (docs/design.md, strings)
_FULL = f"[990525] volcomp_update failed: {REFUSAL}: {REFUSAL}"
LAST_ERROR = _FULL[: _FULL[:253].rindex(" ")] + "..."
#: the first line of /etc/passwd on any Linux: it must never appear in an answer
SECRET = "root:x:0:0:root:/root:/bin/bash"
JSON = zenoh.Encoding.APPLICATION_JSON
#: the traced Python memory the attacks may add: a read of /dev/zero or of the sparse
#: GiB file would add hundreds of MiB, a read up to the correction file limit 16 MiB
MEMORY_BOUND = 12 << 20


@dataclass
class Rig:
    """A stepped machine with a VOLC compensation 0 (its list `volc0.lis` and
    `exx.csv` in the machine's folder), served over ADS and Zenoh, with clients."""

    folder: Path  # the machine's folder (the start-up list's)
    outside: Path  # a folder not allowed
    allowed: Path  # a folder given at start (`--allow-dir`)
    service: ObjectService
    machine: Machine  # (its NC player: stepped until the worker is done)
    ads: AdsServer
    zenoh: Served
    com: Any  # pyads.Connection to AMS port 553 (the COM task)
    geo: Any  # pyads.Connection to AMS port 551 (the GEO task)

    def write_ads(self, name: str) -> int:
        """0x27C by pyads: the ADS return code (0: done)."""
        try:
            self.com.write(COM_GROUP, FILE_W, name, pyads.PLCTYPE_STRING)
        except pyads.ADSError as exc:
            return int(exc.err_code)
        return 0

    def write_zenoh(self, name: str) -> dict:
        """0x27C as raw ADS bytes on Zenoh: the reply_err body ({} when done)."""
        oks, errs = get(
            self.zenoh.session, "cnc/t/ads/553/0x120100/0x27c", name.encode() + b"\0", OCTET
        )
        assert len(oks) + len(errs) == 1, (oks, errs)
        return errs[0] if errs else {}

    def last_error(self) -> str:
        obj = D.by_name("SIM::last_error")
        return self.geo.read(obj.index_group, obj.index_offset(0), pyads.PLCTYPE_STRING)

    def everything_said(self) -> str:
        """Every text the server published about errors: the error list (Zenoh
        `errors` key, SIM::last_error) in one string."""
        return json.dumps(self.service.errors()) + self.last_error()


@pytest.fixture
def rig(loop_thread, lists_copy: Path, tmp_path: Path) -> Iterator[Rig]:
    folder = lists_copy.parent
    add_volc(lists_copy, smooth_files(folder), {})
    outside, allowed = tmp_path / "outside", tmp_path / "allowed"
    outside.mkdir()
    allowed.mkdir()
    m = Machine(load_machine(lists_copy, [allowed]), cycle_s=0.001, homed=True)
    m.motion.set_position(0, 100 * 10_000)
    svc = ObjectService(m)
    srv = AdsServer(svc, AdsOptions(port=0))
    run_in(loop_thread, srv.start())
    served = Served(loop_thread, svc)
    com = pyads.Connection("127.0.0.9.1.1", 553, srv.address)
    geo = pyads.Connection("127.0.0.9.1.1", 551, srv.address)
    com.open()
    geo.open()
    com.write(COM_GROUP, INDEX_W, 0, pyads.PLCTYPE_UINT)  # the next file write updates ID 0
    try:
        yield Rig(folder, outside, allowed, svc, m, srv, served, com, geo)
    finally:
        close_port_first(com)
        close_port_first(geo)
        served.close()
        run_in(loop_thread, srv.close())


def volc_naming(path: str, fmt: str = "ISG_CSV") -> str:
    """A VOLC list whose file[0] (line 7) is `path`."""
    return (
        "X 1\nY 2\nZ 3\nchain YXZ\nfilter_steps 4\nmanual_activation 1\n"
        f"file[0] {path}\nfile_format[0] {fmt}\n"
    )


def serves(r: Rig) -> None:
    """The server still answers on every interface it has here, and reload and save
    answer (a reload needs a cycle to swap: the machine is stepped)."""
    coef = D.by_name("TEMPC::coefficient")
    assert r.geo.read(coef.index_group, coef.index_offset(1), pyads.PLCTYPE_LREAL) == 4000.0
    oks, errs = get(r.zenoh.session, "cnc/t/axis/1/tempc/coefficient")
    assert not errs and json.loads(oks[0][1]) == 4000.0
    oks, errs = get(r.zenoh.session, "cnc/t/cmd/reload", b"{}", JSON)
    assert not errs and json.loads(oks[0][1])["ok"] is True, errs
    access.step(r.service, 1)
    access.write_name(r.service, "TEMPC::coefficient", 1, 4001.0)
    access.step(r.service, 1)
    oks, errs = get(r.zenoh.session, "cnc/t/cmd/save", b"{}", JSON)
    assert not errs and json.loads(oks[0][1])["files"] == [str(r.folder / "achsmd1.lis")], errs


# ---------------------------------------------------------------------- the VOLC file write


def _names(r: Rig) -> dict[str, str]:
    """Every kind of name the issue found answered differently, made real on disk."""
    f, out = r.folder, r.outside
    (out / "volc.lis").write_text(smooth_files(out), encoding="utf-8")  # a valid list, outside
    (f / "a-folder").mkdir()
    os.mkfifo(f / "pipe.lis")
    os.mkfifo(out / "pipe.lis")
    (f / "out.lis").symlink_to(out / "volc.lis")
    (f / "passwd.lis").symlink_to("/etc/passwd")
    (f / "zero.lis").symlink_to("/dev/zero")
    (f / "etc").symlink_to("/etc")
    (f / "binary.lis").write_bytes(bytes(range(256)) * 4)
    with (f / "huge.lis").open("wb") as fh:  # sparse: no disk, no memory
        fh.truncate(LIMITS.volc_list_bytes + 1)
    return {
        "a valid list outside, absolute": str(out / "volc.lis"),
        "/etc/passwd": "/etc/passwd",
        "a folder outside": "/etc",
        "`..` out of the folder": "../outside/volc.lis",
        "`..` to the root": "../../../../../../../../etc/passwd",
        "`..` after a folder": "a-folder/../../outside/volc.lis",
        "missing, inside": "nothing-here.lis",
        "missing, outside": str(out / "nothing-here.lis"),
        "a folder, inside": "a-folder",
        "a FIFO, inside": str(f / "pipe.lis"),
        "a FIFO, outside": str(out / "pipe.lis"),
        "a device": "/dev/zero",
        "a symbolic link to a list outside": "out.lis",
        "a symbolic link to /etc/passwd": "passwd.lis",
        "a symbolic link to /dev/zero": "zero.lis",
        "through a linked folder": "etc/passwd",
        "not a VOLC list, inside": "achsmd1.lis",
        "binary, inside": "binary.lis",
        "larger than the VOLC list limit, inside": "huge.lis",
        "a drive path (looked up by its name here)": "C:\\Windows\\win.ini",
        "empty": "",
    }


def test_every_refused_name_gets_one_answer_on_every_interface(rig: Rig) -> None:
    r = rig
    tracemalloc.start()
    try:
        for what, name in _names(r).items():
            assert r.write_ads(name) == AdsErrorCode.DEVICE_SYNTAX, what  # 0x70D
            access.step(r.service, 1)  # the error list takes the report at the next cycle
            assert r.last_error() == LAST_ERROR, what
            body = r.write_zenoh(name)
            assert body == {
                "ads_error": AdsErrorCode.DEVICE_SYNTAX,
                "name": "volcomp_update",
                "message": f"volcomp_update failed: {REFUSAL}",
            }, what
        # by name on Zenoh (JSON): a NUL byte, which no file name can hold
        oks, errs = get(
            r.zenoh.session, "cnc/t/com/cnc_interpr_vol_comp_file_w", b'"volc0.lis\\u0000x"', JSON
        )
        assert not oks and errs[0]["message"] == f"volcomp_update failed: {REFUSAL}", errs
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < MEMORY_BOUND, f"{peak / 2**20:.1f} MiB traced"
    said = r.everything_said()
    assert SECRET not in said and "/etc" not in said and "outside" not in said
    assert "FIFO" not in said and "device" not in said and "not found" not in said
    assert access.read_name(r.service, "VOLC::available", 0) == 1  # compensation 0 unchanged
    serves(r)


def test_a_name_inside_the_folders_still_updates(rig: Rig) -> None:
    """The manual's procedure (004 p.23) works for lists in the machine's folder, under
    any relative spelling that stays inside, and in a folder allowed at start."""
    r = rig
    (r.folder / "sub").mkdir()
    (r.folder / "sub" / "v.lis").write_text(
        smooth_files(r.folder).replace("exx.csv", "../exx.csv"), encoding="utf-8"
    )
    (r.allowed / "v.lis").write_text(smooth_files(r.allowed), encoding="utf-8")
    (r.folder / "linked.lis").symlink_to(r.folder / "volc0.lis")  # a link inside
    for name, shown in (
        ("volc0.lis", r.folder / "volc0.lis"),
        ("sub/../sub/v.lis", r.folder / "sub" / "v.lis"),
        ("linked.lis", r.folder / "linked.lis"),
        ("C:\\volcomp\\volc0.lis", r.folder / "volc0.lis"),  # 004 p.36's drive paths
        (str(r.allowed / "v.lis"), r.allowed / "v.lis"),
    ):
        assert r.write_ads(name) == 0, (name, r.last_error())
        access.step(r.service, 1)
        assert access.read_name(r.service, "VOLC::file", 0) == str(shown)


def test_a_fifo_never_blocks_the_update_reload_or_save(rig: Rig) -> None:
    """A FIFO as the machine's own correction file: reload is rejected at once (it
    blocked before), naming the file (it is the machine's own); save answers after it,
    and a 0x27C write of a list naming it answers too."""
    r = rig
    os.mkfifo(r.folder / "fifo.csv")
    (r.folder / "volc0.lis").write_text(volc_naming("fifo.csv"), encoding="utf-8")
    oks, errs = get(r.zenoh.session, "cnc/t/cmd/reload", b"{}", JSON)
    assert not oks and errs[0]["ads_error"] == AdsErrorCode.DEVICE_SYNTAX, (oks, errs)
    assert (
        "correction file fifo.csv unreadable: is a FIFO, not a regular file" in (errs[0]["message"])
    )
    assert r.write_ads("volc0.lis") == AdsErrorCode.DEVICE_SYNTAX
    access.step(r.service, 1)
    assert "is a FIFO, not a regular file" in r.last_error()
    access.write_name(r.service, "TEMPC::coefficient", 1, 4002.0)
    access.step(r.service, 1)
    oks, errs = get(r.zenoh.session, "cnc/t/cmd/save", b"{}", JSON)
    assert not errs and json.loads(oks[0][1])["ok"] is True


# ---------------------------------------------------------------------- file[j] of a VOLC list


def test_a_volc_list_naming_another_file_never_publishes_it(rig: Rig) -> None:
    """A VOLC list in the machine's folder whose file[0] leads outside: refused at its
    line with the one text; nothing of the file named appears anywhere. The huge sparse
    file in the folder is refused by its size, unread."""
    r = rig
    (r.outside / "secret.csv").write_text(f"{SECRET}\nX EXX\n0 1\n", encoding="utf-8")
    (r.folder / "pw.csv").symlink_to("/etc/passwd")
    cases = {
        "/etc/passwd": "ISG_CSV",
        "../../../../../../../../etc/passwd": "ETALON_EXCHANGE",
        "pw.csv": "ISG_CSV",
        "/dev/zero": "ISG_CSV",
        str(r.outside / "secret.csv"): "ETALON_EXCHANGE",
        "../outside/secret.csv": "ISG_CSV",
    }
    tracemalloc.start()
    try:
        for i, (target, fmt) in enumerate(cases.items()):
            volc = r.folder / f"evil{i}.lis"
            volc.write_text(volc_naming(target, fmt), encoding="utf-8")
            assert r.write_ads(volc.name) == AdsErrorCode.DEVICE_SYNTAX, target
            body = r.write_zenoh(volc.name)
            assert body["message"] == f"volcomp_update failed: {volc}:7: {REFUSAL}", target
        with (r.folder / "huge.csv").open("wb") as fh:
            fh.truncate(1 << 30)  # a GiB, sparse
        (r.folder / "huge.lis").write_text(volc_naming("huge.csv"), encoding="utf-8")
        body = r.write_zenoh("huge.lis")
        assert body["message"].endswith(
            "correction file huge.csv unreadable: larger than 16777216 bytes (16 MiB)"
        )
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < MEMORY_BOUND, f"{peak / 2**20:.1f} MiB traced"
    said = r.everything_said()
    assert SECRET not in said
    serves(r)


@pytest.mark.parametrize(
    ("fmt", "message"), [("ISG_CSV", NOT_CSV), ("ETALON_EXCHANGE", NOT_ETALON)]
)
def test_a_file_that_is_no_correction_file_is_not_quoted(rig: Rig, fmt: str, message: str) -> None:
    """Even in a folder the user allowed, a file that is not a correction file is
    refused without a line of it (here: a copy of /etc/passwd's first line)."""
    r = rig
    (r.allowed / "passwd").write_text(f"{SECRET}\ndaemon:x:1:1::/:/bin/sh\n", encoding="utf-8")
    (r.folder / "evil.lis").write_text(volc_naming(str(r.allowed / "passwd"), fmt), "utf-8")
    body = r.write_zenoh("evil.lis")
    assert body["message"] == (
        f"volcomp_update failed: {r.allowed / 'passwd'}:1: [990525] volumetric "
        f"compensation 0: {message}"
    )
    assert SECRET not in r.everything_said()


def test_nc_volcomp_update_reads_only_inside(rig: Rig) -> None:
    """`#VOLCOMP [ID0 UPDATE]` over Zenoh re-reads the machine's VOLC list; changed to
    name /etc/passwd, the program ends with the one text and the compensation stays."""
    r = rig
    (r.folder / "volc0.lis").write_text(volc_naming("/etc/passwd"), encoding="utf-8")
    _, errs = get(r.zenoh.session, "cnc/t/nc", b"#VOLCOMP [ID0 UPDATE]\nM30\n", OCTET)
    assert not errs, errs
    m = r.machine
    for _ in range(3000):  # the files are read in a worker thread: wait for it, then step
        updates_read(m)
        access.step(r.service, 1)
        if m.player is None or not m.player.running:
            break
    assert m.player is None or not m.player.running
    last = r.last_error()
    assert "#VOLCOMP [ID0 UPDATE] failed, compensation unchanged" in last
    assert REFUSED in last and SECRET not in r.everything_said()
    assert access.read_name(r.service, "VOLC::available", 0) == 1
    (r.folder / "volc0.lis").write_text(smooth_files(r.folder), encoding="utf-8")
    serves(r)


# ---------------------------------------------------------------------- start-up and reload


def test_the_start_up_list_names_files_only_inside(lists_copy: Path, tmp_path: Path) -> None:
    """The same rule at start and on reload: a VOLC list outside is refused at the
    start-up list's line (the machine starts); given with --allow-dir it loads. Inside,
    the diagnostics name the file and what is wrong with it."""
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "v.lis").write_text(smooth_files(elsewhere), encoding="utf-8")
    add_volc(lists_copy, smooth_files(lists_copy.parent), {})
    text = lists_copy.read_text(encoding="utf-8")
    lists_copy.write_text(
        text.replace("file_name volc0.lis", f"file_name {elsewhere / 'v.lis'}"), encoding="utf-8"
    )
    line = (
        lists_copy.read_text(encoding="utf-8")
        .splitlines()
        .index(f"vol_comp[0].file_name {elsewhere / 'v.lis'}")
    )
    (comp,) = load_machine(lists_copy).volumetric
    assert (comp.available, comp.problem) == (False, REFUSED)
    cfg = load_machine(lists_copy)
    (diag,) = [d for d in cfg.diagnostics if d.error_id == 990525]
    assert (diag.file, diag.line) == (str(lists_copy), line + 1)
    (comp,) = load_machine(lists_copy, [elsewhere]).volumetric
    assert comp.available and comp.path == str(elsewhere / "v.lis")
    # the machine's own files keep their specific diagnostics
    lists_copy.write_text(text, encoding="utf-8")
    (lists_copy.parent / "volc0.lis").write_text(volc_naming("gone.csv"), encoding="utf-8")
    (comp,) = load_machine(lists_copy).volumetric
    assert comp.problem.startswith("correction file gone.csv not found (looked for ")


def test_geo_server_check_takes_allow_dir(lists_copy: Path, tmp_path: Path, capsys) -> None:
    from geo_server.cli import main

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "v.lis").write_text(smooth_files(elsewhere), encoding="utf-8")
    add_volc(lists_copy, smooth_files(lists_copy.parent), {})
    text = lists_copy.read_text(encoding="utf-8")
    lists_copy.write_text(
        text.replace("file_name volc0.lis", f"file_name {elsewhere / 'v.lis'}"), encoding="utf-8"
    )
    assert main(["check", str(lists_copy)]) == 1
    assert REFUSED in capsys.readouterr().out
    assert main(["check", str(lists_copy), "--allow-dir", str(elsewhere)]) == 0


# ---------------------------------------------------------------------- the helper itself


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="no /proc")
def test_the_read_stops_one_byte_past_the_limit(monkeypatch) -> None:
    """A /proc file says size 0 and reads as more: only the read can bound it."""
    read = os.read
    asked: list[int] = []

    def counting(fd: int, n: int) -> bytes:
        asked.append(n)
        return read(fd, n)

    monkeypatch.setattr(os, "read", counting)
    with pytest.raises(FileRefused) as info:
        read_regular("/proc/self/maps", 100)
    assert (info.value.kind, str(info.value)) == ("too_large", "larger than 100 bytes")
    assert sum(asked) <= 101


def test_special_files_are_refused_before_any_read(tmp_path: Path) -> None:
    os.mkfifo(tmp_path / "fifo")
    for path, reason in (
        (tmp_path / "fifo", "is a FIFO, not a regular file"),
        (Path("/dev/zero"), "is a character device, not a regular file"),
        (tmp_path, "is a directory, not a regular file"),
    ):
        with pytest.raises(FileRefused) as info:
            read_regular(path, 1 << 20)
        assert str(info.value) == reason
    with pytest.raises(FileNotFoundError):
        read_regular(tmp_path / "missing", 10)
    (tmp_path / "f").write_bytes(b"x" * 10)
    assert read_regular(tmp_path / "f", 10) == b"x" * 10
    with pytest.raises(FileRefused):
        read_regular(tmp_path / "f", 9)
