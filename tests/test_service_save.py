"""`save` never edits the product's own files: the default machine is read-only wherever
it comes from — an installed wheel's data folder or the `lists/` beside a source
checkout (docs/design.md §4.5; issue 30 item 8)."""

from __future__ import annotations

import hashlib
import json
import shutil
import struct
from pathlib import Path

import pytest
import zenoh
from test_zenoh_commands import OCTET, Served, get

import geo_server.paths
from geo_server import access
from geo_server.errors import AdsErrorCode
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.paths import data_dir, default_startup_list
from geo_server.service import ObjectService


def _digests(folder: Path) -> dict[str, str]:
    return {
        p.name: hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.iterdir())
        if p.is_file()
    }


def _refusal(path: Path) -> str:
    return (
        f"{path} belongs to the default machine shipped with geo-server, which is read-only "
        "wherever it is installed; copy it with `geo-server init DIR` and run "
        "`geo-server run DIR/hochlauf.lis` to save"
    )


def test_save_refuses_the_installed_default_machine(tmp_path: Path, monkeypatch):
    # An installed wheel keeps the default machine in geo_server/_data/lists; pretend
    # tmp_path is that package folder.
    lists = tmp_path / "_data" / "lists"
    shutil.copytree(data_dir("lists"), lists, ignore=shutil.ignore_patterns("examples", "tools"))
    monkeypatch.setattr(geo_server.paths, "PACKAGED_DATA", tmp_path / "_data")
    svc = ObjectService(Machine(load_machine(lists / "hochlauf.lis"), homed=True))
    axis_list = lists / "achsmd1.lis"
    before = axis_list.read_bytes()
    access.write_name(svc, "TEMPC::coefficient", 1, 1234.5)
    access.step(svc, 1)
    result = svc.commands.save()
    assert not result.ok
    assert result.files == []
    assert result.errors == [_refusal(lists / "hochlauf.lis")]
    assert result.code == AdsErrorCode.DEVICE_ERROR  # 0x700, as every failed save
    assert axis_list.read_bytes() == before


def test_save_refuses_the_checkout_default_machine(tmp_path: Path, monkeypatch):
    # A source checkout: <root>/lists beside <root>/geo_server; pretend tmp_path is it.
    lists = tmp_path / "lists"
    shutil.copytree(data_dir("lists"), lists, ignore=shutil.ignore_patterns("examples", "tools"))
    monkeypatch.setattr(geo_server.paths, "CHECKOUT", tmp_path)
    svc = ObjectService(Machine(load_machine(lists / "hochlauf.lis"), homed=True))
    before = _digests(lists)
    access.write_name(svc, "TEMPC::coefficient", 1, 1234.5)
    access.step(svc, 1)
    result = svc.commands.save()
    assert (result.ok, result.files) == (False, [])
    assert result.errors == [_refusal(lists / "hochlauf.lis")]
    assert _digests(lists) == before


def test_an_axis_list_of_the_default_machine_named_from_elsewhere_is_not_saved(tmp_path: Path):
    """A start-up list of the user's that names the shipped axis lists: the user's
    start-up list may be saved into, the shipped lists are not."""
    shipped = data_dir("lists")
    startup = tmp_path / "hochlauf.lis"
    text = default_startup_list().read_text(encoding="utf-8")
    for name in ("achsmd1.lis", "achsmd2.lis", "achsmd3.lis", "achsmd4.lis"):
        text = text.replace(f" {name}", f" {shipped / name}")
    text = "\n".join(ln for ln in text.splitlines() if "achskw" not in ln) + "\n"
    startup.write_text(text, encoding="utf-8")
    cfg = load_machine(startup)
    assert cfg.axes[1].params.path == str(shipped / "achsmd1.lis")
    before = _digests(shipped)
    svc = ObjectService(Machine(cfg, homed=True))
    access.write_name(svc, "TEMPC::coefficient", 1, 1234.5)
    access.step(svc, 1)
    result = svc.commands.save()
    assert (result.ok, result.files) == (False, [])
    assert result.errors == [_refusal(shipped / "achsmd1.lis")]
    assert _digests(shipped) == before


def test_saving_this_checkouts_default_machine_over_zenoh_is_refused(loop_thread):
    """The real `lists/` of this checkout, served as `geo-server run` without a list
    does: `cmd/save` and a write of `SIM::save` are refused with the advice, even with
    nothing changed, and the tracked files stay as they are."""
    shipped = data_dir("lists")
    before = _digests(shipped)
    svc = ObjectService(Machine(load_machine(default_startup_list()), homed=True))
    s = Served(loop_thread, svc)
    try:
        for key, payload, encoding in (
            ("cnc/t/cmd/save", b"{}", zenoh.Encoding.APPLICATION_JSON),
            ("cnc/t/ads/551/0x12f300/0x5", struct.pack("<H", 1), OCTET),  # SIM::save
        ):
            for change in (False, True):
                if change:
                    access.write_name(svc, "TEMPC::coefficient", 1, 1234.5)
                    access.step(svc, 1)
                oks, errs = get(s.session, key, payload, encoding)
                assert not oks and len(errs) == 1, (key, oks, errs)
                assert errs[0]["ads_error"] == AdsErrorCode.DEVICE_ERROR, errs
                message = json.dumps(errs[0])
                assert "geo-server init DIR" in message, errs
                assert "default machine shipped with geo-server" in message, errs
        # the server goes on serving, and reload (a read) still works
        oks, errs = get(s.session, "cnc/t/cmd/reload", b"{}", zenoh.Encoding.APPLICATION_JSON)
        assert not errs and json.loads(oks[0][1])["ok"] is True
    finally:
        s.close()
    assert _digests(shipped) == before


@pytest.mark.parametrize("inside", [False, True])
def test_is_packaged_data(tmp_path: Path, monkeypatch, inside: bool):
    monkeypatch.setattr(geo_server.paths, "PACKAGED_DATA", tmp_path / "pkg" / "_data")
    path = tmp_path / "pkg" / "_data" / "lists" / "x.lis" if inside else tmp_path / "x.lis"
    assert geo_server.paths.is_packaged_data(path) is inside
    assert geo_server.paths.is_product_data(path) is inside


def test_is_product_data_of_a_checkout():
    root = Path(geo_server.paths.__file__).resolve().parent.parent
    assert geo_server.paths.is_product_data(default_startup_list())
    assert geo_server.paths.is_product_data(root / "objects" / "objects.toml")
    assert not geo_server.paths.is_product_data(root / "tests" / "conftest.py")
    assert not geo_server.paths.is_product_data(root / "lists-copy" / "hochlauf.lis")
