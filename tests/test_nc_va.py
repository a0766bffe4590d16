"""The manuals' NC checks of compensation state (000 §5.2 p.95-96, 001 §5.2): the V.A.
variables `V.A.<name>_COMP_INIT|ACTIVE|CURR`, `$IF … $ELSEIF … $ELSE … $ENDIF` and `#MSG`
(docs/design.md §5.9).

The manual's own program ships in `lists/examples/nc/` and runs on a machine whose state
is switched between runs; its messages appear exactly when the states say so, in the
error list, on Zenoh (`cnc/<m>/errors`) and in the web HMI's state, each with its line.
Expected values come from the manual's program text and from hand computation.
"""

from __future__ import annotations

import asyncio
import json
import queue
import urllib.request
from pathlib import Path

import pytest
import zenoh
from conftest import free_port, run_in, wait_until_routed
from test_nc import AXES, FakePort, K, play

from geo_server import access
from geo_server.errors import AdsError
from geo_server.listfile import load_machine
from geo_server.machine.machine import Machine
from geo_server.machine.nc import NcError, parse_program
from geo_server.paths import data_dir, default_startup_list
from geo_server.service import ObjectService
from geo_server.transports.zenoh.options import ZenohOptions
from geo_server.transports.zenoh.server import ZenohInterface
from geo_server.web.server import HmiOptions, HmiServer

NC = data_dir("lists") / "examples" / "nc"
#: 001 §5.2 as printed, and 000 p.96 as the English edition extracts it ("V. A. … . X")
MANUAL = NC / "001_s5.2_va_check.nc"
MANUAL_EN = NC / "000_p96_va_check.nc"
#: the program's messages with their lines in the shipped files (line 1 is the source note)
NOT_INIT_CROSS = ("Cross_Comp for X not init.", 4)
NOT_INIT_TEMP = ("Temp_Comp for X not init.", 7)
NOT_ACTIVE_CROSS = ("Cross_Comp for X not active", 11)
NOT_ACTIVE_TEMP = ("Temp_Comp for X not active", 14)


# --------------------------------------------------------------------------- parsing


def test_the_shipped_manual_programs_parse():
    """Both editions parse (before: "line 3: unexpected '$IF V.A.CROSS_COMP_I'")."""
    for path in (MANUAL, MANUAL_EN):
        prog = parse_program(path.read_text(encoding="utf-8"), AXES)
        msgs = [(b.message, b.line) for b in prog.blocks if b.message is not None]
        assert msgs == [NOT_INIT_CROSS, NOT_INIT_TEMP, NOT_ACTIVE_CROSS, NOT_ACTIVE_TEMP]
        # `N150 ...`: the manual's elision, skipped with a warning naming its line
        assert any(w.line == 16 and "elision" in w.message for w in prog.warnings)


@pytest.mark.parametrize(
    "text",
    [
        "$IF V.A.BACKLASH_COMP_INIT.X == 1\n$ENDIF",  # 000 p.95: no BACKLASH_COMP_INIT
        "$IF V.A.CROSS_COMP_STATE.X == 1\n$ENDIF",
        "$IF V.A.CROSS_COMP_INIT.Q == 1\n$ENDIF",  # no axis Q
        "$IF V.A.CROSS_COMP_INIT[4] == 1\n$ENDIF",  # four axes: index 0 … 3
        "$IF V.A.CROSS_COMP_INIT.X ==\n$ENDIF",
        "$IF V.A.CROSS_COMP_INIT.X TRUE\n$ENDIF",
        "$IF\n$ENDIF",
        "$IF 1\n",  # no $ENDIF
        "$ELSE\n",
        "$ENDIF\n",
        "$IF 1\n$ELSE\n$ELSE\n$ENDIF",
        "$ELSE X1\n",
        'X1 #MSG ["a"]\n',
        "#MSG [a]\n",
    ],
)
def test_bad_conditions_and_blocks_are_refused_with_their_line(text):
    with pytest.raises(NcError) as exc:
        parse_program(text, AXES)
    assert exc.value.line >= 1


