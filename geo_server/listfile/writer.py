"""Token writer for `save`: change value tokens only, keep every other byte.

`apply_changes` is pure (text in, text out); `rewrite_values` reads the file in its own
encoding, applies the changes and writes it back atomically (temporary file in the same
folder, flush, fsync, `os.replace`, fsync of the folder), so a crash leaves either the
old or the new file. Line ends (LF, CRLF, CR) and the encoding (UTF-8 with or without
BOM, CP1252) stay as they were; a file that is no longer a text list file is refused
and left as it is. A temporary file is named `.<list name>.<8 characters>.tmp`; one
that a killed process left behind is removed by `remove_orphan_temps`.
"""

from __future__ import annotations

import contextlib
import os
import re
import stat
import tempfile
from collections.abc import Iterable, Mapping
from pathlib import Path

from geo_server.listfile.syntax import normalize_name, parse_text, read_text, split_lines

Changes = Mapping[str, str] | Iterable[tuple[int, str]]
_LINE_ENDS = ("\r\n", "\r", "\n")  # CRLF first: it also ends in LF


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
    eol = line_end(lines)
    new = [f"{name} {value}{eol}" for name, value in append]
    if end_line:
        lines[end_line - 1 : end_line - 1] = new
    else:
        if lines and not lines[-1].endswith(_LINE_ENDS):
            lines[-1] += eol
        lines += new
    return "".join(lines)


def line_end(lines: list[str]) -> str:
    """The line end of the first line that has one (LF for a file without any)."""
    for line in lines:
        for eol in _LINE_ENDS:
            if line.endswith(eol):
                return eol
    return "\n"


def rewrite_values(path: Path | str, changes: Changes) -> None:
    """Apply `changes` to the list file at `path` atomically, in its own encoding.

    Raises `syntax.NotAListFileError` (an OSError) without touching the file if it is no
    longer a regular text list file (e.g. replaced by a UTF-16 or binary file since it
    was loaded): writing single-byte text into it would corrupt it.
    """
    path = Path(path)
    text, encoding = read_text(path)
    data = apply_changes(text, changes).encode(encoding)
    write_atomic(path, data)


#: Name parts of `write_atomic`'s temporary files: `.<name>.` + 8 random characters
#: of `tempfile` (a-z, 0-9, _) + `.tmp`.
TEMP_SUFFIX = ".tmp"
_TEMP_RANDOM = re.compile(r"[a-z0-9_]{8}")


def temp_prefix(path: Path) -> str:
    """How the temporary files of `path` begin."""
    return f".{path.name}."


class AtomicFile:
    """A file written under a temporary name in `path`'s folder (`.<name>.<8>.tmp`) and
    put in place by `commit` (flush, fsync, `os.replace`, fsync of the folder), so a
    crash at any moment leaves the old `path` or the whole new one. `fh` may be written
    for as long as the caller likes (a recording streams into it, docs/recorder.md §3);
    `abort` removes the temporary file. `path` itself is never opened: a link or another
    name of the old file is not written through."""

    def __init__(self, path: Path) -> None:
        self.path = path
        fd, tmp = tempfile.mkstemp(prefix=temp_prefix(path), suffix=TEMP_SUFFIX, dir=path.parent)
        self.tmp = Path(tmp)
        self.fh = os.fdopen(fd, "wb")

    def commit(self) -> None:
        try:
            self.fh.flush()
            os.fsync(self.fh.fileno())
            self.fh.close()
            with contextlib.suppress(OSError):
                os.chmod(self.tmp, self.path.stat().st_mode & 0o7777)
            os.replace(self.tmp, self.path)
        except BaseException:
            self.abort()
            raise
        _fsync_dir(self.path.parent)

    def abort(self) -> None:
        # best effort: the error that made us abort is the one to report
        with contextlib.suppress(Exception):
            self.fh.close()
        with contextlib.suppress(OSError):
            os.unlink(self.tmp)


def write_atomic(path: Path, data: bytes) -> None:
    """Write `data` to `path` via a temporary file + fsync + rename + directory fsync."""
    f = AtomicFile(path)
    try:
        f.fh.write(data)
    except BaseException:
        f.abort()
        raise
    f.commit()


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


def is_orphan_temp(name: str, path: Path) -> bool:
    """Whether file name `name` is one `write_atomic(path, …)` creates."""
    prefix = temp_prefix(path)
    if not (name.startswith(prefix) and name.endswith(TEMP_SUFFIX)):
        return False
    middle = name[len(prefix) : len(name) - len(TEMP_SUFFIX)]
    return _TEMP_RANDOM.fullmatch(middle) is not None


def remove_orphan_temps(paths: Iterable[Path | str]) -> list[Path]:
    """Remove the temporary files a killed `save` left next to the list files `paths`.

    Only regular files named exactly like `write_atomic`'s temporaries of one of the
    given lists go (`.achsmd1.lis.k3j_x9a2.tmp` for `achsmd1.lis`); anything else in the
    folders stays. A file that cannot be removed is left (and not returned). Call it
    when no save is writing into these folders, e.g. at start-up. Returns the removed
    files, sorted.
    """
    by_folder: dict[Path, list[Path]] = {}
    for p in map(Path, paths):
        by_folder.setdefault(p.parent, []).append(p)
    removed: list[Path] = []
    for folder, lists in by_folder.items():
        try:
            names = os.listdir(folder)
        except OSError:
            continue
        for name in names:
            if any(is_orphan_temp(name, p) for p in lists) and _remove_file(folder / name):
                removed.append(folder / name)
    return sorted(removed)


def _remove_file(path: Path) -> bool:
    """Unlink `path` if it is a regular file (not a link, folder or FIFO)."""
    try:
        if not stat.S_ISREG(os.lstat(path).st_mode):
            return False
        os.unlink(path)
    except OSError:
        return False
    return True
