"""A small NC program player for the manuals' test programs (docs/design.md §5).

Pure state machine: no threads, no sleeping, no wall clock. `Player.step()` is called once
per GEO cycle *before* motion advances and talks to the machine only through the
`MachinePort` protocol.

Supported subset (docs/design.md §5; TF5200 axis compensation manual, 000):

* `N<n>` block numbers, also as labels `N10:` (000 p.24); `;` comments to the end of the
  line and `( … )` comments (an unclosed `(` comments out the rest of the line);
  `\\` at the end of a line continues the block on the next line (000 §5.1).
* `G90`/`G91` absolute/incremental (modal, default G90), `G00`/`G01` rapid/linear
  (modal, default G00 so that the friction example `N35 X22 Y33 Z44` runs without F),
  `F<mm/min>` (modal; rotary axes °/min), axis words `<name><value>` in mm or degrees.
* `G04 <s>` or `G04 X<s>` dwell in seconds, `round(s/dt)` cycles, at least one.
* `G74 <axis>[<order>] …` homing: the axes are marked referenced in place (the order
  numbers of `G74 X1 Y2 Z3`, 000 p.96, are accepted and ignored).
* `<axis>[COMP ON|OFF <kinds…> | OFF_ALL [NO_MOVE]]` (000 §5.1, p.94) with kinds
  BACKLASH CROSS PLANE LEAD TEMP FRICT CROSSTALK, several axes per block; a missing
  closing `]` at the end of a block (000 prints `N10 X[COMP OFF CROSS PLANE`) is
  accepted with a warning.
* `$GOTO N<n>` and `$GOTO [N<n>]`: jump to the block labelled `N<n>:`, else to the first
  block numbered `N<n>` (the temperature program of 000 p.24 numbers three blocks N10).
* `M30` (and `M02`) program end.
* `$IF <condition>` … `$ELSEIF <condition>` … `$ELSE` … `$ENDIF` (nested), each alone in
  its block, and `#MSG ["text"]` (000 §5.2 p.96, 001 §5.2): a condition compares
  operands with `==`, `!=`, `<`, `<=`, `>`, `>=` (or is one operand, true when not 0),
  joined by `AND`/`OR` (AND binds first); operands are numbers, `TRUE`/`FALSE` and the
  V.A. variables of 000 p.95-96, `V.A.<name>_COMP_INIT|ACTIVE|CURR.<axis>` or `[<index>]`
  (the axis' index in the channel, from 0). INIT: the compensation is enabled in the axis
  list and its configuration is valid (`MachinePort.initialised`); ACTIVE: it is
  effective (`MachinePort.effective`, the state the 70435 monitoring checks); CURR: its
  present output in mm (or °). Blanks inside the name (`V. A. CROSS_COMP_INIT. X`, as
  the English edition extracts) are accepted. A `#MSG` is reported with its line
  (`MachinePort.message`); at most one per cycle. A block of only `...` (the manuals'
  elision, `N150 ...` on p.96) is skipped with a warning.
* Axis exchange, alone in its block: `#PUT AX [X, Y]`, `#PUT AX ALL`, `#AX RELEASE […]`
  release axes from the channel (their manual-activation compensations are deselected,
  000 §5.1); `#CALL AX [X, 1, 0]` brings an axis back. Programming a released axis is an
  error. Every program starts with all axes in the channel.
* Volumetric compensation, alone in its block (004 §4.1-4.2, p.21-23): `#VOLCOMP ON
  [ID0]`, `#VOLCOMP ON [ID=0 NO_MOVE CFACT_X=0.5]`, `#VOLCOMP OFF [ID=0]`, `#VOLCOMP ON
  ALL`, `#VOLCOMP OFF ALL`, `#VOLCOMP [ID0 UPDATE]`; the program waits until the ramp
  (filter_steps) or the update is done ("The machine stops when a #VOLCOMP command is
  used", 004 p.22).

Monitoring (000 §5.3, p.97): a motion block that would move an axis whose required
compensations (`MachinePort.required`) are not all effective raises P-ERR-70435 and stops
the program; homing (G74) is not monitored. Errors of `COMP` commands (e.g. P-ERR-70495,
`COMP ON FRICT` without `lr_param.frict_comp`, 000 p.73) come from the port.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Protocol

from geo_server.errors import CncErrorId, GeoError
from geo_server.model import CompKind, Diagnostic
from geo_server.units import UNITS_PER_MM

#: Internal units per mm / degree (docs/design.md §3).

#: Emulator-internal NC runtime errors (runaway `$GOTO` loop, missing feed) carry ID 0.
ERR_NC_RUNTIME = 0

#: At most this many blocks without motion/dwell are executed in one cycle.
MAX_BLOCKS_PER_CYCLE = 1000

KIND_WORDS: dict[str, CompKind] = {
    "BACKLASH": CompKind.BACKLASH,
    "CROSS": CompKind.CROSS,
    "PLANE": CompKind.PLANE,
    "LEAD": CompKind.LEAD,
    "TEMP": CompKind.TEMP,
    "FRICT": CompKind.FRICT,
    "CROSSTALK": CompKind.CROSSTALK,
}

_KNOWN_ERRORS: dict[int, str] = {
    CncErrorId.FRICT_NOT_SELECTED: (
        "COMP ON FRICT but lr_param.frict_comp (P-AXIS-00522) is not set"
    ),
}


class NcError(GeoError, ValueError):
    """An error in the NC program text, with the 1-based line number."""

    def __init__(self, line: int, message: str) -> None:
        super().__init__(f"line {line}: {message}")
        self.line = line
        self.message = message


class MachinePort(Protocol):
    """What the player needs from the machine (implemented by the GEO-cycle machine).

    Positions in internal units, feeds in units/s. Slots are the axis indices used by
    `Motion` and by `parse_program(axis_names=…)`.
    """

    def position(self, slot: int) -> float:
        """Command position of the axis (unwrapped for modulo axes)."""
        ...

    def modulo_period(self, slot: int) -> float:
        """Modulo period in internal units, 0.0 for non-modulo axes."""
        ...

    def move_linear(
        self,
        targets: dict[int, float],
        feed: float | None,
        rapid: bool,
        next_dirs: dict[int, int],
    ) -> None:
        """Start a synchronised move (G00 when `rapid`, else G01 at path `feed`).

        `next_dirs` is the lookahead: direction (−1/0/+1) of each axis' next programmed
        move, for `Motion.announce_next` / reversal detection.
        """
        ...

    def home(self, slots: Sequence[int]) -> None:
        """G74: reference the axes."""
        ...

    def in_position(self, slots: Iterable[int]) -> bool:
        """True when every axis in `slots` is at rest on its target."""
        ...

    def stop_axes(self, slots: Iterable[int]) -> None:
        """Controlled stop of these axes (an error during their motion block)."""
        ...

    def comp(self, slot: int, on: bool, kinds: CompKind, no_move: bool) -> int:
        """`COMP ON|OFF kinds` for one axis; returns 0 or an error ID (e.g. 70495)."""
        ...

    def comp_off_all(self, slot: int, no_move: bool) -> int:
        """`COMP OFF_ALL`; returns 0 or an error ID."""
        ...

    def volcomp(self, cmd: VolcompCommand) -> tuple[int, str]:
        """`#VOLCOMP …` (004 p.21-23); returns (0, "") or (error ID, message)."""
        ...

    def volcomp_settled(self) -> bool:
        """True when the volumetric ramps and updates started by #VOLCOMP are done."""
        ...

    def volcomp_active(self, ident: int) -> bool:
        """`V.G.VOLCOMP[i].ACTIVE` (004 p.18): compensation `ident` active (or ramping)."""
        ...

    def volcomp_file(self, ident: int, index: int) -> str:
        """`V.G.VOLCOMP[i].FILE[j]` (004 p.18): the name of its correction file j, as
        written in its VOLC list or last given by the program; "" if none."""
        ...

    def set_volcomp_file(self, ident: int, index: int, name: str) -> tuple[int, str]:
        """`V.G.VOLCOMP[i].FILE[j] = "name"`: the file the next UPDATE reads as file j;
        returns (0, "") or (error ID, message)."""
        ...

    def comp_settled(self, slots: Iterable[int]) -> bool:
        """True when the offset ramps started by COMP on these axes have finished."""
        ...

    def effective(self, slot: int) -> CompKind:
        """Compensations currently effective on the axis."""
        ...

    def required(self, slot: int) -> CompKind:
        """`prog_movement_requires_compensations` ∩ compensations selected in the list."""
        ...

    def program_end(self) -> None:
        """M30: deselect manual-activation compensations (000 §5.1); reduce the volumetric
        compensations linked to the channel (004 p.24)."""
        ...

    def release_axis(self, slot: int) -> None:
        """`#PUT AX`: the axis leaves the channel; its manual-activation compensations
        are deselected (000 §3.2 p.17, §5.1)."""
        ...

    def report(self, error_id: int, message: str, line: int) -> None:
        """Log an NC runtime error (the player stops after reporting)."""
        ...

    def initialised(self, slot: int) -> CompKind:
        """`V.A.<name>_COMP_INIT` (000 p.95): compensations enabled in the axis list whose
        configuration is valid (they can become effective)."""
        ...

    def current(self, slot: int, kind: CompKind) -> float:
        """`V.A.<name>_COMP_CURR` (000 p.96): the compensation's present output in mm
        (° on rotary axes)."""
        ...

    def message(self, text: str, line: int) -> None:
        """`#MSG ["text"]` (000 p.96): hand the text to every interface with its line."""
        ...


