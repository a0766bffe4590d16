"""NC player (docs/design.md §5): parsing of the manuals' programs, sequencing, COMP, monitoring."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import pytest

from geo_server.machine.motion import Motion
from geo_server.machine.nc import (
    MAX_BLOCKS_PER_CYCLE,
    MachinePort,
    NcError,
    Player,
    parse_program,
    run_lines,
)
from geo_server.model import AxisParams, CompKind

AXES = {"X": 0, "Y": 1, "Z": 2, "C": 3}
DT = 0.001
K = CompKind


@dataclass
class FakePort:
    """Test double of `MachinePort`: moves finish at once, every call is recorded."""

    pos: dict[int, float] = field(default_factory=lambda: dict.fromkeys(range(4), 0.0))
    periods: dict[int, float] = field(default_factory=lambda: {3: 3_600_000.0})
    calls: list[tuple] = field(default_factory=list)
    selected: dict[int, CompKind] = field(default_factory=dict)  # list selection
    active: dict[int, CompKind] = field(default_factory=dict)
    requires: dict[int, CompKind] = field(default_factory=dict)
    frict_allowed: set[int] = field(default_factory=set)
    busy_cycles: int = 0  # in_position stays False this many queries after a move
    _busy: int = 0

    def position(self, slot: int) -> float:
        return self.pos[slot]

    def modulo_period(self, slot: int) -> float:
        return self.periods.get(slot, 0.0)

    def move_linear(self, targets, feed, rapid, next_dirs) -> None:
        self.calls.append(("move", dict(targets), feed, rapid, dict(next_dirs)))
        self.pos.update(targets)
        self._busy = self.busy_cycles

    def home(self, slots: Sequence[int]) -> None:
        self.calls.append(("home", tuple(slots)))

    def in_position(self, slots: Iterable[int]) -> bool:
        if self._busy:
            self._busy -= 1
            return False
        return True

    def stop_axes(self, slots: Iterable[int]) -> None:
        self.calls.append(("stop", tuple(slots)))

    def comp(self, slot: int, on: bool, kinds: CompKind, no_move: bool) -> int:
        self.calls.append(("comp", slot, on, kinds, no_move))
        if on and kinds & K.FRICT and slot not in self.frict_allowed:
            return 70495  # P-ERR-70495 (000 p.73)
        cur = self.active.get(slot, K(0))
        self.active[slot] = cur | kinds if on else cur & ~kinds
        return 0

    def comp_off_all(self, slot: int, no_move: bool) -> int:
        self.calls.append(("off_all", slot, no_move))
        self.active[slot] = K(0)
        return 0

    def comp_settled(self, slots: Iterable[int]) -> bool:
        return True

    def effective(self, slot: int) -> CompKind:
        return self.active.get(slot, K(0))

    def required(self, slot: int) -> CompKind:
        return self.requires.get(slot, K(0)) & self.selected.get(slot, K(0))

    def program_end(self) -> None:
        self.calls.append(("end",))

    def release_axis(self, slot: int) -> None:
        self.calls.append(("release", slot))

    def report(self, error_id: int, message: str, line: int) -> None:
        self.calls.append(("report", error_id, line))

    def initialised(self, slot: int) -> CompKind:
        return self.selected.get(slot, K(0))

    def current(self, slot: int, kind: CompKind) -> float:
        return 0.0

    def message(self, text: str, line: int) -> None:
        self.calls.append(("msg", text, line))

    def kinds(self, name: str) -> list[tuple]:
        return [c for c in self.calls if c[0] == name]


def play(text: str, port: FakePort | None = None, cycles: int = 100) -> tuple[Player, FakePort]:
    port = port or FakePort()
    player = Player(parse_program(text, AXES), port, DT)
    for _ in range(cycles):
        player.step()
    return player, port


# --------------------------------------------------------------------------- parsing


def test_parse_manual_comp_examples_000_p94():
    prog = parse_program(
        "N10 X[COMP OFF CROSS PLANE]\n"
        "N50 X[COMP OFF CROSS] Y[COMP ON LEAD TEMP]\n"
        "N100 Z[COMP OFF_ALL]\n"
        "N200 Y[COMP OFF_ALL NO_MOVE]\n"
        "N300 X [ COMP ON CROSS TEMP ]\n",
        AXES,
    )
    b = prog.blocks
    assert [x.number for x in b] == [10, 50, 100, 200, 300]
    c = b[0].comps[0]
    assert (c.slot, c.on, c.kinds, c.off_all, c.no_move) == (0, False, K.CROSS | K.PLANE, 0, 0)
    assert [(c.slot, c.on, c.kinds) for c in b[1].comps] == [
        (0, False, K.CROSS),
        (1, True, K.LEAD | K.TEMP),
    ]
    assert (b[2].comps[0].slot, b[2].comps[0].off_all, b[2].comps[0].no_move) == (2, 1, 0)
    assert (b[3].comps[0].slot, b[3].comps[0].off_all, b[3].comps[0].no_move) == (1, 1, 1)
    assert b[4].comps[0].kinds == K.CROSS | K.TEMP


def test_missing_closing_bracket_is_warned_not_fatal():
    prog = parse_program("N10 X[COMP OFF CROSS PLANE\nM30", AXES)
    assert prog.blocks[0].comps[0].kinds == K.CROSS | K.PLANE
    assert [(w.line, w.severity) for w in prog.warnings] == [(1, "warning")]
    assert "missing ']'" in prog.warnings[0].message


def test_line_continuation_and_comments():
    prog = parse_program(
        "; header comment\n"
        "N10 X[COMP ON BACKLASH \\\n"
        "   FRICT CROSSTALK] (inline comment) ; trailing\n"
        "N20 G01 X1.5 F600 ( unclosed comment\n"
        "M30\n",
        AXES,
    )
    assert [b.line for b in prog.blocks] == [2, 4, 5]
    assert prog.blocks[0].comps[0].kinds == K.BACKLASH | K.FRICT | K.CROSSTALK
    b = prog.blocks[1]
    assert (b.motion, b.axes, b.feed) == (1, {0: 15_000.0}, 100_000.0)  # 600 mm/min = 10 mm/s


def test_parse_motion_words_units_and_modal_codes():
    b = parse_program("N5 G91 G00 X-200 y.5 Z+3 C90 F1000", AXES).blocks[0]
    assert (b.absolute, b.motion) == (False, 0)
    assert b.axes == {0: -2_000_000.0, 1: 5000.0, 2: 30_000.0, 3: 900_000.0}
    assert b.feed == pytest.approx(1000 / 60 * 10_000)


def test_parse_dwell_home_goto_end():
    prog = parse_program(
        "N10: G04 1\nG04 X0.25\nN20 G74 X1 Y2 Z3\nG74 C\n$GOTO [N10]\n$GOTO N20\nM30", AXES
    )
    b = prog.blocks
    assert (b[0].number, b[0].label, b[0].dwell) == (10, True, 1.0)
    assert b[1].dwell == 0.25
    assert b[2].home == (0, 1, 2) and b[3].home == (3,)
    assert (b[4].goto, b[5].goto) == (0, 2)
    assert b[6].end and prog.warnings == []


@pytest.mark.parametrize(
    ("text", "line", "fragment"),
    [
        ("X10\nQ5", 2, "unknown axis"),
        ("G17 X1", 1, "G17"),
        ("M3", 1, "M3"),
        ("X[COMP ON]", 1, "at least one"),
        ("X[COMP ON SPEED]", 1, "unknown compensation"),
        ("X[COMP OFF_ALL TEMP]", 1, "OFF_ALL"),
        ("X[ON TEMP]", 1, "COMP must be the first"),
        ("N1 X1\n$GOTO N99", 2, "N99"),
        ("G01 X10", 1, "feed"),
        ("G04", 1, "dwell"),
        ("G04 1 X2 Y3", 1, "G04"),
        ("X1 X2", 1, "twice"),
        ("G01 F0 X1", 1, "F must be > 0"),
        ("X1 N10", 1, "first"),
        ("X#1", 1, "unexpected"),
        ("$GOTO N10 X1\nN10", 1, "alone"),
    ],
)
def test_parse_errors_have_line_and_message(text, line, fragment):
    with pytest.raises(NcError) as exc:
        parse_program(text, AXES)
    assert exc.value.line == line
    assert fragment in str(exc.value)


def test_missing_m30_is_warned_for_programs_only():
    assert parse_program("X1", AXES).warnings[0].message.startswith("no M30")
    assert parse_program("X1", AXES, mdi=True).warnings == []


# --------------------------------------------------------------------------- playing

TEMP_PROGRAM = """\
N10: G90 G01 X0 F1000
G04 1
N10 X100
G04 1
N10 X80
G04 1
N10 X50
G04 1
N20 X-200
G04 1

