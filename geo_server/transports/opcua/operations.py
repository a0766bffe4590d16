"""How many operations an OPC UA request carries, read from its encoded body before
asyncua decodes it (docs/security.md, *OPC UA*; docs/design.md §9.1).

asyncua's server takes a Read of 100 000 nodes, decodes all of it and answers it in one
turn of the event loop that every interface shares (seconds). Part 4 §5.2 lets a server
bound the operations of one request (`ServerCapabilities.OperationLimits`, Part 5 §6.3.11)
and refuse a request past them with `BadTooManyOperations`. Here each bound is counted
on the request's bytes, with no allocation per element: a refused request costs a few
bytes of parsing, whatever it claims.

Sans-I/O: `excess(name, body)` takes the request's type name and the bytes after its
RequestHeader (Part 6 §5.2, Part 4 §7.28), and says which bound it passes, or None.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass

#: Part 5 §6.3.11 OperationLimitsType: the operations one request may carry, advertised
#: in the server's `ServerCapabilities/OperationLimits` and refused past them
#: (BadTooManyOperations). Chosen so one request holds the event loop for a few
#: milliseconds on a 2-core VM: a Read of 100 values about 3 ms, a Browse of 20 machine
#: folders about 3 ms (bench/opcua_attacks.py measures what they cost the others).
OPERATION_LIMITS: dict[str, int] = {
    "MaxNodesPerRead": 100,
    "MaxNodesPerWrite": 100,
    "MaxNodesPerMethodCall": 50,
    "MaxNodesPerBrowse": 20,
    "MaxNodesPerRegisterNodes": 100,
    "MaxNodesPerTranslateBrowsePathsToNodeIds": 50,
    "MaxNodesPerNodeManagement": 50,
    "MaxMonitoredItemsPerCall": 100,
    "MaxNodesPerHistoryReadData": 50,
    "MaxNodesPerHistoryReadEvents": 50,
    "MaxNodesPerHistoryUpdateData": 50,
    "MaxNodesPerHistoryUpdateEvents": 50,
}
#: the RelativePath elements of all paths of one TranslateBrowsePathsToNodeIds together
#: (no OperationLimits property names them; each element is a browse)
MAX_PATH_ELEMENTS = 128


class Malformed(ValueError):
    """The body ends before its counts do (BadDecodingError)."""


class _Reader:
    """A cursor over the encoded body (Part 6 §5.2: little endian)."""

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 0

    def skip(self, n: int) -> None:
        if n < 0 or self.pos + n > len(self.data):
            raise Malformed(f"{n} bytes past the end at {self.pos}")
        self.pos += n

    def int32(self) -> int:
        start = self.pos
        self.skip(4)
        value: int = struct.unpack_from("<i", self.data, start)[0]
        return value

    def uint16(self) -> int:
        start = self.pos
        self.skip(2)
        value: int = struct.unpack_from("<H", self.data, start)[0]
        return value

    def byte(self) -> int:
        self.skip(1)
        return self.data[self.pos - 1]

    def count(self) -> int:
        """An array's length (-1: a null array, no elements)."""
        return max(0, self.int32())

    def string(self) -> None:
        self.skip(max(0, self.int32()))

    def node_id(self) -> None:
        """Part 6 §5.2.2.9; the flags of an ExpandedNodeId (§5.2.2.10) included."""
        mask = self.byte()
        kind = mask & 0x3F
        if kind == 0:
            self.skip(1)
        elif kind == 1:
            self.skip(3)
        elif kind == 2:
            self.skip(6)
        elif kind in (3, 5):
            self.skip(2)
            self.string()
        elif kind == 4:
            self.skip(18)
        else:
            raise Malformed(f"NodeId encoding {kind}")
        if mask & 0x80:
            self.string()
        if mask & 0x40:
            self.skip(4)

    def extension_object(self) -> None:
        """Part 6 §5.2.2.15: a type id, an encoding byte, a body if the byte says so."""
        self.node_id()
        if self.byte() & 0x03:
            self.string()


@dataclass(frozen=True)
class Excess:
    """A request past a bound: which, how many it carries, the bound."""

    limit: str
    count: int
    most: int

    def __str__(self) -> str:
        return f"{self.count} operations, {self.limit} is {self.most}"


def _first_count(skip: int) -> Callable[[_Reader], int]:
    def at(r: _Reader) -> int:
        r.skip(skip)
        return r.count()

    return at