def test_message_text_keeps_its_case_and_its_comment_characters():
    prog = parse_program('N10 #MSG ["Temp (X); ok"] ; a comment\nM30', AXES)
    assert prog.blocks[0].message == "Temp (X); ok" and prog.blocks[0].number == 10


# --------------------------------------------------------------------------- branches


def _messages(port: FakePort) -> list[tuple[str, int]]:
    return [(c[1], c[2]) for c in port.calls if c[0] == "msg"]


@pytest.mark.parametrize(
    ("active", "expected"),
    [
        # X cross active: the $IF branch; else Y temp decides between $ELSEIF and $ELSE
        ({0: K.CROSS}, [("cross", 2), ("inner", 4), ("end", 11)]),
        ({1: K.TEMP}, [("temp", 7), ("end", 11)]),
        ({}, [("none", 9), ("end", 11)]),
    ],
)
def test_if_elseif_else_nested(active, expected):
    text = (
        "$IF V.A.CROSS_COMP_ACTIVE.X == TRUE\n"  # 1
        '  #MSG ["cross"]\n'  # 2
        "  $IF V.A.CROSS_COMP_ACTIVE[0] AND V.A.TEMP_COMP_ACTIVE.X != 1\n"  # 3
        '    #MSG ["inner"]\n'  # 4
        "  $ENDIF\n"  # 5
        "$ELSEIF V.A.TEMP_COMP_ACTIVE[1] == TRUE OR V.A.LEAD_COMP_ACTIVE.Y\n"  # 6
        '  #MSG ["temp"]\n'  # 7
        "$ELSE\n"  # 8
        '  #MSG ["none"]\n'  # 9
        "$ENDIF\n"  # 10
        '#MSG ["end"]\n'  # 11
        "M30\n"
    )
    player, port = play(text, FakePort(active=dict(active)))
    assert player.finished and player.error is None
    assert _messages(port) == expected


def test_one_message_per_cycle_in_a_loop():
    """A `$GOTO` loop around a #MSG reports one message per cycle (not a thousand)."""
    _, port = play('N10 #MSG ["tick"]\n$GOTO N10\nM30', cycles=5)
    assert len(_messages(port)) == 5


# --------------------------------------------------------------------------- machine


def _machine_lists(folder: Path, *, requires: str = "") -> Path:
    """Axes X, Y, Z; X is the slave of a cross compensation over Y (2 points) and has
    temperature compensation as in 000 p.24 (position_0 100, offset_0 40, 4000 µm/m)."""
    folder.mkdir(parents=True, exist_ok=True)
    stup = ["zahl_mds 3"]
    for k, name in enumerate("XYZ"):
        nr = k + 1
        lines = [f"kopf.achs_nr {nr}", f"kopf.log_achs_name {name}", "kenngr.achs_typ 1"]
        if name == "X":
            lines += [
                "lr_param.temp_comp 1",
                "lr_param.temp_comp_position_0 100",
                "lr_param.temp_comp_offset_0 40",
                "lr_param.temp_comp_coefficient 4000",
                "lr_param.temp_comp_n_cycles 20",
                "lr_param.crosscomp 1",
            ]
            if requires:
                lines.append(f"lr_param.prog_movement_requires_compensations {requires}")
        (folder / f"achsmd{nr}.lis").write_text("\n".join(lines) + "\n", encoding="utf-8")
        stup += [f"achs_mds_log_ax_nr[{k}] {nr}", f"achs_mds[{k}] achsmd{nr}.lis"]
    stup += ["zahl_kw 1", "achs_kw_log_ax_nr[0] 1", "achs_kw[0] achskw1.lis"]
    (folder / "achskw1.lis").write_text(
        "\n".join(
            [
                "kopf.achs_nr 1",
                "kw.crosscomp.master_ax_nr 2",
                "kw.crosscomp.unit 1",
                "kw.crosscomp.n_cycles 20",
                "kw.crosscomp.last_index 1",
                "kw.crosscomp.table[0].setpoint 0",
                "kw.crosscomp.table[0].correction 50",
                "kw.crosscomp.table[1].setpoint 1000000",
                "kw.crosscomp.table[1].correction 150",
            ]
        )
        + "\n",
        encoding="utf-8",
    )
    (folder / "hochlauf.lis").write_text("\n".join(stup) + "\n", encoding="utf-8")
    return folder / "hochlauf.lis"


