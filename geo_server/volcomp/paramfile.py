"""The correction files of a volumetric compensation: ISG CSV and Etalon exchange (004 §6.3).

Pure functions, text in, data out: `parse_isg_csv` (004 p.32), `parse_etalon` (004 p.33,
p.38), `read_param_file` (the `file[j]` / `file_format[j]` pair of a VOLC list, 004 p.12)
and the writers `write_isg_csv`, `write_etalon`. A file becomes `Block`s of records:
argument columns (X Y Z in mm, A B C in degrees, 004 p.31) and parameter columns (mm or
rad). What the records mean as tables is `geo_server.volcomp.tables`' business.

Conventions the manual leaves open, decided here:

- `//` starts a comment anywhere on a line, also right after a number (004 p.34 prints
  `360.0 -0.000833484486// <- duplicate …`);
- the manuals print elision marks (`…`, `...`, `:`) inside their examples (004 p.23,
  p.32, p.38): a row or Gridpoints entry that is only such a mark is skipped with a
  warning, anywhere else it is an error like any other non-number;
- numbers are decimal with `.` (Python float syntax without `_`, inf or nan);
- a CSV header without rows is dropped with a warning: every block has ≥ 1 row;
- Etalon: `[HEADER]` is metadata, ignored; another block that is not a parameter is
  ignored with a warning; `Gridpoints` only for component errors (the other parameters
  are constants, 004 p.31), over the component error's own axis; a parameter given twice
  in one file is an error;
- a file that is not one of the format at all (a header that is no column names, text
  before the first `[NAME]`) is refused without quoting it (`NOT_CSV`, `NOT_ETALON`):
  an error message never carries a line of a file that is not a correction file; a
  correction file's own mistakes are quoted (a column name is a short word);
- a file is read through `geo_server.safefile.read_regular`, at most
  `FileLimits.correction_file_bytes` (docs/security.md).
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

from geo_server.errors import GeoError
from geo_server.safefile import LIMITS, read_regular
from geo_server.volcomp.names import (
    ARGUMENTS,
    COMPONENT_ERRORS,
    PARAMETERS,
    POSITION_ERRORS,
    axis_of,
)

#: the names of the file formats in a VOLC list (004 p.12)
FORMATS = ("ISG_CSV", "ETALON_EXCHANGE")
#: what the manuals print where they leave records out (004 p.23, p.32, p.38)
ELISIONS = frozenset({"…", "...", ":"})
ELISION_WARNING = "elision mark ignored"
#: the first line of what the writers produce
WRITTEN = "// written by geo-server"
#: a line of a file that is no ISG CSV file at all (not quoted: it may be anything)
NOT_CSV = (
    "not an ISG CSV correction file: this line is neither a comment nor a header of "
    "column names (004 p.32)"
)
#: a line of a file that is no Etalon exchange file at all (not quoted, like NOT_CSV)
NOT_ETALON = (
    "not an Etalon exchange file: this line is neither a comment nor a [NAME] block "
    "header (004 p.33)"
)

# Python float syntax minus `_`, inf, nan: what a measuring system writes
_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
# "CSV": whitespace, `,` or `;` between columns (004 p.32 prints blank-separated columns)
_CSV_SEPARATORS = re.compile(r"[\s,;]+")
_SECTION = re.compile(r"\[\s*([^\]]*?)\s*\]")
# what may be quoted from a header or key: a word as short as a column name (EXX, C0B)
# or a key (VALUE, Gridpoints); anything else may be a line of any file, never quoted
_WORD = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,15}")
# Not str.splitlines: it also breaks at \x0c, \x1c, \x85 …, so line numbers would differ
# from the ones an editor shows.
_NEWLINE = re.compile(r"\r\n?|\n")

Row = tuple[float, ...]


@dataclass(frozen=True)
class Block:
    """One block of records (004 §6.3.2): argument columns, parameter columns, rows."""

    arguments: tuple[str, ...]  # e.g. ("Z", "X"); may be empty (constant parameters)
    parameters: tuple[str, ...]  # e.g. ("EXX", "EYX"); at least one
    rows: tuple[Row, ...]  # each row: argument values then parameter values, file order
    file: str = ""  # where it came from (for messages)
    line: int = 0  # line of its header (1-based)

    def key(self) -> tuple[tuple[str, ...], tuple[str, ...], tuple[Row, ...]]:
        """The data of the block, without where it came from."""
        return self.arguments, self.parameters, self.rows

    def same_data(self, other: Block) -> bool:
        """Whether both blocks hold the same data (file and line aside)."""
        return self.key() == other.key()


@dataclass(frozen=True)
class ParamFile:
    """One correction file read: its blocks in file order and what was tolerated."""

    path: str
    format: str  # "ISG_CSV" | "ETALON_EXCHANGE"
    blocks: tuple[Block, ...]
    warnings: tuple[tuple[int, str], ...] = ()  # (line, message)

    @property
    def records(self) -> int:
        """Data rows over all blocks: what counts against vol_comp[i].max_records (004 p.12)."""
        return sum(len(b.rows) for b in self.blocks)


class ParamFileError(GeoError):
    """A correction file cannot be read: where (path, 1-based line, 0 = the whole file)
    and what is wrong."""

    def __init__(self, path: str, line: int, message: str) -> None:
        self.path, self.line, self.message = path, line, message
        where = _where(path, line)
        super().__init__(f"{where}: {message}" if where else message)


def _where(path: str, line: int) -> str:
    """Where, for a message: "path:line", "path", "line N" or nothing."""
    if path:
        return f"{path}:{line}" if line else path
    return f"line {line}" if line else ""


def _lines(text: str) -> Iterator[tuple[int, str]]:
    """(1-based line number, line) of `text`."""
    return enumerate(_NEWLINE.split(text), start=1)


def _uncomment(line: str) -> str:
    """The line without its `//` comment, stripped (004 p.32, p.33: row comments)."""
    return line.split("//", 1)[0].strip()


def _number(token: str) -> float | None:
    """The token's value, None if it is not a finite decimal number."""
    if not _NUMBER.fullmatch(token):
        return None
    value = float(token)
    return value if math.isfinite(value) else None  # 1e999 overflows to inf