# --------------------------------------------------------------------------- program


@dataclass(frozen=True)
class CompCommand:
    """One `<axis>[COMP …]` group (000 §5.1)."""

    slot: int
    axis: str
    on: bool
    kinds: CompKind
    off_all: bool = False
    no_move: bool = False


@dataclass(frozen=True)
class VolcompCommand:
    """`#VOLCOMP ON|OFF [ID=.. NO_MOVE CFACT_X/Y/Z=..]`, `ON ALL`/`OFF ALL`, `#VOLCOMP
    [ID=.. UPDATE]` (004 §4.1-4.2, p.21-23). `ids` None: ALL."""

    on: bool
    ids: tuple[int, ...] | None
    no_move: bool = False
    cfact: tuple[float, float, float] | None = None
    update: bool = False


#: The V.A. variables of each compensation (000 §5.2 p.95-96): INIT for six of them,
#: ACTIVE and CURR also for BACKLASH (001 §5.2 lists CROSS, PLANE, LEAD, TEMP only).
VA_FIELDS: dict[str, frozenset[str]] = {
    "INIT": frozenset({"CROSS", "PLANE", "LEAD", "TEMP", "FRICT", "CROSSTALK"}),
    "ACTIVE": frozenset(KIND_WORDS),
    "CURR": frozenset(KIND_WORDS),
}


@dataclass(frozen=True)
class VaVariable:
    """`V.A.<word>_COMP_<field>.<axis>` or `[<index>]` (000 p.95-96, 001 §5.2)."""

    kind: CompKind
    field: str  # INIT | ACTIVE | CURR
    slot: int

    def read(self, port: MachinePort) -> float:
        """The variable's value now: 0/1 for INIT and ACTIVE, mm (°) for CURR."""
        if self.field == "INIT":
            return float(bool(port.initialised(self.slot) & self.kind))
        if self.field == "ACTIVE":
            return float(bool(port.effective(self.slot) & self.kind))
        return float(port.current(self.slot, self.kind))


@dataclass(frozen=True)
class VgVariable:
    """`V.G.VOLCOMP[i].ACTIVE` (BOOLEAN) or `V.G.VOLCOMP[i].FILE[j]` (STRING), 004 p.18."""

    ident: int
    index: int | None = None  # j of FILE[j]; None: ACTIVE

    def read(self, port: MachinePort) -> float | str:
        if self.index is None:
            return float(port.volcomp_active(self.ident))
        return port.volcomp_file(self.ident, self.index)


Operand = VaVariable | VgVariable | float | str

_COMPARE: dict[str, Callable[[Any, Any], bool]] = {  # (texts: == and != only)
    "==": lambda a, b: a == b,
    "!=": lambda a, b: a != b,
    "<": lambda a, b: a < b,
    "<=": lambda a, b: a <= b,
    ">": lambda a, b: a > b,
    ">=": lambda a, b: a >= b,
}


@dataclass(frozen=True)
class Condition:
    """A `$IF` condition: comparisons (`left op right`) OR-ed over AND-ed groups."""

    any_of: tuple[tuple[tuple[Operand, str, Operand], ...], ...]

    def holds(self, port: MachinePort) -> bool:
        def value(x: Operand) -> float | str:
            return x.read(port) if isinstance(x, (VaVariable, VgVariable)) else x

        return any(
            all(_COMPARE[op](value(a), value(b)) for a, op, b in group) for group in self.any_of
        )


@dataclass
class Branch:
    """`$IF` / `$ELSEIF` / `$ELSE` / `$ENDIF`; `next` is the block index of the next branch of
    the same `$IF` (where a false condition goes on), `end` that of its `$ENDIF`."""

    kind: str
    condition: Condition | None = None
    next: int = -1
    end: int = -1


@dataclass
class Block:
    """One NC block (a logical line after `\\` continuation)."""

    line: int
    text: str
    number: int | None = None
    label: bool = False
    motion: int | None = None  # 0 = G00, 1 = G01 (modal, programmed in this block)
    absolute: bool | None = None  # G90 True, G91 False (modal)
    feed: float | None = None  # units/s (modal)
    axes: dict[int, float] = field(default_factory=dict)  # slot -> units
    dwell: float | None = None  # seconds
    home: tuple[int, ...] = ()
    comps: tuple[CompCommand, ...] = ()
    goto: int | None = None  # index of the target block
    goto_number: int | None = None
    end: bool = False
    release: tuple[int, ...] = ()  # `#PUT AX` / `#AX RELEASE`: slots leaving the channel
    call: tuple[int, ...] = ()  # `#CALL AX`: slots coming back
    volcomp: VolcompCommand | None = None  # `#VOLCOMP …` (004 p.21)
    branch: Branch | None = None  # `$IF` / `$ELSEIF` / `$ELSE` / `$ENDIF`
    message: str | None = None  # `#MSG ["text"]` (000 p.96)
    volcomp_file: tuple[int, int, str] | None = None  # `V.G.VOLCOMP[i].FILE[j] = "…"`


@dataclass
class Program:
    """A parsed NC program."""

    blocks: list[Block]
    warnings: list[Diagnostic] = field(default_factory=list)
    axis_names: dict[str, int] = field(default_factory=dict)


