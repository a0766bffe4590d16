"""Zenoh client (docs/design.md §7): gets with a timeout, writes as gets with payload.

One machine name must mean one server. Every get goes to all matching queryables without
consolidation, so the client sees each reply with the Zenoh id of the session that sent
it (`Reply.replier_id`); replies from two different sessions for one machine (an
impostor, or a second server started with the same machine name) fail with
`ServerConflictError`, which names both ids, instead of handing out whichever answer came
first. A client may pick one server by its Zenoh id (`server_id`, or the environment
variable `GEO_ZENOH_SERVER_ID`); replies from any other session are then ignored.
"""

from __future__ import annotations

import json
import os
import queue
from collections.abc import Callable, Iterator
from typing import Any

import zenoh

from geo_server.client.base import ObjectClient, probe_zenoh
from geo_server.dictionary import load_dictionary
from geo_server.errors import AdsError
from geo_server.transports.zenoh.keys import KeySpace

JSON = zenoh.Encoding.APPLICATION_JSON
OCTET = zenoh.Encoding.APPLICATION_OCTET_STREAM
#: Environment variable with the Zenoh id of the server to talk to (see `ZenohClient`).
SERVER_ID_ENV = "GEO_ZENOH_SERVER_ID"


class ServerConflictError(AdsError):
    """Two or more Zenoh sessions answered for one machine.

    An `AdsError` (0x700, a general device error) so that every caller that reports
    refused requests reports this one too; `zenoh_ids` lists the sessions that answered.
    """

    def __init__(self, machine: str, key: str, zenoh_ids: list[str]) -> None:
        self.machine, self.key, self.zenoh_ids = machine, key, zenoh_ids
        listed = " and ".join(zenoh_ids)
        super().__init__(
            0x700,
            f"{len(zenoh_ids)} Zenoh sessions answered {key} for machine {machine!r}: "
            f"{listed}. Only one may serve a machine name: one of them is an impostor or "
            "a second geo-server with the same --machine. Stop it or give each server its "
            "own machine name; admit only known sessions (Zenoh access control, TLS, "
            f"user/password authentication); or choose a server by its Zenoh id "
            f"(environment variable {SERVER_ID_ENV}=<id>, or ZenohClient(server_id=<id>); "
            "a server logs its id at start and shows it as zenoh_id in its status).",
        )

    def __reduce__(self) -> tuple[Any, ...]:
        return (type(self), (self.machine, self.key, self.zenoh_ids))


def client_config(
    connect: list[str], mode: str = "peer", config_file: str | None = None
) -> zenoh.Config:
    """A Zenoh config that connects to explicit endpoints with multicast scouting off.

    TLS certificates, user/password and the like come from `config_file`, or else from
    the file named by Zenoh's own environment variable `ZENOH_CONFIG` (so `geo-client`
    can join a locked-down network); mode, endpoints and scouting are always set here.
    """
    if config_file:
        cfg = zenoh.Config.from_file(config_file)
    elif os.environ.get("ZENOH_CONFIG"):
        cfg = zenoh.Config.from_env()
    else:
        cfg = zenoh.Config()
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