def _is_elision(tokens: list[str]) -> bool:
    return bool(tokens) and all(t in ELISIONS for t in tokens)


# --- ISG CSV (004 §6.3.2, p.32) ------------------------------------------------------------


class _CsvReader:
    """The state of reading an ISG CSV file line by line: the current header and rows."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.blocks: list[Block] = []
        self.warnings: list[tuple[int, str]] = []
        self.columns: tuple[str, ...] | None = None  # current header, file order
        self.header_line = 0
        self.arguments: tuple[str, ...] = ()
        self.parameters: tuple[str, ...] = ()
        self.order: tuple[int, ...] = ()  # file column of each (arguments…, parameters…)
        self.rows: list[Row] = []

    def error(self, line: int, message: str) -> ParamFileError:
        return ParamFileError(self.path, line, message)

    def feed(self, no: int, line: str) -> None:
        """One line of the file."""
        if line.lstrip().startswith("#"):
            self.close()  # file break: a new header follows (004 p.32)
            return
        tokens = [t for t in _CSV_SEPARATORS.split(_uncomment(line)) if t]
        if not tokens:
            return
        if _is_elision(tokens):
            self.warnings.append((no, ELISION_WARNING))
        elif self.columns is None:
            self.header(no, tokens)
        else:
            self.row(no, tokens)

    def header(self, no: int, tokens: list[str]) -> None:
        """A header: argument and parameter names in any order (004 p.32)."""
        if _number(tokens[0]) is not None:
            raise self.error(
                no, "data row before any header: a header naming the columns comes first"
            )
        for i, name in enumerate(tokens):
            if name not in ARGUMENTS and name not in PARAMETERS:
                if not _WORD.fullmatch(name):
                    raise self.error(no, NOT_CSV)
                raise self.error(
                    no,
                    f"unknown column {name!r}: neither an argument ({' '.join(ARGUMENTS)}) "
                    "nor a parameter of 004 p.30",
                )
            if name in tokens[:i]:
                raise self.error(no, f"column {name!r} named twice")
        arguments = tuple(t for t in tokens if t in ARGUMENTS)
        parameters = tuple(t for t in tokens if t not in ARGUMENTS)
        if not parameters:
            raise self.error(
                no, f"header without a parameter column: {', '.join(arguments)} are arguments"
            )
        self.columns, self.header_line = tuple(tokens), no
        self.arguments, self.parameters = arguments, parameters
        self.order = tuple(tokens.index(c) for c in arguments + parameters)

    def row(self, no: int, tokens: list[str]) -> None:
        """A data row under the current header, reordered to (arguments…, parameters…)."""
        assert self.columns is not None
        if all(t in ARGUMENTS or t in PARAMETERS for t in tokens):
            raise self.error(no, "a new header must follow a '#' line (file break, 004 p.32)")
        if len(tokens) != len(self.columns):
            raise self.error(
                no,
                f"row has {len(tokens)} values, the header (line {self.header_line}) "
                f"names {len(self.columns)} columns",
            )
        values = []
        for column, token in zip(self.columns, tokens, strict=True):
            value = _number(token)
            if value is None:
                raise self.error(no, f"value {token!r} in column {column} is not a number")
            values.append(value)
        self.rows.append(tuple(values[i] for i in self.order))

    def close(self) -> None:
        """End the current block (file break or end of file)."""
        if self.columns is not None and self.rows:
            self.blocks.append(
                Block(
                    self.arguments, self.parameters, tuple(self.rows), self.path, self.header_line
                )
            )
        elif self.columns is not None:
            self.warnings.append((self.header_line, "header without rows: block ignored"))
        self.columns, self.rows = None, []


def parse_isg_csv(text: str, path: str = "") -> ParamFile:
    """Read an ISG CSV correction file (004 §6.3.2, p.32). Raises ParamFileError."""
    reader = _CsvReader(path)
    for no, line in _lines(text):
        reader.feed(no, line)
    reader.close()
    return _result(path, "ISG_CSV", reader.blocks, reader.warnings)


def _result(path: str, fmt: str, blocks: list[Block], warnings: list[tuple[int, str]]) -> ParamFile:
    if not blocks:
        warnings.append((0, "no records in the file"))
    return ParamFile(path, fmt, tuple(blocks), tuple(warnings))


# --- Etalon exchange (004 §6.3.3, p.33, p.38) ----------------------------------------------


def _etalon_axis(name: str) -> str:
    """The argument of a Gridpoints table of `name`: a component error's own axis (EXY
    over Y, 004 p.31); "" for every other parameter (constants)."""
    return axis_of(name) if name in COMPONENT_ERRORS else ""


class _EtalonReader:
    """The state of reading an Etalon exchange file line by line (INI-like, 004 p.33)."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.blocks: list[Block] = []
        self.warnings: list[tuple[int, str]] = []
        self.seen: dict[str, int] = {}  # parameter -> line of its [NAME]
        self.section: str | None = None  # None: before the first [NAME]
        self.section_line = 0
        self.is_parameter = False
        self.value: float | None = None
        self.grid: list[float] | None = None
        self.grid_line = 0
        self.grid_open = False

    def error(self, line: int, message: str) -> ParamFileError:
        return ParamFileError(self.path, line, message)

    def feed(self, no: int, line: str) -> None:
        """One line of the file."""
        text = _uncomment(line)
        if self.grid_open:
            self.grid_values(no, text)
            return
        if not text:
            return
        section = _SECTION.fullmatch(text)
        if section:
            self.close()
            self.open(no, section[1])
            return
        key, equals, value = text.partition("=")
        if self.section is None:
            if not equals or not _WORD.fullmatch(key.strip()):
                raise self.error(no, NOT_ETALON)
            raise self.error(no, f"{key.strip()} = … outside any [block]")
        if not equals:
            raise self.error(no, f"expected 'KEY = value' or '[NAME]', not {text!r}")
        if self.is_parameter:
            self.parameter_entry(no, key.strip(), value.strip())

    def open(self, no: int, name: str) -> None:
        """`[NAME]`: a parameter block, or metadata ([HEADER], 004 p.38)."""
        self.section, self.section_line = name, no
        self.is_parameter = name in PARAMETERS
        self.value, self.grid = None, None
        if self.is_parameter and name in self.seen:
            raise self.error(no, f"[{name}] given twice (first at line {self.seen[name]})")
        if self.is_parameter:
            self.seen[name] = no
        elif name.upper() != "HEADER":
            self.warnings.append((no, f"block [{name}] is not a parameter of 004 p.30: ignored"))

    def parameter_entry(self, no: int, key: str, value: str) -> None:
        """`VALUE = v` or `Gridpoints = { … }` of the current parameter (004 p.33)."""
        name = self.section
        assert name is not None
        if key.upper() not in ("VALUE", "GRIDPOINTS"):
            self.warnings.append((no, f"unknown key {key!r} in [{name}] ignored"))
            return
        if self.value is not None or self.grid is not None:
            raise self.error(no, f"[{name}] has a second VALUE or Gridpoints")
        if key.upper() == "VALUE":
            self.value = _number(value)
            if self.value is None:
                raise self.error(no, f"VALUE of {name}: {value!r} is not a number")
            return
        self.open_grid(no, name, value)

    def open_grid(self, no: int, name: str, value: str) -> None:
        if name in POSITION_ERRORS:
            raise self.error(
                no, f"{name} is a position error, a constant: VALUE, not Gridpoints (004 p.31)"
            )
        if not _etalon_axis(name):
            raise self.error(
                no, f"{name} is a constant (not a component error): VALUE, not Gridpoints"
            )
        if not value.startswith("{"):
            raise self.error(no, f"Gridpoints of {name}: '{{' expected after '='")
        self.grid, self.grid_line, self.grid_open = [], no, True
        self.grid_values(no, value[1:])

    def grid_values(self, no: int, text: str) -> None:
        """Numbers inside `Gridpoints = { … }`, up to the closing `}`."""
        assert self.grid is not None
        if text.startswith("["):
            raise self.error(
                no, f"Gridpoints of {self.section} (line {self.grid_line}) not closed: '}}' missing"
            )
        body, brace, rest = text.partition("}")
        if rest.strip():
            raise self.error(no, f"unexpected {rest.strip()!r} after '}}'")
        tokens = body.split()
        if any(t in ELISIONS for t in tokens):
            self.warnings.append((no, ELISION_WARNING))
        for token in (t for t in tokens if t not in ELISIONS):
            value = _number(token)
            if value is None:
                raise self.error(
                    no, f"value {token!r} in Gridpoints of {self.section} is not a number"
                )
            self.grid.append(value)
        if brace:
            self.grid_open = False
            self.check_grid(no)

    def check_grid(self, no: int) -> None:
        """Gridpoints are pairs 'argument value' (004 p.33), at least one."""
        assert self.grid is not None
        n = len(self.grid)
        if n == 0 or n % 2:
            raise self.error(
                self.grid_line,
                f"Gridpoints of {self.section} (lines {self.grid_line}-{no}) has {n} values: "
                "pairs 'argument value' expected",
            )

    def close(self) -> None:
        """End the current block: a parameter block becomes a Block."""
        name = self.section
        if not self.is_parameter or name is None:
            return
        if self.value is not None:
            self.add(name, (), ((self.value,),))
        elif self.grid is not None:
            g = self.grid
            rows = tuple((g[i], g[i + 1]) for i in range(0, len(g), 2))
            self.add(name, (_etalon_axis(name),), rows)
        else:
            raise self.error(self.section_line, f"[{name}] has neither VALUE nor Gridpoints")

    def add(self, name: str, arguments: tuple[str, ...], rows: tuple[Row, ...]) -> None:
        self.blocks.append(Block(arguments, (name,), rows, self.path, self.section_line))

    def finish(self) -> None:
        """End of the file."""
        if self.grid_open:
            raise self.error(
                self.grid_line,
                f"Gridpoints of {self.section} not closed: no '}}' before the end of the file",
            )
        self.close()


