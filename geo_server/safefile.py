"""Reading a file the server is asked to read: bounded, never blocking, regular files only.

Every file read because of a request — the lists on `reload`, the VOLC list named by a
`cnc_interpr_vol_comp_file_w` write (ADS port 553, 0x27C) or re-read by `#VOLCOMP [ID..
UPDATE]`, a VOLC list's correction files `file[j]`, the twin file — goes through
`read_regular` (docs/security.md, "Files"):

* the name is `os.stat`-ed first and only a regular file is opened (a device is never
  opened: opening some has side effects), then opened with `O_NONBLOCK` where the
  platform has it (a FIFO swapped in meanwhile opens at once instead of waiting for a
  writer) and checked again with `os.fstat` on the open descriptor;
* at most `limit` bytes are read: the size `fstat` reports is checked before reading and
  the read itself stops one byte past the limit (a `/proc` file reports size 0 and reads
  as more), so a runaway file never costs more memory than the limit;
* `FileRefused` says why in plain words (`"is a FIFO, not a regular file"`), never with
  the file's content.

Names that arrive over the wire must also lie inside the machine's folders: `confine`
refuses anything that resolves (symbolic links and `..` followed) outside them, and the
caller answers such a name, and any name it cannot read as what was asked for, with the
one text `REFUSED`, which says neither whether nor what the file is.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from geo_server.errors import GeoError

#: The one answer to a file name from the network that is not read: the same text for a
#: name outside the machine's folders, a missing file, a folder, a FIFO, a device and a
#: file that is not what was asked for, so the answer tells nothing about the file system.
REFUSED = (
    "file refused: only regular files of the right kind inside the machine's folder or a "
    "folder given with `geo-server run --allow-dir` are read"
)

#: The file types refused, in the words of the reason.
_KINDS = (
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)
#: The most one `os.read` asks for: a runaway file is read in pieces, never in one
#: buffer of the whole limit.
_CHUNK = 1 << 20
_FLAGS = os.O_RDONLY
for _name in ("O_NONBLOCK", "O_NOCTTY", "O_BINARY", "O_CLOEXEC"):
    _FLAGS |= getattr(os, _name, 0)


@dataclass(frozen=True)
class FileLimits:
    """Largest files read on request (docs/limits.md); a larger one is refused unread
    beyond the limit. List files have their own bound, `listfile.MAX_LIST_BYTES`."""

    #: a VOLC list (004 §3.1): some twenty lines; 1 MiB leaves room for any comment
    volc_list_bytes: int = 1 << 20
    #: a correction file (004 §6.3): a 41³ grid of all 21 parameters of a linear axis
    #: in ISG CSV is about 12 MiB
    correction_file_bytes: int = 16 << 20


#: The limits in force (the defaults; `FileLimits` documents them).
LIMITS = FileLimits()


class FileRefused(GeoError, OSError):
    """A file not read: outside the allowed folders, not a regular file, or too large.

    An OSError like any file that cannot be read. `str()` is the reason alone (callers
    add the file name where they may); `kind` is "outside", "special" or "too_large".
    """

    def __init__(self, path: Path | str, reason: str, kind: str) -> None:
        super().__init__(reason)
        self.filename, self.reason, self.kind = str(path), reason, kind

    def __str__(self) -> str:
        return self.reason


def too_large(limit: int) -> str:
    """The reason of a file beyond `limit` bytes."""
    mib = f" ({limit >> 20} MiB)" if limit and limit % (1 << 20) == 0 else ""
    return f"larger than {limit} bytes{mib}"


def require_regular(path: Path | str, st: os.stat_result, limit: int) -> None:
    """`FileRefused` unless `st` is a regular file of at most `limit` bytes."""
    if not stat.S_ISREG(st.st_mode):
        kind = next((k for test, k in _KINDS if test(st.st_mode)), "a special file")
        raise FileRefused(path, f"is {kind}, not a regular file", "special")
    if st.st_size > limit:
        raise FileRefused(path, too_large(limit), "too_large")


def read_regular(path: Path | str, limit: int) -> bytes:
    """The bytes of the regular file `path`, at most `limit` of them (see the module
    docstring). Raises `FileRefused`, or the OSError of a file that cannot be opened
    (FileNotFoundError, PermissionError …)."""
    require_regular(path, os.stat(path), limit)  # the only check where O_NONBLOCK is absent
    fd = os.open(path, _FLAGS)
    try:
        st = os.fstat(fd)
        require_regular(path, st, limit)  # the name may have been swapped since the stat
        chunks: list[bytes] = []
        total = 0
        want = min(st.st_size, limit) + 1  # one read for an honest file, +1 to see the end
        while True:
            chunk = os.read(fd, min(want, _CHUNK))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
            if total > limit:
                raise FileRefused(path, too_large(limit), "too_large")
            want = limit + 1 - total
    finally:
        os.close(fd)
    return b"".join(chunks)


def _key(path: str) -> str:
    return os.path.normcase(os.path.realpath(path))


def is_inside(path: Path | str, roots: Iterable[Path | str]) -> bool:
    """Whether `path`, with every symbolic link and `..` resolved, is one of `roots` or
    lies below one of them (resolved alike). A name that cannot be resolved (a NUL
    byte, longer than the system allows) is inside nothing."""
    try:
        real = _key(os.fspath(path))
    except (ValueError, OSError):
        return False
    for root in roots:
        base = _key(os.fspath(root))
        try:
            if os.path.commonpath([real, base]) == base:
                return True
        except ValueError:  # another drive (Windows)
            continue
    return False


def confine(path: Path | str, roots: Iterable[Path | str]) -> None:
    """`FileRefused` with `REFUSED` unless `path` lies inside one of `roots`."""
    if not is_inside(path, roots):
        raise FileRefused(path, REFUSED, "outside")


__all__ = [
    "LIMITS",
    "REFUSED",
    "FileLimits",
    "FileRefused",
    "confine",
    "is_inside",
    "read_regular",
    "require_regular",
    "too_large",
]
