"""What a get that reads is answered with (docs/design.md §7): one object's key, a
wildcard from one snapshot, the status and the errors list.

A get of an object's own key (raw or named, as the server spells it) can be answered on
Zenoh's thread when the cycle due is there without waiting (`Reads.plain`): what the
loop would answer, without the hop to it and back. Its reply is kept while the machine
rests on the snapshot it came from (docs/design.md §13, *Repeated reads*)."""

from __future__ import annotations

import json
import logging
import weakref

import zenoh

from geo_server.dictionary import ObjectDef
from geo_server.errors import AdsError, AdsErrorCode
from geo_server.service import (
    ObjectService,
    check_readable,
    rests_on,
    snapshot_for,
    varies_at_rest,
)
from geo_server.snapshot import Snapshot
from geo_server.transports.zenoh.keys import KeySpace, Route

log = logging.getLogger(__name__)

OCTET = zenoh.Encoding.APPLICATION_OCTET_STREAM
JSON = zenoh.Encoding.APPLICATION_JSON
#: a reply's payload and encoding
Reply = tuple[bytes, zenoh.Encoding]


def error_payload(exc: AdsError) -> bytes:
    """A `reply_err`'s payload: the ADS code and the message, as JSON."""
    return json.dumps(exc.as_dict()).encode()


def _json_reply(snap: Snapshot, obj: ObjectDef, axis: int) -> bytes:
    """A named key's reply: the decoded value as JSON."""
    return json.dumps(snap.value(obj, axis)).encode()


class Reads:
    """The read answers of one machine's Zenoh interface (keys built once: a wildcard
    intersects every readable key, and building a KeyExpr from a str each time is pure
    overhead on the loop the GEO cycle shares the interpreter lock with)."""

    def __init__(self, service: ObjectService, keys: KeySpace) -> None:
        self._service = service
        self.keys = keys
        self._readable = [
            (zenoh.KeyExpr(key), key, route) for key, route in keys.readable_keys().items()
        ]
        #: the keys a get is answered for on the Zenoh thread (`plain`): each readable
        #: object's own named and raw key, as the server spells them (any other
        #: spelling of an address is parsed and answered on the loop)
        self.plain_keys = {
            key: route for _, key, route in self._readable if route.kind in ("raw", "named")
        }
        #: the reply to the last get of each plain key and the snapshot it came from
        self.kept: dict[str, tuple[weakref.ref[Snapshot], bytes, zenoh.Encoding]] = {}

    def is_plain(self, key: str) -> bool:
        return key in self.kept or key in self.plain_keys

    def plain(self, key: str) -> Reply | None:
        """Zenoh thread: the reply to a get of a plain key, never waiting for a
        catch-up (None: it would wait, or fails; the loop answers it). A reply is kept
        when its object cannot vary at rest and it came from the snapshot a read at rest
        takes; it answers the next gets of `key` while that snapshot is still the one:
        one per plain key, with a weak reference to the snapshot (nothing kept keeps a
        snapshot alive)."""
        svc = self._service
        kept = self.kept.get(key)
        if kept is not None and rests_on(svc, kept[0]()):
            return kept[1], kept[2]
        route = self.plain_keys[key]
        assert route.obj is not None  # (a plain key is an object's own)
        try:
            if varies_at_rest(route.obj):
                return self.read(route, None, wait=0)
            snap = snapshot_for(svc, route.obj, wait=0)
            data, enc = self.read(route, snap)
        except AdsError:
            return None
        if rests_on(svc, snap):
            self.kept[key] = (weakref.ref(snap), data, enc)
        return data, enc

    def read(self, route: Route, snap: Snapshot | None, wait: float | None = None) -> Reply:
        """A read-only route's reply from `snap` (None: the snapshot due now for this
        one object, waiting at most `wait` for a catch-up; status and errors are
        answered even while the cycle is stalled)."""
        svc = self._service
        if route.kind == "status":
            return json.dumps(svc.status()).encode(), JSON
        if route.kind == "errors":
            return json.dumps(svc.errors()).encode(), JSON
        if route.kind == "raw":
            data = svc.read(route.index_group, route.index_offset, None, snap, wait=wait)
            return data, OCTET
        if route.kind == "named":
            assert route.obj is not None
            check_readable(route.obj)
            snap = snap or snapshot_for(svc, route.obj, wait)
            obj, axis = route.obj, route.axis
            return snap.kept("json", obj, axis, lambda: _json_reply(snap, obj, axis)), JSON
        raise AdsError(
            AdsErrorCode.DEVICE_INVALIDACCESS,
            f"{route.kind} needs a payload (get with payload runs it)",
        )

    def wildcard(self, query: zenoh.Query) -> None:
        """One reply per readable key the wildcard matches, all from one snapshot.

        The candidates are `KeySpace.readable_keys`: write-only objects (the commands
        `SIM::reload`/`SIM::save`, `SIM::set_position`) are not among them, so a wildcard
        skips them silently, and `status`/`errors` are answered when it matches them.
        Should one key still fail to read, it is skipped and logged: the keys after it
        are answered all the same (one bad object must not hide the rest, which a
        `reply_err` in the middle would, since clients stop at the first error). While
        the GEO cycle is stalled the object keys are not served as current: `status`
        and `errors` are answered, then one `reply_err` 0x707 stands for the rest.

        A wildcard that matches none of our keys (an unconfigured axis, a misspelt
        field) is answered with `reply_err` (every get is answered), not with silence
        that the client can only tell from its own timeout.
        """
        ke = query.key_expr
        matched = [(key, route) for kexpr, key, route in self._readable if kexpr.intersects(ke)]
        if not matched:
            raise self.keys.no_match(str(ke))
        try:
            snap: Snapshot | None = self._service.current()
            stalled: AdsError | None = None
        except AdsError as exc:
            snap, stalled = None, exc
        for key, route in matched:
            if snap is None and route.kind in ("raw", "named"):
                continue
            try:
                payload, enc = self.read(route, snap)
            except AdsError as exc:
                log.warning("wildcard %s: %s skipped: %s", ke, key, exc.message)
                continue
            query.reply(key, payload, encoding=enc)
        if stalled is not None:
            query.reply_err(error_payload(stalled), encoding=JSON)
