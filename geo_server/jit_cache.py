"""Where the compiled cycle's machine code is kept between runs, and when that is safe
(docs/design.md §13.3, The cache).

numba keeps a compiled function in a folder next to its source, stamped with the source
file's modification time: a reinstall, or the same code installed twice (a checkout and
the copy in a virtualenv), compiles again, and the folder is whatever numba finds
writable. Here the laws' cache is keyed by content instead (`cache_key`: the compiled
modules' sources, numba's, numpy's and Python's versions and the processor), so every
copy of the same code on one machine shares one compile, and it lives in one folder that
`cache.cache_folder` checks before anything is read from it: numba's index is a pickle,
and loading a pickle someone else wrote runs their code as this user.

This module is the one place that knows numba's cache classes (`law_cache` replaces a
dispatcher's `_cache`); tests/test_jit_cache.py fails when a numba release changes them.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import sys
from pathlib import Path
from typing import Any

log = logging.getLogger("geo_server.jit")


def cache_key(package: Path, modules: tuple[str, ...]) -> str:
    """A key of what the machine code is made from: the bytes of every compiled module,
    the compiler's and numpy's versions, Python's, and the processor numba targets (a
    cache copied to another machine is never loaded there)."""
    import llvmlite.binding as llvm
    import numba
    import numpy
    from numba.core import config as _config

    config: Any = _config  # (its settings are made at run time: no annotations)
    cpu = config.CPU_NAME or llvm.get_host_cpu_name()
    features = config.CPU_FEATURES or llvm.get_host_cpu_features().flatten()
    h = hashlib.blake2b(digest_size=12)
    h.update(f"{numba.__version__} {numpy.__version__} {sys.version} {cpu} {features}".encode())
    for rel in modules:
        h.update(f"\0{rel}\0".encode())
        h.update((package / rel).read_bytes())
    return h.hexdigest()


def numba_fits() -> str | None:
    """Why numba's cache classes cannot be used as `law_cache` expects (None: they can):
    the classes it subclasses, and the index file's arguments."""
    import inspect

    import numba

    try:  # (the classes `law_cache` imports)
        from numba.core.caching import (  # noqa: F401
            CompileResultCacheImpl,
            FunctionCache,
            IndexDataCacheFile,
            _CacheLocator,
        )

        args = list(inspect.signature(IndexDataCacheFile).parameters)
    except (ImportError, AttributeError, TypeError, ValueError) as exc:
        return f"numba {numba.__version__}: {exc}"
    if args != ["cache_path", "filename_base", "source_stamp"]:
        return f"numba {numba.__version__}: its cache index takes {args}"
    return None


def law_cache(py_func: Any, folder: Path, stamp: str, tag: str) -> Any:
    """numba's function cache for `py_func` (a law's copy) in `folder`, its index stamped
    with `stamp` (the content key: never a file's modification time) and its files named
    by `tag` (the module's path in the package, so `kernel/step.py` and `volcomp/step.py`
    never share a name). A cache file that cannot be read (truncated, corrupt, from
    another build) is compiled again and rewritten; one that cannot be written (a full
    disk, a read-only folder) leaves the machine code in memory: either way the law runs
    compiled."""
    from numba.core.caching import (
        CompileResultCacheImpl,
        FunctionCache,
        IndexDataCacheFile,
        _CacheLocator,
    )

    class Locator(_CacheLocator):
        def __init__(self) -> None:
            self._lineno = py_func.__code__.co_firstlineno

        def ensure_cache_path(self) -> None:
            folder.mkdir(mode=0o700, parents=True, exist_ok=True)

        def get_cache_path(self) -> str:
            return str(folder)

        def get_source_stamp(self) -> str:
            return stamp

        def get_disambiguator(self) -> str:
            return str(self._lineno)

    class Impl(CompileResultCacheImpl):
        def __init__(self) -> None:  # (numba's looks for a locator by the source's path)
            self._lineno = py_func.__code__.co_firstlineno
            self._locator = Locator()
            abiflags = getattr(sys, "abiflags", "")
            self._filename_base = self.get_filename_base(f"{tag}.{py_func.__qualname__}", abiflags)

    class Cache(FunctionCache):
        def __init__(self) -> None:
            self._name = repr(py_func)
            self._py_func = py_func
            self._impl = Impl()
            self._cache_path = str(folder)
            self._cache_file = IndexDataCacheFile(str(folder), self._impl.filename_base, stamp)
            self.enable()

        def load_overload(self, sig: Any, target_context: Any) -> Any:
            try:
                return super().load_overload(sig, target_context)
            except Exception as exc:  # a broken file: compile, and the save repairs it
                log.warning(
                    "the compiled cycle's cache file for %s could not be read (%s: %s): "
                    "compiling it again",
                    tag,
                    type(exc).__name__,
                    exc,
                )
                with contextlib.suppress(OSError):
                    Path(self._cache_file._index_path).unlink()
                return None

        def save_overload(self, sig: Any, data: Any) -> None:
            try:
                super().save_overload(sig, data)
            except OSError as exc:
                _not_saved(folder, exc)

    return Cache()


_warned: set[str] = set()


def _not_saved(folder: Path, exc: OSError) -> None:
    """Says once per folder that machine code stays in memory only."""
    if str(folder) not in _warned:
        _warned.add(str(folder))
        log.warning(
            "the compiled cycle could not be written to its cache %s (%s): it runs compiled "
            "from memory and compiles again at the next start",
            folder,
            exc.strerror or exc,
        )