def _run(m: Machine, text: str, cycles: int = 300) -> list[tuple[str, int]]:
    """Run a program to its end; the #MSG events it reported, with their lines."""
    since = len(m.events)
    m.start_program(text)
    for _ in range(cycles):
        m.step()
        if m.player is not None and not m.player.running:
            break
    assert m.player is not None and m.player.finished and m.player.error is None
    events = list(m.events)[since:]
    return [
        (e.diagnostic.message, e.diagnostic.line)
        for e in events
        if e.diagnostic.severity == "message"
    ]


@pytest.mark.parametrize("path", [MANUAL, MANUAL_EN], ids=lambda p: p.name)
def test_the_manual_program_reports_exactly_what_the_states_say(tmp_path, path):
    text = path.read_text(encoding="utf-8")
    m = Machine(load_machine(_machine_lists(tmp_path / "m")), cycle_s=0.001)
    assert not m.cfg.diagnostics
    # 1. everything configured, homed by the program's G74, drives enabled: no message
    assert _run(m, text) == []
    # 2. the drive of X disabled (000 p.97 item 4): cross stays initialised but is not
    #    active after COMP ON; temperature needs no drive enable
    m.apply_write("SIM::drive_enable", 1, 0)
    assert _run(m, text) == [NOT_ACTIVE_CROSS]
    m.apply_write("SIM::drive_enable", 1, 1)
    assert _run(m, text) == []
    # 3. the default machine: X has no cross compensation (not initialised, and COMP ON
    #    cannot make it active); its temperature compensation is both
    d = Machine(load_machine(default_startup_list()), cycle_s=0.001)
    assert _run(d, text) == [NOT_INIT_CROSS, NOT_ACTIVE_CROSS]


def test_curr_values_in_mm_computed_by_hand(tmp_path):
    """CURR (000 p.96, Real in mm). Temperature at X = 0: 40 + 4000e-6·(0 − 100) = 39.6
    units of 0.1 µm = 0.00396 mm; at X = 100 mm (1 000 000 units): 40 + 0.004·999 900 =
    4039.6 → 0.40396 mm. Cross at Y = 0: 50 → 0.005 mm; at Y = 50 mm (half way): 100 →
    0.01 mm."""
    m = Machine(load_machine(_machine_lists(tmp_path / "m")), cycle_s=0.001)
    text = (
        "G74 X1 Y2 Z3\n"
        "G04 0.1\n"  # 100 cycles: the sin² ramps (20 cycles) are over
        "$IF V.A.TEMP_COMP_CURR.X > 0.003959 AND V.A.TEMP_COMP_CURR[0] < 0.003961\n"
        '#MSG ["temp 0.00396"]\n'
        "$ENDIF\n"
        "$IF V.A.CROSS_COMP_CURR.X > 0.004999 AND V.A.CROSS_COMP_CURR.X < 0.005001\n"
        '#MSG ["cross 0.005"]\n'
        "$ENDIF\n"
        "G01 X100 Y50 F60000\n"
        "G04 0.1\n"
        "$IF V.A.TEMP_COMP_CURR.X > 0.403959 AND V.A.TEMP_COMP_CURR.X < 0.403961\n"
        '#MSG ["temp 0.40396"]\n'
        "$ENDIF\n"
        "$IF V.A.CROSS_COMP_CURR.X > 0.009999 AND V.A.CROSS_COMP_CURR.X < 0.010001\n"
        '#MSG ["cross 0.01"]\n'
        "$ELSE\n"
        '#MSG ["cross wrong"]\n'
        "$ENDIF\n"
        "$IF V.A.PLANE_COMP_CURR.X == 0 AND V.A.PLANE_COMP_INIT.X == FALSE\n"
        '#MSG ["no plane"]\n'
        "$ENDIF\n"
        "M30\n"
    )
    got = [msg for msg, _ in _run(m, text, cycles=5000)]
    assert got == ["temp 0.00396", "cross 0.005", "temp 0.40396", "cross 0.01", "no plane"]