def parse_etalon(text: str, path: str = "") -> ParamFile:
    """Read an Etalon exchange file, "Vendor" variant (004 §6.3.3, p.33, p.38). One
    block per parameter: `VALUE` -> no arguments, one row; `Gridpoints` -> rows
    (argument, value) over the component error's axis. Raises ParamFileError."""
    reader = _EtalonReader(path)
    for no, line in _lines(text):
        reader.feed(no, line)
    reader.finish()
    return _result(path, "ETALON_EXCHANGE", reader.blocks, reader.warnings)


def read_param_file(path: str | os.PathLike[str], fmt: str) -> ParamFile:
    """Read one correction file in `fmt`, "ISG_CSV" or "ETALON_EXCHANGE" (004 p.12).

    UTF-8 (a BOM is dropped), else Latin-1: measuring software on Windows writes either.
    Only a regular file of at most `FileLimits.correction_file_bytes` is read
    (`safefile.read_regular`). Raises ParamFileError (unknown format, content) and
    OSError (FileNotFoundError, `safefile.FileRefused` …)."""
    name = os.fspath(path)
    if fmt not in FORMATS:
        raise ParamFileError(
            name, 0, f"unknown file format {fmt!r}: {' or '.join(FORMATS)} (004 p.12)"
        )
    data = read_regular(name, LIMITS.correction_file_bytes)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = data.decode("latin-1")
    parse = parse_isg_csv if fmt == "ISG_CSV" else parse_etalon
    return parse(text, name)