class ZenohClient(ObjectClient):
    """Read and write geo-server objects over Zenoh."""

    def __init__(
        self,
        machine: str = "local",
        connect: list[str] | None = None,
        timeout: float = 2.0,
        mode: str = "peer",
        config_file: str | None = None,
        session: zenoh.Session | None = None,
        server_id: str | None = None,
    ) -> None:
        self.machine = machine
        self.timeout = timeout
        #: Only replies from this Zenoh session count (None: any one session, but only one).
        self.server_id = server_id or os.environ.get(SERVER_ID_ENV) or None
        self._own = session is None
        endpoints = connect or ["tcp/127.0.0.1:7447"]
        if session is None and mode == "peer":
            probe_zenoh(endpoints, timeout)  # else a get would wait for its timeout
        self.session = session or zenoh.open(client_config(endpoints, mode, config_file))
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
        self,
        key: str,
        payload: bytes | None = None,
        encoding: Any = None,
        timeout: float | None = None,
    ) -> list[tuple[str, bytes]]:
        """All OK replies of a get as (key, payload); the first error raises AdsError.

        Replies from more than one Zenoh session raise `ServerConflictError` (unless
        `server_id` picks one). A write (a get with payload) reaches every session that
        answers, so a conflict there is reported after the fact: the server's value may
        have been written, and the other session has seen it.
        """
        wait = self.timeout if timeout is None else timeout
        kwargs: dict[str, Any] = {
            "timeout": wait,
            # every matching queryable, every reply: the only way to see a second server
            "target": zenoh.QueryTarget.ALL,
            "consolidation": zenoh.ConsolidationMode.NONE,
        }
        if payload is not None:
            kwargs["payload"] = payload
            kwargs["encoding"] = encoding or JSON
        replies = [(_replier(reply), reply) for reply in self.session.get(key, **kwargs)]
        if self.server_id is not None:
            replies = [(zid, r) for zid, r in replies if zid == self.server_id]
        else:
            sessions = sorted({zid for zid, _ in replies if zid is not None})
            if len(sessions) > 1:
                raise ServerConflictError(self.machine, key, sessions)
        out: list[tuple[str, bytes]] = []
        for _zid, reply in replies:
            if reply.ok is not None:
                out.append((str(reply.ok.key_expr), reply.ok.payload.to_bytes()))
            elif reply.err.payload.to_bytes() == b"Timeout":
                # Zenoh's own error reply when the get's timeout ran out before the
                # server answered (the server's errors are JSON): a timeout, transient
                raise TimeoutError(f"no reply for {key} within {wait} s (the get timed out)")
            else:
                raise _error(reply.err)
        if not out:
            chosen = f" from Zenoh session {self.server_id}" if self.server_id else ""
            raise TimeoutError(
                f"no reply for {key}{chosen} within {wait} s ({self._who_answers(wait)})"
            )
        return out

    def _who_answers(self, wait: float) -> str:
        """Why a get went unanswered, as far as Zenoh tells: the machines whose servers
        are alive on this network (their liveliness tokens `cnc/<name>/alive`), so that
        a client of a fleet started without --machine learns the names (issue 45 #16)."""
        names = set()
        for reply in self.session.liveliness().get("cnc/*/alive", timeout=min(wait, 1.0)):
            if reply.ok is not None:
                parts = str(reply.ok.key_expr).split("/")
                if len(parts) == 3:
                    names.add(parts[1])
        if not names:
            return f"is a server running with machine name {self.machine!r}?"
        if self.machine in names:  # alive, but it did not answer this key (in time)
            return f"machine {self.machine!r} is alive but did not answer"
        listed = ", ".join(sorted(names)[:20]) + (", …" if len(names) > 20 else "")
        return (
            f"no machine named {self.machine!r}; machines alive: {listed} (choose with --machine)"
        )

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

    # the replies are JSON documents: objects (a list of them for `errors`)

    def status(self) -> dict[str, Any]:
        status: dict[str, Any] = json.loads(self._one(f"cnc/{self.machine}/status"))
        return status

    def errors(self) -> list[dict[str, Any]]:
        errors: list[dict[str, Any]] = json.loads(self._one(f"cnc/{self.machine}/errors"))
        return errors

    def nc(self, text: str) -> dict[str, Any]:
        result: dict[str, Any] = json.loads(
            self._one(f"cnc/{self.machine}/nc", text.encode(), zenoh.Encoding.TEXT_PLAIN)
        )
        return result

    def reload(self) -> dict[str, Any]:
        result: dict[str, Any] = json.loads(
            self._one(f"cnc/{self.machine}/cmd/reload", b"{}", JSON)
        )
        return result

    def reset(self) -> dict[str, Any]:
        result: dict[str, Any] = json.loads(self._one(f"cnc/{self.machine}/cmd/reset", b"{}", JSON))
        return result

    def save(self) -> dict[str, Any]:
        result: dict[str, Any] = json.loads(self._one(f"cnc/{self.machine}/cmd/save", b"{}", JSON))
        return result

    def fault(self, inject: str | None = None, clear: int | str | None = None) -> dict[str, Any]:
        """`cmd/fault` (docs/faults.md): inject a fault (`"ads:error=0x707,count=2"`),
        clear one by id or `"all"`, or (neither) list them; the reply lists the active
        faults under `faults`."""
        body: dict[str, Any] = {}
        if inject is not None:
            body["inject"] = inject
        if clear is not None:
            body["clear"] = clear
        key = f"cnc/{self.machine}/cmd/fault"
        result: dict[str, Any] = json.loads(self._one(key, json.dumps(body).encode(), JSON))
        return result

    def measure(self, plan: dict[str, Any], timeout: float | None = None) -> dict[str, Any]:
        """`cmd/measure`: an ISO 230-2 test on the server's twin (docs/twin.md). `plan`:
        {"axis": "X", "targets": [...], "runs": 5, ...}; the reply holds the figures. A
        test takes minutes of machine time: `timeout` (s) replaces the client's."""
        key = f"cnc/{self.machine}/cmd/measure"
        body = self.get(key, json.dumps(plan).encode(), JSON, timeout)[0][1]
        result: dict[str, Any] = json.loads(body)
        return result

    def watch(self, key_expr: str) -> Iterator[tuple[str, Any]]:
        """Yield (key, decoded JSON): the current values first, then every publication
        on `key_expr` (blocking; publications arrive on change, docs/design.md §7)."""
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


def _replier(reply: zenoh.Reply) -> str | None:
    """The Zenoh id of the session that sent `reply` (None for Zenoh's own, e.g. a timeout)."""
    rid = reply.replier_id
    return str(rid.zid) if rid is not None else None


def _decode(key: str, data: bytes) -> Any:
    """JSON for named keys; raw ADS keys (`…/ads/551/…`) carry little-endian bytes,
    shown as hex because only the dictionary knows their type."""
    if "/ads/" in key:
        return data.hex()
    return json.loads(data)