_TOKEN = re.compile(
    r"""\s*(?:
      (?P<goto>\$GOTO)
    | (?P<group>[A-Z][A-Z0-9_]*)\s*\[(?P<content>[^\]]*)(?P<close>\])?
    | (?P<addr>[A-Z]+)\s*(?:=\s*)?(?P<value>[+-]?(?:\d+\.?\d*|\.\d+))?(?P<colon>:)?
    | (?P<number>[+-]?(?:\d+\.?\d*|\.\d+))
    )""",
    re.VERBOSE,
)
#: Warnings of one program kept for the error list (the rest are counted in one line).
MAX_WARNINGS = 20
_GOTO_TARGET = re.compile(r"\s*(?:\[\s*N(\d+)\s*\]|N(\d+))")
#: The axis exchange commands, as a regular expression alternative.
_EXCHANGE_COMMANDS = r"PUT\s+AX|AX\s+RELEASE|CALL\s+AX"
#: Axis exchange: `#PUT AX [X, B]`, `#PUT AX ALL`, `#AX RELEASE […]`, `#CALL AX [X, 1, 0]`,
#: programmed alone in their block (an optional block number first).
_AXIS_EXCHANGE = re.compile(
    rf"(?:N(?P<n>\d+)(?P<colon>:)?\s*)?#\s*(?P<cmd>{_EXCHANGE_COMMANDS})\b\s*(?P<rest>.*)"
)
_EXCHANGE_WORD = re.compile(rf"#\s*(?:{_EXCHANGE_COMMANDS})\b")
_EXCHANGE_GROUP = re.compile(r"\s*\[(?P<content>[^\]]*)\]")


def parse_program(text: str, axis_names: Mapping[str, int], *, mdi: bool = False) -> Program:
    """Parse NC text into blocks; raises `NcError` with the line number on errors.

    `axis_names` maps axis names (case-insensitive, letters) to slots. With `mdi` a
    missing M30 is not warned about.
    """
    names = {k.upper(): v for k, v in axis_names.items()}
    prog = Program(blocks=[], axis_names=names)
    for line, body in _logical_lines(text):
        block = _parse_block(line, body, names, prog.warnings)
        if block is not None:
            prog.blocks.append(block)
    _resolve_gotos(prog.blocks)
    _resolve_branches(prog.blocks)
    _check_feed(prog.blocks)
    if not mdi and not any(b.end for b in prog.blocks):
        prog.warnings.append(_warning(0, "no M30: the end of the text ends the program"))
    if len(prog.warnings) > MAX_WARNINGS:
        # every warning becomes an event in the error list (100 deep) at the cycle that
        # starts the program: a few tell the story, thousands would flush the list
        more = len(prog.warnings) - MAX_WARNINGS
        prog.warnings[MAX_WARNINGS:] = [_warning(0, f"{more} more warnings not listed")]
    return prog


def _warning(line: int, message: str) -> Diagnostic:
    return Diagnostic(severity="warning", message=message, file="<nc>", line=line)


def _strip_comments(raw: str) -> str:
    """Remove `;` comments and `( … )` comments (unclosed `(` runs to the line end);
    inside a `"…"` text (`#MSG`) neither starts a comment."""
    out, depth, quoted = [], 0, False
    for ch in raw:
        if depth == 0 and ch == '"':
            quoted = not quoted
        if quoted or (depth == 0 and ch == '"'):
            out.append(ch)
            continue
        if depth == 0 and ch == ";":
            break
        if ch == "(":
            depth += 1
        elif ch == ")" and depth:
            depth -= 1
        elif depth == 0:
            out.append(ch)
    return "".join(out).strip()


def _logical_lines(text: str) -> Iterable[tuple[int, str]]:
    """Yield (first line number, block text) with `\\` continuations joined."""
    start = 0
    parts: list[str] = []
    for i, raw in enumerate(text.splitlines(), start=1):
        body = _strip_comments(raw)
        if not parts:
            start = i
        if body.endswith("\\"):
            parts.append(body[:-1])
            continue
        parts.append(body)
        joined = " ".join(p.strip() for p in parts).strip()
        parts = []
        if joined:
            yield start, joined
    if parts:
        joined = " ".join(p.strip() for p in parts).strip()
        if joined:
            yield start, joined


@dataclass
class _Words:
    """Raw tokens of one block before interpretation."""

    number: int | None = None
    label: bool = False
    gcodes: list[int] = field(default_factory=list)
    mcodes: list[int] = field(default_factory=list)
    feed: float | None = None
    axes: list[tuple[str, float | None]] = field(default_factory=list)
    numbers: list[float] = field(default_factory=list)
    groups: list[tuple[str, str]] = field(default_factory=list)
    goto: int | None = None


def _tokenize(line: int, body: str, warnings: list[Diagnostic]) -> _Words:
    """Split a block into words, bracket groups, bare numbers and `$GOTO`."""
    w, text, pos = _Words(), body.upper(), 0
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if m is None or m.end() == pos:
            raise NcError(line, f"unexpected {text[pos:].strip()[:20]!r}")
        pos = m.end()
        if m["goto"]:
            pos = _goto_target(line, text, pos, w)
        elif m["group"]:
            if m["close"] is None:
                warnings.append(_warning(line, f"missing ']' after {m['group']}[{m['content']}"))
            w.groups.append((m["group"], m["content"]))
        elif m["addr"]:
            _add_word(line, w, m["addr"], m["value"], bool(m["colon"]))
        elif m["number"] is not None:
            w.numbers.append(float(m["number"]))
    return w


def _goto_target(line: int, text: str, pos: int, w: _Words) -> int:
    m = _GOTO_TARGET.match(text, pos)
    if m is None:
        raise NcError(line, "$GOTO needs a target N<number> or [N<number>]")
    w.goto = int(m[1] or m[2])
    return m.end()


def _add_word(line: int, w: _Words, addr: str, value: str | None, colon: bool) -> None:
    """Sort one address word into the block's word lists."""
    if colon and addr != "N":
        raise NcError(line, f"unexpected ':' after {addr}")
    num = None if value is None else float(value)
    if addr in ("N", "G", "M", "F") and num is None:
        raise NcError(line, f"{addr} needs a number")
    if addr == "N":
        if w.number is not None or w.gcodes or w.axes or w.groups:
            raise NcError(line, "block number N must come first")
        w.number, w.label = _integer(line, addr, num), colon
    elif addr == "G":
        w.gcodes.append(_integer(line, addr, num))
    elif addr == "M":
        w.mcodes.append(_integer(line, addr, num))
    elif addr == "F":
        w.feed = num
    else:
        w.axes.append((addr, num))


def _integer(line: int, addr: str, num: float | None) -> int:
    if num is None or num != int(num) or num < 0:
        raise NcError(line, f"{addr} needs a non-negative integer, got {num}")
    return int(num)


#: `#VOLCOMP …` (004 p.21), alone in its block after an optional block number
_VOLCOMP = re.compile(r"(?:N(?P<n>\d+)(?P<colon>:)?\s*)?#\s*VOLCOMP\b\s*(?P<rest>.*)")
_VOLCOMP_ID = re.compile(r"ID\s*=?\s*(\d+)$")
_VOLCOMP_CFACT = re.compile(r"CFACT_([XYZ])\s*=\s*([+-]?(?:\d+\.?\d*|\.\d+)(?:E[+-]?\d+)?)$")


