"""The COM task's objects over Zenoh (docs/volumetric.md §7): the raw keys of AMS port 553
and the named `cnc/<m>/com/…` keys, with a real Zenoh session on loopback (peer mode,
multicast scouting off, explicit endpoints, a timeout on every get), stepped machine."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest
from test_volcomp import add_volc, smooth_files
from test_zenoh_commands import JSON, OCTET, Served, get, get_err

from geo_server import access
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.service import ObjectService


@pytest.fixture
def served_volc(loop_thread, lists_copy: Path):
    add_volc(lists_copy, smooth_files(lists_copy.parent), {})
    m = Machine(load_machine(lists_copy), homed=True)
    m.motion.set_position(0, 100 * 10_000)
    s = Served(loop_thread, ObjectService(m))
    yield s
    s.close()


def value(s: Served, key: str):
    oks, errs = get(s.session, key)
    assert not errs and len(oks) == 1, (oks, errs)
    return json.loads(oks[0][1])


def test_enable_update_disable_through_zenoh(served_volc: Served) -> None:
    s, svc = served_volc, served_volc.service
    oks, errs = get(s.session, "cnc/t/ads/553/0x120100/0x291", struct.pack("<H", 0), OCTET)
    assert not errs and len(oks) == 1
    access.step(svc, 6)  # filter_steps 4
    assert value(s, "cnc/t/sim/machine/volc_active") == 1
    # EXX = 2e-5·x at x = 100 mm: −2e-5·100/1.00002 mm = −19.9996 increments
    assert value(s, "cnc/t/sim/axis/1/volc_correction") == -20
    # an update by name: the ID, then the file (the second write loads, 004 p.23)
    folder = Path(svc.info.config.startup_path).parent
    (folder / "twice.csv").write_text("X EXX\n-1000 -0.04\n1000 0.04\n", encoding="utf-8")
    (folder / "v2.lis").write_text(
        smooth_files(folder).replace("exx.csv", "twice.csv"), encoding="utf-8"
    )
    oks, errs = get(s.session, "cnc/t/com/cnc_interpr_vol_comp_index_w", b"0", JSON)
    assert not errs
    access.step(svc, 1)
    path = str(folder / "v2.lis").encode() + b"\0"
    oks, errs = get(s.session, "cnc/t/ads/553/0x120100/0x27c", path, OCTET)
    assert not errs, errs
    access.step(svc, 1)
    assert value(s, "cnc/t/sim/machine/volc_file") == str(folder / "v2.lis")
    assert value(s, "cnc/t/sim/machine/volc_active") == 0  # switched off by the update
    get(s.session, "cnc/t/com/cnc_vol_comp_enable_index_w", b"0", JSON)
    access.step(svc, 6)
    assert value(s, "cnc/t/sim/axis/1/volc_correction") == -40
    get(s.session, "cnc/t/com/cnc_vol_comp_disable_index_w", b"0", JSON)
    access.step(svc, 6)
    assert value(s, "cnc/t/sim/machine/volc_active") == 0


def test_com_group_only_on_its_port(served_volc: Served) -> None:
    err = get_err(served_volc.session, "cnc/t/ads/551/0x120100/0x291", struct.pack("<H", 0), OCTET)
    assert err["ads_error"] == 0x702
    err = get_err(served_volc.session, "cnc/t/ads/553/0x120300/0x10043")
    assert err["ads_error"] == 0x702
    err = get_err(served_volc.session, "cnc/t/com/cnc_vol_comp_enable_index_w")
    assert err["ads_error"] == 0x704  # write-only (004 p.19)
    err = get_err(served_volc.session, "cnc/t/com/cnc_vol_comp_enable_index_w", b"7", JSON)
    assert err["ads_error"] == 0x706  # IDs 0-4
