"""Framing between the server process and the GEO-cycle process (sans-I/O).

A frame is a 4-byte little-endian length and a pickled message. `FrameDecoder` turns
received bytes (any split, any coalescing) back into messages; `OutBuffer` holds frames
the cycle process could not write yet, so the cycle never blocks on a slow reader: a
message marked *droppable* (a snapshot that the next one supersedes) is left out while
the buffer is over its limit, the others (acknowledgements, events) are always kept.

Both ends are our own processes on one machine, so pickle is safe here; nothing from
the network ever reaches this channel.
"""

from __future__ import annotations

import pickle
import struct
from collections.abc import Callable
from typing import Any

from geo_server.errors import GeoError

_LEN = struct.Struct("<I")
MAX_FRAME = 64 * 1024 * 1024  # a reload carries a whole machine configuration


class ChannelError(GeoError, ValueError):
    """The byte stream between the two processes is not a sequence of frames (a defect,
    never user input)."""


def encode_frame(message: Any) -> bytes:
    body = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    if len(body) > MAX_FRAME:
        raise ChannelError(f"message of {len(body)} bytes exceeds {MAX_FRAME}")
    return _LEN.pack(len(body)) + body


class FrameDecoder:
    """Bytes in, messages out."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[Any]:
        self._buf += data
        out: list[Any] = []
        while len(self._buf) >= _LEN.size:
            (n,) = _LEN.unpack_from(self._buf)
            if n > MAX_FRAME:
                raise ChannelError(f"frame length {n} exceeds {MAX_FRAME}")
            end = _LEN.size + n
            if len(self._buf) < end:
                break
            out.append(pickle.loads(self._buf[_LEN.size : end]))
            del self._buf[:end]
        return out


class OutBuffer:
    """Frames waiting to be written by a non-blocking writer."""

    def __init__(self, limit: int = 1 << 20) -> None:
        self.limit = limit
        self._buf = bytearray()
        self.dropped = 0

    def __len__(self) -> int:
        return len(self._buf)

    def add(self, message: Any, droppable: bool = False) -> None:
        if droppable and len(self._buf) > self.limit:
            self.dropped += 1
            return
        self._buf += encode_frame(message)

    def flush(self, write: Callable[[bytearray], int]) -> None:
        """Write as much as `write` takes; `write` returns the count written and may
        raise BlockingIOError when it takes nothing."""
        while self._buf:
            try:
                n = write(self._buf)
            except BlockingIOError:
                return
            if n <= 0:
                return
            del self._buf[:n]


class SlotTable:
    """Shared state of the operations in flight between the two processes.

    Each queued operation owns one slot. The server marks it QUEUED before sending the
    operation; the cycle process, when it reads the operation, takes it (QUEUED → TAKEN)
    or finds it withdrawn (WITHDRAWN → FREE, the operation is skipped). The server
    withdraws (QUEUED → WITHDRAWN) only under the same lock, so an operation is either
    taken by a cycle or withdrawn, never both — even if one process is stopped (SIGSTOP)
    at any instruction: a lock held by a stopped process makes the other side wait (the
    server with a timeout), it never makes it guess.
    """

    FREE, QUEUED, TAKEN, WITHDRAWN = 0, 1, 2, 3

    def __init__(self, ctx: Any, capacity: int = 4096) -> None:
        self.lock = ctx.Lock()
        self.state = ctx.RawArray("B", capacity)
        self.capacity = capacity
        self._next = 0  # server side: where to look for a free slot first

    def __getstate__(self) -> dict[str, Any]:
        return {"lock": self.lock, "state": self.state, "capacity": self.capacity, "_next": 0}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)

    # server side

    def allocate(self) -> int | None:
        """A free slot, marked QUEUED; None when every slot is in flight."""
        with self.lock:
            for i in range(self.capacity):
                s = (self._next + i) % self.capacity
                if self.state[s] == self.FREE:
                    self.state[s] = self.QUEUED
                    self._next = (s + 1) % self.capacity
                    return s
        return None

    def withdraw(self, slot: int, timeout: float = 0.05) -> bool:
        """QUEUED → WITHDRAWN. False when a cycle took it, or the lock is held by a
        stopped process (try again later)."""
        if not self.lock.acquire(timeout=timeout):
            return False
        try:
            if self.state[slot] != self.QUEUED:
                return False
            self.state[slot] = self.WITHDRAWN
            return True
        finally:
            self.lock.release()

    def release(self, slot: int) -> None:
        """The server has the outcome of a taken operation: the slot is free again."""
        with self.lock:
            self.state[slot] = self.FREE

    # cycle-process side

    def take(self, slot: int) -> bool:
        """True: carry the operation out. False: it was withdrawn (the slot is freed)."""
        with self.lock:
            if self.state[slot] == self.QUEUED:
                self.state[slot] = self.TAKEN
                return True
            self.state[slot] = self.FREE
            return False