def _browse(r: _Reader) -> int:
    r.node_id()  # View.ViewId
    r.skip(8 + 4 + 4)  # View.Timestamp, View.ViewVersion, RequestedMaxReferencesPerNode
    return r.count()


def _history_read(r: _Reader) -> int:
    r.extension_object()  # HistoryReadDetails
    r.skip(4 + 1)  # TimestampsToReturn, ReleaseContinuationPoints
    return r.count()


#: request type (Part 4 §5) -> (its bound, where its operation array is)
_REQUESTS: dict[str, tuple[str, Callable[[_Reader], int]]] = {
    "ReadRequest": ("MaxNodesPerRead", _first_count(8 + 4)),  # MaxAge, TimestampsToReturn
    "WriteRequest": ("MaxNodesPerWrite", _first_count(0)),
    "CallRequest": ("MaxNodesPerMethodCall", _first_count(0)),
    "BrowseRequest": ("MaxNodesPerBrowse", _browse),
    "BrowseNextRequest": ("MaxNodesPerBrowse", _first_count(1)),
    "RegisterNodesRequest": ("MaxNodesPerRegisterNodes", _first_count(0)),
    "UnregisterNodesRequest": ("MaxNodesPerRegisterNodes", _first_count(0)),
    "TranslateBrowsePathsToNodeIdsRequest": (
        "MaxNodesPerTranslateBrowsePathsToNodeIds",
        _first_count(0),
    ),
    "AddNodesRequest": ("MaxNodesPerNodeManagement", _first_count(0)),
    "AddReferencesRequest": ("MaxNodesPerNodeManagement", _first_count(0)),
    "DeleteNodesRequest": ("MaxNodesPerNodeManagement", _first_count(0)),
    "DeleteReferencesRequest": ("MaxNodesPerNodeManagement", _first_count(0)),
    # SubscriptionId, TimestampsToReturn / MonitoringMode
    "CreateMonitoredItemsRequest": ("MaxMonitoredItemsPerCall", _first_count(4 + 4)),
    "ModifyMonitoredItemsRequest": ("MaxMonitoredItemsPerCall", _first_count(4 + 4)),
    "SetMonitoringModeRequest": ("MaxMonitoredItemsPerCall", _first_count(4 + 4)),
    "DeleteMonitoredItemsRequest": ("MaxMonitoredItemsPerCall", _first_count(4)),
    # subscription ids: no property names them; bounded as monitored items
    "DeleteSubscriptionsRequest": ("MaxMonitoredItemsPerCall", _first_count(0)),
    "SetPublishingModeRequest": ("MaxMonitoredItemsPerCall", _first_count(1)),
    "TransferSubscriptionsRequest": ("MaxMonitoredItemsPerCall", _first_count(0)),
    "HistoryReadRequest": ("MaxNodesPerHistoryReadData", _history_read),
    "HistoryUpdateRequest": ("MaxNodesPerHistoryUpdateData", _first_count(0)),
}


def bounded_requests() -> tuple[str, ...]:
    """The request types whose operations are counted."""
    return tuple(_REQUESTS)


def excess(request: str, body: bytes) -> Excess | None:
    """The bound request type `request` with this body (after its RequestHeader)
    passes, or None. Raises `Malformed` when the body ends before its counts."""
    entry = _REQUESTS.get(request)
    if entry is None:
        return None
    limit, where = entry
    r = _Reader(body)
    count = where(r)
    most = OPERATION_LIMITS[limit]
    if count > most:
        return Excess(limit, count, most)
    if request == "TranslateBrowsePathsToNodeIdsRequest":
        return _path_elements(r, count)
    return None


def _path_elements(r: _Reader, paths: int) -> Excess | None:
    """Each BrowsePath: StartingNode, RelativePath.Elements[] of (ReferenceTypeId,
    IsInverse, IncludeSubtypes, TargetName); counted until the bound is passed."""
    total = 0
    for _ in range(paths):
        r.node_id()
        elements = r.count()
        total += elements
        if total > MAX_PATH_ELEMENTS:
            return Excess("RelativePath elements", total, MAX_PATH_ELEMENTS)
        for _ in range(elements):
            r.node_id()
            r.skip(2)
            r.uint16()
            r.string()
    return None


__all__ = ["MAX_PATH_ELEMENTS", "OPERATION_LIMITS", "Excess", "Malformed", "excess"]