def _parse_volcomp(line: int, number: str | None, rest: str) -> VolcompCommand:
    """The words of `#VOLCOMP` (004 p.21): ON | OFF [ID=.. NO_MOVE CFACT_X=..], ON ALL,
    OFF ALL, [ID=.. UPDATE]; `\\` continuations are already joined."""
    m = re.fullmatch(r"(?P<mode>ON|OFF)?\s*(?:(?P<all>ALL)|\[(?P<args>[^\]]*)\])?\s*", rest)
    if m is None:
        if re.search(r"(\]|\bALL)\s*\S", rest):
            raise NcError(line, "#VOLCOMP must stand alone in its block (004 p.21)")
        raise NcError(
            line, f"#VOLCOMP {rest.strip()}: expected ON|OFF [ID=..], ON|OFF ALL or [ID=.. UPDATE]"
        )
    mode, args = m["mode"], m["args"]
    if m["all"]:
        if mode is None:
            raise NcError(line, "#VOLCOMP ALL needs ON or OFF")
        return VolcompCommand(mode == "ON", None)
    w = _volcomp_words(line, args)
    ident = w.ident
    if ident is None:
        raise NcError(line, "#VOLCOMP: name the compensation with ID=.. (0 … 4) or use ALL")
    if ident > 4:
        raise NcError(line, f"#VOLCOMP ID={ident}: the IDs are 0 … 4 (004 p.21)")
    if w.update:
        if mode is not None or w.no_move or w.weighted:
            raise NcError(
                line, "#VOLCOMP [ID=.. UPDATE] takes no ON/OFF, NO_MOVE or CFACT (004 p.21)"
            )
        return VolcompCommand(False, (ident,), update=True)
    if mode is None:
        raise NcError(line, "#VOLCOMP needs ON, OFF or [ID=.. UPDATE]")
    if w.weighted and mode != "ON":
        raise NcError(line, "#VOLCOMP: CFACT_* only with ON (004 p.21)")
    return VolcompCommand(mode == "ON", (ident,), w.no_move, tuple(w.cfact) if w.weighted else None)  # type: ignore[arg-type]


@dataclass(slots=True)
class _VolcompWords:
    """The words in the brackets of one `#VOLCOMP` (004 p.21)."""

    ident: int | None = None
    no_move: bool = False
    update: bool = False
    cfact: list[float] = field(default_factory=lambda: [1.0, 1.0, 1.0])  # CFACT_X, _Y, _Z
    weighted: bool = False  # some CFACT_* given


def _volcomp_words(line: int, args: str | None) -> _VolcompWords:
    """ID=.., NO_MOVE, UPDATE and CFACT_X/Y/Z=.. (0.0 … 1.0) of `#VOLCOMP [..]` (004
    p.21), separated by blanks or commas, `=` with or without blanks around it."""
    w = _VolcompWords()
    for word in re.sub(r"\s*=\s*", "=", args or "").replace(",", " ").split():
        if (mi := _VOLCOMP_ID.match(word)) is not None:
            if w.ident is not None:
                raise NcError(line, f"#VOLCOMP: one ID per command ({w.ident} and {mi[1]})")
            w.ident = int(mi[1])
        elif word == "NO_MOVE":
            w.no_move = True
        elif word == "UPDATE":
            w.update = True
        elif (mc := _VOLCOMP_CFACT.match(word)) is not None:
            value = float(mc[2])
            if not 0.0 <= value <= 1.0:
                raise NcError(
                    line,
                    f"#VOLCOMP CFACT_{mc[1]}={value:g}: permitted values are 0.0 … 1.0 (004 p.21)",
                )
            w.cfact["XYZ".index(mc[1])] = value
            w.weighted = True
        else:
            raise NcError(
                line, f"#VOLCOMP: unknown word {word!r} (ID=.., NO_MOVE, CFACT_X/Y/Z=.., UPDATE)"
            )
    return w


def _parse_block(
    line: int, body: str, names: dict[str, int], warnings: list[Diagnostic]
) -> Block | None:
    """Interpret the words of one block."""
    volcomp = _VOLCOMP.fullmatch(body.upper())
    if volcomp is not None:
        number = int(volcomp["n"]) if volcomp["n"] else None
        cmd = _parse_volcomp(line, volcomp["n"], volcomp["rest"])
        return Block(line=line, text=body, number=number, label=bool(volcomp["colon"]), volcomp=cmd)
    if "#VOLCOMP" in body.upper().replace(" ", ""):
        raise NcError(line, "#VOLCOMP must stand alone in its block (004 p.21)")
    special = _parse_control(line, body, names, warnings)
    if special is not None:
        return special
    m = _VG_FILE_WRITE.fullmatch(body.strip())
    if m is not None:
        ident, index = _vg_indices(line, m["i"], m["j"])
        assert index is not None
        b = Block(line=line, text=body, number=int(m["n"]) if m["n"] else None)
        b.label, b.volcomp_file = bool(m["colon"]), (ident, index, m["text"])
        return b
    if re.search(r"V\s*\.\s*G\s*\.", body.upper()):
        raise NcError(
            line,
            'V.G.VOLCOMP[i].FILE[j] = "name" stands alone in its block; V.G.VOLCOMP[i].ACTIVE '
            "is read only, in $IF (004 p.18)",
        )
    exchange = _AXIS_EXCHANGE.fullmatch(body.upper())
    if exchange is not None:
        return _parse_exchange(line, body, exchange, names, warnings)
    if _EXCHANGE_WORD.search(body.upper()):
        raise NcError(line, "axis exchange (#PUT AX, #AX RELEASE, #CALL AX) must stand alone")
    w = _tokenize(line, body, warnings)
    b = Block(line=line, text=body, number=w.number, label=w.label)
    _apply_gcodes(line, w, b)
    _apply_mcodes(line, w, b)
    if w.feed is not None:
        if w.feed <= 0:
            raise NcError(line, f"feed F must be > 0, got {w.feed:g}")
        b.feed = w.feed / 60.0 * UNITS_PER_MM
    b.comps = tuple(_parse_comp(line, axis, content, names) for axis, content in w.groups)
    _apply_axes(line, w, b, names)
    if w.goto is not None:
        if b.axes or b.dwell is not None or b.home or b.comps or b.end or w.gcodes:
            raise NcError(line, "$GOTO must stand alone in its block")
        b.goto_number = w.goto
    return b