# --- writers -------------------------------------------------------------------------------


def _format(value: float) -> str:
    """repr: the shortest text that reads back to the same float (exact round trip)."""
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{value!r} cannot be written: not a finite number")
    return repr(v)


def _check(block: Block) -> None:
    """ValueError unless the block is one the parsers could have produced."""
    names = block.arguments + block.parameters
    if not block.parameters:
        raise ValueError(f"block ({' '.join(names)}) has no parameter column")
    for i, name in enumerate(names):
        known = ARGUMENTS if i < len(block.arguments) else PARAMETERS
        if name not in known or name in names[:i]:
            raise ValueError(f"block ({' '.join(names)}): column {name!r} unknown or twice")
    if not block.rows:
        raise ValueError(f"block ({' '.join(names)}) has no rows")
    for row in block.rows:
        if len(row) != len(names):
            raise ValueError(f"block ({' '.join(names)}): row {row!r} has {len(row)} values")


def write_isg_csv(blocks: Iterable[Block]) -> str:
    """ISG CSV text of `blocks` (004 p.32): a header per block, rows in repr format,
    blocks separated by a `#` line. Raises ValueError for a malformed block."""
    lines = [WRITTEN]
    for i, block in enumerate(blocks):
        _check(block)
        if i:
            lines.append("#")
        lines.append(" ".join(block.arguments + block.parameters))
        lines.extend(" ".join(_format(v) for v in row) for row in block.rows)
    return "\n".join(lines) + "\n"


