"""The user's private cache folder, and when it is safe to read what it holds
(docs/design.md §13.3, The cache): the compiled cycle's machine code (`jit_cache`) and
OPC UA's imported NodeSets (`transports/opcua/companions.py`), both pickles."""

from __future__ import annotations

import os
import stat
import sys
import tempfile
from pathlib import Path


def user_cache() -> Path:
    """The platform's cache folder for this user (`geo-server` in it)."""
    if sys.platform == "win32":
        base = os.environ.get("LOCALAPPDATA") or str(Path.home() / "AppData" / "Local")
        return Path(base) / "geo-server" / "Cache"
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Caches" / "geo-server"
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "geo-server"


def unsafe_because(folder: Path) -> str | None:
    """Why nothing cached (machine code, NodeSets) may be loaded from `folder` (None: it may).

    The folder must be this user's and writable by nobody else, and so must every folder
    above it be this user's or root's and not writable by others — except a shared folder
    with the sticky bit (/tmp), where others cannot rename or replace what is ours.
    Anyone who could write there could plant a pickle that runs as this user. On Windows
    (no owners here) the user's own profile folder is trusted."""
    if not hasattr(os, "getuid"):
        return None
    uid = os.getuid()
    try:
        real = folder.resolve(strict=True)
        st = real.stat()
    except OSError as exc:
        return f"{folder}: {exc.strerror or exc}"
    if not stat.S_ISDIR(st.st_mode):
        return f"{real} is not a folder"
    if st.st_uid != uid:
        return f"{real} belongs to user {st.st_uid}, not to this user ({uid})"
    if st.st_mode & 0o022:
        return f"{real} is writable by others (mode {stat.S_IMODE(st.st_mode):o})"
    for parent in real.parents:
        pst = parent.stat()
        if pst.st_uid not in (uid, 0):
            return f"{parent} (above {real}) belongs to user {pst.st_uid}"
        if pst.st_mode & 0o022 and not pst.st_mode & stat.S_ISVTX:
            return f"{parent} (above {real}) is writable by others without the sticky bit"
    return None


def cache_folder(key: str) -> tuple[Path | None, str]:
    """The folder `key` in the cache and how it was chosen, or (None, why not):
    `GEO_SERVER_JIT_CACHE` when set, else the user's cache folder, else a folder of this
    user's own under the system's temporary folder; each created private (0700) and used
    only if `unsafe_because` finds nothing. Machine code goes to `jit-<cache_key>` (None:
    the cycle compiles in memory), OPC UA's imported NodeSets to `opcua-nodesets`."""
    given = os.environ.get("GEO_SERVER_JIT_CACHE")
    if given:
        places = [(Path(given), "GEO_SERVER_JIT_CACHE")]
    else:
        uid = os.getuid() if hasattr(os, "getuid") else "user"
        places = [
            (user_cache(), "the user's cache folder"),
            (Path(tempfile.gettempdir()) / f"geo-server-{uid}", "the temporary folder"),
        ]
    reasons = []
    for base, how in places:
        try:
            base.mkdir(mode=0o700, parents=True, exist_ok=True)
            why = unsafe_because(base)
            if why is None:
                (base / key).mkdir(mode=0o700, exist_ok=True)
                why = unsafe_because(base / key)
            if why is None:
                with tempfile.TemporaryFile(dir=base / key):
                    pass
                return base / key, how
        except OSError as exc:
            why = f"{base}: {exc.strerror or exc}"
        reasons.append(why)
    return None, "; ".join(reasons)
