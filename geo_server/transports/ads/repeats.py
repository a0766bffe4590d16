"""Repeated reads (docs/design.md §13, *Repeated reads*).

An HMI or a test polls the same objects again and again, and on a machine at rest their
values stay what they were. So a connection keeps the answer to each Read it sent of an
object that cannot vary at rest (`varies_at_rest`), with the snapshot that answered it.
The same request again (the same bytes but the invoke id) is answered from what was kept
while that snapshot is still the one a read at rest is answered from
(`service.rests_on`). These are the very bytes the whole path would
answer, without framing, dispatching and resolving the request again.

What is kept, and when it answers, is decided here:

- kept: the answer to a Read by address or by symbol handle of an object without an
  attribute that cannot vary at rest, answered while the machine shows its rest, on a
  machine without a share of the loop (a fleet's shares are charged per request), while
  no fault is injected; with a weak reference to its snapshot (a connection holds bytes
  only, never a snapshot);
- at most `MAX_REPEATS` answers per connection of at most `MAX_REPEAT_SIZE` bytes each;
  one more forgets the others;
- answered from it: a request that arrives as one whole frame with nothing buffered or
  waiting before it, while no fault is injected and the machine may serve another
  request in this loop step (it counts like any other: `requests_per_step`);
- a symbol handle given back forgets the connection's answers (a read by that handle is
  0x710 from then on).
"""

from __future__ import annotations

import weakref
from typing import NamedTuple

from geo_server.service import rests_on, snapshot_for, varies_at_rest
from geo_server.snapshot import Snapshot
from geo_server.transports.ads import codec
from geo_server.transports.ads.codec import AmsPacket
from geo_server.transports.ads.device import Device

#: answers one connection keeps for its repeated reads
MAX_REPEATS = 128
#: the largest answer kept (ADS data of the response, result and length included)
MAX_REPEAT_SIZE = 256

_AT = codec.INVOKE_ID_AT


class Kept(NamedTuple):
    """The answer to a Read, kept for its repeats."""

    device: Device
    #: the snapshot at rest it was answered from (a weak reference: what is kept never
    #: keeps a snapshot alive, so a connection holds only its answers' bytes)
    snapshot: weakref.ref[Snapshot]
    #: the answer frame before and after its invoke id
    head: bytes
    tail: bytes


#: what one connection keeps: by the request less its invoke id (`Connection.repeats`)
Repeats = dict[bytes, Kept]


def read(
    dev: Device, kept: Repeats, packet: AmsPacket, port: int, ig: int, io: int, length: int
) -> bytes:
    """The answer to a Read of the object at (`ig`, `io`) (`tasks.serve_task`), kept in
    `kept`, its connection's, for its repeats when it may be."""
    service = dev.service
    obj, _, attr = service.resolve(ig, io, port=port)
    if attr or not obj.readable or varies_at_rest(obj) or dev.share is not None:
        return codec.read_response(0, service.read(ig, io, length, port=port))
    snap = snapshot_for(service, obj)  # (the one `ObjectService.read` takes)
    payload = codec.read_response(0, service.read(ig, io, length, snap, port=port))
    if len(payload) <= MAX_REPEAT_SIZE and not service.faults.active and rests_on(service, snap):
        key = codec.without_invoke_id(codec.encode_frame(packet.header, packet.data))
        if key not in kept and len(kept) >= MAX_REPEATS:
            kept.clear()
        frame = codec.response_frame(packet.header, payload)
        kept[key] = Kept(dev, weakref.ref(snap), *_split(frame))
    return payload


def _split(frame: bytes) -> tuple[bytes, bytes]:
    return frame[:_AT], frame[_AT + 4 :]


def still(repeats: Repeats, frame: bytes) -> Kept | None:
    """What a connection kept (`repeats`) for `frame`, a whole frame, if it still
    answers it (the server counts the request and sends `answer`)."""
    if len(frame) != codec.READ_FRAME_SIZE:
        return None
    kept = repeats.get(codec.without_invoke_id(frame))
    if kept is None:
        return None
    service = kept.device.service
    if service.faults.active or not rests_on(service, kept.snapshot()):
        return None
    return kept


def answer(kept: Kept, frame: bytes) -> bytes:
    """The answer frame to `frame`: what was kept, with `frame`'s invoke id."""
    return kept.head + frame[_AT : _AT + 4] + kept.tail
