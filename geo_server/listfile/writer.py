"""Token writer for `save` (SPEC §4): change value tokens only, keep every other byte.

`apply_changes` is pure (text in, text out); `rewrite_values` reads the file in its own
encoding, applies the changes and writes it back atomically (temporary file in the same
folder, flush, fsync, `os.replace`, fsync of the folder), so a crash leaves either the
old or the new file.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterable, Mapping
from pathlib import Path

from geo_server.listfile.syntax import normalize_name, parse_text, read_text, split_lines

Changes = Mapping[str, str] | Iterable[tuple[int, str]]


def apply_changes(text: str, changes: Changes) -> str:
    """Return `text` with the value tokens replaced.

    `changes` maps entry names (normalized like the tokenizer: `lr_param.temp_comp`) to
    new value text, or is a list of (1-based line, new value text). A name not in the
    text is appended as `name value` before the `End`/`Ende` line, else at the end, with
    the file's line ending. If a name occurs twice the last occurrence (the one that
    counts when reading) is changed.
    """
    parsed = parse_text(text)
    lines = split_lines(text)
    by_line: dict[int, str] = {}
    append: list[tuple[str, str]] = []
    if isinstance(changes, Mapping):
        last = {e.name: e.line for e in parsed.entries}
        for name, value in changes.items():
            line = last.get(normalize_name(name))
            if line is None:
                append.append((name, value))
            else:
                by_line[line] = value
    else:
        by_line.update(dict(changes))
    spans = {e.line: e.span for e in parsed.entries}
    for line, value in by_line.items():
        if line not in spans:
            raise KeyError(f"line {line} holds no entry")
        start, end = spans[line]
        lines[line - 1] = lines[line - 1][:start] + value + lines[line - 1][end:]
    return _append(lines, append, parsed.end_line)


def _append(lines: list[str], append: list[tuple[str, str]], end_line: int) -> str:
    if not append:
        return "".join(lines)
    eol = "\r\n" if lines and lines[0].endswith("\r\n") else "\n"
    new = [f"{name} {value}{eol}" for name, value in append]
    if end_line:
        lines[end_line - 1 : end_line - 1] = new
    else:
        if lines and not lines[-1].endswith("\n"):
            lines[-1] += eol
        lines += new
    return "".join(lines)


def rewrite_values(path: Path | str, changes: Changes) -> None:
    """Apply `changes` to the list file at `path` atomically, in its own encoding."""
    path = Path(path)
    text, encoding = read_text(path)
    data = apply_changes(text, changes).encode(encoding)
    write_atomic(path, data)


def write_atomic(path: Path, data: bytes) -> None:
    """Write `data` to `path` via a temporary file + fsync + rename + directory fsync."""
    folder = path.parent
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        with contextlib.suppress(OSError):
            os.chmod(tmp, path.stat().st_mode & 0o7777)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    _fsync_dir(folder)


def _fsync_dir(folder: Path) -> None:
    """Make the rename durable (POSIX; a no-op where folders cannot be opened)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        with contextlib.suppress(OSError):
            os.fsync(fd)
    finally:
        os.close(fd)
