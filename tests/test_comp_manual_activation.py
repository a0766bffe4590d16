"""Manual activation (000 §3.2 p.17, §4.4 P-COMP-00028, §4.6 P-COMP-00065, §5.1 p.94)
and the deselection on release of the axis, cycle by cycle in stepped mode.

"If the parameter P-COMP-00065 is set to 1, crosstalk compensation must be explicitly
activated by an NC command [...] Compensation is deactivated at the end of the NC
program, when the CNC is reset or when the compensating axis is released" (000 p.87);
the same for LSEC (kw.ssfk.manual_activation, 000 p.57) and temperature (000 p.17).
Releasing an axis is the axis exchange command `#PUT AX [<axis>]`.

Expected values by hand from the manual's formulas and examples.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest

from geo_server import access
from geo_server.errors import AdsError
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.paths import data_dir
from geo_server.service import ObjectService

X, Y = 1, 2


def rhaz(x: float) -> int:
    return math.floor(abs(x) + 0.5) * (1 if x >= 0 else -1)


def sin2(k: int, n: int) -> float:
    return math.sin(math.pi * k / (2 * n)) ** 2


def _edit(path: Path, drop: str, add: str) -> None:
    """Remove the lines starting with `drop` (case-insensitive) and append `add`."""
    keep = [ln for ln in path.read_text().splitlines() if not ln.lower().startswith(drop)]
    path.write_text("\n".join(keep) + "\n" + add)


@pytest.fixture
def manual_machine(lists_copy: Path) -> tuple[Machine, ObjectService]:
    """The default machine with
    - Y's crosstalk replaced by the manual's mode-1 example (000 p.91: acceleration
      ±10000 mm/s², corrections 25/25 positive, 50/50 negative direction; no n_cycles, so
      the switch is a jump) and `kw.crosstalk.manual_activation 1`;
    - `kw.ssfk.manual_activation 1` for X's LSEC;
    - `lr_param.temp_comp_manual_activation 1` for X's temperature compensation."""
    example = data_dir("lists") / "examples" / "000_p91_crosstalk_mode1.lis"
    xt = [ln for ln in example.read_text().splitlines() if ln.lower().startswith("kw.crosstalk")]
    assert len(xt) == 9  # mode, master, velocity_dependent, 2 accelerations, 4 values
    lists = lists_copy.parent
    _edit(
        lists / "achskw2.lis",
        "kw.crosstalk",
        "\n".join(xt) + "\nkw.crosstalk.manual_activation 1\n",
    )
    _edit(lists / "achskw1.lis", "kw.ssfk.manual_activation", "kw.ssfk.manual_activation 1\n")
    _edit(
        lists / "achsmd1.lis",
        "lr_param.temp_comp_manual_activation",
        "lr_param.temp_comp_manual_activation 1\n",
    )
    cfg = load_machine(lists_copy)
    assert not [d for d in cfg.diagnostics if d.severity == "error"]
    m = Machine(cfg, homed=True)
    m.step(40)
    return m, ObjectService(m)


def _run(m: Machine, svc: ObjectService, program: str, reads: list[tuple[str, int]]) -> list[dict]:
    m.start_program(program)
    rows = []
    for _ in range(20_000):
        m.run_cycle()
        p = m.player
        assert p is not None
        row: dict = {"line": p.line, "error": p.error}
        row.update({f"{n}@{a}": access.read_name(svc, n, a) for n, a in reads})
        rows.append(row)
        if not p.running:
            return rows
    raise AssertionError("program did not end")