def _per_parameter(block: Block) -> Iterator[Block]:
    """The block split into one block per parameter (the Etalon form)."""
    k = len(block.arguments)
    for j, name in enumerate(block.parameters):
        rows = tuple((*row[:k], row[k + j]) for row in block.rows)
        yield Block(block.arguments, (name,), rows, block.file, block.line)


def _etalon_lines(block: Block) -> list[str]:
    """One single-parameter block as Etalon text: VALUE or Gridpoints (004 p.33)."""
    name = block.parameters[0]
    if not block.arguments and len(block.rows) == 1:
        return [f"[{name}]", f"VALUE = {_format(block.rows[0][0])}"]
    if block.arguments and block.arguments == (_etalon_axis(name),):
        pairs = [f"{_format(a)} {_format(v)}" for a, v in block.rows]
        return [f"[{name}]", "Gridpoints = {", *pairs, f"}} // end of {name}"]
    over = ", ".join(block.arguments) or f"nothing, {len(block.rows)} rows"
    raise ValueError(
        f"{name} over ({over}) cannot be written in the Etalon exchange format, "
        "which has only 1-D tables over the parameter's own axis"
    )


def write_etalon(blocks: Iterable[Block]) -> str:
    """Etalon exchange text of `blocks` (004 p.33): one `[NAME]` block per parameter.
    Raises ValueError for what the format cannot hold: several rows without arguments,
    a table over anything but a component error's own axis, a parameter twice."""
    lines = [WRITTEN]
    seen: set[str] = set()
    for block in blocks:
        _check(block)
        for single in _per_parameter(block):
            name = single.parameters[0]
            if name in seen:
                raise ValueError(
                    f"{name} in two blocks: the Etalon exchange format has one per parameter"
                )
            seen.add(name)
            lines.extend(["", *_etalon_lines(single)])
    return "\n".join(lines) + "\n"
