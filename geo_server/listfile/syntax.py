"""Tokenizer of the ASCII list files (002/003 §1.3–1.4; 002 §1.3).

Rules (each cites where it comes from):

* one entry per line, `name value` (002 §1.3);
* a line starting with `#` is a comment (002 §1.4 asks for `# `; the examples also use a
  bare `#`, `#…` and `# End`, so any `#` at the start of a line makes it a comment);
* after a numeric value anything after a blank is a comment (`1 Comment`, `1 # c`,
  `1 ( c`, `1 /* c */`, `100 [0.1µm]`; 002 §1.4, 000 p.24);
* after a STRING value only `(` opens a comment; the string runs up to it, trailing
  blanks removed, so `kopf.log_achs_name Y AXIS` is "Y AXIS" (002 §1.4, 000 p.62);
* strings in inverted commas `"…"` (printed `″…″`, also `“…”`) may hold any character;
  trailing blanks inside are removed (002 §1.3);
* blanks inside brackets are allowed (`table[ 0][ 1]`, 000 p.49);
* `End`/`Ende` ends the list (002 §3.2.15 example, 001);
* the first name segment is case-insensitive (`Kw.crosstalk…`, 000 p.91);
* a blank after a dot (`lr_param. n_backlash_cyc`, 000 p.13, an extraction artefact) is
  accepted with a warning;
* elision lines of the printed examples (`:`, `...`, `…`, `etc.`) are ignored;
* a line ends in LF, CRLF or a CR alone (old Mac editors); a file may mix them;
* list files are ASCII files (002 §1.3): read as UTF-8, else CP1252 (Windows lists).
  Anything that is no such text — UTF-16/UTF-32, NUL bytes, control characters other
  than TAB/LF/VT/FF/CR/SUB, bytes that are neither UTF-8 nor CP1252 — is refused with
  `NotAListFileError`, never guessed (a guess would load a machine with every
  parameter defaulted);
* only regular files of at most `MAX_LIST_BYTES` are read: a FIFO, a device, a socket
  or a folder is refused before it is opened (reading one would block or never end),
  through `geo_server.safefile.read_regular`, like every file read on request.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from geo_server.errors import GeoError
from geo_server.listfile.schema import value_class
from geo_server.model import Diagnostic
from geo_server.safefile import FileRefused, read_regular

#: Largest list file read, in bytes. The largest table of the manuals (plane
#: compensation, 10201 points) takes well under 1 MiB; the bound keeps a device or a
#: runaway file from filling the memory.
MAX_LIST_BYTES = 64 * 1024 * 1024
#: Quote characters accepted around strings: ASCII and the typographic ones printed.
QUOTES = '"\u2033\u201c\u201d\u201e'
_END_WORDS = {"end", "ende"}
_ELISION = re.compile(r"^(?::+|\.{2,}|…+|etc\.?)(?:\s.*)?$", re.IGNORECASE)
_NAME = re.compile(r"[A-Za-z_]\w*(?:\[-?\d+\])*(?:\.[A-Za-z_]\w*(?:\[-?\d+\])*)*")
_INDEX = re.compile(r"\[(-?\d+)\]")
_MASK_VALUE = re.compile(r"[\w]+(?:\s*\|\s*[\w]+)*")
_NUMBER_STOP = re.compile(r"#|/\*|\(|\[")
_LINE = re.compile(r"[^\r\n]*(?:\r\n|\r|\n)|[^\r\n]+\Z")
_BREAK = re.compile(r"\r\n|\r|\n")
#: Control characters no text list holds (TAB LF VT FF CR are blanks and line ends; SUB
#: is the end-of-file mark old DOS editors append).
_CONTROL = re.compile("[\x00-\x08\x0e-\x19\x1b-\x1f\x7f]")
_UTF16_BOMS = (b"\xff\xfe", b"\xfe\xff")
_SAVE_AS_TEXT = "save it as ASCII/UTF-8"


class NotAListFileError(GeoError, OSError):
    """The file cannot be a list file: not a regular file, too large, or not text.

    An OSError like any file that cannot be read, so whoever reports unreadable files
    reports this one too. `str()` is the reason alone (callers prefix the file name);
    `filename` and `line` (1-based, 0 if no line applies) say where.
    """

    def __init__(self, path: Path | str, reason: str, line: int = 0) -> None:
        super().__init__(reason)
        self.filename, self.reason, self.line = str(path), reason, line

    def __str__(self) -> str:
        return self.reason


@dataclass(frozen=True)
class Entry:
    """One `name value` line.

    `name` is normalized (no blanks, lower-case first segment): `kw.ssfk.table[3].pos`;
    `base` has the indices replaced by `[]`; `span` is the [start, end) character range of
    the value token in `text_line` (quotes included) so the writer can replace exactly it.
    """

    name: str
    base: str
    indices: tuple[int, ...]
    raw: str  # value text as written (quotes included)
    value: str  # value text with quotes removed and trailing blanks stripped
    span: tuple[int, int]
    file: str
    line: int  # 1-based
    raw_name: str = ""


@dataclass
class ParsedList:
    """Every entry of one list file, in file order, with the tokenizer's warnings."""

    path: str
    entries: list[Entry] = field(default_factory=list)
    warnings: list[Diagnostic] = field(default_factory=list)
    encoding: str = "utf-8"
    end_line: int = 0  # 1-based line of `End`/`Ende`, 0 if none