def test_a_message_is_no_error(tmp_path):
    """#MSG is an event of severity "message"; SIM::last_error keeps the last error."""
    m = Machine(load_machine(_machine_lists(tmp_path / "m")), cycle_s=0.001)
    before = m.last_error
    _run(m, '#MSG ["hello"]\nM30')
    assert m.last_error == before and m.last_error_id == 0


# --------------------------------------------------------------------------- interfaces


def _session(endpoint: str) -> zenoh.Session:
    c = zenoh.Config()
    c.insert_json5("mode", json.dumps("peer"))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", "[]")
    c.insert_json5("connect/endpoints", json.dumps([endpoint]))
    return zenoh.open(c)


def test_messages_reach_errors_zenoh_and_the_web_hmi(loop_thread: asyncio.AbstractEventLoop):
    """The manual's program over the service (as `geo-client nc` sends it): its messages
    are in `errors()`, published on `cnc/t/errors` and listed by the web HMI, with line."""
    m = Machine(load_machine(default_startup_list()), cycle_s=0.001)
    svc = ObjectService(m)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    opts = ZenohOptions(machine="t", listen=[endpoint], publish_period=0.01, status_period=0.05)
    iface = ZenohInterface(svc, opts)
    run_in(loop_thread, iface.start())
    hmi = HmiServer(svc, HmiOptions(port=0, machine="t"))
    run_in(loop_thread, hmi.start())
    zs = _session(endpoint)
    got: queue.Queue[dict] = queue.Queue()
    sub = zs.declare_subscriber("cnc/t/errors", lambda s: got.put(json.loads(s.payload.to_bytes())))
    try:
        wait_until_routed(zs, "cnc/t/status")
        svc.nc.run(MANUAL.read_text(encoding="utf-8"))
        for _ in range(300):
            access.step(svc)
        want = [
            {"severity": "message", "message": msg, "file": "<nc>", "line": line}
            for msg, line in (NOT_INIT_CROSS, NOT_ACTIVE_CROSS)
        ]

        def only_messages(events: list[dict]) -> list[dict]:
            keys = ("severity", "message", "file", "line")
            return [{k: e[k] for k in keys} for e in events if e["severity"] == "message"]

        assert only_messages(svc.errors()) == want
        published: list[dict] = []
        while len(only_messages(published)) < 2:
            published.append(got.get(timeout=10))
        assert only_messages(published) == want
        with urllib.request.urlopen(f"http://{hmi.address}/api/state", timeout=10) as r:
            state = json.loads(r.read())
        assert only_messages(state["errors"]) == want
    finally:
        sub.undeclare()
        zs.close()
        run_in(loop_thread, hmi.close())
        run_in(loop_thread, iface.close())


def test_bad_nc_text_is_refused_over_the_service_with_the_line():
    svc = ObjectService(Machine(load_machine(default_startup_list()), cycle_s=0.001))
    with pytest.raises(AdsError) as exc:
        svc.nc.run("N10 G74 X1\n$IF V.A.BACKLASH_COMP_INIT.X != TRUE\n$ENDIF")
    assert "line 2" in str(exc.value) and "BACKLASH_COMP_INIT" in str(exc.value)