#: `$IF …`, `$ELSEIF …`, `$ELSE`, `$ENDIF`, alone in the block after an optional block number
_BRANCH = re.compile(
    r"(?:N(?P<n>\d+)(?P<colon>:)?\s*)?\$(?P<kind>IF|ELSEIF|ELSE|ENDIF)\b\s*(?P<rest>.*)"
)
#: `#MSG ["text"]` (000 p.96), alone in its block; the text keeps its case
_MSG = re.compile(
    r'(?:N(?P<n>\d+)(?P<colon>:)?\s*)?#\s*MSG\s*\[\s*"(?P<text>[^"]*)"\s*\]', re.IGNORECASE
)
#: `V.G.VOLCOMP[i].FILE[j] = "name"` (004 p.18), alone in its block; the name keeps its case
_VG_FILE_WRITE = re.compile(
    r"(?:N(?P<n>\d+)(?P<colon>:)?\s*)?V\s*\.\s*G\s*\.\s*VOLCOMP\s*\[\s*(?P<i>\d+)\s*\]\s*\.\s*"
    r'FILE\s*\[\s*(?P<j>\d+)\s*\]\s*=\s*"(?P<text>[^"]*)"',
    re.IGNORECASE,
)
#: `N150 ...`: the manuals' elision of the rest of a program (000 p.96)
_ELISION = re.compile(r"(?:N(?P<n>\d+)(?P<colon>:)?\s*)?(?:\.\.\.+|…)")
_CONDITION_TOKEN = re.compile(
    r"""\s*(?:
      (?P<va>V\s*\.\s*A\s*\.\s*(?P<word>[A-Z]+)_COMP_(?P<field>[A-Z]+)\s*
          (?:\.\s*(?P<axis>[A-Z][A-Z0-9_]*)|\[\s*(?P<index>\d+)\s*\]))
    | (?P<vg>V\s*\.\s*G\s*\.\s*VOLCOMP\s*\[\s*(?P<vi>\d+)\s*\]\s*\.\s*
          (?:(?P<active>ACTIVE)|FILE\s*\[\s*(?P<vj>\d+)\s*\]))
    | "(?P<text>[^"]*)"
    | (?P<op>==|!=|<=|>=|<|>)
    | (?P<logic>AND|OR)\b
    | (?P<bool>TRUE|FALSE)\b
    | (?P<number>[+-]?(?:\d+\.?\d*|\.\d+))
    )""",
    re.VERBOSE,
)


def _parse_control(
    line: int, body: str, names: dict[str, int], warnings: list[Diagnostic]
) -> Block | None:
    """`$IF`/`$ELSEIF`/`$ELSE`/`$ENDIF`, `#MSG` and the elision `...` (000 p.96); None
    for any other block."""
    upper = body.upper()
    m = _BRANCH.fullmatch(_upper_outside_texts(body))
    if m is not None:
        kind, rest = m["kind"], m["rest"].strip()
        b = Block(line=line, text=body, number=int(m["n"]) if m["n"] else None)
        b.label = bool(m["colon"])
        if kind in ("IF", "ELSEIF"):
            if not rest:
                raise NcError(line, f"${kind} needs a condition")
            b.branch = Branch(kind, _parse_condition(line, rest, names))
        elif rest:
            raise NcError(line, f"${kind} must stand alone in its block, got {rest[:20]!r}")
        else:
            b.branch = Branch(kind)
        return b
    if re.search(r"\$(?:IF|ELSEIF|ELSE|ENDIF)\b", upper):
        raise NcError(line, "$IF, $ELSEIF, $ELSE and $ENDIF begin their block")
    m = _MSG.fullmatch(body)
    if m is not None:
        b = Block(line=line, text=body, number=int(m["n"]) if m["n"] else None)
        b.label, b.message = bool(m["colon"]), m["text"]
        return b
    if re.search(r"#\s*MSG\b", upper):
        raise NcError(line, '#MSG ["text"] must stand alone in its block (000 p.96)')
    m = _ELISION.fullmatch(body.strip())
    if m is not None:
        warnings.append(_warning(line, "'...' (an elision in the manual's listing): skipped"))
        return Block(line=line, text=body, number=int(m["n"]) if m["n"] else None)
    return None


def _parse_condition(line: int, text: str, names: dict[str, int]) -> Condition:
    """`<operand> [<op> <operand>] {AND|OR …}` with the V.A. variables of 000 p.95-96."""
    groups: list[list[tuple[Operand, str, Operand]]] = [[]]
    pos, expect = 0, "operand"
    left: Operand | None = None
    right: Operand = 0.0
    op: str | None = None

    def close() -> None:
        nonlocal left, op
        if left is None or (op is not None and expect == "operand"):
            raise NcError(line, f"$IF {text}: incomplete condition")
        texts = (_is_text(left), op is not None and _is_text(right))
        if any(texts) and (op not in ("==", "!=") or not all(texts)):
            raise NcError(
                line,
                f'$IF {text}: a text (V.G.VOLCOMP[i].FILE[j], "…") is '
                "compared with a text by == or != only",
            )
        groups[-1].append((left, "!=", 0.0) if op is None else (left, op, right))
        left, op = None, None

    while pos < len(text):
        m = _CONDITION_TOKEN.match(text, pos)
        if m is None or m.end() == pos:
            if not text[pos:].strip():
                break
            raise NcError(line, f"$IF: unexpected {text[pos:].strip()[:20]!r}")
        pos = m.end()
        if m["op"] or m["logic"]:
            if expect != "operator" or (m["op"] and op is not None):
                raise NcError(line, f"$IF {text}: unexpected {m['op'] or m['logic']!r}")
            if m["op"]:
                op, expect = m["op"], "operand"
                continue
            close()
            if m["logic"] == "OR":
                groups.append([])
            expect = "operand"
            continue
        if expect != "operand":
            raise NcError(line, f"$IF {text}: an operator (==, !=, <, >, AND, OR) is missing")
        value = _operand(line, m, names)
        if op is None:
            left = value
        else:
            right = value
        expect = "operator"
    close()
    return Condition(tuple(tuple(g) for g in groups))


def _is_text(x: Operand) -> bool:
    return isinstance(x, str) or (isinstance(x, VgVariable) and x.index is not None)


def _upper_outside_texts(body: str) -> str:
    """The block in capitals but for its `"…"` texts (a file name keeps its case)."""
    parts = body.split('"')
    return '"'.join(p.upper() if i % 2 == 0 else p for i, p in enumerate(parts))


def _vg_indices(line: int, i: str, j: str | None) -> tuple[int, int | None]:
    """The compensation ID 0 … 4 and the file index 0 … 9 of a V.G.VOLCOMP variable
    (004 p.12: five compensations, up to 10 files each)."""
    ident, index = int(i), None if j is None else int(j)
    if ident > 4:
        raise NcError(line, f"V.G.VOLCOMP[{ident}]: the ID is 0 … 4 (004 p.21)")
    if index is not None and index > 9:
        raise NcError(line, f"V.G.VOLCOMP[{ident}].FILE[{index}]: the index is 0 … 9 (004 p.12)")
    return ident, index


def _operand(line: int, m: re.Match[str], names: dict[str, int]) -> Operand:
    if m["text"] is not None:
        return m["text"]
    if m["vg"]:
        ident, index = _vg_indices(line, m["vi"], m["vj"])
        return VgVariable(ident, index)
    if m["bool"]:
        return 1.0 if m["bool"] == "TRUE" else 0.0
    if m["number"] is not None:
        return float(m["number"])
    word, fld = m["word"], m["field"]
    name = f"V.A.{word}_COMP_{fld}"
    if fld not in VA_FIELDS:
        raise NcError(line, f"{name}: the variables are _INIT, _ACTIVE and _CURR (000 p.95-96)")
    if word not in VA_FIELDS[fld]:
        known = " ".join(sorted(VA_FIELDS[fld]))
        raise NcError(line, f"{name} does not exist (_{fld} is defined for {known}, 000 p.95-96)")
    if m["axis"] is not None:
        return VaVariable(KIND_WORDS[word], fld, _axis_slot(line, m["axis"], names))
    index, count = int(m["index"]), len(set(names.values()))
    if index >= count:
        raise NcError(line, f"{name}[{index}]: the axis index is 0 … {count - 1}")
    return VaVariable(KIND_WORDS[word], fld, index)


