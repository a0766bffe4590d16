"""The compiled cycle's cache (geo_server/jit_cache.py, docs/design.md §13.3): keyed by
content, shared by every copy of the same code, loaded only from a folder nobody else can
write, repaired when broken, and never needed to run compiled.

Each case runs a fresh interpreter (the cache is read once per process) against a cache
folder of its own, seeded from the one tests/conftest.py compiled, so nothing here
compiles more than one small law.
"""

from __future__ import annotations

import json
import os
import pickle
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from geo_server import jit, jit_cache
from geo_server.cache import unsafe_because

ROOT = Path(__file__).resolve().parents[1]

#: a fresh process that loads the compiled cycle (every law the warm-up calls, or only
#: `tables.interp` with ONE) and prints what numba's dispatchers did
PROBE = textwrap.dedent(
    """
    import json, logging, os, sys
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    import numpy as np
    from geo_server import jit
    from geo_server.kernel import tables
    if os.environ.get("ONE"):
        tables.interp(np.array([0.0, 10.0, 1.0, 3.0]), 0, 2, 5.0)
    else:
        import geo_server.machine.machine
    jit.load()
    laws = [law for law in jit._laws if law.dispatcher is not None]
    print(json.dumps({
        "folder": str(jit.cache_dir()),
        "hits": sum(sum(law.dispatcher.stats.cache_hits.values()) for law in laws),
        "misses": sum(sum(law.dispatcher.stats.cache_misses.values()) for law in laws),
        "interp_compiled": bool(tables.interp.dispatcher.signatures),
        "interp": tables.interp(np.array([0.0, 10.0, 1.0, 3.0]), 0, 2, 5.0),
    }))
    """
)


def _probe(tmp: Path, cache: Path | None, *, one: bool = False, tree: Path = ROOT,
           limit_bytes: int | None = None) -> tuple[dict[str, object], str]:  # fmt: skip
    env = {k: v for k, v in os.environ.items() if k != "GEO_SERVER_JIT_CACHE"}
    env["PYTHONPATH"] = str(tree)
    if cache is not None:
        env["GEO_SERVER_JIT_CACHE"] = str(cache)
    if one:
        env["ONE"] = "1"
    prelude = ""
    if limit_bytes is not None:  # files over this size cannot be written (a full disk)
        prelude = (
            "import resource, signal\n"
            "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
            f"resource.setrlimit(resource.RLIMIT_FSIZE, ({limit_bytes}, {limit_bytes}))\n"
        )
    done = subprocess.run(
        [sys.executable, "-c", prelude + PROBE], cwd=tmp, env=env, capture_output=True,
        text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1]), done.stderr


def _seed(cache: Path, without: str | None = None) -> Path:
    """A copy of the suite's compiled cache under `cache` (less one law's files)."""
    here = jit.cache_dir()
    assert here is not None, "the suite's own cache is not in use"
    dst = cache / here.name
    shutil.copytree(here, dst, ignore=shutil.ignore_patterns(*([f"{without}*"] if without else [])))
    cache.chmod(0o700)
    dst.chmod(0o700)
    return dst