$GOTO [N10]
M30
"""


def test_temperature_program_000_p24_loops_with_goto():
    player, port = play(TEMP_PROGRAM, cycles=3 * 10 * 1002)
    moves = [c[1][0] for c in port.kinds("move")]
    cycle_mm = [0.0, 1_000_000.0, 800_000.0, 500_000.0, -2_000_000.0]
    assert moves[:10] == cycle_mm * 2
    assert all(c[2] == pytest.approx(1000 / 60 * 10_000) for c in port.kinds("move"))
    assert player.running and not player.finished and port.kinds("end") == []


def test_temperature_program_timing_one_dwell_is_1000_cycles():
    player, port = play(TEMP_PROGRAM, cycles=1)
    assert len(port.kinds("move")) == 1  # X0 issued in cycle 1
    for _ in range(1):
        player.step()  # cycle 2: move done, G04 1 starts
    for _ in range(999):
        player.step()
        assert len(port.kinds("move")) == 1
    player.step()  # cycle 1002: 1000 cycles after the dwell started
    assert len(port.kinds("move")) == 2


def test_g91_incremental_and_g90_modulo_shortest_way():
    port = FakePort()
    port.pos[3] = 3_500_000.0  # C at 350°
    player, port = play("G91 X10\nX10\nX-5\nG90 C10\nC180\nM30", port)
    moves = [c[1] for c in port.kinds("move")]
    assert moves[:3] == [{0: 100_000.0}, {0: 200_000.0}, {0: 150_000.0}]
    assert moves[3] == {3: 3_700_000.0}  # 350° -> 10° goes +20°, unwrapped
    assert moves[4] == {3: pytest.approx(5_400_000.0)}  # 370° -> 540° (=180°), +170°
    assert player.finished and port.kinds("end") == [("end",)]


def test_g00_is_rapid_and_default():
    _, port = play("X1 Y2\nG01 X3 F60\nG00 X0\nM30")
    assert [(c[2], c[3]) for c in port.kinds("move")] == [
        (None, True),
        (pytest.approx(10_000.0), False),
        (None, True),
    ]


def test_lookahead_directions_through_dwell_and_goto():
    _, port = play(TEMP_PROGRAM, cycles=6 * 1002)
    dirs = [c[4] for c in port.kinds("move")]
    # X0 -> X100 (+), X100 -> X80 (−), X80 -> X50 (−), X50 -> X-200 (−), X-200 -> X0 (+)
    assert dirs[:5] == [{0: 1}, {0: -1}, {0: -1}, {0: -1}, {0: 1}]


def test_dwell_cycle_count_rounds_and_waits_for_motion():
    port = FakePort(busy_cycles=3)
    player = Player(parse_program("X1\nG04 0.0024\nY1\nM30", AXES), port, DT)
    counts = []
    for _ in range(11):
        player.step()
        counts.append(len(port.kinds("move")))
    # X1 in cycle 1; in position at cycle 5; dwell round(2.4) = 2 cycles; Y1 in cycle 7,
    # in position (and M30) at cycle 11
    assert counts == [1, 1, 1, 1, 1, 1, 2, 2, 2, 2, 2]
    assert player.finished


def test_friction_example_000_p73_and_70495():
    text = (
        "N15 X[COMP ON FRICT] ;Activates X axis\n"
        "N25 Y[COMP OFF FRICT] ;Deactivates Y axis\n"
        "N35 X22 Y33 Z44\n"
        "N45 X[COMP OFF FRICT] ;Deactivates X axis\n"
        "N55 M30 ;Program end\n"
    )
    player, port = play(text, FakePort(frict_allowed={0, 1}))
    assert player.finished and player.error is None
    assert port.kinds("comp") == [
        ("comp", 0, True, K.FRICT, False),
        ("comp", 1, False, K.FRICT, False),
        ("comp", 0, False, K.FRICT, False),
    ]
    assert port.kinds("move")[0][1] == {0: 220_000.0, 1: 330_000.0, 2: 440_000.0}
    assert port.calls[-1] == ("end",)

    player, port = play(text, FakePort(frict_allowed=set()))
    assert not player.running and not player.finished
    assert (player.error.error_id, player.error.line) == (70495, 1)
    assert "P-AXIS-00522" in player.error.message
    assert port.kinds("report") == [("report", 70495, 1)]
    assert port.kinds("move") == [] and port.kinds("end") == []


def test_70435_required_compensation_not_effective():
    port = FakePort(selected={0: K.TEMP | K.LEAD}, requires={0: K.TEMP | K.LEAD | K.CROSS})
    text = "G74 X1\nX[COMP ON LEAD]\nN30 X10\nM30"
    player, port = play(text, port)
    assert port.kinds("home") == [("home", (0,))]  # homing is not monitored
    assert player.error.error_id == 70435 and player.error.line == 3
    assert "TEMP" in player.error.message and "CROSS" not in player.error.message
    assert port.kinds("move") == [] and port.kinds("report") == [("report", 70435, 3)]


def test_70435_not_raised_without_monitoring_manual_mode():
    port = FakePort(selected={0: K.TEMP}, requires={0: K.TEMP})
    player = run_lines("X10", port, AXES, DT, monitor=False)
    player.step()
    assert player.error is None and port.kinds("move")[0][1] == {0: 100_000.0}


def test_70435_satisfied_and_unmoved_axes_not_checked():
    port = FakePort(selected={0: K.TEMP, 1: K.TEMP}, requires={0: K.TEMP, 1: K.TEMP})
    player, port = play("X[COMP ON TEMP]\nX10 Y0\nM30", port)
    assert player.finished and player.error is None  # Y does not move
    assert len(port.kinds("move")) == 1


def test_comp_off_all_no_move_and_program_end():
    player, port = play("N100 Z[COMP OFF_ALL]\nN200 Y[COMP OFF_ALL NO_MOVE]\nN55 M30")
    assert port.kinds("off_all") == [("off_all", 2, False), ("off_all", 1, True)]
    assert player.finished and port.calls[-1] == ("end",)


def test_goto_self_loop_is_an_error_not_a_hang():
    player, _ = play("N10 $GOTO N10\nM30", cycles=1)
    assert not player.running and player.error.error_id == 0
    assert str(MAX_BLOCKS_PER_CYCLE) in player.error.message


def test_end_of_text_is_program_end_but_not_for_mdi():
    player, port = play("X1")
    assert player.finished and port.kinds("end") == [("end",)]
    port = FakePort()
    player = run_lines("X[COMP ON TEMP]\nX2", port, AXES, DT)
    for _ in range(5):
        player.step()
    assert player.finished and port.kinds("end") == []
    player = run_lines("M30", port, AXES, DT)
    player.step()
    assert port.kinds("end") == [("end",)]


def test_m30_in_a_motion_block_ends_after_the_motion():
    port = FakePort(busy_cycles=2)
    player = Player(parse_program("X1 M30", AXES), port, DT)
    player.step()
    assert player.running and port.kinds("end") == []
    for _ in range(3):
        player.step()
    assert player.finished and port.kinds("end") == [("end",)]


# --------------------------------------------------------------------------- real motion


class MotionPort(FakePort):
    """FakePort whose motion is the real `Motion` (adapter for an end-to-end test)."""

    def __init__(self, motion: Motion) -> None:
        super().__init__()
        self.m = motion

    def position(self, slot: int) -> float:
        return float(self.m.pos[slot])

    def modulo_period(self, slot: int) -> float:
        return float(self.m.period[slot])

    def move_linear(self, targets, feed, rapid, next_dirs) -> None:
        self.calls.append(("move", dict(targets), feed, rapid, dict(next_dirs)))
        self.m.move_linear(targets, feed, rapid)
        for slot, d in next_dirs.items():
            self.m.announce_next(slot, d)

    def home(self, slots: Sequence[int]) -> None:
        for s in slots:
            self.m.home(s)

    def in_position(self, slots: Iterable[int]) -> bool:
        return self.m.all_in_position(slots)


def test_player_drives_real_motion_cycle_by_cycle():
    params = [AxisParams(log_nr=i + 1, v_max=1e6, a_max=1.0) for i in range(4)]
    m = Motion(params, DT)
    port: MachinePort = MotionPort(m)
    # F60 mm/min = 10000 units/s; 2 mm at a = 10000 units/s²: ta 1 s, T = 3 s
    player = Player(parse_program("G74 X\nG01 X2 F60\nG04 0.5\nX0\nM30", AXES), port, DT)
    cycles = 0
    while player.running and cycles < 10_000:
        player.step()
        m.step()
        cycles += 1
    assert player.finished and m.homed[0] and m.pos[0] == 0.0
    # G74 (1) + G01 issued and sampled (3000) + dwell (1 + 500) + X0 (3000); M30 in the
    # cycle after the last sample
    assert cycles == 1 + 3000 + 1 + 500 + 3000


def test_warnings_of_one_program_are_capped():
    """500 unclosed COMP groups: the first 20 warnings name their lines, one more line
    counts the rest (the error list keeps 100 events; one program must not flush it)."""
    text = "\n".join(f"N{i} X[COMP ON TEMP" for i in range(500))
    prog = parse_program(text, {"X": 0}, mdi=True)
    assert len(prog.warnings) == 21
    assert [w.line for w in prog.warnings[:3]] == [1, 2, 3]
    assert prog.warnings[-1].message == "480 more warnings not listed"


# --------------------------------------------------------------------------- axis exchange


def test_axis_exchange_parsing():
    prog = parse_program(
        "N10 #PUT AX [X, B]\n"
        "n20: #put ax [y]\n"
        "N30 #AX RELEASE ALL ; every axis\n"
        "N40 #CALL AX [X, 1, 0], [Y, 2, 1] [Z, 3, 2]\n"
        "N50 #PUT AX [ALL]\n"
        "N60 #PUT AX \\\n  [Z]\n"
        "M30\n",
        AXES,
    )
    b = prog.blocks
    assert b[0].release == (0,) and b[0].number == 10
    assert b[1].release == (1,) and b[1].label
    assert b[2].release == tuple(sorted(AXES.values()))
    assert b[3].call == (0, 1, 2)
    assert b[4].release == () and b[5].release == (2,)
    # no error for names the machine does not have (the programming manual), but a warning
    messages = [w.message for w in prog.warnings]
    assert any("B is not an axis" in m for m in messages)
    assert any("#PUT AX ALL, without brackets" in m for m in messages)


def test_axis_exchange_in_the_player():
    """A released axis is released once, cannot be programmed until it is called back,
    and `$GOTO` into an exchange block works."""
    player, port = play(
        "N10 #PUT AX [X]\nN20 #PUT AX [X]\nN30 #CALL AX [X, 1, 0]\nN40 X5\n"
        "N50 $GOTO N70\nN60 X9\nN70 #AX RELEASE [X]\nN80 X1\nM30"
    )
    assert port.kinds("release") == [("release", 0), ("release", 0)]
    assert len(port.kinds("move")) == 1  # N40; N80 fails
    assert player.error is not None and player.error.line == 8
    assert "axis X is not in the channel" in player.error.message


def test_70435_while_moving_stops_the_block_and_its_axes():
    """Issue 45 #5, 000 §5.3 p.97: "The CNC then outputs the error message P-ERR-70435
    if the axis is moved in automatic mode and the specified axis compensations are not
    active": also when a required compensation drops out during the motion, not only at
    the block's start. The block's axes come to a controlled stop; no later block runs."""
    port = FakePort(selected={0: K.LEAD}, requires={0: K.LEAD}, active={0: K.LEAD})
    port.busy_cycles = 10
    player = Player(parse_program("N10 G01 X10 F1000\nN20 Y5\nM30", AXES), port, DT)
    for _ in range(3):
        player.step()
    assert player.running and player.motion_wait() == (0,)
    port.active[0] = K(0)  # e.g. the axis lost its reference
    assert player.motion_wait() == ()  # no batch may skip the cycle that reports it
    player.step()
    assert not player.running and (player.error.error_id, player.error.line) == (70435, 1)
    assert port.kinds("stop") == [("stop", (0,))]
    assert len(port.kinds("move")) == 1 and port.kinds("end") == []