def _parse_exchange(
    line: int, body: str, m: re.Match[str], names: dict[str, int], warnings: list[Diagnostic]
) -> Block:
    """Axis exchange (TwinCAT CNC programming manual, "Axis exchange commands"; needed
    here for "deselected on release of the axis", 000 §3.2 p.17 and §5.1).

    `#PUT AX [<axis>{, <axis>}]` / `#AX RELEASE [...]` hand axes back to the axis
    management; names that are not (or no longer) in the channel are no error. `ALL`
    releases every axis. `#CALL AX [<axis>, <number>, <index>] {[...]}` brings axes back;
    the emulator's axes keep their names and numbers, so only the name counts. Releasing
    a name the machine does not have only warns (the manual: no error message).
    """
    b = Block(line=line, text=body, number=int(m["n"]) if m["n"] else None, label=bool(m["colon"]))
    cmd, rest = " ".join(m["cmd"].split()), m["rest"].strip()
    if cmd != "CALL AX" and rest == "ALL":
        b.release = tuple(sorted(set(names.values())))
        return b
    groups: list[str] = []
    pos = 0
    while pos < len(rest):
        if groups and rest[pos] == ",":  # `[X, 1, 0], [Y, 2, 1]`
            pos += 1
        g = _EXCHANGE_GROUP.match(rest, pos)
        if g is None:
            raise NcError(line, f"#{cmd}: expected [<axis>, …], got {rest[pos:].strip()[:20]!r}")
        groups.append(g["content"])
        pos = g.end()
    if not groups:
        raise NcError(
            line, f"#{cmd} needs [<axis>{{, <axis>}}]" + ("" if cmd == "CALL AX" else " or ALL")
        )
    if cmd == "CALL AX":
        b.call = tuple(_axis_slot(line, g.split(",")[0].strip(), names) for g in groups)
        return b
    if len(groups) > 1:
        raise NcError(line, f"#{cmd}: name the axes in one [ ]")
    axes = [a.strip() for a in groups[0].split(",")]
    if not all(axes):
        raise NcError(line, f"#{cmd}: empty axis name")
    for a in axes:
        if a not in names:
            hint = " (all axes: #PUT AX ALL, without brackets)" if a == "ALL" else ""
            warnings.append(_warning(line, f"#{cmd}: {a} is not an axis of this machine{hint}"))
    b.release = tuple(names[a] for a in axes if a in names)
    return b


def _apply_gcodes(line: int, w: _Words, b: Block) -> None:
    for g in w.gcodes:
        if g in (0, 1):
            b.motion = g
        elif g in (90, 91):
            b.absolute = g == 90
        elif g == 4:
            b.dwell = math.nan  # filled in by _apply_axes
        elif g == 74:
            b.home = (-1,)  # marker, filled in by _apply_axes
        else:
            raise NcError(line, f"G{g:02d} is not supported (G00 G01 G04 G74 G90 G91)")


def _apply_mcodes(line: int, w: _Words, b: Block) -> None:
    for m in w.mcodes:
        if m not in (2, 30):
            raise NcError(line, f"M{m} is not supported (M30 program end)")
        b.end = True


def _axis_slot(line: int, name: str, names: dict[str, int]) -> int:
    if name not in names:
        known = " ".join(names) or "none"
        raise NcError(line, f"unknown axis or address {name!r} (axes: {known})")
    return names[name]


def _apply_axes(line: int, w: _Words, b: Block, names: dict[str, int]) -> None:
    """Axis words are motion targets, homing axes (G74) or the dwell time (G04 X<s>)."""
    if b.dwell is not None:
        _apply_dwell(line, w, b)
        return
    if w.numbers:
        raise NcError(line, f"unexpected number {w.numbers[0]:g}")
    if b.home:
        b.home = tuple(_axis_slot(line, a, names) for a, _ in w.axes)
        if not b.home:
            raise NcError(line, "G74 needs at least one axis")
        return
    for name, value in w.axes:
        slot = _axis_slot(line, name, names)
        if value is None:
            raise NcError(line, f"axis {name} needs a value")
        if slot in b.axes:
            raise NcError(line, f"axis {name} programmed twice")
        b.axes[slot] = value * UNITS_PER_MM


def _apply_dwell(line: int, w: _Words, b: Block) -> None:
    """`G04 <s>` (000 p.24) or `G04 X<s>`."""
    if b.home:
        raise NcError(line, "G04 and G74 in one block")
    times: list[float | None] = list(w.numbers)
    if len(w.axes) == 1 and w.axes[0][0] == "X" and not times:
        times = [w.axes[0][1]]
    elif w.axes:
        raise NcError(line, "G04 cannot be combined with axis motion")
    if len(times) != 1 or times[0] is None or times[0] < 0:
        raise NcError(line, "G04 needs one dwell time >= 0 in seconds")
    b.dwell = times[0]


def _parse_comp(line: int, axis: str, content: str, names: dict[str, int]) -> CompCommand:
    """`<axis>[COMP ON|OFF <kinds…> | OFF_ALL [NO_MOVE]]` (000 §5.1, p.94)."""
    slot = _axis_slot(line, axis, names)
    words = content.replace("\\", " ").split()
    if not words or words[0] != "COMP":
        raise NcError(line, f"{axis}[…]: COMP must be the first keyword")
    no_move = "NO_MOVE" in words
    rest = [x for x in words[1:] if x != "NO_MOVE"]
    if not rest or rest[0] not in ("ON", "OFF", "OFF_ALL"):
        raise NcError(line, f"{axis}[COMP …]: expected ON, OFF or OFF_ALL")
    if rest[0] == "OFF_ALL":
        if len(rest) > 1:
            raise NcError(line, f"{axis}[COMP OFF_ALL]: no keywords may follow OFF_ALL")
        return CompCommand(slot, axis, False, CompKind(0), off_all=True, no_move=no_move)
    kinds = CompKind(0)
    for word in rest[1:]:
        if word not in KIND_WORDS:
            raise NcError(line, f"{axis}[COMP {rest[0]}]: unknown compensation {word!r}")
        kinds |= KIND_WORDS[word]
    if not kinds:
        raise NcError(line, f"{axis}[COMP {rest[0]}]: name at least one compensation")
    return CompCommand(slot, axis, rest[0] == "ON", kinds, no_move=no_move)


def _resolve_gotos(blocks: list[Block]) -> None:
    """`$GOTO N<n>`: a block labelled `N<n>:` wins, else the first block numbered n."""
    first: dict[int, int] = {}
    labels: dict[int, int] = {}
    for i, b in enumerate(blocks):
        if b.number is not None:
            first.setdefault(b.number, i)
            if b.label:
                labels.setdefault(b.number, i)
    for b in blocks:
        if b.goto_number is None:
            continue
        target = labels.get(b.goto_number, first.get(b.goto_number))
        if target is None:
            raise NcError(b.line, f"$GOTO target N{b.goto_number} does not exist")
        b.goto = target