def read_text(path: Path | str, limit: int | None = None) -> tuple[str, str]:
    """Decode a list file: UTF-8 (BOM kept as utf-8-sig), else CP1252.

    Raises `NotAListFileError` for anything that is not a regular text file of at most
    `limit` bytes (default `MAX_LIST_BYTES`; see the module docstring), other OSErrors
    if the file cannot be read.
    """
    return decode_list(read_bytes(path, limit), path)


def read_bytes(path: Path | str, limit: int | None = None) -> bytes:
    """The bytes of a regular file of at most `limit` bytes (default `MAX_LIST_BYTES`),
    read with `geo_server.safefile.read_regular`: never blocking on a FIFO, never
    opening a device, never reading past the limit."""
    bound = MAX_LIST_BYTES if limit is None else limit
    try:
        return read_regular(path, bound)
    except FileRefused as exc:
        reason = f"not a list file: {exc.reason}" if exc.kind == "too_large" else exc.reason
        raise NotAListFileError(path, reason) from None


def decode_list(data: bytes, path: Path | str = "") -> tuple[str, str]:
    """Text and encoding of list file bytes; `NotAListFileError` if they are no text."""
    if data.startswith(_UTF16_BOMS):
        raise NotAListFileError(
            path, f"not a list file: UTF-16 text (byte order mark) — {_SAVE_AS_TEXT}", 1
        )
    nul = data.find(b"\x00")
    if nul >= 0:
        line = _line_of(data, nul)
        reason = f"not a list file: contains NUL bytes (UTF-16?) — {_SAVE_AS_TEXT}"
        raise NotAListFileError(path, reason, line)
    text, encoding = _decode(data, path)
    bad = _CONTROL.search(text)
    if bad:
        line = _line_of(text, bad.start())
        reason = f"not a list file: control character 0x{ord(bad.group()):02X} (binary data?)"
        raise NotAListFileError(path, reason, line)
    return text, encoding


def _decode(data: bytes, path: Path | str) -> tuple[str, str]:
    encoding = "utf-8-sig" if data.startswith(b"\xef\xbb\xbf") else "utf-8"
    try:
        return data.decode(encoding), encoding
    except UnicodeDecodeError:
        pass
    try:
        return data.decode("cp1252"), "cp1252"
    except UnicodeDecodeError as exc:
        byte = data[exc.start]
        reason = (
            f"not a list file: byte 0x{byte:02X} is neither UTF-8 nor Windows-1252 text "
            f"— {_SAVE_AS_TEXT}"
        )
        raise NotAListFileError(path, reason, _line_of(data, exc.start)) from None


def _line_of(data: bytes | str, pos: int) -> int:
    """1-based line of character or byte `pos` (line ends as `split_lines` counts them)."""
    head = data[:pos]
    text = head.decode("latin-1") if isinstance(head, bytes) else head
    return len(_BREAK.findall(text)) + 1


def split_lines(text: str) -> list[str]:
    """Split after every line end (CRLF, LF or a CR alone), keeping the line ends."""
    return _LINE.findall(text)


def normalize_name(raw: str) -> str:
    """Drop blanks and lower-case the first segment (`Kw.crosstalk` -> `kw.crosstalk`)."""
    name = re.sub(r"\s+", "", raw)
    cut = min((i for i in (name.find("."), name.find("[")) if i >= 0), default=len(name))
    return name[:cut].lower() + name[cut:]


