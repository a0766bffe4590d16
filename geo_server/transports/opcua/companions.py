"""The companion models' types in asyncua's address space: the OPC Foundation's NodeSets
imported once, then restored from a cache of what the import added (docs/opcua.md,
Start-up).

asyncua's XML import of the five NodeSets (CNC, DI, Machinery, IA, Machine Tool; about
1 700 nodes) takes 3 s of pure Python on a quiet 2-core host and twice that while a
fleet's machines start; it is most of the time until OPC UA serves. What it leaves is
plain data: the nodes it added, the references it appended to nodes of the standard
address space, the namespaces it registered, and the classes of the models' own
structures and enumerations (asyncua makes them from the data types' definitions).
`add` records the first three after an import into `companions-<key>.pickle`, and the
next start with the same key puts them back and lets asyncua make the classes again
(`load_data_type_definitions`, as its import does): tests/test_opcua_companion.py
compares both address spaces node by node.

The key covers everything the result depends on: the NodeSets' bytes, asyncua's and
Python's versions, this module's source and the namespaces registered before. The cache
lives in the folder the compiled cycle's does (`cache.cache_folder`: this user's,
written by nobody else; a pickle from anyone else would run their code). A cache that
cannot be read is imported again and rewritten; one that cannot be written leaves the
import as it was.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import logging
import os
import pickle
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, fields, is_dataclass, replace
from pathlib import Path
from typing import Any

from geo_server import cache
from geo_server.transports.opcua import cnc, internals, machinetool
from geo_server.transports.opcua.space import APPLICATION_URI, NAMESPACE_URI

log = logging.getLogger("geo_server.opcua")

#: a temporary file older than this is left over from a process that ended while it
#: wrote (younger ones may be another process's, writing now)
STALE_TEMPORARY_S = 600.0
#: the NodeSets in the order they need each other
NODESETS: tuple[Path, ...] = (cnc.NODESET, *(path for _, path in machinetool.NODESETS))


@dataclass(frozen=True)
class _Late:
    """A value of a class asyncua makes at run time (a model's structure or
    enumeration), kept by name until the class is made again."""

    name: str
    value: Any  # an enumeration's number, or a structure's fields by name


@dataclass
class _Added:
    """What an import added to an address space: its namespaces (in order), its nodes,
    the references it appended to older nodes (after how many they had), and where
    values of made classes are."""

    namespaces: list[str]
    nodes: dict[Any, Any]
    references: dict[Any, tuple[int, list[Any]]]
    late: list[tuple[Any, Any]]


async def add(server: Any, closing: Callable[[], bool]) -> None:
    """The companion models' types in `server` (after `init`): from the cache when it
    has them, else imported (and cached). Stops between two NodeSets once the interface
    is `closing` (nobody waits for it then)."""
    nodes = internals.nodes(server)
    uris = list(await server.get_namespace_array())
    path = _cache_path(uris)
    if path is not None and path.is_file():
        try:
            added = _read(path)
        except Exception as exc:  # (truncated, corrupt: imported again below)
            log.warning("OPC UA: the NodeSet cache %s cannot be read (%s)", path, exc)
        else:
            if _fits(nodes, added):
                try:
                    await _restore(server, added)
                except BaseException:
                    # the address space is half changed: this start fails; the cache goes,
                    # so the next one imports (and writes it again)
                    with contextlib.suppress(OSError):
                        path.unlink()
                    raise
                return
            log.warning("OPC UA: the NodeSet cache %s is of another address space", path)
    before = {nodeid: len(data.references) for nodeid, data in nodes.items()}
    for nodeset in NODESETS:
        if closing():
            return
        await server.import_xml(str(nodeset), strict_mode=False)
    if path is not None:
        uris_after = list(await server.get_namespace_array())
        try:
            added = _added(nodes, before, uris_after[len(uris) :])
        except Exception as exc:  # (the import stands; only the cache is not written)
            log.info("OPC UA: the NodeSet cache %s is not written (%s)", path, exc)
        else:
            _write(path, added)


async def warm() -> None:
    """The cache filled for the address space a server starts with (its application
    URI, then geo-server's namespace: `OpcUaInterface`), as an image does when it is
    built (Containerfile): every container started from it then restores."""
    from asyncua import Server

    server = Server()
    await server.init()
    await server.set_application_uri(APPLICATION_URI)
    await server.register_namespace(NAMESPACE_URI)
    uris = list(await server.get_namespace_array())
    await add(server, lambda: False)
    path = _cache_path(uris)
    if path is None or not path.is_file():  # (an image without it would import each start)
        raise RuntimeError(f"the NodeSet cache was not written ({path or 'no safe folder'})")


def _cache_path(uris: list[str]) -> Path | None:
    folder, why = cache.cache_folder("opcua-nodesets")
    if folder is None:
        log.info("OPC UA: the NodeSets are imported at every start (%s)", why)
        return None
    import asyncua  # (its version: in the key)

    h = hashlib.blake2b(digest_size=12)
    h.update(f"{asyncua.__version__} {sys.version}\0{chr(0).join(uris)}".encode())
    h.update(Path(__file__).read_bytes())
    for nodeset in NODESETS:
        h.update(nodeset.read_bytes())
    return folder / f"companions-{h.hexdigest()}.pickle"


def _added(every: dict[Any, Any], before: dict[Any, int], namespaces: list[str]) -> _Added:
    nodes = {nodeid: data for nodeid, data in every.items() if nodeid not in before}
    references = {
        nodeid: (count, list(every[nodeid].references[count:]))
        for nodeid, count in before.items()
        if len(every[nodeid].references) != count
    }
    late = [
        (nodeid, attr)
        for nodeid, data in nodes.items()
        for attr, held in data.attributes.items()
        if held.value is not None
        and held.value.Value is not None
        and _holds(held.value.Value.Value, lambda v: _is_made(type(v)))
    ]
    return _Added(namespaces, nodes, references, late)


def _holds(value: Any, found: Callable[[Any], bool]) -> bool:
    """Whether `value`, the items of a list or the fields of a structure (at any depth)
    hold a value `found` says yes to."""
    if found(value):
        return True
    if isinstance(value, list):
        return any(_holds(item, found) for item in value)
    return (
        is_dataclass(value)
        and not isinstance(value, type)
        and any(_holds(getattr(value, f.name), found) for f in fields(value))
    )


def _is_made(cls: type) -> bool:
    """One of asyncua's classes that pickle cannot find by its module and name (those
    it made at run time)."""
    if not cls.__module__.startswith("asyncua."):
        return False
    module = sys.modules.get(cls.__module__)
    return module is None or getattr(module, cls.__qualname__, None) is not cls


class _Pickler(pickle.Pickler):
    def reducer_override(self, obj: Any) -> Any:
        cls = type(obj)
        if isinstance(obj, type) or not _is_made(cls):
            return NotImplemented
        if isinstance(obj, int):  # (an enumeration: IntEnum, IntFlag)
            return _Late, (cls.__name__, int(obj))
        return _Late, (cls.__name__, {f.name: getattr(obj, f.name) for f in fields(obj)})


def _write(path: Path, added: _Added) -> None:
    """`added` pickled into `path`, whole or not at all (a temporary file renamed: two
    fleets started at once), and the caches of other keys removed (an upgrade of
    asyncua or of geo-server left its old one behind)."""
    temporary = ""
    try:
        buffer = io.BytesIO()
        _Pickler(buffer, pickle.HIGHEST_PROTOCOL).dump(added)
        fd, temporary = tempfile.mkstemp(dir=path.parent, prefix="companions-", suffix=".tmp")
        with os.fdopen(fd, "wb") as file:
            file.write(buffer.getvalue())
        os.replace(temporary, path)
    except Exception as exc:  # (a full disk, an object pickle cannot take: not cached)
        log.info("OPC UA: the NodeSet cache %s cannot be written (%s)", path, exc)
        if temporary:
            with contextlib.suppress(OSError):
                os.unlink(temporary)
        return
    stale = time.time() - STALE_TEMPORARY_S
    for old in path.parent.glob("companions-*"):
        if old == path:
            continue
        with contextlib.suppress(OSError):  # (another process's, removed meanwhile)
            if old.suffix == ".pickle" or old.stat().st_mtime < stale:
                old.unlink()


def _read(path: Path) -> _Added:
    with path.open("rb") as file:
        added = pickle.load(file)  # (a folder only this user writes: `cache_folder`)
    if not isinstance(added, _Added):
        raise TypeError(f"holds {type(added).__name__}")
    return added


def _fits(nodes: Any, added: _Added) -> bool:
    """Whether the address space is as it was before the import `added` records (the
    key makes it so; this checks what a restore relies on before it changes anything)."""
    return not any(nodeid in nodes for nodeid in added.nodes) and all(
        nodeid in nodes and len(nodes[nodeid].references) == count
        for nodeid, (count, _) in added.references.items()
    )


async def _restore(server: Any, added: _Added) -> None:
    """Put back what an import added, into the address space it was taken from (the
    key's), and make the models' classes as asyncua's import does."""
    ua = sys.modules["asyncua.ua"]
    for uri in added.namespaces:
        await server.register_namespace(uri)
    nodes = internals.nodes(server)
    nodes.update(added.nodes)
    for nodeid, (_, references) in added.references.items():
        nodes[nodeid].references.extend(references)
    await server.load_data_type_definitions()
    for nodeid, attr in added.late:
        holder = nodes[nodeid].attributes[attr]
        data = holder.value
        variant = replace(data.Value, Value=_made_again(ua, data.Value.Value))
        holder.value = replace(data, Value=variant)


def _made_again(ua: Any, value: Any) -> Any:
    if isinstance(value, list):
        return [_made_again(ua, item) for item in value]
    if isinstance(value, _Late):
        cls = getattr(ua, value.name)
        if isinstance(value.value, int):
            return cls(value.value)
        return cls(**{name: _made_again(ua, v) for name, v in value.value.items()})
    if is_dataclass(value) and not isinstance(value, type) and _holds(value, _is_late):
        return replace(
            value, **{f.name: _made_again(ua, getattr(value, f.name)) for f in fields(value)}
        )
    return value


def _is_late(value: Any) -> bool:
    return isinstance(value, _Late)