def _resolve_branches(blocks: list[Block]) -> None:
    """Pair every `$IF` with its `$ELSEIF`/`$ELSE`/`$ENDIF` (nested)."""
    open_ifs: list[list[int]] = []
    for i, b in enumerate(blocks):
        br = b.branch
        if br is None:
            continue
        if br.kind == "IF":
            open_ifs.append([i])
            continue
        if not open_ifs:
            raise NcError(b.line, f"${br.kind} without $IF")
        members = open_ifs[-1]
        last = blocks[members[-1]].branch
        assert last is not None
        if br.kind != "ENDIF" and last.kind == "ELSE":
            raise NcError(b.line, f"${br.kind} after $ELSE (line {blocks[members[-1]].line})")
        last.next = i
        if br.kind != "ENDIF":
            members.append(i)
            continue
        for j in open_ifs.pop():
            member = blocks[j].branch
            assert member is not None
            member.end = i
    if open_ifs:
        raise NcError(blocks[open_ifs[-1][0]].line, "$IF without $ENDIF")


def _check_feed(blocks: list[Block]) -> None:
    """G01 motion needs a feed programmed before it (in text order)."""
    motion, feed = 0, None
    for b in blocks:
        motion = b.motion if b.motion is not None else motion
        feed = b.feed if b.feed is not None else feed
        if motion == 1 and b.axes and feed is None:
            raise NcError(b.line, "G01 without feed F")


# --------------------------------------------------------------------------- player


@dataclass
class _Modal:
    """Modal state of the channel."""

    absolute: bool = True
    motion: int = 0
    feed: float | None = None

    def update(self, b: Block) -> None:
        self.absolute = b.absolute if b.absolute is not None else self.absolute
        self.motion = b.motion if b.motion is not None else self.motion
        self.feed = b.feed if b.feed is not None else self.feed


@dataclass
class _Wait:
    """What the current block waits for before the next block may run."""

    motion: tuple[int, ...] = ()
    comp: tuple[int, ...] = ()
    volcomp: bool = False  # #VOLCOMP: ramps and updates finished (004 p.22)
    until_cycle: int = 0
    end: bool = False  # M30 in the waiting block: end after the wait