def test_crosstalk_manual_activation(manual_machine):
    """Y's crosstalk over X's acceleration (X's a_max 2000 mm/s², so |a|/a_ref = 0.2):
    0 until `Y[COMP ON CROSSTALK]`; then 50·0.2 = 10 while X accelerates or decelerates
    in the negative direction (000 §4.6 p.84, p.91); 0 again after `#PUT AX [Y]`; and
    deselected at M30 although `#CALL AX` brought Y back and COMP switched it on again."""
    m, svc = manual_machine
    assert access.read_name(svc, "CROSSTALK::activated", Y) is False
    prog = (
        "N10 G91 G01 X20 F6000\n"
        "N20 Y[COMP ON CROSSTALK]\n"
        "N30 G91 G01 X-20 F6000\n"
        "N40 #PUT AX [Y]\n"
        "N50 G91 G01 X20 F6000\n"
        "N60 #CALL AX [Y, 2, 1]\n"
        "N70 Y[COMP ON CROSSTALK]\n"
        "N80 M30\n"
    )
    reads = [
        ("CROSSTALK::actual_offset", Y),
        ("CROSSTALK::activated", Y),
        ("SIM::acceleration", X),
        ("SIM::velocity", X),
    ]
    rows = _run(m, svc, prog, reads)
    assert rows[-1]["error"] is None
    by_line = {ln: [r for r in rows if r["line"] == ln] for ln in range(1, 9)}
    full = {1: 2000, 3: -2000, 5: 2000}  # X's acceleration phase in each move
    for line, want in ((1, 0), (3, 10), (5, 0)):
        block = by_line[line]
        acc = [r for r in block if r["SIM::acceleration@1"] == full[line]]
        dec = [r for r in block if r["SIM::acceleration@1"] == -full[line]]
        assert len(acc) >= 40 and len(dec) >= 40, line  # 100 mm/s at 2000 mm/s²
        for r in acc + dec:
            assert r["CROSSTALK::actual_offset@2"] == want, (line, r)
        assert all(r["CROSSTALK::activated@2"] is (line == 3) for r in block)
    # cruising (a = 0): no crosstalk
    cruise = [r for r in by_line[3] if r["SIM::acceleration@1"] == 0 and r["SIM::velocity@1"]]
    assert cruise and all(r["CROSSTALK::actual_offset@2"] == 0 for r in cruise)
    assert by_line[7][-1]["CROSSTALK::activated@2"] is True  # COMP ON after #CALL AX
    assert access.read_name(svc, "CROSSTALK::activated", Y) is False  # M30


def test_lsec_and_temperature_manual_activation_and_axis_release(manual_machine):
    """X at 0 mm: LSEC −table[50].pos = 9 and temperature 40 + 4000e-6·(0 − 100) = 39.6
    (000 p.17, p.57; lists/achskw1.lis, achsmd1.lis) only after COMP ON, ramped over
    n_backlash_cyc 10 and temp_comp_n_cycles 20. At −490 mm LSEC is −table[1].pos = −15.
    `#PUT AX [X]` deselects both and ramps them out; backlash (automatic) stays."""
    m, svc = manual_machine
    assert access.read_name(svc, "ssfk activated", X) is False
    assert access.read_name(svc, "TEMPC::activated", X) is False
    assert access.read_name(svc, "LSEC::sum epsilon", X) == 0
    assert access.read_name(svc, "TEMPC::actual_offset", X) == 0
    reads = [
        ("LSEC::sum epsilon", X),
        ("TEMPC::actual_offset", X),
        ("ssfk activated", X),
        ("TEMPC::activated", X),
        ("SIM::backlash_selected", X),
    ]
    rows = _run(m, svc, "N10 X[COMP ON LEAD TEMP]\nN20 M30\n", reads)
    for k in range(1, 21):
        r = rows[k - 1]
        assert r["TEMPC::actual_offset@1"] == rhaz(39.6 * sin2(k, 20)), k
        assert r["LSEC::sum epsilon@1"] == rhaz(9 * sin2(min(k, 10), 10)), k
    # M30 deselects them again: the ramps back to 0 run after the program's end
    m.step(25)
    assert access.read_name(svc, "LSEC::sum epsilon", X) == 0
    assert access.read_name(svc, "TEMPC::activated", X) is False

    prog = (
        "N10 X[COMP ON LEAD TEMP]\nN20 G90 G01 X-490 F6000\nN30 #PUT AX [X]\n"
        "N40 G04 0.03\nN50 M30\n"
    )
    rows = _run(m, svc, prog, reads)
    # #PUT AX does not wait: the dwell after it starts in the same cycle
    at = next(i for i, r in enumerate(rows) if r["line"] == 4)
    before = rows[at - 1]
    assert before["LSEC::sum epsilon@1"] == -15
    temp_held = 40 + 4000e-6 * (-4_900_000 - 100)  # −1920.4
    assert before["TEMPC::actual_offset@1"] == rhaz(temp_held)
    for k in range(1, 21):  # the release takes effect in the cycle it runs
        r = rows[at + k - 1]
        assert r["ssfk activated@1"] is False and r["TEMPC::activated@1"] is False
        assert r["SIM::backlash_selected@1"] is True
        assert r["LSEC::sum epsilon@1"] == rhaz(-15 * (1 - sin2(min(k, 10), 10))), k
        assert r["TEMPC::actual_offset@1"] == rhaz(temp_held * (1 - sin2(k, 20))), k