def base_name(name: str) -> tuple[str, tuple[int, ...]]:
    """`kw.crosscomp2.table[3][4].correction` -> (`kw.crosscomp2.table[][].correction`, (3, 4))."""
    return _INDEX.sub("[]", name), tuple(int(i) for i in _INDEX.findall(name))


def parse_text(text: str, file: str = "") -> ParsedList:
    """Tokenize list text into entries (see the module docstring for the rules)."""
    result = ParsedList(path=file)
    for number, line in enumerate(split_lines(text), start=1):
        content = line.rstrip("\r\n")
        stripped = content.strip()
        if not stripped or stripped.startswith("#") or _ELISION.match(stripped):
            continue
        if stripped.split()[0].lower() in _END_WORDS:
            result.end_line = number
            break
        entry = _parse_entry(content, file, number, result.warnings)
        if entry is not None:
            result.entries.append(entry)
    return result


def parse_list(path: Path | str, limit: int | None = None) -> ParsedList:
    """Read and tokenize one list file of at most `limit` bytes (default
    `MAX_LIST_BYTES`).

    OSError if it cannot be read; `NotAListFileError` (an OSError) if it is no regular
    text file.
    """
    text, encoding = read_text(path, limit)
    parsed = parse_text(text, str(path))
    parsed.encoding = encoding
    return parsed


def _warn(warnings: list[Diagnostic], file: str, line: int, entry: str, msg: str) -> None:
    warnings.append(Diagnostic("warning", msg, file=file, line=line, entry=entry))


def _scan_name(content: str) -> tuple[int, bool]:
    """End of the name token and whether a blank after a dot had to be skipped."""
    i, depth, dot_gap = len(content) - len(content.lstrip()), 0, False
    while i < len(content):
        c = content[i]
        if c == "[":
            depth += 1
        elif c == "]":
            depth -= 1
        elif c in QUOTES and depth == 0:
            break
        elif c.isspace() and depth <= 0:
            if not content[:i].rstrip().endswith(".") or not content[i:].strip():
                break
            dot_gap = True
        i += 1
    return i, dot_gap


def _parse_entry(content: str, file: str, number: int, warnings: list[Diagnostic]) -> Entry | None:
    end, dot_gap = _scan_name(content)
    raw_name = content[:end].strip()
    name = normalize_name(raw_name)
    if not _NAME.fullmatch(name):
        _warn(warnings, file, number, raw_name, "malformed line ignored (not `name value`)")
        return None
    if dot_gap:
        _warn(warnings, file, number, name, f"blank after a dot in {raw_name!r} ignored")
    base, indices = base_name(name)
    start = end + len(content[end:]) - len(content[end:].lstrip())
    token = _value_token(content, start, value_class(base))
    if token is None:
        _warn(warnings, file, number, name, "entry without a value ignored")
        return None
    (vs, ve), value = token
    tail = content[ve:].strip()
    if content[vs] in QUOTES and tail and not tail.startswith("("):
        # after a string only `( c` is a comment (002 §1.4): anything else is a typo the
        # user should see, e.g. a value split by a stray inverted comma
        _warn(warnings, file, number, name, f"text after the closing quote ignored: {tail!r}")
    return Entry(name, base, indices, content[vs:ve], value, (vs, ve), file, number, raw_name)


def _value_token(content: str, start: int, kind: str) -> tuple[tuple[int, int], str] | None:
    """Locate the value after `start`: its span and its text (002 §1.3–1.4)."""
    rest = content[start:]
    if not rest.strip():
        return None
    if rest[0] in QUOTES:
        close = next((i for i in range(1, len(rest)) if rest[i] in QUOTES), None)
        if close is not None:
            return (start, start + close + 1), rest[1:close].rstrip()
    if kind == "string":
        text = rest.split("(", 1)[0].rstrip() if not rest.startswith("(") else ""
        return ((start, start + len(text)), text) if text else None
    if kind == "mask":
        m = _MASK_VALUE.match(rest)
        if m:
            return (start, start + m.end()), m.group()
    token = rest.split(None, 1)[0]
    stop = _NUMBER_STOP.search(token, 1)
    token = token[: stop.start()] if stop else token
    return (start, start + len(token)), token