class Player:
    """Executes a `Program` block by block, driven by `step()` once per GEO cycle.

    At most one block that waits (motion, homing, dwell, COMP with offset move) is
    started per cycle; the next block runs in the first cycle in which the wait is over
    (motion in position, dwell of n cycles elapsed — n cycles after it started, COMP
    ramps settled). At most `MAX_BLOCKS_PER_CYCLE` blocks run per cycle, so
    `N10 $GOTO N10` ends with an error instead of hanging.

    A program (not `mdi`) that reaches M30 or its end calls `MachinePort.program_end()`;
    an MDI run (`run_lines`) calls it only on an explicit M30, so `nc "X[COMP ON TEMP]"`
    stays in effect. After an error the player stops without `program_end` (the
    machine's reset does that).
    """

    def __init__(
        self,
        prog: Program,
        port: MachinePort,
        dt: float,
        *,
        mdi: bool = False,
        monitor: bool = True,
    ) -> None:
        if dt <= 0:
            raise ValueError(f"cycle time must be > 0, got {dt}")
        self.prog, self.port, self.dt = prog, port, dt
        self.mdi, self.monitor = mdi, monitor
        self.running = True
        self.finished = False
        self.error: Diagnostic | None = None
        self.cycle = 0
        self.index = 0  # next block to execute
        self.line = 0  # line of the block executed last
        self._modal = _Modal()
        self._wait: _Wait | None = None
        #: axes handed back by `#PUT AX` (every program starts with all axes in the channel)
        self.released: set[int] = set()

    def step(self) -> None:
        """One GEO cycle: finish the waiting block if its condition holds, run blocks."""
        if not self.running:
            return
        self.cycle += 1
        if self._wait is not None:
            if self.monitor and not self._still_compensated(self._wait.motion):
                return
            if not self._wait_over(self._wait):
                return
            end, self._wait = self._wait.end, None
            if end:
                self._finish(explicit=True)
                return
        for _ in range(MAX_BLOCKS_PER_CYCLE):
            if self.index >= len(self.prog.blocks):
                self._finish(explicit=False)
                return
            block = self.prog.blocks[self.index]
            self.index += 1
            self.line = block.line
            self._execute(block)
            if not self.running or self._wait is not None:
                return
        self._fail(ERR_NC_RUNTIME, f"{MAX_BLOCKS_PER_CYCLE} blocks without motion in one cycle")

    def motion_wait(self) -> tuple[int, ...]:
        """The axes whose motion the waiting block waits for (empty when it waits for
        nothing or for something else as well, or when the 70435 monitoring has an
        error to give): while one of them moves, `step` only counts the cycle."""
        w = self._wait
        if w is None or w.comp or w.end or w.volcomp:
            return ()
        if self.monitor and any(self._missing(s) for s in w.motion):
            return ()
        return w.motion

    def skip(self, n: int) -> None:
        """`n` cycles in which `step` would only count (the machine checked that an
        axis of `motion_wait` moves throughout)."""
        self.cycle += n

    def abort(self) -> None:
        """Stop executing (CNC reset); the machine handles the reset semantics."""
        self.running = False
        self._wait = None

    # ------------------------------------------------------------------ blocks

    def _execute(self, b: Block) -> None:
        """Run one block: modal words, G74, COMP, motion or dwell, then $GOTO/M30."""
        if b.branch is not None:
            self._branch(b.branch)
            return
        if b.message is not None:
            self.port.message(b.message, b.line)
            # the next block runs in the next cycle: a loop around a #MSG reports one
            # message per cycle, not a thousand
            self._wait = _Wait(until_cycle=self.cycle + 1)
            return
        self._modal.update(b)
        if b.release or b.call:
            self._exchange(b)
            return
        if b.volcomp_file is not None or b.volcomp is not None:
            self._volcomp(b)
            return
        if not self._in_channel(b):
            return
        wait = _Wait()
        if b.home:
            self.port.home(b.home)
            wait.motion = b.home
        if b.comps and not self._run_comps(b, wait):
            return
        if b.axes and not self._run_motion(b, wait):
            return
        if b.dwell is not None:
            wait.until_cycle = self.cycle + max(1, math.floor(b.dwell / self.dt + 0.5))
        if b.goto is not None:
            self.index = b.goto
        waits = bool(wait.motion or wait.comp or wait.until_cycle)
        if b.end and not waits:
            self._finish(explicit=True)
        elif waits:
            wait.end = b.end
            self._wait = wait

    def _volcomp(self, b: Block) -> None:
        """`V.G.VOLCOMP[i].FILE[j] = "…"`, or `#VOLCOMP …` and its wait ("The machine
        stops when a #VOLCOMP command is used", 004 p.22)."""
        if b.volcomp_file is not None:
            err, message = self.port.set_volcomp_file(*b.volcomp_file)
        else:
            assert b.volcomp is not None
            err, message = self.port.volcomp(b.volcomp)
        if err:
            self._fail(err, message)
        elif b.volcomp is not None:
            self._wait = _Wait(volcomp=True)

    def _branch(self, br: Branch) -> None:
        """`$IF`: the first branch whose condition holds runs, else the `$ELSE` branch;
        a `$ELSEIF`/`$ELSE` reached from the branch before it ends that branch. The
        V.A. variables are read when the block is reached, i.e. after the blocks before
        it have finished (000 p.95: reading them flushes the channel)."""
        if br.kind in ("ELSEIF", "ELSE"):
            self.index = br.end + 1
            return
        if br.kind == "ENDIF":
            return
        blocks = self.prog.blocks
        current: Branch | None = br
        while current is not None and current.kind in ("IF", "ELSEIF"):
            assert current.condition is not None
            if current.condition.holds(self.port):
                return  # (self.index is already the block after the one that holds)
            self.index = current.next + 1
            current = blocks[current.next].branch
        # an $ELSE or the $ENDIF: self.index is the block after it

    def _exchange(self, b: Block) -> None:
        """`#PUT AX` / `#CALL AX`: a released axis loses its manual-activation
        compensations (000 §5.1) and cannot be programmed until it is called back."""
        for slot in b.release:
            if slot not in self.released:
                self.released.add(slot)
                self.port.release_axis(slot)
        self.released.difference_update(b.call)

    def _in_channel(self, b: Block) -> bool:
        """Every axis the block programs must be in the channel; False after the error."""
        used = set(b.axes) | set(b.home) | {c.slot for c in b.comps}
        out = sorted(used & self.released)
        if out:
            names = ", ".join(self._axis_name(s) for s in out)
            self._fail(ERR_NC_RUNTIME, f"axis {names} is not in the channel (#PUT AX)")
            return False
        return True

    def _run_comps(self, b: Block, wait: _Wait) -> bool:
        """Issue the COMP commands of a block; False after an error."""
        for c in b.comps:
            if c.off_all:
                err = self.port.comp_off_all(c.slot, c.no_move)
            else:
                err = self.port.comp(c.slot, c.on, c.kinds, c.no_move)
            if err:
                self._fail(err, _comp_message(err, c))
                return False
        wait.comp = tuple(c.slot for c in b.comps if not c.no_move)
        return True

    def _run_motion(self, b: Block, wait: _Wait) -> bool:
        """Start the motion of a block; False after an error (70435, missing F)."""
        targets = self._targets(b, self._modal.absolute, self.port.position)
        moving = [s for s, t in targets.items() if t != self.port.position(s)]
        if self.monitor and not self._check_required(moving):
            return False
        rapid = self._modal.motion == 0
        if not rapid and self._modal.feed is None:
            self._fail(ERR_NC_RUNTIME, "G01 without feed F")
            return False
        next_dirs = self._lookahead(targets)
        self.port.move_linear(targets, None if rapid else self._modal.feed, rapid, next_dirs)
        wait.motion = tuple(targets)
        return True

    def _still_compensated(self, slots: tuple[int, ...]) -> bool:
        """000 §5.3 p.97: the monitoring holds while an axis moves, not only when its
        block starts ("if the axis is moved in automatic mode and the specified axis
        compensations are not active"): a required compensation that drops out during
        the motion (its master unreferenced, a drive disabled) raises 70435 then, and
        the block's axes come to a controlled stop. False after that error."""
        lacking = [s for s in slots if self._missing(s)]
        moving = [s for s in lacking if not self.port.in_position((s,))]
        if self._check_required(moving):
            return True
        self.port.stop_axes(slots)
        return False

    def _missing(self, slot: int) -> CompKind:
        """The required compensations of the axis that are not effective now."""
        return self.port.required(slot) & ~self.port.effective(slot)

    def _check_required(self, slots: Iterable[int]) -> bool:
        """000 §5.3: required compensations must be effective on every moved axis."""
        for s in slots:
            missing = self._missing(s)
            if missing:
                names = " ".join(k.name or "" for k in CompKind if k & missing)
                axis = self._axis_name(s)
                msg = f"P-ERR-70435: axis {axis} moved without required compensations {names}"
                self._fail(CncErrorId.REQUIRED_COMP_MISSING, msg)
                return False
        return True

    def _targets(self, b: Block, absolute: bool, base: Callable[[int], float]) -> dict[int, float]:
        """Absolute targets of a block; modulo axes take the shortest way under G90."""
        out: dict[int, float] = {}
        for slot, value in b.axes.items():
            cur = float(base(slot))
            if not absolute:
                out[slot] = cur + value
                continue
            period = self.port.modulo_period(slot)
            out[slot] = cur + _shortest(value - cur, period) if period > 0 else value
        return out

    def _lookahead(self, targets: dict[int, float]) -> dict[int, int]:
        """Direction of each axis' next programmed move (through $GOTO, dwell, COMP).

        Stops at M30 or the program end (direction 0) and after MAX_BLOCKS_PER_CYCLE.
        """
        modal = _Modal(self._modal.absolute, self._modal.motion, self._modal.feed)
        index = self.index
        for _ in range(MAX_BLOCKS_PER_CYCLE):
            if index >= len(self.prog.blocks):
                break
            b = self.prog.blocks[index]
            modal.update(b)
            index = b.goto if b.goto is not None else index + 1
            if b.axes:
                nxt = self._targets(b, modal.absolute, partial(_base, targets, self.port))
                return {s: _sign(nxt.get(s, t) - t) for s, t in targets.items()}
            if b.end:
                break
        return dict.fromkeys(targets, 0)

    # ------------------------------------------------------------------ end states

    def _wait_over(self, w: _Wait) -> bool:
        return (
            self.cycle >= w.until_cycle
            and (not w.motion or self.port.in_position(w.motion))
            and (not w.comp or self.port.comp_settled(w.comp))
            and (not w.volcomp or self.port.volcomp_settled())
        )

    def _finish(self, explicit: bool) -> None:
        self.running = False
        self.finished = True
        if explicit or not self.mdi:
            self.port.program_end()

    def _fail(self, error_id: int, message: str) -> None:
        self.running = False
        self._wait = None
        self.error = Diagnostic(
            severity="error", message=message, file="<nc>", line=self.line, error_id=error_id
        )
        self.port.report(error_id, message, self.line)

    def _axis_name(self, slot: int) -> str:
        for name, s in self.prog.axis_names.items():
            if s == slot:
                return name
        return f"#{slot}"


def _comp_message(err: int, c: CompCommand) -> str:
    what = "OFF_ALL" if c.off_all else ("ON " if c.on else "OFF ") + _kind_names(c.kinds)
    reason = _KNOWN_ERRORS.get(err, "rejected by the machine")
    return f"P-ERR-{err}: {c.axis}[COMP {what}]: {reason}"


def _kind_names(kinds: CompKind) -> str:
    return " ".join(w for w, k in KIND_WORDS.items() if k & kinds)


def _shortest(delta: float, period: float) -> float:
    """Shortest signed way on a modulo axis, in (−period/2, period/2]."""
    d = math.fmod(delta, period)
    if d > period / 2:
        d -= period
    elif d <= -period / 2:
        d += period
    return d


def _base(targets: dict[int, float], port: MachinePort, slot: int) -> float:
    """Position an axis will have after the current block (lookahead base)."""
    return targets[slot] if slot in targets else port.position(slot)


def _sign(x: float) -> int:
    return (x > 0) - (x < 0)


def run_lines(
    lines: str,
    port: MachinePort,
    axis_names: Mapping[str, int],
    dt: float,
    *,
    monitor: bool = True,
) -> Player:
    """Parse one or more NC lines (MDI, the transports' `nc` command) into a Player.

    Same semantics as a tiny program, except that `program_end` is only called on an
    explicit M30. `monitor=False` models manual mode (no 70435, 000 §5.3). Raises
    `NcError` for bad text; the caller steps the player once per cycle.
    """
    prog = parse_program(lines, axis_names, mdi=True)
    return Player(prog, port, dt, mdi=True, monitor=monitor)
