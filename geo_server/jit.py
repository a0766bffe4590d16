"""The compiler of the GEO cycle's laws (numba; docs/design.md §13.3).

The compensation laws, the motion profiles and the twin's per-cycle work are plain Python
functions over numpy arrays and floats, written once, and compiled to machine code by
numba (`compiled`): a cycle of the default machine is then one call of a few
microseconds instead of some 110 numpy calls. A pass of many cycles is the same function
in a loop, so a single cycle and a pass give the same numbers by construction.

Compiling costs seconds, so the machine code is cached on disk (`cache_dir`) and loaded
at the next start (`numba`'s own cache: one file per function and signature). Its key
is the stamp (size, modification time) of every module that holds compiled code
(`MODULES`), so an edited law is never served from a stale cache — numba itself only
checks the file of the function it compiles, not the files of the laws it calls.

`GEO_SERVER_JIT_CACHE` names another cache folder; `NUMBA_DISABLE_JIT=1` runs every
law as plain Python (slow; for debugging).
"""

from __future__ import annotations

import hashlib
import os
import sys
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar, cast

F = TypeVar("F", bound=Callable[..., Any])

#: The modules (relative to the package) that define compiled functions. Their stamps key
#: the cache; tests/test_architecture.py checks that every module using `compiled` is
#: listed here.
MODULES = (
    "jit.py",
    "kernel/common.py",
    "kernel/layout.py",
    "kernel/sin2.py",
    "kernel/tables.py",
    "kernel/temperature.py",
    "kernel/plane.py",
    "kernel/crosstalk.py",
    "kernel/lsec.py",
    "kernel/friction.py",
    "kernel/step.py",
    "volcomp/law.py",
    "volcomp/step.py",
    "machine/motion.py",
    "machine/cycle.py",
    "twin/engine.py",
)

_PACKAGE = Path(__file__).resolve().parent
_lock = threading.Lock()
_dir: Path | None = None


def _stamp() -> str:
    """A key of the compiled modules' sources and of the compiler's versions."""
    import numba
    import numpy

    h = hashlib.blake2b(digest_size=10)
    h.update(f"{numba.__version__} {numpy.__version__} {sys.version}".encode())
    for rel in MODULES:
        st = (_PACKAGE / rel).stat()
        h.update(f"{rel} {st.st_size} {st.st_mtime_ns}\n".encode())
    return h.hexdigest()


def _user_cache() -> Path:
    """The platform's cache folder for this user."""
    if sys.platform == "win32":
        base = os.environ.get("LOCALAPPDATA") or str(Path.home() / "AppData" / "Local")
        return Path(base) / "geo-server" / "Cache"
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Caches" / "geo-server"
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "geo-server"


def _writable(path: Path) -> bool:
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError:
        return False
    return True


def cache_dir() -> Path:
    """Where the machine code is cached: `GEO_SERVER_JIT_CACHE`, else the package's
    `__pycache__` (a source checkout or a virtualenv), else the user's cache folder (a
    read-only installation); a folder per `_stamp`."""
    global _dir
    if _dir is None:
        key = f"jit-{_stamp()}"
        given = os.environ.get("GEO_SERVER_JIT_CACHE")
        places = [Path(given)] if given else [_PACKAGE / "__pycache__", _user_cache()]
        for base in places:
            if _writable(base / key):
                _dir = base / key
                break
        else:
            _dir = Path(tempfile.gettempdir()) / "geo-server" / key
    return _dir


def compiled(fn: F) -> F:
    """`fn` compiled (numba `njit`: no Python objects, the GIL released while it runs,
    numpy's rules for a division by zero — inf or nan, as the array code had) and cached
    in `cache_dir`. Other compiled functions may call it."""
    import numba
    from numba.core import config as _config

    config: Any = _config  # (its settings are made at run time: no annotations)
    with _lock:
        where = str(cache_dir())
        before = config.CACHE_DIR
        config.CACHE_DIR = where  # read when the dispatcher is made (its locator)
        try:
            out = numba.njit(cache=True, nogil=True, error_model="numpy")(fn)
        finally:
            config.CACHE_DIR = before
    return cast(F, out)


__all__ = ["MODULES", "cache_dir", "compiled"]
