"""`save` never edits the lists inside an installed package (site-packages)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

import geo_server.paths
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.paths import data_dir
from geo_server.service import ObjectService


def test_save_refuses_the_installed_default_machine(tmp_path: Path, monkeypatch):
    # An installed wheel keeps the default machine in geo_server/_data/lists; pretend
    # tmp_path is that package folder.
    lists = tmp_path / "_data" / "lists"
    shutil.copytree(data_dir("lists"), lists, ignore=shutil.ignore_patterns("examples", "tools"))
    monkeypatch.setattr(geo_server.paths, "PACKAGED_DATA", tmp_path / "_data")
    svc = ObjectService(Machine(load_machine(lists / "hochlauf.lis"), homed=True))
    axis_list = lists / "achsmd1.lis"
    before = axis_list.read_bytes()
    svc.write_name("TEMPC::coefficient", 1, 1234.5)
    svc.step(1)
    result = svc.save()
    assert not result.ok
    assert result.files == []
    assert len(result.errors) == 1
    assert "achsmd1.lis belongs to the installed package" in result.errors[0]
    assert "geo-server init" in result.errors[0]
    assert axis_list.read_bytes() == before


@pytest.mark.parametrize("inside", [False, True])
def test_is_packaged_data(tmp_path: Path, monkeypatch, inside: bool):
    monkeypatch.setattr(geo_server.paths, "PACKAGED_DATA", tmp_path / "pkg" / "_data")
    path = tmp_path / "pkg" / "_data" / "lists" / "x.lis" if inside else tmp_path / "x.lis"
    assert geo_server.paths.is_packaged_data(path) is inside
