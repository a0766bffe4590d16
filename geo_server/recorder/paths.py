"""Where a recording may write (docs/recorder.md §7, docs/security.md).

A recording requested over an interface (Zenoh `cmd/record`) names its file, and that
name comes from the network: it is only ever a file *in the recordings folder*
(`geo-server run --record-dir DIR`; by default `recordings/` beside the start-up list,
see `default_record_dir`). `output_path` turns the name into that file or refuses it
with `RecordPathError` (0x70B) and one plain reason:

* a plain file name ending in `.csv` or `.parquet` — no separators (`/`, `\\`), no `.`
  or `..`, no hidden name (`.x`, the form of the temporary files), no NUL, at most
  `RecorderLimits.max_text` characters; an absolute path is accepted only when it names
  a file directly in the folder (symbolic links resolved), anything else is "outside";
* an existing file is replaced only when asked (`overwrite`), and never when it is a
  symbolic link, not a regular file, a list file (`*.lis`) or a file the machine loaded
  (its lists, twin file and correction files), whatever `overwrite` says — the same for
  the inputs file beside it (`<stem>.inputs.jsonl`).

The file is then written under a temporary name and put in place atomically
(`listfile.writer.AtomicFile`), so even a replaced trace is never written through.
The command line (`geo-server run --record-out FILE`) writes where the local user says
(`check_target` with `overwrite=True`: only the machine's own files are refused).
"""

from __future__ import annotations

import os
import stat
from collections.abc import Iterable
from pathlib import Path

from geo_server.errors import GeoError
from geo_server.model import MachineConfig
from geo_server.paths import default_startup_list
from geo_server.recorder.inputs import inputs_path
from geo_server.recorder.recorder import LIMITS

#: What a recording's file may be called over the network.
SUFFIXES = (".csv", ".parquet")
#: The folder a recording goes to, beside the start-up list.
RECORDINGS = "recordings"


class RecordPathError(GeoError, ValueError):
    """A recording's file name that is refused; the message says why."""


def default_record_dir(startup: Path) -> Path:
    """`recordings/` beside the start-up list — or in the working folder for the shipped
    default machine, whose folder is the product's own (never written to)."""
    try:
        shipped = os.path.samefile(startup, default_startup_list())
    except OSError:  # (no default machine in this installation)
        shipped = False
    return (Path.cwd() if shipped else Path(startup).resolve().parent) / RECORDINGS


def machine_files(cfg: MachineConfig) -> list[Path]:
    """Every file the machine `cfg` was loaded from (start-up list, axis and
    compensation lists, twin file, VOLC lists and their correction files)."""
    from geo_server.twin.file import twin_path

    startup = Path(cfg.startup_path)
    base = startup.parent
    files = [startup, twin_path(startup), *(base / f for f in cfg.list_files)]
    for v in cfg.volumetric:  # (VolComp: typed loosely in the model, see there)
        files += [Path(f) for f in (v.path, *v.param_files) if f]
    return files


def output_path(
    name: str,
    folder: Path,
    *,
    overwrite: bool = False,
    protected: Iterable[Path] = (),
    max_text: int = LIMITS.max_text,
) -> Path:
    """The file of the recordings folder `folder` that the name `name` (from the network)
    stands for; `RecordPathError` if it is not one or may not be written."""
    if not isinstance(name, str) or not name:
        raise RecordPathError("record: out must be a file name such as 'trace.csv'")
    if len(name) > max_text or "\0" in name:
        raise RecordPathError(f"record: out must be a file name of at most {max_text} characters")
    real_folder = Path(os.path.realpath(folder))
    outside = RecordPathError(
        f"record: out must name a file in the recordings folder {real_folder} "
        "(a name such as 'trace.csv'; paths elsewhere are refused)"
    )
    if os.path.isabs(name):
        if Path(os.path.realpath(os.path.dirname(name))) != real_folder:
            raise outside
        name = os.path.basename(name)
    if "/" in name or "\\" in name or name in (".", ".."):
        raise outside
    if name.startswith("."):
        raise RecordPathError(f"record: out {name!r}: a hidden name is not a recording's")
    if not name.lower().endswith(SUFFIXES):
        raise RecordPathError(f"record: out {name!r} must end in .csv or .parquet")
    target = real_folder / name
    check_target(target, overwrite=overwrite, protected=protected)
    return target


def check_target(target: Path, *, overwrite: bool, protected: Iterable[Path] = ()) -> None:
    """`RecordPathError` unless `target` and its inputs file may be written: new, or
    (with `overwrite`) an existing regular file that is neither a list file nor one of
    the machine's `protected` files."""
    guarded = list(protected)
    for p in (target, inputs_path(target)):
        try:
            st = os.lstat(p)
        except FileNotFoundError:
            continue
        except OSError as exc:
            raise RecordPathError(f"record: {p.name}: cannot be written ({exc.strerror})") from None
        if stat.S_ISLNK(st.st_mode):
            raise RecordPathError(f"record: {p.name} is a symbolic link: not replaced")
        if not stat.S_ISREG(st.st_mode):
            raise RecordPathError(f"record: {p.name} exists and is not a regular file")
        if p.suffix.lower() == ".lis" or any(_same(st, q) for q in guarded):
            raise RecordPathError(f"record: {p.name} is a file of the machine: never replaced")
        if not overwrite:
            raise RecordPathError(
                f"record: {p.name} exists; ask for overwrite (true) to replace it, or name "
                "another file"
            )


def _same(st: os.stat_result, other: Path) -> bool:
    try:
        o = os.stat(other)
    except OSError:
        return False
    return (st.st_dev, st.st_ino) == (o.st_dev, o.st_ino)


__all__ = [
    "RECORDINGS",
    "SUFFIXES",
    "RecordPathError",
    "check_target",
    "default_record_dir",
    "machine_files",
    "output_path",
]