@pytest.mark.slow
def test_a_copy_of_the_same_code_elsewhere_loads_the_machine_code_compiled_once(
    tmp_path: Path,
) -> None:
    """A reinstall, or the checkout next to its installed copy: other paths, other
    modification times, the same bytes: nothing compiles again."""
    tree = tmp_path / "tree"
    for part in ("geo_server", "objects", "lists"):  # copied, not copy2: new mtimes
        shutil.copytree(ROOT / part, tree / part, copy_function=shutil.copy,
                        ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    cache = tmp_path / "cache"
    folder = _seed(cache)
    before = sorted(p.name for p in folder.iterdir())
    got, _ = _probe(tmp_path, cache, tree=tree)
    assert got["folder"] == str(folder)
    assert got["misses"] == 0 and got["hits"], got  # loaded, none compiled
    assert sorted(p.name for p in folder.iterdir()) == before


@pytest.mark.slow
def test_a_cache_cut_short_is_not_warm_until_a_load_made_every_law(tmp_path: Path) -> None:
    """A compile cut short leaves some laws' files (here: all but `interp`'s) and no
    mark: not warm (a fleet says "compiling", not "loading"); the next full load makes
    the missing law and marks the cache whole."""
    cache = tmp_path / "cache"
    folder = _seed(cache, without="interp")
    (folder / jit.WHOLE).unlink(missing_ok=True)
    assert any(folder.glob("*.nbi"))
    env = {k: v for k, v in os.environ.items() if k != "GEO_SERVER_JIT_CACHE"}
    env |= {"PYTHONPATH": str(ROOT), "GEO_SERVER_JIT_CACHE": str(cache)}
    code = (
        "import geo_server.machine.machine\nfrom geo_server import jit\n"
        "print(jit.cache_is_warm()); jit.load(); print(jit.cache_is_warm())"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True,
        text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["False", "True"]
    assert (folder / jit.WHOLE).is_file()


def test_an_edited_law_is_never_served_from_the_cache(tmp_path: Path) -> None:
    """The key is the content: one byte more in a compiled module is another folder."""
    tree = tmp_path / "tree"
    shutil.copytree(ROOT / "geo_server", tree / "geo_server",
                    ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    key = jit_cache.cache_key(tree / "geo_server", jit.MODULES)
    assert f"jit-{key}" == jit.cache_dir().name  # type: ignore[union-attr]
    with (tree / "geo_server" / "kernel" / "tables.py").open("a") as f:
        f.write("\n# edited\n")
    assert jit_cache.cache_key(tree / "geo_server", jit.MODULES) != key


@pytest.mark.slow
def test_a_truncated_cache_file_is_compiled_again_and_repaired(tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    folder = _seed(cache)
    (index,) = folder.glob("kernel.tables.interp-*.nbi")
    for f in [index, *folder.glob("kernel.tables.interp-*.nbc")]:
        f.write_bytes(f.read_bytes()[: len(f.read_bytes()) // 2])
    got, err = _probe(tmp_path, cache, one=True)
    assert "could not be read" in err and "kernel.tables" in err, err
    assert got["interp_compiled"] and got["interp"] == 2.0 and got["misses"] == 1, got
    again, err = _probe(tmp_path, cache, one=True)  # repaired: loaded, not compiled
    assert again["misses"] == 0 and again["hits"] == 1, (again, err)


@pytest.mark.slow
@pytest.mark.skipif(not hasattr(os, "getuid"), reason="file size limits are POSIX")
def test_a_full_disk_compiles_in_memory_and_runs_compiled(tmp_path: Path) -> None:
    """No cache file can be written (RLIMIT_FSIZE: every write past 64 bytes fails, as on
    a full disk): the law compiles, says why it is not cached, and runs compiled."""
    cache = tmp_path / "cache"
    _seed(cache, without="kernel.tables.interp-")
    got, err = _probe(tmp_path, cache, one=True, limit_bytes=64)
    assert "could not be written to its cache" in err, err
    assert got["interp_compiled"] and got["interp"] == 2.0 and got["misses"] == 1, got


def _planted(folder: Path, marker: Path) -> None:
    """A cache index for `tables.interp` that runs code when unpickled."""
    import numba

    class Payload:
        def __reduce__(self) -> tuple[object, ...]:
            return (os.system, (f"touch {marker}",))

    from geo_server.kernel import tables

    lineno = tables.interp.py_func.__code__.co_firstlineno
    name = f"kernel.tables.interp-{lineno}.py{sys.version_info[0]}{sys.version_info[1]}.nbi"
    with (folder / name).open("wb") as f:
        pickle.dump(numba.__version__, f)
        f.write(pickle.dumps(Payload()))


@pytest.mark.slow
@pytest.mark.skipif(not hasattr(os, "getuid"), reason="owners and modes are POSIX")
def test_a_cache_folder_others_can_write_is_never_read(tmp_path: Path) -> None:
    """Another local user made the folder first (0777) and planted a pickle in it: the
    server compiles in memory, says why, and the planted code never runs."""
    cache = tmp_path / "shared"
    cache.mkdir()
    cache.chmod(0o777)
    key = jit.cache_dir().name  # type: ignore[union-attr]
    (cache / key).mkdir()
    (cache / key).chmod(0o777)
    marker = tmp_path / "planted-code-ran"
    _planted(cache / key, marker)
    got, err = _probe(tmp_path, cache, one=True)
    assert not marker.exists()
    assert got["folder"] == "None" and "writable by others" in err, (got, err)
    assert got["interp_compiled"] and got["interp"] == 2.0, got


@pytest.mark.skipif(not hasattr(os, "getuid") or os.getuid() != 0, reason="needs chown (root)")
def test_a_cache_folder_of_another_user_is_never_read(tmp_path: Path) -> None:
    cache = tmp_path / "theirs"
    cache.mkdir(mode=0o700)
    os.chown(cache, 65534, 65534)
    why = unsafe_because(cache)
    assert why is not None and "belongs to user 65534" in why


@pytest.mark.skipif(not hasattr(os, "getuid"), reason="owners and modes are POSIX")
def test_a_private_folder_below_a_sticky_shared_one_is_used(tmp_path: Path) -> None:
    shared = tmp_path / "tmp"
    shared.mkdir()
    shared.chmod(0o1777)
    mine = shared / "geo-server-me"
    mine.mkdir(mode=0o700)
    assert unsafe_because(mine) is None
    shared.chmod(0o777)  # without the sticky bit anyone could replace it
    assert "without the sticky bit" in (unsafe_because(mine) or "")


def test_numba_still_has_the_cache_classes_this_project_subclasses() -> None:
    """Fails on a numba release that changed them (geo_server/jit_cache.py)."""
    assert jit_cache.numba_fits() is None
