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

_LEN = struct.Struct("<I")
MAX_FRAME = 64 * 1024 * 1024  # a reload carries a whole machine configuration


class FramingError(ValueError):
    """The byte stream is not a sequence of frames (a defect, never user input)."""


def encode_frame(message: Any) -> bytes:
    body = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    if len(body) > MAX_FRAME:
        raise FramingError(f"message of {len(body)} bytes exceeds {MAX_FRAME}")
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
                raise FramingError(f"frame length {n} exceeds {MAX_FRAME}")
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

    def flush(self, write: Callable[[bytes], int]) -> None:
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
