"""Zenoh client for geo-server (SPEC §7): gets with a timeout, writes as gets with payload."""

from __future__ import annotations

import json
import queue
from collections.abc import Callable, Iterator
from typing import Any

import zenoh

from geo_server.dictionary import AdsError, load_dictionary
from geo_server.transports.keys import KeySpace

JSON = zenoh.Encoding.APPLICATION_JSON
OCTET = zenoh.Encoding.APPLICATION_OCTET_STREAM


def client_config(
    connect: list[str], mode: str = "peer", config_file: str | None = None
) -> zenoh.Config:
    """A Zenoh config that connects to explicit endpoints with multicast scouting off."""
    cfg = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("listen/endpoints", "[]")
    cfg.insert_json5("connect/endpoints", json.dumps(connect))
    return cfg


def _error(reply_err: Any) -> AdsError:
    raw = reply_err.payload.to_bytes()
    try:
        body = json.loads(raw)
        return AdsError(
            int(body.get("ads_error", 0x700)), body.get("message", ""), body.get("name", "")
        )
    except (ValueError, AttributeError):
        return AdsError(0x700, raw.decode("utf-8", "replace"))


class ZenohClient:
    """Read and write geo-server objects over Zenoh."""

    def __init__(
        self,
        machine: str = "local",
        connect: list[str] | None = None,
        timeout: float = 2.0,
        mode: str = "peer",
        config_file: str | None = None,
        session: zenoh.Session | None = None,
    ) -> None:
        self.machine = machine
        self.timeout = timeout
        self._own = session is None
        self.session = session or zenoh.open(
            client_config(connect or ["tcp/127.0.0.1:7447"], mode, config_file)
        )
        self.dictionary = load_dictionary()
        self._subs: list[Any] = []

    def keyspace(self, axes: tuple[int, ...] = ()) -> KeySpace:
        return KeySpace(self.machine, self.dictionary, axes)

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self._subs.clear()
        if self._own:
            self.session.close()

    def __enter__(self) -> ZenohClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ primitives

    def get(
        self, key: str, payload: bytes | None = None, encoding: Any = None
    ) -> list[tuple[str, bytes]]:
        """All OK replies of a get as (key, payload); the first error raises AdsError."""
        kwargs: dict[str, Any] = {"timeout": self.timeout}
        if payload is not None:
            kwargs["payload"] = payload
            kwargs["encoding"] = encoding or JSON
        out: list[tuple[str, bytes]] = []
        for reply in self.session.get(key, **kwargs):
            if reply.ok is not None:
                out.append((str(reply.ok.key_expr), reply.ok.payload.to_bytes()))
            else:
                raise _error(reply.err)
        if not out:
            raise TimeoutError(
                f"no reply for {key} within {self.timeout} s (is the server "
                f"running with machine name {self.machine!r}?)"
            )
        return out

    def _one(self, key: str, payload: bytes | None = None, encoding: Any = None) -> bytes:
        return self.get(key, payload, encoding)[0][1]

    # ------------------------------------------------------------------ objects

    def _named_key(self, name: str, axis: int) -> str:
        obj = self.dictionary.by_name(name)
        return KeySpace(self.machine, self.dictionary, ()).named_key(obj, axis)

    def read(self, name: str, axis: int = 0) -> Any:
        return json.loads(self._one(self._named_key(name, axis)))

    def write(self, name: str, axis: int, value: Any) -> Any:
        key = self._named_key(name, axis)
        return json.loads(self._one(key, json.dumps(value).encode(), JSON))

    def read_raw(self, index_group: int, index_offset: int, length: int = 0) -> bytes:
        key = KeySpace(self.machine, self.dictionary, ()).raw_key(index_group, index_offset)
        data = self._one(key)
        return data[:length] if length else data

    def write_raw(self, index_group: int, index_offset: int, data: bytes) -> None:
        key = KeySpace(self.machine, self.dictionary, ()).raw_key(index_group, index_offset)
        self._one(key, data, OCTET)

    # ------------------------------------------------------------------ commands

    def status(self) -> dict[str, Any]:
        return json.loads(self._one(f"cnc/{self.machine}/status"))

    def errors(self) -> list[dict[str, Any]]:
        return json.loads(self._one(f"cnc/{self.machine}/errors"))

    def nc(self, text: str) -> dict[str, Any]:
        return json.loads(
            self._one(f"cnc/{self.machine}/nc", text.encode(), zenoh.Encoding.TEXT_PLAIN)
        )

    def reload(self) -> dict[str, Any]:
        return json.loads(self._one(f"cnc/{self.machine}/cmd/reload", b"{}", JSON))

    def reset(self) -> dict[str, Any]:
        return json.loads(self._one(f"cnc/{self.machine}/cmd/reset", b"{}", JSON))

    def save(self) -> dict[str, Any]:
        return json.loads(self._one(f"cnc/{self.machine}/cmd/save", b"{}", JSON))

    def watch(self, key_expr: str) -> Iterator[tuple[str, Any]]:
        """Yield (key, decoded JSON): the current values first, then every publication
        on `key_expr` (blocking; publications arrive on change, SPEC §7)."""
        q: queue.Queue[tuple[str, bytes]] = queue.Queue()
        self.subscribe(key_expr, lambda k, v: q.put((k, v)))
        for key, data in self.get(key_expr):
            yield key, _decode(key, data)
        while True:
            key, data = q.get()
            yield key, _decode(key, data)

    def subscribe(self, key_expr: str, callback: Callable[[str, bytes], None]) -> None:
        def on_sample(sample: zenoh.Sample) -> None:
            callback(str(sample.key_expr), sample.payload.to_bytes())

        self._subs.append(self.session.declare_subscriber(key_expr, on_sample))


def _decode(key: str, data: bytes) -> Any:
    """JSON for named keys; raw ADS keys (`…/ads/551/…`) carry little-endian bytes,
    shown as hex because only the dictionary knows their type."""
    if "/ads/" in key:
        return data.hex()
    return json.loads(data)