def test_released_axis_cannot_be_programmed(manual_machine):
    m, svc = manual_machine
    rows = _run(m, svc, "N10 #PUT AX ALL\nN20 G91 G01 X1 F6000\nN30 M30\n", [])
    err = rows[-1]["error"]
    assert err is not None and err.line == 2
    assert "axis X is not in the channel" in err.message
    # every program starts with all axes in the channel; unknown names are no error
    rows = _run(
        m, svc, "N10 #PUT AX [X, B]\nN20 #CALL AX [X, 1, 0]\nN30 G91 G01 X1 F6000\nN40 M30\n", []
    )
    assert rows[-1]["error"] is None


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("N10 #PUT AX [X] G01 X1", "expected [<axis>, …]"),
        ("N10 G01 X1 #PUT AX [X]", "must stand alone"),
        ("N10 #PUT AX", "needs [<axis>"),
        ("N10 #CALL AX [Q, 9, 0]", "unknown axis"),
    ],
)
def test_axis_exchange_syntax_errors(manual_machine, text, message):
    m, _ = manual_machine
    with pytest.raises(ValueError, match=re.escape(message)):
        m.start_program(text + "\nM30\n")


def test_comp_on_switches_on_only_what_the_axis_list_enables(lists_copy: Path) -> None:
    """Issue 45 #8, 000 p.35 and §5.1 p.94: COMP ON selects a compensation the axis list
    enables ("activated (selected) via" its parameter). X has no cross compensation
    (`lr_param.crosscomp 0`): `X[COMP ON CROSS]` leaves CROSSC::activated FALSE. X's
    temperature compensation is switched off by its list's error (n_cycles 25 is outside
    0…20: 990271, `temp_comp` 0): `X[COMP ON TEMP]` leaves it off, its offset_0 (40, i.e.
    4 µm) never output. Before: activated TRUE, and 40 + 4000e-6·(0 - position_0)
    output. Neither is an error (the manual names one for friction only)."""
    _edit(lists_copy.parent / "achsmd1.lis", "lr_param.temp_comp_n_cycles", "")
    with (lists_copy.parent / "achsmd1.lis").open("a", encoding="utf-8") as f:
        f.write("lr_param.temp_comp_n_cycles 25\n")
    cfg = load_machine(lists_copy)
    assert [d.error_id for d in cfg.diagnostics if d.axis == X] == [990271]
    m = Machine(cfg, homed=True)
    svc = ObjectService(m)
    m.step(5)
    prog = "N10 X[COMP ON CROSS TEMP]\nN20 G04 0.05\nN30 M30\n"
    reads = [
        ("CROSSC::activated", X),
        ("TEMPC::activated", X),
        ("TEMPC::actual_offset", X),
    ]
    rows = _run(m, svc, prog, reads)
    assert rows[-1]["error"] is None
    assert all(r["CROSSC::activated@1"] is False for r in rows)
    assert all(r["TEMPC::activated@1"] is False for r in rows)
    assert all(r["TEMPC::actual_offset@1"] == 0 for r in rows)
    # the object activates temperature compensation also without temp_comp 1 (000 p.17),
    # but not one a list error deactivated: refused with 0x70B naming the diagnostic
    pending = access.write_name(svc, "TEMPC::activated", X, True)
    m.step(1)
    with pytest.raises(AdsError) as refused:
        pending.result(timeout=0)
    assert refused.value.code == 0x70B
    assert "[990271]" in refused.value.message and "achsmd1.lis" in refused.value.message
    m.step(20)
    assert access.read_name(svc, "TEMPC::activated", X) is False
    assert access.read_name(svc, "TEMPC::actual_offset", X) == 0
    pending = access.write_name(svc, "TEMPC::activated", X, False)  # off stays allowed
    m.step(1)
    assert pending.result(timeout=0) is None
