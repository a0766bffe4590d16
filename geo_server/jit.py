"""The compiler of the GEO cycle's laws (numba; docs/design.md §13.3).

The compensation laws, the motion profiles and the twin's per-cycle work are plain Python
functions over numpy arrays and floats, written once, and compiled to machine code by
numba: a cycle of the default machine is then one call of a few microseconds instead of
some 110 numpy calls. A pass of many cycles is the same function in a loop, so a single
cycle and a pass give the same numbers by construction.

`compiled` makes a function a `Law`: called from Python it runs the machine code once
that is loaded, and the plain Python function — the same code, interpreted: the same
numbers, about a thousand times slower — until then. Loading (`load`, or `start` in the
background) imports numba (half a second), initialises its code generator (another half)
and loads the machine code from its cache, or compiles it when the cache is cold (some
twenty seconds, once per installation and source change). So nothing that needs no cycle
(`geo-server objects`, the clients) pays for the compiler, and a server answers as soon
as its interfaces are up: its first cycles run interpreted while the code loads.

The cache (`cache_dir`, geo_server/jit_cache.py) is numba's own, one file per function
and signature, keyed by the content of every module that holds compiled code (`MODULES`),
numba's version and the processor: an edited law is never served from a stale cache
(numba itself only checks the file of the function it compiles, not the files of the laws
it calls), and a reinstall or a second copy of the same code loads the first one's machine
code. It is used only from a folder nobody else can write (else the laws compile in
memory, and a log line says why).

Nothing here starts a thread or changes a setting at import: the composition root (`geo-
server run`, a fleet, the cycle's process) calls `start` or `load`, once.

Compiled code calls other laws by their plain names (`from m import f`, never `m.f`): a
law's compiled copy sees the machine code of every law in its globals (`_compile`).

`GEO_SERVER_JIT_CACHE` names another cache folder (a CI keeps it between runs);
`NUMBA_DISABLE_JIT=1` keeps every law interpreted (slow; for debugging).
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar, cast

from geo_server import cache, jit_cache

F = TypeVar("F", bound=Callable[..., Any])
#: A part's typed bundle (a `NamedTuple` of its arrays: `KernelState`, `MotionState` …) as
#: Python hands it to compiled code: a plain tuple in the bundle's order, named again on
#: entry (`k = KernelState(*kernel)`, free in compiled code). numba types a plain tuple in
#: C and a named one in Python, about 0.4 µs more per argument and call (docs/design.md
#: §13.3).
Packed = tuple[Any, ...]
log = logging.getLogger(__name__)

#: The modules (relative to the package) that define compiled functions or the
#: constants and plain laws they use. Their stamps key the cache; tests/
#: test_architecture.py checks that every module using `compiled` is listed here.
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
    "machine/profile.py",
    "machine/cycle.py",
    "twin/noise.py",
    "twin/laws.py",
)

_PACKAGE = Path(__file__).resolve().parent
_dir: tuple[Path | None, str] | None = None  # (the cache folder or None, how or why not)


def cache_dir() -> Path | None:
    """Where the machine code is cached (cache.cache_folder): `GEO_SERVER_JIT_CACHE`,
    else the user's cache folder, else a private one under the temporary folder, in a
    folder per content key; None when none of them is safe (the laws compile in memory)."""
    global _dir
    if _dir is None:
        _dir = cache.cache_folder(f"jit-{jit_cache.cache_key(_PACKAGE, MODULES)}")
        if _dir[0] is None:
            log.warning("the compiled cycle is not cached (it compiles in memory): %s", _dir[1])
    return _dir[0]


class Law:
    """A compiled function's face in Python: calls run its machine code once `load` has
    made it (`dispatcher`), the plain function (`py_func`) until then."""

    def __init__(self, fn: Callable[..., Any]) -> None:
        self.py_func = fn
        self.dispatcher: Any = None
        self._fn: Callable[..., Any] = self._interpreted
        self._sample: tuple[Any, ...] | None = None  # a call's arguments, for `load`
        self.__name__ = fn.__name__
        self.__qualname__ = fn.__qualname__
        self.__module__ = fn.__module__
        self.__doc__ = fn.__doc__
        self.__wrapped__ = fn

    def __call__(self, *args: Any) -> Any:
        return self._fn(*args)

    def _interpreted(self, *args: Any) -> Any:
        if _loaded.is_set() and _jit:  # a law made after `load` (its module imported since)
            _compile()
            return self._fn(*args)
        if _depth.value == 0 and self._sample is None:
            self._sample = args  # called from Python: `load` compiles this signature
        _depth.value += 1
        try:
            return self.py_func(*args)
        finally:
            _depth.value -= 1

    def __repr__(self) -> str:
        return f"<law {self.__module__}.{self.__qualname__}>"


class _Depth(threading.local):
    value = 0  # nesting of interpreted law calls on this thread


_depth = _Depth()
_laws: list[Law] = []
_warm_ups: list[Callable[[], None]] = []
_lock = threading.Lock()  # the registry of laws and their dispatchers
_loading = threading.Lock()  # held while `load` runs
_busy = False  # `load` runs (its warm-ups make machines, which `start` it)
_loaded = threading.Event()
_thread: threading.Thread | None = None
_jit = os.environ.get("NUMBA_DISABLE_JIT") != "1"  # (else every law stays interpreted)


def compiled(fn: F) -> F:
    """`fn` as a `Law`: compiled by numba (`njit`: no Python objects, the GIL released
    while it runs, numpy's rules for a division by zero — inf or nan) when `load`ed;
    interpreted until then. Other compiled functions may call it."""
    law = Law(fn)
    _laws.append(law)
    return cast(F, law)


def on_load(warm_up: Callable[[], None]) -> None:
    """`load` runs `warm_up` once its dispatchers are made: code that calls the laws the
    way their users do (a few cycles of a machine), so that their machine code is loaded
    before the first real call. Registered after `load`, it runs at once."""
    _warm_ups.append(warm_up)
    if _loaded.is_set() and _jit:
        warm_up()


#: written into the cache folder once a `load` there has made every law's machine code
#: and run the warm-ups: the cache is whole (a compile cut short leaves some laws'
#: files and not this one)
WHOLE = "whole"


def cache_is_warm() -> bool:
    """The cache holds the machine code of every law the warm-ups call: `load` reads it
    instead of compiling (what a slow start is then waiting for: issue 45 #17). A cache
    with only some laws' files (a compile cut short) is not warm."""
    folder = cache_dir()
    return folder is not None and (folder / WHOLE).is_file()


def loaded() -> bool:
    """The machine code runs (else the laws run interpreted)."""
    return _loaded.is_set()


def start() -> None:
    """`load` in a background thread (nothing when loaded or loading); the laws stay
    interpreted until it is done. Called by the composition root once its interfaces are
    up (`geo-server run`), never by a library object."""
    global _thread
    with _lock:
        if _loaded.is_set() or _thread is not None or _busy:
            return
        _thread = threading.Thread(target=_load_quietly, name="geo-jit", daemon=True)
        _thread.start()


def _load_quietly() -> None:
    try:
        load()
    except Exception:  # the laws keep running interpreted: slow, but right
        log.exception("the compiled cycle could not be loaded; it runs interpreted")


def load() -> None:
    """Make every law's machine code (from the cache, or compiled into it) and switch its
    calls to it; returns when done (at once when done before). Compiles the signatures
    the laws were called with so far, the rest at their first call; a law made later (its
    module imported since) gets its machine code at its first call."""
    global _busy
    with _loading:
        if _loaded.is_set():
            return
        _busy = True
        try:
            if _jit:
                _compile()
                for warm_up in _warm_ups:
                    warm_up()
                _mark_whole()
        finally:
            _busy = False
        _loaded.set()


def _mark_whole() -> None:
    """`WHOLE` in the cache folder, after a `load` that made every law (nothing when
    there is no folder, or it cannot be written: the next start compiles again)."""
    folder = cache_dir()
    if folder is not None and _warm_ups:
        with contextlib.suppress(OSError):
            (folder / WHOLE).touch()


def _compile() -> None:
    """Dispatchers for the laws that have none yet (all of them, the first time)."""
    with _lock:
        new = [law for law in _laws if law.dispatcher is None]
        if new:
            _dispatch(new)


def _dispatch(new: list[Law]) -> None:
    import numba

    folder = cache_dir()
    unfit = jit_cache.numba_fits() if folder is not None else None
    if unfit is not None:
        log.warning("the compiled cycle is not cached (it compiles in memory): %s", unfit)
        folder = None
    # each law's copy gets its module's globals with every law replaced by its
    # dispatcher: what numba resolves when it compiles a call to another law
    copies: list[tuple[Law, dict[str, Any]]] = []
    for law in new:
        fn = law.py_func
        scope: dict[str, Any] = {}
        twin = types.FunctionType(fn.__code__, scope, fn.__name__, fn.__defaults__, fn.__closure__)
        twin.__qualname__, twin.__module__ = fn.__qualname__, fn.__module__
        twin.__doc__, twin.__annotations__ = fn.__doc__, fn.__annotations__
        law.dispatcher = numba.njit(nogil=True, error_model="numpy")(twin)
        if folder is not None:  # numba's cache, keyed by content, in the checked folder
            tag = fn.__module__.removeprefix("geo_server.")
            # (the folder's name is the content key: the index's stamp)
            law.dispatcher._cache = jit_cache.law_cache(twin, folder, folder.name, tag)
        copies.append((law, scope))
    for law, scope in copies:
        for name, value in law.py_func.__globals__.items():
            scope[name] = value.dispatcher if isinstance(value, Law) else value
    for law in new:  # the signatures used so far: loaded (or compiled) now
        if law._sample is not None:
            law.dispatcher.compile(tuple(numba.typeof(a) for a in law._sample))
            law._sample = None
    for law in new:
        law._fn = law.dispatcher


__all__ = [
    "MODULES",
    "Law",
    "cache_dir",
    "cache_is_warm",
    "compiled",
    "load",
    "loaded",
    "on_load",
    "start",
]
